"""The node places each camera at its own time (issue #38) over real DDS: a surround6 drive whose
cameras fire 90 ms apart (5 Hz), odometry on /odom. The published grids equal the core's IPM on
the rig placed by hand from the same poses; a camera without a pose at its stamp and a camera
stamped too far from its set are mapped as calibrated, counted in /diagnostics, never a traceback."""

from __future__ import annotations

import numpy as np
from nav_msgs.msg import Odometry
from ros_helpers import REPO, rclpy, spin_until, start_process, stop_process
from test_node import Driver, node_view_of_rig
from test_node_temporal import odometry

from bev_mapper_core.geometry.grid import BevGrid
from bev_mapper_core.geometry.pose_buffer import PoseBuffer
from bev_mapper_core.geometry.rig import RigCamera, preset_rig
from bev_mapper_core.mapper import MapperConfig
from bev_mapper_core.methods.ipm.mapper import IpmMapper
from bev_mapper_core.synth import SynthConfig, generate_drive
from msg_adapters import RclpyFactory, make_image

PARAMS = REPO / "config" / "surround6.yaml"
CLASSES = ("drivable", "vehicle")
GRID = BevGrid(x_min=-12, x_max=12, y_min=-8, y_max=8, resolution=0.25)
MAX_OFFSET_S = 0.08  # front_left fires 90 ms after the set's stamp: beyond it, every set


def _hand_rig(base, frame, poses: PoseBuffer, placed: tuple[str, ...]):
    """``base`` with cameras ``placed`` at ``inv(world_from_ego(ref)) @ world_from_ego(t_cam) @ ego_from_cam``."""
    ref = poses.at(frame.stamp_ns)
    rig = base
    for name in placed:
        c = base[name]
        E = np.linalg.inv(ref) @ poses.at(frame.cameras[name].stamp_ns) @ c.ego_from_cam_array
        rig = rig.with_camera(RigCamera(c.name, c.model, E, c.frame_id))
    return rig


def test_node_places_each_camera_at_its_time_as_the_core_and_counts_what_it_cannot(tmp_path, ros_domain):
    rig = preset_rig("surround6")
    g = GRID.to_dict()
    log = tmp_path / "node.log"
    proc = start_process(["bev_mapper_ros.mapper_node", "--ros-args", "--params-file", str(PARAMS),
                          "-p", "method:=ipm", "-p", "threads:=1", "-p", "diagnostics_period_s:=0.2",
                          "-p", "sync_slop_s:=0.1", "-p", "time_placement_step_cells:=0.0",
                          "-p", f"time_placement_max_offset_s:={MAX_OFFSET_S}",
                          "-p", f"classes:={list(CLASSES)}".replace("'", '"'),
                          *[a for k, v in g.items() for a in ("-p", f"grid.{k}:={float(v)}")]], ros_domain, log)
    frames = list(generate_drive(rig, GRID, SynthConfig(frames=4, seed=950_000_031, rate_hz=5.0, stagger_ms=90.0)))
    offsets = [f.cameras[n].stamp_ns - f.stamp_ns for f in frames[:1] for n in rig.names]
    assert offsets == [0, 18_000_000, 36_000_000, 54_000_000, 72_000_000, 90_000_000]
    poses = PoseBuffer()  # the node's odometry, as the core sees it
    factory = RclpyFactory()
    node = None
    try:
        rclpy.init(domain_id=ros_domain)
        node = rclpy.create_node("bev_test_time_placement")
        odom = node.create_publisher(Odometry, "/odom", 50)
        d = Driver(node, rig, log, classes=CLASSES)
        assert spin_until(node, lambda: odom.get_subscription_count() > 0, 30.0), log.read_text()
        for k, f in enumerate(frames[:3]):
            assert d.calibrate(f.stamp_ns, 60.0), log.read_text()
            # frames 0, 1: odometry at the frame and the next (every camera's stamp between);
            # frame 2: none after its stamp (cameras 54 and 72 ms later: no pose, 50 ms at most past the end)
            for g_ in frames[k:k + 2] if k < 2 else frames[k:k + 1]:
                if poses.latest_stamp_ns is None or g_.stamp_ns > poses.latest_stamp_ns:
                    odom.publish(odometry(g_.stamp_ns, g_.world_from_ego))
                    poses.add(g_.stamp_ns, g_.world_from_ego)
                    spin_until(node, lambda: False, 0.03)
            spin_until(node, lambda: False, 0.1)
            d.send_frame(f, override={n: make_image(factory, c.labels, "mono8", c.stamp_ns, rig[n].frame_id)
                                      for n, c in f.cameras.items()})
            assert d.wait_for(f.stamp_ns, 60.0), f"no grids for frame {k}:\n{log.read_text()}"
        n = len(d.diags)
        assert spin_until(node, lambda: len(d.diags) > n + 1, 10.0)
        v = d.diag_values()
        assert proc.poll() is None, log.read_text()
    finally:
        if node is not None:
            node.destroy_node()
        rclpy.try_shutdown()
        assert stop_process(proc) in (0, -2), log.read_text()
    base = node_view_of_rig(rig, PARAMS)
    cfg = MapperConfig(method="ipm", classes=CLASSES)
    placed = ("front_right", "back_right", "back", "back_left")  # front at the set's stamp; front_left jumped
    for k, f in enumerate(frames[:3]):
        hand = _hand_rig(base, f, poses, placed if k < 2 else ())
        pred = IpmMapper(hand, GRID, cfg).map({n: c.labels for n, c in f.cameras.items()})
        for ci, c in enumerate(CLASSES):
            got = np.asarray(d.grids[c][f.stamp_ns].data, dtype=np.int16)
            want = GRID.to_occupancy(pred.probs[ci], pred.known).astype(np.int16)
            assert np.abs(got - want).max() <= 1 and (got == want).mean() > 0.999, (c, k)
    assert v["time_placement"] == "auto"
    assert v["placement_sets_placed"] == "2" and v["placement_sets_static"] == "1", v
    assert v["placement_stamp_jumps"] == "3" and v["placement_cameras_without_pose"] == "2", v
    assert float(v["placement_max_offset_m"]) > 0.2
    text = log.read_text()
    assert "time placement: cameras ['front_left'] stamped more than 0.08 s" in text
    assert "time placement: no ego pose at the stamps of ['back', 'back_left']" in text
    assert "Traceback" not in text
