"""The node's temporal fusion over real DDS: odometry on /odom aligns the frames, and the
published grids equal the core's fusion (bev_mapper_core.temporal) of the core mapper's maps;
abused odometry is counted and every frame still mapped (issue #29); FocusBEV's memory bank."""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
from model_helpers import memory_focusbev
from nav_msgs.msg import Odometry
from ros_helpers import REPO, loaded_torch, rclpy, spin_until, start_process, stop_process
from test_node import Driver, node_view_of_rig

from bev_mapper_core.geometry.grid import grid_preset
from bev_mapper_core.geometry.rig import preset_rig
from bev_mapper_core.geometry.transforms import rot_to_quat
from bev_mapper_core.mapper import MapperConfig, create_mapper
from bev_mapper_core.methods.ipm.mapper import IpmMapper
from bev_mapper_core.synth import SynthConfig, generate_drive
from bev_mapper_core.temporal import TemporalConfig, TemporalFusion

PARAMS = REPO / "config" / "front1.yaml"
CLASSES = ("drivable", "lane_divider", "vehicle")


def odometry(stamp_ns: int, T: np.ndarray) -> Odometry:
    msg = Odometry()
    msg.header.stamp.sec, msg.header.stamp.nanosec = divmod(int(stamp_ns), 1_000_000_000)
    msg.header.frame_id, msg.child_frame_id = "odom", "base_link"
    p, q = msg.pose.pose.position, msg.pose.pose.orientation
    p.x, p.y, p.z = (float(v) for v in T[:3, 3])
    q.x, q.y, q.z, q.w = (float(v) for v in rot_to_quat(T[:3, :3]))
    return msg


S = 1_000_000_000
#: clean frames first (their grids are compared with the core's fusion), then the abused ones
CLEAN, ABUSED = 4, 12


def _abused(k: int, f) -> list:
    """The odometry messages sent before abused frame ``k`` (the abuse of that frame)."""
    T = f.world_from_ego.copy()
    good = odometry(f.stamp_ns, T)
    if k == 2:  # NaN position: refused by the adapter (bad_input), frame mapped without pose
        msg = odometry(f.stamp_ns, T)
        msg.pose.pose.position.x = math.nan
        return [msg]
    if k == 3:  # a non-unit quaternion: refused too
        msg = odometry(f.stamp_ns, T)
        msg.pose.pose.orientation.w *= 1.7
        return [msg]
    if k == 5:  # a 4 m spike (under the 5 m reset): a jump no vehicle makes
        spike = T.copy()
        spike[0, 3] += 4.0
        return [odometry(f.stamp_ns, spike)]
    if k == 6:  # ... and back; plus a NaN covariance on a good pose
        good.pose.covariance[0] = math.nan
        return [good]
    if k == 7:  # a kilometre jump
        far = T.copy()
        far[0, 3] += 1000.0
        return [odometry(f.stamp_ns, far)]
    if k == 9:  # time going back, then the same stamp twice
        return [odometry(f.stamp_ns - 5 * S, T), good, odometry(f.stamp_ns, T)]
    if k == 10:  # a pose an hour in the future, then the right one
        return [odometry(f.stamp_ns + 3600 * S, T), good]
    return [good]


