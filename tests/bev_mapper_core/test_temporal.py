"""Method-independent temporal fusion (bev_mapper_core/temporal.py): log-odds averaging of
frames aligned by ego motion, memory resets (stamp back, gap, pose jump, no pose), and settings."""

from __future__ import annotations

import numpy as np
import pytest

from bev_mapper_core.errors import ConfigError
from bev_mapper_core.geometry.grid import BevGrid
from bev_mapper_core.geometry.transforms import rpy_to_rot
from bev_mapper_core.mapper import BevPrediction
from bev_mapper_core.temporal import ODOMETRY_PROBLEMS, OdometryCheck, TemporalConfig, TemporalFusion

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
    assert m["temporal"] == {"window": 2, "fused_frames": 7, "resets": 0, "frames_without_pose": 0,
                             "odometry_problems": dict.fromkeys(ODOMETRY_PROBLEMS, 0)}
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


# ------------------------------------------------------------------ odometry abuse (issue #29)
DT = S // 10  # 10 Hz


def _drive(check: OdometryCheck, n: int, start: int = 0, speed: float = 10.0, **kw):
    """Feed ``n`` frames of a 10 m/s drive; the verdicts."""
    return [check.check(start + k * DT, pose(speed * (start + k * DT) / S), start + k * DT, ("odom", "base_link"),
                        **kw) for k in range(n)]


def test_odometry_check_passes_a_plain_drive_and_counts_nothing():
    check = OdometryCheck()
    verdicts = _drive(check, 30)
    assert all(v.pose is not None and not v.reset and not v.problem for v in verdicts)
    assert check.counts == dict.fromkeys(ODOMETRY_PROBLEMS, 0) and check.resets == 0


@pytest.mark.parametrize("case, kind, pose_used", [
    ("nan", "bad_pose", False),
    ("not_rigid", "bad_pose", False),  # a non-unit quaternion's matrix
    ("none", "no_pose", False),
    ("spike_4m", "jump", True),  # under max_jump_m 5: a velocity change no vehicle makes
    ("km_jump", "jump", True),
    ("stamp_back", "stamp_back", False),
    ("duplicate_stamp", "duplicate_stamp", False),
    ("far_future", "far_stamp", False),
    ("frame_change", "frame_change", True),
])
def test_odometry_check_counts_each_abuse_and_asks_for_a_reset(case, kind, pose_used):
    check = OdometryCheck()
    _drive(check, 5)
    t = 5 * DT
    good = pose(10.0 * t / S)
    args = {"nan": (t, np.full((4, 4), np.nan), t), "not_rigid": (t, good * 1.3, t), "none": (t, None, None),
            "spike_4m": (t, pose(10.0 * t / S + 4.0), t), "km_jump": (t, pose(2000.0), t),
            "stamp_back": (t, good, t - 3 * DT), "duplicate_stamp": (t, good, 4 * DT),
            "far_future": (t, good, t + 3600 * S), "frame_change": (t, good, t)}[case]
    frames = ("map", "base_link") if case == "frame_change" else ("odom", "base_link")
    v = check.check(*args, frames)
    assert v.problem == kind and v.reset and v.note and check.counts[kind] == 1
    assert (v.pose is not None) == pose_used
    # the stream goes on: later plain frames pass again
    later = [check.check(t + k * DT, pose(10.0 * (t + k * DT) / S + (4.0 if case == "spike_4m" else 0.0)),
                         t + k * DT, ("map", "base_link") if case == "frame_change" else ("odom", "base_link"))
             for k in range(1, 6)]
    if case == "km_jump":  # the next frame jumps back: counted too, then clean
        later = later[1:]
    assert all(not lv.problem for lv in later), [lv.note for lv in later]


def test_odometry_check_counts_a_nan_covariance_and_uses_the_pose():
    check = OdometryCheck()
    cov = np.zeros(36)
    cov[7] = np.nan
    verdicts = _drive(check, 3, covariance=cov)
    assert check.counts["bad_covariance"] == 3 and all(v.pose is not None and not v.reset for v in verdicts)


