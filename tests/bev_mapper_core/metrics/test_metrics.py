"""Tests of bev_mapper_core.metrics against hand-computed values."""

import json
import math

import numpy as np
import pytest

from bev_mapper_core.errors import ConfigError, InputError
from bev_mapper_core.geometry.grid import BevGrid
from bev_mapper_core.metrics import MetricAccumulator, chamfer, format_table, iou, mean_iou

# 10 x 10 cells at 0.5 m; x, y in [0, 5) m.
SMALL = BevGrid(x_min=0.0, x_max=5.0, y_min=0.0, y_max=5.0, resolution=0.5)


def layers(C, H=10, W=10, cells=None):
    """(C, H, W) bool stack with True at {class: [(row, col), ...]}."""
    out = np.zeros((C, H, W), dtype=bool)
    for c, rc in (cells or {}).items():
        for r, col in rc:
            out[c, r, col] = True
    return out


def probs_of(pred_bool):
    return np.where(pred_bool, 0.9, 0.1).astype(np.float32)


# --------------------------------------------------------------------------------- IoU
def test_iou_hand_values():
    # class 0: pred 3 cells, gt 2 cells, 1 shared -> I=1, U=4 -> 0.25
    # class 1: pred == gt on 2 cells -> 1.0
    pred = layers(2, cells={0: [(0, 0), (0, 1), (0, 2)], 1: [(5, 5), (5, 6)]})
    gt = layers(2, cells={0: [(0, 2), (3, 3)], 1: [(5, 5), (5, 6)]})
    np.testing.assert_allclose(iou(pred, gt), [0.25, 1.0])
    assert mean_iou(iou(pred, gt)) == pytest.approx(0.625)


def test_iou_mask_restricts_scoring():
    pred = layers(1, cells={0: [(0, 0), (0, 1), (9, 9)]})
    gt = layers(1, cells={0: [(0, 0), (8, 8)]})
    assert iou(pred, gt)[0] == pytest.approx(1 / 4)
    mask = np.zeros((10, 10), dtype=bool)
    mask[:5, :5] = True  # removes (9, 9) and (8, 8) -> I=1, U=2
    assert iou(pred, gt, mask)[0] == pytest.approx(0.5)


def test_iou_empty_union_is_nan_and_excluded_from_miou():
    pred = layers(3, cells={0: [(1, 1)], 2: [(2, 2)]})
    gt = layers(3, cells={0: [(1, 1)], 2: [(2, 3)]})
    ious = iou(pred, gt)
    assert ious[0] == 1.0 and math.isnan(ious[1]) and ious[2] == 0.0
    assert mean_iou(ious) == pytest.approx(0.5)
    assert math.isnan(mean_iou([np.nan, np.nan]))


def test_iou_input_errors():
    good = layers(2)
    with pytest.raises(InputError):
        iou(good.astype(np.uint8), good)
    with pytest.raises(InputError):
        iou(good, layers(3))
    with pytest.raises(InputError):
        iou(good[0], good[0])
    with pytest.raises(InputError):
        iou(good, good, mask=np.ones((10, 9), bool))
    with pytest.raises(InputError):
        iou(good, good, mask=np.ones((10, 10), np.uint8))


# --------------------------------------------------------------------------------- Chamfer
def test_chamfer_single_pixels_three_cells_apart():
    pred = np.zeros((10, 10), bool)
    gt = np.zeros((10, 10), bool)
    gt[4, 2] = True
    pred[4, 5] = True  # 3 cells along x at 0.5 m -> 1.5 m
    cd_p, cd_l, cd = chamfer(pred, gt, 0.5)
    assert (cd_p, cd_l, cd) == pytest.approx((1.5, 1.5, 1.5))
    # diagonal: 3 x 4 cells -> 5 cells -> 2.5 m (exact L2, not a chamfer-mask approximation)
    pred2 = np.zeros((10, 10), bool)
    pred2[7, 6] = True
    gt2 = np.zeros((10, 10), bool)
    gt2[3, 3] = True
    assert chamfer(pred2, gt2, 0.5) == pytest.approx((2.5, 2.5, 2.5))


def test_chamfer_asymmetric_extra_far_prediction():
    gt = np.zeros((10, 10), bool)
    gt[0, 0] = True
    pred = gt.copy()
    pred[0, 4] = True  # extra prediction 4 cells = 2 m away
    cd_p, cd_l, cd = chamfer(pred, gt, 0.5)
    # CD_p = (0 + 2) / 2 = 1; CD_L = 0 (the gt cell is hit); CD = 0.5
    assert cd_p == pytest.approx(1.0)
    assert cd_l == pytest.approx(0.0)
    assert cd == pytest.approx(0.5)
    assert cd_p > cd_l


