"""Method-independent temporal fusion (bev_mapper_core/temporal.py): log-odds averaging of
frames aligned by ego motion, memory resets (stamp back, gap, pose jump, no pose), and settings."""

from __future__ import annotations

import numpy as np
import pytest

from bev_mapper_core.errors import ConfigError
from bev_mapper_core.grid import BevGrid
from bev_mapper_core.mapper import BevPrediction
from bev_mapper_core.temporal import TemporalConfig, TemporalFusion
from bev_mapper_core.transforms import rpy_to_rot

GRID = BevGrid(-10.0, 10.0, -5.0, 5.0, 0.5)  # 40 x 20 cells
S = 1_000_000_000  # ns per s


def pose(x=0.0, y=0.0, yaw=0.0) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = rpy_to_rot(0.0, 0.0, yaw)
    T[:3, 3] = (x, y, 0.0)
    return T


def pred(p: np.ndarray, known: np.ndarray | None = None) -> BevPrediction:
    return BevPrediction(("drivable",), p[None].astype(np.float32),
                         np.ones(GRID.shape, bool) if known is None else known)


def test_static_evidence_is_averaged_in_log_odds_after_undoing_the_ego_motion():
    fusion = TemporalFusion(GRID, TemporalConfig(window=2))
    first = np.full(GRID.shape, 0.5)
    first[10, 20] = 0.9  # a cell seen at 0.9 from the first pose
    r1 = fusion.update(pred(first), 0, pose())
    assert r1.frames == 1 and r1.note == ""
    # one cell (0.5 m) forward: the same world cell is now column 19; this frame says 0.6 there
    second = np.full(GRID.shape, 0.5)
    second[10, 19] = 0.6
    second[:, -1] = 0.7
    r2 = fusion.update(pred(second), S // 10, pose(x=0.5))
    assert r2.frames == 2
    logit = lambda q: np.log(q / (1 - q))  # noqa: E731
    want = 1 / (1 + np.exp(-(logit(0.9) + logit(0.6)) / 2))
    assert r2.prediction.probs[0, 10, 19] == pytest.approx(want, abs=1e-4)
    # the column the car drove into is known from this frame alone
    np.testing.assert_allclose(r2.prediction.probs[0, :, -1], 0.7, atol=1e-4)
    assert r2.prediction.probs[0, 3, -2] == pytest.approx(0.5, abs=1e-4)  # both frames: 0.5 and 0.5


def test_hidden_now_but_seen_before_stays_known_and_unknown_evidence_is_ignored():
    fusion = TemporalFusion(GRID, TemporalConfig(window=3))
    p = np.full(GRID.shape, 0.8)
    fusion.update(pred(p), 0, pose())
    hidden = np.ones(GRID.shape, bool)
    hidden[5:8, 5:8] = False
    r = fusion.update(pred(np.full(GRID.shape, 0.1), hidden), S // 10, pose())
    assert r.prediction.known.all()  # the hidden block keeps the first frame's evidence
    assert r.prediction.probs[0, 6, 6] == pytest.approx(0.8, abs=1e-4)
    # and a cell both frames know averages the two
    assert 0.1 < r.prediction.probs[0, 0, 0] < 0.8
    fresh = TemporalFusion(GRID, TemporalConfig(window=3))
    r = fresh.update(pred(np.full(GRID.shape, 0.1), hidden), 0, pose())
    assert not r.prediction.known[6, 6]  # nothing to remember: unknown stays unknown


@pytest.mark.parametrize("stamp, where, reason", [
    (S // 20, pose(x=0.2), "went back"),          # a bag loop: earlier than the last frame
    (2 * S, pose(x=0.2), "since the previous frame"),
    (S // 5, pose(x=40.0), "jumped"),
    (S // 5, None, "no ego pose"),
])
def test_memory_drops_on_a_loop_a_gap_a_pose_jump_or_no_pose(stamp, where, reason):
    fusion = TemporalFusion(GRID, TemporalConfig(window=2, max_gap_s=0.5, max_jump_m=5.0))
    fusion.update(pred(np.full(GRID.shape, 0.9)), S // 10, pose())
    r = fusion.update(pred(np.full(GRID.shape, 0.2)), stamp, where)
    assert reason in r.note and r.frames == 1
    np.testing.assert_allclose(r.prediction.probs, 0.2, atol=1e-6)  # the frame alone


def test_window_one_is_the_identity_and_bad_settings_are_refused():
    fusion = TemporalFusion(GRID)
    p = pred(np.random.default_rng(0).random(GRID.shape))
    for i in range(3):
        r = fusion.update(p, i * S // 10, pose(x=0.1 * i))
        assert r.prediction is p and r.frames == 1
    for bad in ({"window": 0}, {"window": 2.0}, {"max_gap_s": 0}, {"max_jump_m": float("nan")}):
        with pytest.raises(ConfigError):
            TemporalConfig(**bad)
    with pytest.raises(ConfigError, match="not on the grid"):
        TemporalFusion(GRID, TemporalConfig(window=2)).update(
            BevPrediction(("drivable",), np.zeros((1, 3, 3), np.float32), np.ones((3, 3), bool)), 0, pose())
