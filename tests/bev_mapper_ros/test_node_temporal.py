"""The node's temporal fusion over real DDS: odometry on /odom aligns the frames, and the
published grids equal the core's fusion (bev_mapper_core.temporal) of the core mapper's maps."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
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


def test_node_fuses_frames_by_odometry_exactly_as_the_core(tmp_path, ros_domain):
    grid, rig = grid_preset("ahead"), preset_rig("front1")
    g = grid.to_dict()
    log = tmp_path / "node.log"
    proc = start_process(["bev_mapper_ros.mapper_node", "--ros-args", "--params-file", str(PARAMS),
                          "-p", "method:=ipm", "-p", "temporal_window:=2", "-p", "threads:=1",
                          "-p", f"classes:={list(CLASSES)}".replace("'", '"'),
                          *[a for k, v in g.items() for a in ("-p", f"grid.{k}:={float(v)}")]], ros_domain, log)
    frames = list(generate_drive(rig, grid, SynthConfig(frames=4, seed=950_000_013)))
    node = None
    try:
        rclpy.init(domain_id=ros_domain)
        node = rclpy.create_node("bev_test_temporal")
        odom = node.create_publisher(Odometry, "/odom", 50)
        d = Driver(node, rig, log, classes=CLASSES)
        assert spin_until(node, lambda: odom.get_subscription_count() > 0, 30.0), log.read_text()
        for f in frames:
            assert d.calibrate(f.stamp_ns, 60.0), log.read_text()
            odom.publish(odometry(f.stamp_ns, f.world_from_ego))
            spin_until(node, lambda: False, 0.1)  # the pose is there before the image
            d.send_frame(f)
            assert d.wait_for(f.stamp_ns, 60.0), f"no grids for frame {f.index}:\n{log.read_text()}"
        assert loaded_torch(proc.pid) == []  # IPM with temporal fusion runs without torch
    finally:
        if node is not None:
            node.destroy_node()
        rclpy.try_shutdown()
        assert stop_process(proc) in (0, -2), log.read_text()
    mapper = IpmMapper(node_view_of_rig(rig, PARAMS), grid, MapperConfig(classes=CLASSES))
    fusion = TemporalFusion(grid, TemporalConfig(window=2))
    changed = 0
    for f in frames:
        alone = mapper.map({n: c.labels for n, c in f.cameras.items()})
        res = fusion.update(alone, f.stamp_ns, f.world_from_ego)
        assert res.note == "" and res.frames == (1 if f is frames[0] else 2)
        for ci, c in enumerate(CLASSES):
            got = np.asarray(d.grids[c][f.stamp_ns].data, dtype=np.int16)
            want = grid.to_occupancy(res.prediction.probs[ci], res.prediction.known).astype(np.int16)
            assert np.abs(got - want).max() <= 1 and (got == want).mean() > 0.999, (c, f.index)
            changed += int((want != grid.to_occupancy(alone.probs[ci], alone.known)).any())
    assert changed > 0  # the fusion did something the single frames would not


def test_node_runs_focusbev_with_its_memory_bank_exactly_as_the_core(tmp_path, ros_domain):
    """``--params-file config/front1_focusbev.yaml``: the shipped FocusBEV weights, odometry on
    /odom, frames at 10 Hz. The published grids equal the core mapper's fed the same frames in
    order with the same poses (``bev-bag replay``'s path), the memory interval of 0.3 s brings
    in an earlier frame from frame 2 on, and a stamp going back (a bag loop) starts a new bank."""
    params = REPO / "config" / "front1_focusbev.yaml"
    grid, rig = grid_preset("ahead"), preset_rig("front1")
    classes = ("drivable", "vehicle")
    log = tmp_path / "node.log"
    proc = start_process(["bev_mapper_ros.mapper_node", "--ros-args", "--params-file", str(params),
                          "-p", "threads:=1", "-p", "backend:=torch",
                          "-p", f"classes:={list(classes)}".replace("'", '"')], ros_domain, log)
    frames = list(generate_drive(rig, grid, SynthConfig(frames=5, seed=950_000_014)))
    back = 2_000_000_000  # a loop: more than the synchronizer's jump_back_ns behind
    looped = replace(frames[3], stamp_ns=frames[3].stamp_ns - back,
                     cameras={n: replace(c, stamp_ns=c.stamp_ns - back) for n, c in frames[3].cameras.items()})
    expected = create_mapper(node_view_of_rig(rig, params), grid,
                             MapperConfig(method="focusbev", input_kind="rgb", classes=classes, threads=1, backend="torch"))
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