def test_chamfer_clipping():
    H, W = 4, 30
    gt = np.zeros((H, W), bool)
    gt[0, 0] = True
    pred = gt.copy()
    pred[0, 20] = True  # 20 cells = 10 m away, clipped to 5 m
    cd_p, cd_l, _ = chamfer(pred, gt, 0.5, clip=5.0)
    assert cd_p == pytest.approx((0 + 5.0) / 2)
    assert cd_l == pytest.approx(0.0)
    cd_p, _, _ = chamfer(pred, gt, 0.5, clip=20.0)
    assert cd_p == pytest.approx((0 + 10.0) / 2)


def test_chamfer_empty_sides():
    gt = np.zeros((10, 10), bool)
    gt[2, 2] = gt[2, 3] = True
    empty = np.zeros((10, 10), bool)
    assert chamfer(empty, gt, 0.5, clip=5.0) == pytest.approx((5.0, 5.0, 5.0))
    assert chamfer(gt, empty, 0.5, clip=3.0) == pytest.approx((3.0, 3.0, 3.0))
    assert all(math.isnan(v) for v in chamfer(empty, empty, 0.5))
    # mask removes the only gt cell far from the prediction
    pred = np.zeros((10, 10), bool)
    pred[2, 2] = True
    gt2 = pred.copy()
    gt2[9, 9] = True
    mask = np.ones((10, 10), bool)
    mask[9, 9] = False
    assert chamfer(pred, gt2, 0.5, mask=mask) == pytest.approx((0.0, 0.0, 0.0))


# ----------------------------------------------------------------------------- accumulator
def test_dataset_level_iou_differs_from_mean_of_frames():
    acc = MetricAccumulator(SMALL, ["a"], range_bands=())
    # frame 1: I=1, U=1 -> 1.0
    f1 = acc.update(probs_of(layers(1, cells={0: [(0, 0)]})), layers(1, cells={0: [(0, 0)]}))
    # frame 2: pred 1 cell, gt 3 cells incl. it -> I=1, U=3 -> 1/3
    f2 = acc.update(
        probs_of(layers(1, cells={0: [(1, 1)]})), layers(1, cells={0: [(1, 1), (1, 2), (1, 3)]})
    )
    assert f1[0] == pytest.approx(1.0) and f2[0] == pytest.approx(1 / 3)
    res = acc.result()
    assert res["frames"] == 2
    # dataset level: (1 + 1) / (1 + 3) = 0.5, not mean of frames 2/3
    assert res["classes"]["a"]["iou"] == pytest.approx(0.5)
    assert res["miou"] == pytest.approx(0.5)
    assert res["classes"]["a"]["iou"] != pytest.approx((f1[0] + f2[0]) / 2)


def test_accumulator_visibility_and_known():
    gt = layers(1, cells={0: [(0, 0), (0, 1), (9, 9)]})
    pred = layers(1, cells={0: [(0, 0), (0, 1), (5, 5)]})
    vis = np.zeros((10, 10), bool)
    vis[:6, :6] = True  # hides gt (9, 9)
    known = np.ones((10, 10), bool)
    known[0, 1] = False  # prediction there counts as negative
    acc = MetricAccumulator(SMALL, ["a"], range_bands=())
    acc.update(probs_of(pred), gt, visibility=vis, known=known)
    # scored: pred {(0,0), (5,5)}, gt {(0,0), (0,1)} -> I=1, U=3; TP=1, FP=1
    r = acc.result()["classes"]["a"]
    assert r["iou"] == pytest.approx(1 / 3)
    assert r["precision"] == pytest.approx(0.5)
    # use_visibility=False: gt (9, 9) is scored too -> I=1, U=4
    acc2 = MetricAccumulator(SMALL, ["a"], range_bands=(), use_visibility=False)
    acc2.update(probs_of(pred), gt, visibility=vis, known=known)
    assert acc2.result()["classes"]["a"]["iou"] == pytest.approx(1 / 4)


def test_accumulator_threshold_is_inclusive():
    acc = MetricAccumulator(SMALL, ["a"], range_bands=(), threshold=0.5)
    probs = np.zeros((1, 10, 10), np.float64)
    probs[0, 3, 3] = 0.5
    probs[0, 3, 4] = 0.49
    acc.update(probs, layers(1, cells={0: [(3, 3), (3, 4)]}))
    assert acc.result()["classes"]["a"]["iou"] == pytest.approx(0.5)


