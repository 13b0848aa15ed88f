"""The node reads TF over real DDS with the real tf2_ros (built into the venv by
scripts/setup_venv.sh from ../shared/ros2src): camera extrinsics from ``/tf_static``, the ego
pose from ``/tf`` (``odom -> base_link``), and every kind of bad TF counted without a crash or a
bad map."""

from __future__ import annotations

import os
import time
from dataclasses import replace

import numpy as np
import pytest
from model_helpers import memory_focusbev
from ros_helpers import REPO, rclpy, spin_until, start_process, stop_process
from test_node import Driver

from bev_mapper_core.geometry.grid import grid_preset
from bev_mapper_core.geometry.rig import Rig, RigCamera, preset_rig
from bev_mapper_core.geometry.transforms import make_transform, quat_to_rot, rot_to_quat
from bev_mapper_core.mapper import MapperConfig
from bev_mapper_core.methods.ipm.mapper import IpmMapper
from bev_mapper_core.synth import SynthConfig, generate_drive
from bev_mapper_core.temporal import TemporalConfig, TemporalFusion
from msg_adapters import RclpyFactory, camera_info_to_model, make_camera_info

# CI builds tf2_ros (scripts/setup_venv.sh): there its absence is a failure, not a skip
tf2_ros = __import__("tf2_ros") if os.environ.get("CI") else pytest.importorskip(
    "tf2_ros", reason="tf2_ros is not built into this venv (bash scripts/setup_venv.sh builds it)")
from geometry_msgs.msg import TransformStamped  # noqa: E402
from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile  # noqa: E402
from tf2_msgs.msg import TFMessage  # noqa: E402

PARAMS = REPO / "config" / "front1.yaml"
CLASSES = ("drivable", "lane_divider", "vehicle")


def at_now(frames):
    """The drive's frames re-stamped to start now: the node runs on the wall clock."""
    shift = time.time_ns() - frames[0].stamp_ns
    return [replace(f, stamp_ns=f.stamp_ns + shift,
                    cameras={n: replace(c, stamp_ns=c.stamp_ns + shift) for n, c in f.cameras.items()})
            for f in frames]


def transform(parent: str, child: str, T: np.ndarray, stamp_ns: int = 0) -> TransformStamped:
    msg = TransformStamped()
    msg.header.stamp.sec, msg.header.stamp.nanosec = divmod(int(stamp_ns), 1_000_000_000)
    msg.header.frame_id, msg.child_frame_id = parent, child
    t, q = msg.transform.translation, msg.transform.rotation
    t.x, t.y, t.z = (float(v) for v in T[:3, 3])
    q.x, q.y, q.z, q.w = (float(v) for v in rot_to_quat(T[:3, :3]))
    return msg


def through_tf(T: np.ndarray) -> np.ndarray:
    """``T`` as it comes out of a TransformStamped (quaternion round trip)."""
    return make_transform(quat_to_rot(*rot_to_quat(T[:3, :3])), T[:3, 3])


def rig_with(rig: Rig, extrinsics: dict) -> Rig:
    """The rig as the node sees it: intrinsics via CameraInfo, the given extrinsics."""
    factory = RclpyFactory()
    return Rig(rig.name, tuple(
        RigCamera(c.name, camera_info_to_model(make_camera_info(factory, c.model, 0, c.frame_id)),
                  extrinsics[c.name], c.frame_id) for c in rig.cameras))


def node_args(*extra: str) -> list[str]:
    g = grid_preset("ahead").to_dict()
    return ["bev_mapper_ros.mapper_node", "--ros-args", "--params-file", str(PARAMS), "-p", "method:=ipm",
            "-p", "threads:=1", "-p", "diagnostics_period_s:=0.2", "-p", f"classes:={list(CLASSES)}".replace("'", '"'),
            *[a for k, v in g.items() for a in ("-p", f"grid.{k}:={float(v)}")], *extra]


def assert_grids(d: Driver, grid, stamp_ns: int, pred, what: str) -> None:
    for ci, c in enumerate(CLASSES):
        got = np.asarray(d.grids[c][stamp_ns].data, dtype=np.int16)
        want = grid.to_occupancy(pred.probs[ci], pred.known).astype(np.int16)
        assert np.abs(got - want).max() <= 1 and (got == want).mean() > 0.999, (what, c)


