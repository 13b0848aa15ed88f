"""Issue #28: the scorer's counts from layers packed one bit per class (metrics/_packed.py)."""

from __future__ import annotations

import numpy as np
import pytest

from bev_mapper_core.errors import InputError
from bev_mapper_core.geometry.grid import BevGrid
from bev_mapper_core.metrics import MetricAccumulator
from bev_mapper_core.metrics._packed import CellCounter, pack, unpack

GRID = BevGrid(x_min=-10.0, x_max=10.0, y_min=-6.0, y_max=6.0, resolution=0.5)


@pytest.mark.parametrize("n_classes", [1, 7, 8, 9, 17])
def test_pack_unpack_and_counts_equal_each_layer(n_classes):
    """Any number of classes (several bytes a cell past 8), overlapping bands and a band no cell
    is in: the counts per class and band are each layer's own."""
    rng = np.random.default_rng(n_classes)
    layers = rng.random((n_classes, 24, 40)) < rng.random((n_classes, 1, 1))
    bands = np.stack([rng.random(24 * 40) < 0.5, rng.random(24 * 40) < 0.3, np.zeros(24 * 40, bool)])
    bits = pack(layers)
    assert bits.shape == (-(-n_classes // 8), 24 * 40) and bits.dtype == np.uint8
    for c in range(n_classes):
        np.testing.assert_array_equal(unpack(bits, c), layers[c].ravel())
    counter = CellCounter(n_classes, bands)
    totals, per_band = counter.counts(bits)
    flat = layers.reshape(n_classes, -1)
    np.testing.assert_array_equal(totals, flat.sum(axis=1))
    np.testing.assert_array_equal(counter.totals(bits), flat.sum(axis=1))
    np.testing.assert_array_equal(per_band, (flat[:, None, :] & bands[None]).sum(axis=2))
    no_bands = CellCounter(n_classes, np.zeros((0, 24 * 40), bool)).counts(bits)
    assert no_bands[1].shape == (n_classes, 0)
    np.testing.assert_array_equal(no_bands[0], flat.sum(axis=1))


def test_accumulator_counts_with_many_classes_masks_and_known_equal_plain_numpy():
    """11 classes (two bytes a cell), per-class scoring masks and unknown cells: IoU counts,
    precision counts and band counts are those of the plain per-class arithmetic."""
    rng = np.random.default_rng(11)
    C = 11
    acc = MetricAccumulator(GRID, [f"c{i}" for i in range(C)])
    inter = np.zeros(C, np.int64)
    union = np.zeros(C, np.int64)
    fp = np.zeros(C, np.int64)
    band_inter = np.zeros_like(acc._band_inter)
    for _ in range(3):
        probs = rng.random((C,) + GRID.shape).astype(np.float32)
        gt = rng.random((C,) + GRID.shape) < 0.3
        mask = rng.random((C,) + GRID.shape) < 0.8
        known = rng.random(GRID.shape) < 0.9
        probs[:, ~known] = np.nan  # unknown cells may hold anything
        iou = acc.update(probs, gt, mask, known)
        with np.errstate(invalid="ignore"):
            pred = (probs >= 0.5) & known & mask
        g = gt & mask
        frame_inter, frame_union = (pred & g).sum(axis=(1, 2)), (pred | g).sum(axis=(1, 2))
        np.testing.assert_array_equal(iou, frame_inter / frame_union)
        inter += frame_inter
        union += frame_union
        fp += (pred & ~g).sum(axis=(1, 2))
        for b, (lo, hi) in enumerate(acc.range_bands):
            band = (GRID.ranges >= lo) & (GRID.ranges < hi)
            band_inter[:, b] += (pred & g & band).sum(axis=(1, 2))
    np.testing.assert_array_equal(acc._inter, inter)
    np.testing.assert_array_equal(acc._union, union)
    np.testing.assert_array_equal(acc._fp, fp)
    np.testing.assert_array_equal(acc._band_inter, band_inter)


def test_finite_check_is_per_cell_when_the_class_sum_is_not_finite():
    """Finite probabilities whose sum overflows are accepted; an infinity in one known cell is
    refused, and accepted when that cell is unknown."""
    acc = MetricAccumulator(GRID, ["a", "b"])
    gt = np.zeros((2,) + GRID.shape, bool)
    huge = np.full((2,) + GRID.shape, 3e38, np.float32)  # each finite, their sum is not
    acc.update(huge, gt)
    bad = np.zeros((2,) + GRID.shape, np.float32)
    bad[1, 3, 4] = -np.inf
    with pytest.raises(InputError, match="NaN or infinite"):
        acc.update(bad, gt)
    known = np.ones(GRID.shape, bool)
    known[3, 4] = False
    acc.update(bad, gt, known=known)


@pytest.mark.parametrize("threshold", [0.5, 0.335, 0.0, 1.0])
def test_whole_grid_scores_from_the_percent_alone_equal_those_from_the_probabilities(threshold, monkeypatch):
    """``WholeGridAccumulator.update(None, ..., percent=...)`` (the replay's scorer) counts the
    claims and the calibration exactly as from the published probabilities, on both of its
    calibration paths."""
    import bev_mapper_core.metrics.whole_grid as whole_grid
    from bev_mapper_core.metrics import WholeGridAccumulator

    rng = np.random.default_rng(7)
    names = ("a", "b", "c")
    for exact_cells in (whole_grid._EXACT_PERCENT_CELLS, 0):  # 0: the per-cell sums
        monkeypatch.setattr(whole_grid, "_EXACT_PERCENT_CELLS", exact_cells)
        from_probs = WholeGridAccumulator(GRID, names, threshold=threshold)
        from_percent = WholeGridAccumulator(GRID, names, threshold=threshold)
        for _ in range(3):
            percent = rng.integers(0, 101, (3,) + GRID.shape).astype(np.uint8)
            probs = np.arange(101, dtype=np.float32)[percent] / 100.0
            known, seen = rng.random(GRID.shape) < 0.8, rng.random(GRID.shape) < 0.6
            gt, truth = rng.random((3,) + GRID.shape) < 0.4, rng.random((3,) + GRID.shape) < 0.4
            percent[:, ~known] = 255  # unknown cells hold anything
            from_probs.update(probs, known, seen, gt, truth, percent=percent)
            from_percent.update(None, known, seen, gt, truth, percent=percent)
        assert from_percent.state() == from_probs.state()
        assert from_percent._claims.sum() > 0 or threshold == 1.0
    with pytest.raises(InputError, match="percent must be uint8"):
        from_percent.update(None, known, seen, gt, truth, percent=percent.astype(np.int16))


def test_counts_with_more_bands_than_bits_of_an_integer():
    """Past 62 bands the cells' band patterns are found row by row: the same counts."""
    rng = np.random.default_rng(70)
    layers = rng.random((3, 300)) < 0.5
    bands = rng.random((70, 300)) < 0.2
    totals, per_band = CellCounter(3, bands).counts(pack(layers))
    np.testing.assert_array_equal(per_band, (layers[:, None, :] & bands[None]).sum(axis=2))
    np.testing.assert_array_equal(totals, layers.sum(axis=1))