def test_range_band_hit_at_5m_counts_only_in_0_10():
    # 0.5 m cells whose centres sit on multiples of 0.5 m: cell centre (5, 0) exists
    grid = BevGrid(x_min=-30.25, x_max=30.25, y_min=-15.25, y_max=15.25, resolution=0.5)
    row, col = grid.metric_to_cell(5.0, 0.0)
    assert grid.ranges[row, col] == pytest.approx(5.0)
    gt = np.zeros((1,) + grid.shape, bool)
    gt[0, row, col] = True
    acc = MetricAccumulator(grid, ["a"])
    assert acc.band_labels == ("0-10", "10-20", "20-30", "30-40")
    acc.update(probs_of(gt), gt)
    res = acc.result()
    assert res["iou_by_range"]["0-10"]["a"] == pytest.approx(1.0)
    assert res["iou_by_range"]["0-10"]["miou"] == pytest.approx(1.0)
    for band in ("10-20", "20-30", "30-40"):
        assert res["iou_by_range"][band]["a"] is None
        assert res["iou_by_range"][band]["miou"] is None


def test_range_bands_half_open():
    # a miss at exactly 10 m belongs to [10, 20), not [0, 10)
    grid = BevGrid(x_min=-30.25, x_max=30.25, y_min=-15.25, y_max=15.25, resolution=0.5)
    r5, c5 = grid.metric_to_cell(5.0, 0.0)
    r10, c10 = grid.metric_to_cell(10.0, 0.0)
    gt = np.zeros((1,) + grid.shape, bool)
    gt[0, r5, c5] = gt[0, r10, c10] = True
    pred = np.zeros_like(gt)
    pred[0, r5, c5] = True
    acc = MetricAccumulator(grid, ["a"], range_bands=((0, 10), (10, 20)))
    acc.update(probs_of(pred), gt)
    res = acc.result()
    assert res["iou_by_range"]["0-10"]["a"] == pytest.approx(1.0)
    assert res["iou_by_range"]["10-20"]["a"] == pytest.approx(0.0)
    assert res["classes"]["a"]["iou"] == pytest.approx(0.5)


def test_counts_per_band_and_class_equal_a_loop_over_cells():
    """Overlapping bands, cells beyond every band, several classes and frames: the counts kept
    per class and band are those of a plain loop over the cells."""
    grid = BevGrid(x_min=-12.0, x_max=12.0, y_min=-8.0, y_max=8.0, resolution=0.5)
    bands = ((0, 6), (4, 9), (9, math.inf))
    rng = np.random.default_rng(28)
    acc = MetricAccumulator(grid, ["a", "b", "c"], range_bands=((0, 6), (4, 9), (20, 30)))
    acc2 = MetricAccumulator(grid, ["a", "b", "c"], range_bands=bands)
    inter = np.zeros((3, 3), np.int64)
    union = np.zeros((3, 3), np.int64)
    n_inter = np.zeros(3, np.int64)
    for _ in range(3):
        pred = rng.random((3,) + grid.shape) < 0.4
        gt = rng.random((3,) + grid.shape) < 0.3
        acc.update(probs_of(pred), gt)
        acc2.update(probs_of(pred), gt)
        for c in range(3):
            n_inter[c] += sum(pred[c][i] and gt[c][i] for i in np.ndindex(grid.shape))
            for b, (lo, hi) in enumerate(bands):
                inside = (grid.ranges >= lo) & (grid.ranges < hi)
                for i in zip(*np.nonzero(inside)):
                    inter[c, b] += pred[c][i] and gt[c][i]
                    union[c, b] += pred[c][i] or gt[c][i]
    np.testing.assert_array_equal(acc2._band_inter, inter)
    np.testing.assert_array_equal(acc2._band_union, union)
    np.testing.assert_array_equal(acc2._inter, n_inter)
    assert (acc._band_union[:, 2] == 0).all() and (acc._band_union[:, :2] == union[:, :2]).all()


def test_precision_and_map_hand_case():
    # class a: 4 predicted, 3 correct -> 0.75; class b: 2 predicted, 1 correct -> 0.5
    # class c: never predicted -> precision undefined, excluded from mAP
    pred = layers(3, cells={0: [(0, 0), (0, 1), (0, 2), (0, 3)], 1: [(5, 5), (5, 6)]})
    gt = layers(3, cells={0: [(0, 0), (0, 1), (0, 2)], 1: [(5, 5)], 2: [(7, 7)]})
    acc = MetricAccumulator(SMALL, ["a", "b", "c"], range_bands=())
    acc.update(probs_of(pred), gt)
    res = acc.result()
    assert res["classes"]["a"]["precision"] == pytest.approx(0.75)
    assert res["classes"]["b"]["precision"] == pytest.approx(0.5)
    assert res["classes"]["c"]["precision"] is None
    assert res["map"] == pytest.approx(0.625)
    # precision accumulates counts: a second frame for "a" with 1 predicted, 0 correct
    acc.update(probs_of(layers(3, cells={0: [(9, 9)]})), layers(3))
    assert acc.result()["classes"]["a"]["precision"] == pytest.approx(3 / 5)