def wait_diag(node, d: Driver, predicate, timeout: float = 10.0) -> dict:
    spin_until(node, lambda: predicate(d.diag_values()), timeout)
    return d.diag_values()


def drive_with_tf_motion(ros_domain, proc, log, rig, frames, kind, classes, grid_timeout):
    """Send each frame's ego pose as ``odom -> base_link`` on ``/tf``, then its images; wait for its
    grids. Stops the node process; returns the driver (its grids) and the last ``/diagnostics``
    values with a ``pose_source``.
    """
    node = None
    try:
        rclpy.init(domain_id=ros_domain)
        node = rclpy.create_node("bev_test_tf_motion")
        tf = tf2_ros.TransformBroadcaster(node)
        d = Driver(node, rig, log, kind=kind, classes=classes)
        assert spin_until(node, lambda: tf.pub_tf.get_subscription_count() > 0, 60.0), log.read_text()
        for f in frames:
            assert d.calibrate(f.stamp_ns, 60.0), log.read_text()
            tf.sendTransform(transform("odom", "base_link", f.world_from_ego, f.stamp_ns))
            spin_until(node, lambda: False, 0.1)
            d.send_frame(f)
            assert d.wait_for(f.stamp_ns, grid_timeout), f"no grids for frame {f.index}:\n{log.read_text()}"
        values = wait_diag(node, d, lambda v: v.get("pose_source"))
    finally:
        if node is not None:
            node.destroy_node()
        rclpy.try_shutdown()
        assert stop_process(proc) in (0, -2), log.read_text()
    return d, values


def test_node_maps_with_the_extrinsics_of_tf_static(tmp_path, ros_domain):
    """``/tf_static`` (a StaticTransformBroadcaster, as robot_state_publisher) mounts the front
    camera 0.4 m higher and 0.5 m further forward than the preset: the node maps with TF's
    extrinsic, says so, and its grids equal the core's map with it."""
    grid, rig = grid_preset("ahead"), preset_rig("front1")
    cam = rig.cameras[0]
    moved = cam.ego_from_cam_array.copy()
    moved[:3, 3] += (0.5, 0.0, 0.4)
    log = tmp_path / "node.log"
    proc = start_process(node_args(), ros_domain, log)
    frames = at_now(list(generate_drive(rig, grid, SynthConfig(frames=2, seed=950_000_021))))
    node = None
    try:
        rclpy.init(domain_id=ros_domain)
        node = rclpy.create_node("bev_test_tf_static")
        static = tf2_ros.StaticTransformBroadcaster(node)
        static.sendTransform(transform("base_link", cam.frame_id, moved))
        d = Driver(node, rig, log, classes=CLASSES)
        assert spin_until(node, lambda: static.pub_tf.get_subscription_count() > 0, 30.0), log.read_text()
        for f in frames:
            assert d.calibrate(f.stamp_ns, 60.0), log.read_text()
            d.send_frame(f)
            assert d.wait_for(f.stamp_ns, 60.0), f"no grids for frame {f.index}:\n{log.read_text()}"
        values = wait_diag(node, d, lambda v: v.get("extrinsics_source"))
    finally:
        if node is not None:
            node.destroy_node()
        rclpy.try_shutdown()
        assert stop_process(proc) in (0, -2), log.read_text()
    text = log.read_text()
    assert "extrinsics: front: TF (base_link <- front_optical_frame)" in text, text
    assert values["extrinsics_source"] == "front:tf" and values["tf"] == "tf2_ros", values
    with_tf = IpmMapper(rig_with(rig, {"front": through_tf(moved)}), grid, MapperConfig(classes=CLASSES))
    preset = IpmMapper(rig_with(rig, {"front": cam.ego_from_cam_array}), grid, MapperConfig(classes=CLASSES))
    for f in frames:
        labels = {n: c.labels for n, c in f.cameras.items()}
        assert_grids(d, grid, f.stamp_ns, with_tf.map(labels), f"frame {f.index}")
        assert not np.array_equal(with_tf.map(labels).known, preset.map(labels).known)  # TF made a difference


