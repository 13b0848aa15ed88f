"""Method-independent temporal fusion (bev_mapper_core/temporal.py): log-odds averaging of
frames aligned by ego motion, memory resets (stamp back, gap, pose jump, no pose), and settings."""

from __future__ import annotations

import numpy as np
import pytest

from bev_mapper_core.errors import ConfigError
from bev_mapper_core.geometry.grid import BevGrid
from bev_mapper_core.geometry.transforms import rpy_to_rot
from bev_mapper_core.mapper import BevPrediction
from bev_mapper_core.temporal import TemporalConfig, TemporalFusion

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


def test_known_cells_are_the_current_frames_and_object_layers_are_not_fused_by_default():
    def two(p1, p2, known2, **cfg):
        fusion = TemporalFusion(GRID, TemporalConfig(window=3, **cfg))
        fusion.update(BevPrediction(("drivable", "vehicle"), np.stack([p1, p1]).astype(np.float32),
                                    np.ones(GRID.shape, bool)), 0, pose())
        return fusion.update(BevPrediction(("drivable", "vehicle"), np.stack([p2, p2]).astype(np.float32), known2),
                             S // 10, pose()).prediction

    hidden = np.ones(GRID.shape, bool)
    hidden[5:8, 5:8] = False
    out = two(np.full(GRID.shape, 0.8), np.full(GRID.shape, 0.1), hidden)
    np.testing.assert_array_equal(out.known, hidden)  # hidden now stays unknown
    assert out.probs[0, 6, 6] == pytest.approx(0.1, abs=1e-6)  # (the method's own value, untouched)
    assert 0.1 < out.probs[0, 0, 0] < 0.8  # the flat layer: both frames
    assert out.probs[1, 0, 0] == pytest.approx(0.1, abs=1e-6)  # vehicles: this frame only
    both = two(np.full(GRID.shape, 0.8), np.full(GRID.shape, 0.1), hidden, layers="all")
    assert both.probs[1, 0, 0] == pytest.approx(both.probs[0, 0, 0], abs=1e-6)  # fused like the flat one


@pytest.mark.parametrize("stamp, where, reason", [
    (S // 20, pose(x=0.2), "went back"),          # a bag loop: earlier than the last frame
    (2 * S, pose(x=0.2), "since the previous frame"),
    (S // 5, pose(x=40.0), "jumped"),
    (S // 5, None, "no ego pose"),
    (S // 5, np.full((4, 4), np.nan), "not a finite rigid"),
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
    for bad in ({"window": 0}, {"window": 2.0}, {"max_gap_s": 0}, {"max_jump_m": float("nan")}, {"layers": "some"}):
        with pytest.raises(ConfigError):
            TemporalConfig(**bad)
    with pytest.raises(ConfigError, match="not on the grid"):
        TemporalFusion(GRID, TemporalConfig(window=2)).update(
            BevPrediction(("drivable",), np.zeros((1, 3, 3), np.float32), np.ones((3, 3), bool)), 0, pose())


@pytest.mark.slow
def test_replay_fuses_over_the_bags_odometry_exactly_as_the_core(tmp_path):
    """``bev-bag replay --temporal-window 2``: every frame after the first is fused with the one
    before, aligned by the bag's /odom; the output grids equal the core's fusion of the core
    mapper's maps, and the default (window 1) leaves them the method's own."""
    from bag_helpers import replay_ipm, synth_small

    from bags.io.reader import BagReader
    from bags.replay import BAG_DIR, METRICS_FILE
    from bev_mapper_core.mapper import MapperConfig, create_mapper

    bag = synth_small(tmp_path / "bag", frames=4)
    assert replay_ipm(bag, tmp_path / "fused", "--temporal-window", "2", "--no-pictures", "--no-report") == 0
    assert replay_ipm(bag, tmp_path / "alone", "--no-pictures", "--no-report") == 0
    import json

    m = json.loads((tmp_path / "fused" / METRICS_FILE).read_text())
    assert m["temporal"] == {"window": 2, "fused_frames": 7, "resets": 0, "frames_without_pose": 0}
    with BagReader(bag) as r:
        grid = r.grid()
        mapper = create_mapper(r.rig(), grid, MapperConfig(method="ipm"))
        fusion = TemporalFusion(grid, TemporalConfig(window=2))
        want, alone = {}, {}
        for f in r.frames(rgb=False):
            pred = mapper.map(f.labels)
            alone[f.stamp_ns] = grid.to_occupancy(pred.layer("lane_divider"), pred.known)
            fused = fusion.update(pred, f.stamp_ns, f.odom.world_from_ego).prediction
            want[f.stamp_ns] = grid.to_occupancy(fused.layer("lane_divider"), fused.known)

    def grids(out):
        with BagReader(out / BAG_DIR) as r:
            return {m.msg.header.stamp.sec * 1_000_000_000 + m.msg.header.stamp.nanosec: np.asarray(m.msg.data)
                    for m in r.messages(["/bev/lane_divider"])}

    got, got_alone = grids(tmp_path / "fused"), grids(tmp_path / "alone")
    assert sorted(got) == sorted(want) and len(got) == 4
    for stamp in want:
        np.testing.assert_array_equal(got[stamp], want[stamp])
        np.testing.assert_array_equal(got_alone[stamp], alone[stamp])
    assert any((got[s] != got_alone[s]).any() for s in list(want)[1:])  # fusion changed something


def test_eval_fuses_each_drive_over_its_poses(tmp_path):
    """``evaluate_mapper(..., temporal=TemporalConfig(window=2))`` (``bev-train eval
    --temporal-window 2``) scores exactly the fusion of the mapper's maps over each drive's frames
    in order, the memory dropped between drives."""
    from bev_mapper_core.geometry.grid import grid_preset
    from bev_mapper_core.geometry.rig import preset_rig
    from bev_mapper_core.mapper import MapperConfig, create_mapper
    from bev_mapper_core.metrics import MetricAccumulator, scope_masks
    from bev_mapper_core.training.evaluate import evaluate_mapper, held_out_frames

    classes = ("drivable", "lane_divider", "sidewalk")
    rig, grid = preset_rig("front1"), grid_preset("ahead")
    fs = held_out_frames(rig, grid, classes, (950_000_013, 950_000_014), frames=3, cache=str(tmp_path))
    mapper = create_mapper(rig, grid, MapperConfig(method="ipm", classes=classes))
    res = evaluate_mapper(mapper, fs, grid, temporal=TemporalConfig(window=2))
    acc, fusion = MetricAccumulator(grid, classes), TemporalFusion(grid, TemporalConfig(window=2))
    fused = 0
    for i in range(len(fs)):
        if i % 3 == 0:
            fusion.reset()
        out = fusion.update(mapper.map({"front": fs.labels[i, 0]}), int(fs.stamps[i]), fs.poses[i])
        fused += out.frames > 1
        pred = out.prediction
        acc.update(pred.probs, fs.target[i], scope_masks(classes, fs.mask[i], fs.ground_mask[i], "visible"), pred.known)
    assert fused == 4  # frames 1, 2 of each drive
    assert res["miou"] == pytest.approx(acc.result()["miou"], abs=1e-12)
    assert res["miou"] != evaluate_mapper(mapper, fs, grid)["miou"]