def test_accumulator_chamfer_frame_average_and_skips_empty_frames():
    acc = MetricAccumulator(SMALL, ["a"], range_bands=(), clip=5.0)
    # frame 1: single pixels 3 cells apart -> 1.5 m both ways
    acc.update(probs_of(layers(1, cells={0: [(4, 5)]})), layers(1, cells={0: [(4, 2)]}))
    # frame 2: class absent in both -> does not contribute
    acc.update(probs_of(layers(1)), layers(1))
    # frame 3: empty prediction -> charged clip = 5 both sides
    acc.update(probs_of(layers(1)), layers(1, cells={0: [(1, 1), (1, 2)]}))
    r = acc.result()["classes"]["a"]
    assert r["cd_p"] == pytest.approx((1.5 + 5.0) / 2)
    assert r["cd_l"] == pytest.approx((1.5 + 5.0) / 2)
    assert r["cd"] == pytest.approx(3.25)


def test_accumulator_chamfer_pixel_reduction():
    acc = MetricAccumulator(SMALL, ["a"], range_bands=(), clip=5.0, chamfer_reduction="pixel")
    # frame 1: gt {(0,0)}, pred {(0,0), (0,4)} -> pred-side distances [0, 2], gt-side [0]
    acc.update(probs_of(layers(1, cells={0: [(0, 0), (0, 4)]})), layers(1, cells={0: [(0, 0)]}))
    # frame 2: empty prediction, 2 gt cells -> gt side gets 2 x 5 m, pred side nothing
    acc.update(probs_of(layers(1)), layers(1, cells={0: [(1, 1), (1, 2)]}))
    r = acc.result()["classes"]["a"]
    assert r["cd_p"] == pytest.approx((0 + 2.0) / 2)
    assert r["cd_l"] == pytest.approx((0 + 5.0 + 5.0) / 3)
    assert r["cd"] == pytest.approx((1.0 + 10 / 3) / 2)


def test_result_is_strict_json_and_table_renders():
    acc = MetricAccumulator(SMALL, ["drivable", "vehicle"])
    acc.update(probs_of(layers(2, cells={0: [(0, 0)]})), layers(2, cells={0: [(0, 0)]}))
    res = acc.result()
    text = json.dumps(res, allow_nan=False)  # None for undefined values, no NaN
    assert json.loads(text) == res
    assert set(res) == {"frames", "classes", "miou", "map", "iou_by_range"}
    assert set(res["classes"]["vehicle"]) == {"iou", "cd_p", "cd_l", "cd", "precision"}
    assert res["classes"]["vehicle"]["iou"] is None
    table = format_table(res)
    assert "drivable" in table and "vehicle" in table and "100.0" in table and "0-10" in table
    # empty accumulator is still valid JSON
    json.dumps(MetricAccumulator(SMALL, ["a"]).result(), allow_nan=False)


def test_accumulator_input_errors():
    acc = MetricAccumulator(SMALL, ["a", "b"])
    good_p = np.zeros((2, 10, 10), np.float32)
    good_g = np.zeros((2, 10, 10), bool)
    with pytest.raises(InputError):
        acc.update(good_p.astype(np.uint8), good_g)
    with pytest.raises(InputError):
        acc.update(good_p, good_g.astype(np.uint8))
    with pytest.raises(InputError):
        acc.update(good_p[:1], good_g)
    with pytest.raises(InputError):
        acc.update(good_p, good_g, visibility=np.ones((10, 10), np.float32))
    with pytest.raises(InputError):
        acc.update(good_p, good_g, known=np.ones((5, 5), bool))
    bad = good_p.copy()
    bad[0, 0, 0] = np.nan
    with pytest.raises(InputError):
        acc.update(bad, good_g)
    known = np.ones((10, 10), bool)
    known[0, 0] = False
    acc.update(bad, good_g, known=known)  # NaN in an unknown cell is fine
    with pytest.raises(ConfigError):
        MetricAccumulator(SMALL, ["a", "a"])
    with pytest.raises(ConfigError):
        MetricAccumulator(SMALL, ["a"], range_bands=((10, 5),))
    with pytest.raises(ConfigError):
        MetricAccumulator(SMALL, ["a"], chamfer_reduction="mean")