def test_tf_ego_motion_drives_temporal_fusion_as_odometry_does(tmp_path, ros_domain):
    """``pose_source:=tf``: ``odom -> base_link`` on ``/tf`` (a TransformBroadcaster) at each
    image stamp aligns the fused frames: the grids equal the core's fusion with the same poses,
    which is what the same motion on ``/odom`` gives (tests/bev_mapper_ros/test_node_temporal.py)."""
    grid, rig = grid_preset("ahead"), preset_rig("front1")
    log = tmp_path / "node.log"
    proc = start_process(node_args("-p", "temporal_window:=2", "-p", "pose_source:=tf"), ros_domain, log)
    frames = at_now(list(generate_drive(rig, grid, SynthConfig(frames=4, seed=950_000_013))))
    d, values = drive_with_tf_motion(ros_domain, proc, log, rig, frames, "labels", CLASSES, 60.0)
    assert values["pose_source"] == "tf" and values["temporal_note"] == "", values
    assert all(values[k] == "0" for k in values if k.startswith("tf_errors_")), values
    mapper = IpmMapper(rig_with(rig, {"front": rig.cameras[0].ego_from_cam_array}), grid, MapperConfig(classes=CLASSES))
    fusion = TemporalFusion(grid, TemporalConfig(window=2))
    changed = 0
    for f in frames:
        alone = mapper.map({n: c.labels for n, c in f.cameras.items()})
        res = fusion.update(alone, f.stamp_ns, f.world_from_ego)
        assert res.note == "" and res.frames == (1 if f is frames[0] else 2)
        assert_grids(d, grid, f.stamp_ns, res.prediction, f"frame {f.index}")
        changed += int(any((grid.to_occupancy(res.prediction.probs[i], res.prediction.known)
                            != grid.to_occupancy(alone.probs[i], alone.known)).any() for i in range(len(CLASSES))))
    assert changed > 0  # the poses from TF fused something


def test_bad_tf_is_counted_and_never_reaches_a_map(tmp_path, ros_domain):
    """A missing link, NaN transforms (on /tf and /tf_static), a stamp 1 h in the future, a cycle
    and an extrinsic jumping by metres: each counted in /diagnostics under its kind, the node
    keeps mapping, and every grid equals the core's with the last good transforms (a frame
    without a good pose is mapped without its history, as the core does with no pose)."""
    grid, rig = grid_preset("ahead"), preset_rig("front1")
    cam = rig.cameras[0]
    log = tmp_path / "node.log"
    proc = start_process(node_args("-p", "temporal_window:=2", "-p", "pose_source:=tf"), ros_domain, log)
    frames = at_now(list(generate_drive(rig, grid, SynthConfig(frames=7, seed=950_000_022))))
    nan = np.eye(4)
    nan[0, 3] = float("nan")
    jumped = cam.ego_from_cam_array.copy()
    jumped[0, 3] += 3.0

    def odom(f, T=None, stamp_ns=None):
        return transform("odom", "base_link", f.world_from_ego if T is None else T,
                         f.stamp_ns if stamp_ns is None else stamp_ns)

    hour = 3600 * 1_000_000_000
    # per frame: (what goes on /tf before it, what /tf_static says then, the pose the node should use)
    plan = [
        ("missing link: no odom frame yet", lambda f: [], cam.ego_from_cam_array, False),
        ("good", lambda f: [odom(f)], cam.ego_from_cam_array, True),
        ("NaN on /tf and /tf_static", lambda f: [odom(f, nan)], nan, False),
        ("1 h in the future", lambda f: [odom(f, stamp_ns=f.stamp_ns + hour)], cam.ego_from_cam_array, False),
        ("cycle base_link <-> loop", lambda f: [transform("loop", "base_link", np.eye(4), f.stamp_ns),
                                                 transform("base_link", "loop", np.eye(4), f.stamp_ns)],
         cam.ego_from_cam_array, False),
        ("extrinsic jumps 3 m", lambda f: [odom(f)], jumped, True),
        ("good again", lambda f: [odom(f)], cam.ego_from_cam_array, True),
    ]
    node = None
    try:
        rclpy.init(domain_id=ros_domain)
        node = rclpy.create_node("bev_test_tf_errors")
        # tf2_ros's StaticTransformBroadcaster sends a frame's first transform for good: a latched
        # publisher of its QoS (as robot_state_publisher's) sends each new /tf_static
        static = node.create_publisher(TFMessage, "/tf_static", QoSProfile(
            depth=1, history=HistoryPolicy.KEEP_LAST, durability=DurabilityPolicy.TRANSIENT_LOCAL))
        tf = tf2_ros.TransformBroadcaster(node)
        d = Driver(node, rig, log, classes=CLASSES)
        assert spin_until(node, lambda: tf.pub_tf.get_subscription_count() > 0, 30.0), log.read_text()
        for f, (what, tf_msgs, static_T, _) in zip(frames, plan):
            static.publish(TFMessage(transforms=[transform("base_link", cam.frame_id, static_T)]))
            for m in tf_msgs(f):
                tf.sendTransform(m)
            spin_until(node, lambda: False, 0.15)
            assert d.calibrate(f.stamp_ns, 60.0), log.read_text()
            d.send_frame(f)
            assert d.wait_for(f.stamp_ns, 60.0), f"no grids after {what}:\n{log.read_text()}"
            assert proc.poll() is None, log.read_text()
        values = wait_diag(node, d, lambda v: v.get("tf_errors_extrinsic_jump", "0") != "0")
    finally:
        if node is not None:
            node.destroy_node()
        rclpy.try_shutdown()
        assert stop_process(proc) in (0, -2), log.read_text()
    for kind in ("no_path", "invalid", "future_stamp", "extrapolation", "cycle", "extrinsic_jump"):
        assert int(values[f"tf_errors_{kind}"]) >= 1, "\n".join(f"{k}={v}" for k, v in values.items() if "tf" in k)
    assert values["extrinsics_source"] == "front:tf", values
    text = log.read_text()
    assert "Traceback" not in text and "TF (invalid)" in text and "TF (future_stamp)" in text, text
    assert int(values["tf_errors_invalid"]) >= 2, values  # the NaN on /tf and the one on /tf_static
    mapper = IpmMapper(rig_with(rig, {"front": through_tf(cam.ego_from_cam_array)}), grid, MapperConfig(classes=CLASSES))
    fusion = TemporalFusion(grid, TemporalConfig(window=2))
    for f, (what, _, _, good_pose) in zip(frames, plan):
        res = fusion.update(mapper.map({n: c.labels for n, c in f.cameras.items()}), f.stamp_ns,
                            f.world_from_ego if good_pose else None)
        assert_grids(d, grid, f.stamp_ns, res.prediction, what)


