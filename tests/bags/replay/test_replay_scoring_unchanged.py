"""Issue #28: replay's faster scoring gives every output it gave before.

The reference is the straightforward scoring the replay did before #28 (``bench/replay_reference.py``,
also the reference of ``bench/bench_replay_rate.py``): the
Chamfer distances from one distance transform of the whole grid per class and side, the
calibration counts summed cell by cell, and each frame's IoU for the captions and the report
scored a second time by ``FrameScores.add``. The replay of a small drive with pictures must give
the same ``metrics.json`` (all but the timings), the same pictures and the same report.
"""

from __future__ import annotations

import json
import math
import sys
from pathlib import Path

import numpy as np
import pytest
from bag_helpers import replay_ipm, synth_small

import bev_mapper_core.metrics.whole_grid as whole_grid
from bags.replay import FRAMES_DIR, METRICS_FILE
from bev_mapper_core.metrics import functional
from bev_mapper_core.metrics._packed import pack

sys.path.insert(0, str(Path(__file__).resolve().parents[3] / "bench"))
from replay_reference import reference_chamfer_terms, reference_scoring  # noqa: E402 - bench/ is no package

pytest.importorskip("bev_mapper_core.synth")


def _outputs(out):
    metrics = json.loads((out / METRICS_FILE).read_text())
    metrics.pop("latency_ms")
    metrics.pop("score_process")
    metrics.pop("bag")
    pictures = {p.name: p.read_bytes() for p in sorted((out / FRAMES_DIR).glob("*.png"))}
    report = (out / "report.html").read_text().replace(str(out), "OUT")
    # everything from the mapping latency on is timing (its numbers and its chart)
    return metrics, pictures, report[:report.index("<h2>Mapping latency</h2>")]


def test_replay_outputs_equal_the_straightforward_scoring(tmp_path):
    bag = synth_small(tmp_path / "drive", frames=5, seed=28)
    assert replay_ipm(bag, tmp_path / "fast", "--frames-every", "2") == 0
    with reference_scoring():  # bench/replay_reference.py: the scoring as it was, swapped in
        assert replay_ipm(bag, tmp_path / "reference", "--frames-every", "2") == 0
    fast, ref = _outputs(tmp_path / "fast"), _outputs(tmp_path / "reference")
    assert fast[0]["frames_scored"] == 5 and fast[0]["classes"]["drivable"]["cd"] is not None
    assert fast[0] == ref[0]
    assert fast[1] == ref[1] and len(fast[1]) == 3
    assert "mIoU per frame" in fast[2] and fast[2] == ref[2]


@pytest.mark.parametrize("path", ["compiled", "numpy"])
def test_chamfer_distances_equal_the_whole_grid_transform(path, monkeypatch):
    """Random layers of every density, sizes and clips: the distances of the compiled kernel, and
    those the numpy path finds nearby, per tile and in boxes, are those of one transform of the
    whole grid, bit for bit."""
    if path == "numpy":
        monkeypatch.setattr(functional, "_compiled", None)
    rng = np.random.default_rng(28)
    checked = 0
    for trial in range(300):
        H, W = (int(v) for v in rng.integers(3, 260, 2))
        pred = rng.random((H, W)) < rng.random() * 0.3
        gt = rng.random((H, W)) < rng.random() ** 3 * 0.3
        if trial % 3 == 0:  # one cell
            gt[:] = False
            gt[rng.integers(H), rng.integers(W)] = True
        if trial % 5 == 0:  # one line
            gt[:] = False
            gt[rng.integers(H), : rng.integers(1, W + 1)] = True
        res = float(rng.choice([0.1, 0.15, 0.25, 0.5]))
        clip = float(rng.choice([0.3, 1.0, 2.5, 5.0, 20.0]))
        if trial % 7 == 0:  # a layer seen through a strided view
            pred = np.ascontiguousarray(np.repeat(pred, 2, axis=1))[:, ::2]
        if not gt.any() or not pred.any():
            continue
        for a, b in zip(functional._chamfer_terms(pred, gt, res, clip), reference_chamfer_terms(pred, gt, res, clip)):
            np.testing.assert_array_equal(a, b)
        checked += 1
    assert checked > 250


def test_the_compiled_chamfer_kernel_is_built():
    """``pip install -e .`` (scripts/setup_venv.sh) builds it; without it scoring is ~5x slower."""
    assert functional._compiled is not None, "bev_mapper_core/metrics/_chamfer.c was not built: pip install -e ."


def test_the_compiled_chamfer_kernel_refuses_mismatched_buffers():
    """Wrong sizes, bits or reaches are a ValueError, never a read or write outside a buffer."""
    kernel = functional._compiled
    if kernel is None:
        pytest.skip("not built")
    cells, out = np.zeros(12, np.uint8), np.empty(12)
    kernel.distances(cells, cells, 1, 3, 4, 5, 0.5, 2.0, out, out)  # the sizes that fit
    for args in [(cells[:11], cells, 1, 3, 4, 5, 0.5, 2.0, out, out),  # a layer too small
                 (cells, cells, 1, 3, 4, 5, 0.5, 2.0, out[:11], out),  # an output too small
                 (cells, cells, 0, 3, 4, 5, 0.5, 2.0, out, out),  # no bit
                 (cells, cells, 1, 3, 4, -1, 0.5, 2.0, out, out),  # a negative reach
                 (cells, cells, 1, 40000, 30000, 5, 0.5, 2.0, out, out)]:  # H + W past uint16
        with pytest.raises(ValueError):
            kernel.distances(*args)


def test_packed_chamfer_distances_equal_each_class_alone():
    """The kernel reads each class's bit of the packed layers in place (11 classes: two bytes a
    cell), an empty class and a class in one set only included."""
    rng = np.random.default_rng(30)
    C, H, W = 11, 37, 53
    pred = rng.random((C, H, W)) < rng.random((C, 1, 1)) * 0.2
    gt = rng.random((C, H, W)) < rng.random((C, 1, 1)) * 0.2
    pred[3], gt[3] = False, False
    gt[9] = False
    packed_pred, packed_gt = pack(pred), pack(gt)
    for c in range(C):
        got = functional._packed_chamfer_terms(packed_pred, packed_gt, c, (H, W), 0.25, 3.0)
        want = functional._numpy_terms(pred[c], gt[c], 0.25, 3.0)
        for a, b in zip(got, want):
            np.testing.assert_array_equal(a, b)
    assert len(got[0]) == int(pred[10].sum())


def test_percent_calibration_counts_equal_the_per_cell_sums():
    rng = np.random.default_rng(29)
    values = np.arange(101, dtype=np.float32) / 100.0
    for _ in range(40):
        C, H, W = int(rng.integers(1, 8)), int(rng.integers(2, 90)), int(rng.integers(2, 90))
        percent = rng.integers(0, 101, (C, H, W)).astype(np.uint8)
        percent[rng.random((C, H, W)) < 0.3] = rng.choice([0, 100])
        probs = values[percent]
        truth, mask = rng.random((C, H, W)) < 0.4, rng.random((C, H, W)) < 0.7
        fast = whole_grid._percent_calibration_counts(percent, values, truth, mask, 10)
        slow = whole_grid._calibration_counts(probs, truth, mask, 10)
        for a, b in zip(fast, slow):
            assert a.dtype == b.dtype
            np.testing.assert_array_equal(a, b)
    assert math.isclose(float(values[57]), 0.57, rel_tol=1e-6)