def test_node_fuses_frames_by_odometry_exactly_as_the_core_and_counts_abused_odometry(tmp_path, ros_domain):
    """One IPM node with temporal fusion, odometry on /odom. First 4 clean frames: the grids equal
    the core's fusion of the core mapper's maps. Then 12 frames under abused odometry (issue #29):
    NaN poses, a non-unit quaternion, a 4 m spike, a kilometre jump, a stamp going back, a
    duplicated stamp, a NaN covariance and a pose far in the future. Every frame is still mapped
    (finite grids, none withheld waiting for rejected odometry), each abuse is counted in
    ``/diagnostics`` (``odometry_<kind>``, ``bad_input``) with the memory resets
    (``temporal_resets``), and the node keeps running."""
    grid, rig = grid_preset("ahead"), preset_rig("front1")
    g = grid.to_dict()
    log = tmp_path / "node.log"
    proc = start_process(["bev_mapper_ros.mapper_node", "--ros-args", "--params-file", str(PARAMS),
                          "-p", "method:=ipm", "-p", "temporal_window:=2", "-p", "threads:=1",
                          "-p", "diagnostics_period_s:=0.2",
                          "-p", f"classes:={list(CLASSES)}".replace("'", '"'),
                          *[a for k, v in g.items() for a in ("-p", f"grid.{k}:={float(v)}")]], ros_domain, log)
    frames = list(generate_drive(rig, grid, SynthConfig(frames=CLEAN + ABUSED, seed=950_000_013)))
    node = None
    try:
        rclpy.init(domain_id=ros_domain)
        node = rclpy.create_node("bev_test_temporal")
        odom = node.create_publisher(Odometry, "/odom", 50)
        d = Driver(node, rig, log, classes=CLASSES)
        assert spin_until(node, lambda: odom.get_subscription_count() > 0, 30.0), log.read_text()
        for i, f in enumerate(frames):
            assert d.calibrate(f.stamp_ns, 60.0), log.read_text()
            for msg in [odometry(f.stamp_ns, f.world_from_ego)] if i < CLEAN else _abused(i - CLEAN, f):
                odom.publish(msg)
                spin_until(node, lambda: False, 0.03)
            spin_until(node, lambda: False, 0.1)  # the pose is there before the image
            d.send_frame(f)
            assert d.wait_for(f.stamp_ns, 60.0), f"no grids for frame {f.index}:\n{log.read_text()}"
        n = len(d.diags)
        assert spin_until(node, lambda: len(d.diags) > n + 1, 10.0)
        v = d.diag_values()
        assert proc.poll() is None, log.read_text()
        assert loaded_torch(proc.pid) == []  # IPM with temporal fusion runs without torch
    finally:
        if node is not None:
            node.destroy_node()
        rclpy.try_shutdown()
        assert stop_process(proc) in (0, -2), log.read_text()
    mapper = IpmMapper(node_view_of_rig(rig, PARAMS), grid, MapperConfig(classes=CLASSES))
    fusion = TemporalFusion(grid, TemporalConfig(window=2))
    changed = 0
    for f in frames[:CLEAN]:
        alone = mapper.map({n: c.labels for n, c in f.cameras.items()})
        res = fusion.update(alone, f.stamp_ns, f.world_from_ego)
        assert res.note == "" and res.frames == (1 if f is frames[0] else 2)
        for ci, c in enumerate(CLASSES):
            got = np.asarray(d.grids[c][f.stamp_ns].data, dtype=np.int16)
            want = grid.to_occupancy(res.prediction.probs[ci], res.prediction.known).astype(np.int16)
            assert np.abs(got - want).max() <= 1 and (got == want).mean() > 0.999, (c, f.index)
            changed += int((want != grid.to_occupancy(alone.probs[ci], alone.known)).any())
    assert changed > 0  # the fusion did something the single frames would not
    for c in CLASSES:  # every frame mapped, grids within the occupancy range
        assert len(d.grids[c]) == len(frames)
        for msg in d.grids[c].values():
            data = np.asarray(msg.data)
            assert ((data >= 0) & (data <= 100) | (data == -1)).all()
    counts = {k: int(v[k]) for k in v if k.startswith("odometry_") or k in ("temporal_resets", "bad_input",
                                                                           "frames_without_pose")}
    assert int(v["bad_input"]) >= 2, counts  # NaN position, non-unit quaternion
    assert counts["odometry_jump"] >= 2, counts  # the spike (and back), the km jump (and back)
    assert counts["odometry_bad_covariance"] >= 1, counts
    assert counts["odometry_stamp_back"] >= 1 and counts["odometry_duplicate_stamp"] >= 1, counts
    assert counts["odometry_far_stamp"] >= 1, counts
    assert counts["temporal_resets"] >= 3, counts
    assert int(v["clock_jumps_back"]) == 0
    text = log.read_text()
    assert "mapped without temporal fusion" in text and "Traceback" not in text  # said (throttled)