def test_focusbev_memory_follows_tf_with_pose_source_auto(tmp_path, ros_domain):
    """``config/front1_focusbev.yaml`` with the default ``pose_source: auto`` and no ``/odom``:
    FocusBEV's memory bank is aligned by ``odom -> base_link`` from ``/tf``, and the grids equal
    the core mapper's fed the same frames with the same poses (as with /odom,
    test_node_temporal.py)."""
    from bev_mapper_core.mapper import create_mapper

    params = REPO / "config" / "front1_focusbev.yaml"
    weights = memory_focusbev(tmp_path / "focusbev_w2.safetensors")  # the shipped file maps frames alone
    grid, rig = grid_preset("ahead"), preset_rig("front1")
    classes = ("drivable", "vehicle")
    log = tmp_path / "node.log"
    proc = start_process(["bev_mapper_ros.mapper_node", "--ros-args", "--params-file", str(params),
                          "-p", "threads:=1", "-p", f"weights:={weights}", "-p", "diagnostics_period_s:=0.2", "-p", "backend:=torch",
                          "-p", f"classes:={list(classes)}".replace("'", '"')], ros_domain, log)
    frames = at_now(list(generate_drive(rig, grid, SynthConfig(frames=4, seed=950_000_014))))
    expected = create_mapper(rig_with(rig, {"front": rig.cameras[0].ego_from_cam_array}), grid,
                             MapperConfig(method="focusbev", input_kind="rgb", classes=classes, threads=1, backend="torch",
                                          weights=weights))
    d, values = drive_with_tf_motion(ros_domain, proc, log, rig, frames, "rgb", classes, 120.0)
    assert values["pose_source"] == "tf", values
    fused = []
    for f in frames:
        pred = expected.map({n: c.rgb for n, c in f.cameras.items()}, f.world_from_ego, f.stamp_ns)
        fused.append(pred.frames)
        for ci, c in enumerate(classes):
            got = np.asarray(d.grids[c][f.stamp_ns].data, dtype=np.int16)
            want = grid.to_occupancy(pred.probs[ci], pred.known).astype(np.int16)
            assert np.abs(got - want).max() <= 1 and (got == want).mean() > 0.999, (c, f.index)
    assert max(fused) == 2  # the memory bank brought in an earlier frame, aligned by TF's poses