def test_fused_maps_stay_finite_under_any_pose_stream():
    """Random abuse fed through check + fusion (as replay and the node do): every map finite."""
    rng = np.random.default_rng(0)
    check, fusion = OdometryCheck(), TemporalFusion(GRID, TemporalConfig(window=3))
    stamp = 0
    for _ in range(200):
        stamp += int(rng.choice([DT, 0, -DT, DT, DT, 10 * S]))
        roll = rng.random()
        T = pose(rng.normal() * (1e6 if roll < 0.1 else 1.0), rng.normal(), rng.normal())
        if roll > 0.9:
            T = np.full((4, 4), np.nan if roll > 0.95 else 1e308)
        v = check.check(stamp, T, stamp + int(rng.choice([0, 0, 0, -DT, 3600 * S])))
        if v.reset and v.pose is not None:
            fusion.reset()
        out = fusion.update(pred(rng.random(GRID.shape)), stamp, v.pose).prediction
        assert np.isfinite(out.probs).all() and out.probs.min() >= 0 and out.probs.max() <= 1
    assert sum(check.counts.values()) > 0


@pytest.mark.slow
@pytest.mark.parametrize("abuse", ["spike_4m", "frame_change", "duplicate_stamps", "nan_covariance"])
def test_replay_counts_odometry_abuse(tmp_path, abuse):
    """``bev-bag replay --temporal-window 3`` on a drive whose /odom is abused from frame 2 on:
    the problems are counted in ``metrics.json`` (``temporal.odometry_problems``), the memory
    reset is counted, the maps are finite and the replay completes (no data was lost)."""
    import dataclasses
    import json

    from bag_damage import make_base, rewrite
    from bag_helpers import replay_ipm

    from bags.io import topics as T
    from bags.replay import METRICS_FILE

    base = make_base(tmp_path / "base")

    def edit(t, ty, ns, msg, i):
        if t != T.ODOM or i < 2:
            return [(t, ns, msg)]
        if abuse == "spike_4m" and i == 4:
            p = msg.pose.pose
            p = dataclasses.replace(p, position=dataclasses.replace(p.position, x=p.position.x + 4.0))
            msg = dataclasses.replace(msg, pose=dataclasses.replace(msg.pose, pose=p))
        elif abuse == "frame_change" and i % 2 == 0:
            msg = dataclasses.replace(msg, header=dataclasses.replace(msg.header, frame_id="map"))
        elif abuse == "duplicate_stamps" and i % 2 == 1:  # this pose stamped as the previous one
            s = msg.header.stamp
            total = s.sec * S + s.nanosec - DT
            msg = dataclasses.replace(msg, header=dataclasses.replace(
                msg.header, stamp=dataclasses.replace(s, sec=total // S, nanosec=total % S)))
        elif abuse == "nan_covariance":
            cov = np.array(msg.pose.covariance, dtype=np.float64)
            cov[0] = np.nan
            msg = dataclasses.replace(msg, pose=dataclasses.replace(msg.pose, covariance=cov))
        return [(t, ns, msg)]

    (tmp_path / "w").mkdir()
    bag = rewrite(base, tmp_path / "w", edit)
    out = tmp_path / "out"
    rc = replay_ipm(bag, out, "--temporal-window", "3", "--no-pictures", "--no-report")
    m = json.loads((out / METRICS_FILE).read_text())
    problems = m["temporal"]["odometry_problems"]
    want = {"spike_4m": "jump", "frame_change": "frame_change", "duplicate_stamps": None,
            "nan_covariance": "bad_covariance"}[abuse]
    if want is not None:
        assert problems[want] >= 1, problems
        assert (m["temporal"]["resets"] >= 1) == (want != "bad_covariance"), m["temporal"]
    if abuse == "duplicate_stamps":  # a pose matched to the wrong frame is counted, not fused
        assert problems["duplicate_stamp"] + problems["stamp_back"] + problems["far_stamp"] + \
            m["temporal"]["frames_without_pose"] >= 1, m["temporal"]
    assert rc == 0 and m["complete"], m["damage"]
    assert np.isfinite(m["miou"])