def test_node_runs_focusbev_with_its_memory_bank_exactly_as_the_core(tmp_path, ros_domain):
    """``--params-file config/front1_focusbev.yaml``: the shipped FocusBEV weights, odometry on
    /odom, frames at 10 Hz. The published grids equal the core mapper's fed the same frames in
    order with the same poses (``bev-bag replay``'s path), the memory interval of 0.3 s brings
    in an earlier frame from frame 2 on, and a stamp going back (a bag loop) starts a new bank."""
    params = REPO / "config" / "front1_focusbev.yaml"
    weights = memory_focusbev(tmp_path / "focusbev_w2.safetensors")  # the shipped file maps frames alone
    grid, rig = grid_preset("ahead"), preset_rig("front1")
    classes = ("drivable", "vehicle")
    log = tmp_path / "node.log"
    proc = start_process(["bev_mapper_ros.mapper_node", "--ros-args", "--params-file", str(params),
                          "-p", "threads:=1", "-p", f"weights:={weights}", "-p", "backend:=torch",
                          "-p", f"classes:={list(classes)}".replace("'", '"')], ros_domain, log)
    frames = list(generate_drive(rig, grid, SynthConfig(frames=5, seed=950_000_014)))
    back = 2_000_000_000  # a loop: more than the synchronizer's jump_back_ns behind
    looped = replace(frames[3], stamp_ns=frames[3].stamp_ns - back,
                     cameras={n: replace(c, stamp_ns=c.stamp_ns - back) for n, c in frames[3].cameras.items()})
    expected = create_mapper(node_view_of_rig(rig, params), grid,
                             MapperConfig(method="focusbev", input_kind="rgb", classes=classes, threads=1, backend="torch",
                                          weights=weights))
    node = None
    got = []  # (frame, {class: grid data}) in the order sent
    try:
        rclpy.init(domain_id=ros_domain)
        node = rclpy.create_node("bev_test_focusbev")
        odom = node.create_publisher(Odometry, "/odom", 50)
        d = Driver(node, rig, log, kind="rgb", classes=classes)
        assert spin_until(node, lambda: odom.get_subscription_count() > 0, 60.0), log.read_text()
        for f in frames + [looped]:  # ... then frame 3 again, 2 s back in time
            assert d.calibrate(f.stamp_ns, 60.0), log.read_text()
            odom.publish(odometry(f.stamp_ns, f.world_from_ego))
            spin_until(node, lambda: False, 0.1)  # the pose is there before the image
            for c in classes:
                d.grids[c].pop(f.stamp_ns, None)
            d.send_frame(f)
            assert d.wait_for(f.stamp_ns, 60.0), f"no grids for frame {f.index}:\n{log.read_text()}"
            got.append((f, {c: np.asarray(d.grids[c][f.stamp_ns].data, dtype=np.int16) for c in classes}))
    finally:
        if node is not None:
            node.destroy_node()
        rclpy.try_shutdown()
        assert stop_process(proc) in (0, -2), log.read_text()
    fused_frames = []
    for f, grids in got:
        pred = expected.map({n: c.rgb for n, c in f.cameras.items()}, f.world_from_ego, f.stamp_ns)
        fused_frames.append(pred.frames)
        for ci, c in enumerate(classes):
            want = grid.to_occupancy(pred.probs[ci], pred.known).astype(np.int16)
            assert np.abs(grids[c] - want).max() <= 1 and (grids[c] == want).mean() > 0.999, (c, f.index)
    # from frame 2 on, the kept frame nearest 0.3 s back (within 0.15 s) is fused; the loop drops the bank
    assert fused_frames == [1, 1, 2, 2, 2, 1]
    assert "stamp went back" in log.read_text()
