"""The node under abused odometry over real DDS (issue #29): NaN poses, a non-unit quaternion,
a 4 m spike, a kilometre jump, a stamp going back, a duplicated stamp, a NaN covariance and a
pose far in the future. Every frame is still mapped (finite grids, none withheld waiting for
rejected odometry), each abuse is counted in ``/diagnostics`` (``odometry_<kind>``,
``bad_input``) with the memory resets (``temporal_resets``), and the node keeps running."""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
from ros_helpers import REPO, rclpy, spin_until, start_process, stop_process
from test_node import Driver
from test_node_temporal import odometry

from bev_mapper_core.geometry.grid import grid_preset
from bev_mapper_core.geometry.rig import preset_rig
from bev_mapper_core.synth import SynthConfig, generate_drive

PARAMS = REPO / "config" / "front1.yaml"
CLASSES = ("drivable", "lane_divider")
S = 1_000_000_000


def _abused(k: int, f) -> list:
    """The odometry messages sent before frame ``k`` (the abuse of that frame)."""
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


def test_node_counts_odometry_abuse_and_maps_every_frame(tmp_path, ros_domain):
    grid, rig = grid_preset("ahead"), preset_rig("front1")
    g = grid.to_dict()
    log = tmp_path / "node.log"
    proc = start_process(["bev_mapper_ros.mapper_node", "--ros-args", "--params-file", str(PARAMS),
                          "-p", "method:=ipm", "-p", "temporal_window:=3", "-p", "threads:=1",
                          "-p", "diagnostics_period_s:=0.2",
                          "-p", f"classes:={list(CLASSES)}".replace("'", '"'),
                          *[a for k, v in g.items() for a in ("-p", f"grid.{k}:={float(v)}")]], ros_domain, log)
    frames = list(generate_drive(rig, grid, SynthConfig(frames=12, seed=950_000_029)))
    node = None
    try:
        rclpy.init(domain_id=ros_domain)
        node = rclpy.create_node("bev_test_odometry")
        from nav_msgs.msg import Odometry

        odom = node.create_publisher(Odometry, "/odom", 50)
        d = Driver(node, rig, log, classes=CLASSES)
        assert spin_until(node, lambda: odom.get_subscription_count() > 0, 30.0), log.read_text()
        for k, f in enumerate(frames):
            assert d.calibrate(f.stamp_ns, 60.0), log.read_text()
            for msg in _abused(k, f):
                odom.publish(msg)
                spin_until(node, lambda: False, 0.03)
            spin_until(node, lambda: False, 0.1)
            d.send_frame(f)
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


def test_latency_is_never_negative_and_a_clock_jump_back_is_counted_not_subtracted():
    from bev_mapper_ros.odometry import ClockWatch

    w = ClockWatch()
    assert w.latency_ms(10 * S, 10 * S - 50_000_000, 3.0, 5.0) == 50.0
    assert w.latency_ms(11 * S, 11 * S + 43_700_000, 3.0, 5.0) == 3.0  # stamp ahead of a coarse sim clock
    assert w.latency_ms(2 * S, 2 * S - 10_000_000, 3.0, 5.0) is None  # the clock jumped back 9 s (a loop)
    assert w.jumps_back == 1 and w.last_jump_s == 9.0
    assert w.latency_ms(2 * S + 100_000_000, 2 * S, 3.0, 5.0) == 100.0  # then measured again
    assert w.latency_ms(100 * S, 10 * S, 3.0, 5.0) is None  # clocks disagree: not a latency


def test_diagnostics_keep_their_period_under_sim_time_that_stops_and_loops(tmp_path, ros_domain):
    """``use_sim_time``: /clock stands still, then loops back. ``/diagnostics`` (on the steady
    clock) keeps coming meanwhile, the clock jump back is counted, and latency is never negative."""
    from rosgraph_msgs.msg import Clock

    grid, rig = grid_preset("ahead"), preset_rig("front1")
    g = grid.to_dict()
    log = tmp_path / "node.log"
    proc = start_process(["bev_mapper_ros.mapper_node", "--ros-args", "--params-file", str(PARAMS),
                          "-p", "method:=ipm", "-p", "threads:=1", "-p", "use_sim_time:=true",
                          "-p", "diagnostics_period_s:=0.2", "-p", f"classes:={list(CLASSES)}".replace("'", '"'),
                          *[a for k, v in g.items() for a in ("-p", f"grid.{k}:={float(v)}")]], ros_domain, log)
    frames = list(generate_drive(rig, grid, SynthConfig(frames=4, seed=950_000_030)))
    node = None
    try:
        rclpy.init(domain_id=ros_domain)
        node = rclpy.create_node("bev_test_sim_clock")
        clock = node.create_publisher(Clock, "/clock", 10)

        def tick(ns: int) -> None:
            msg = Clock()
            msg.clock.sec, msg.clock.nanosec = divmod(int(ns), S)
            clock.publish(msg)

        d = Driver(node, rig, log, classes=CLASSES)
        assert spin_until(node, lambda: clock.get_subscription_count() > 0, 30.0), log.read_text()
        for k, f in enumerate(frames[:2]):
            tick(f.stamp_ns - 40_000_000)  # the sim clock a little behind the images (coarse /clock)
            assert d.calibrate(f.stamp_ns, 60.0), log.read_text()
            d.send_frame(f)
            assert d.wait_for(f.stamp_ns, 60.0), f"no grids for frame {k}:\n{log.read_text()}"
        tick(frames[1].stamp_ns)
        n = len(d.diags)  # /clock now stands still: the diagnostics go on
        assert spin_until(node, lambda: len(d.diags) >= n + 3, 20.0), (len(d.diags), n)
        for f in frames[2:]:  # the bag loops: the clock goes back 5 s, and so do the images
            back = replace(f, stamp_ns=f.stamp_ns - 5 * S,
                           cameras={c: replace(cf, stamp_ns=cf.stamp_ns - 5 * S) for c, cf in f.cameras.items()})
            tick(back.stamp_ns - 40_000_000)
            spin_until(node, lambda: False, 0.1)
            d.send_frame(back)
            assert d.wait_for(back.stamp_ns, 60.0), log.read_text()
        n = len(d.diags)
        assert spin_until(node, lambda: len(d.diags) >= n + 2, 20.0)
        v = d.diag_values()
    finally:
        if node is not None:
            node.destroy_node()
        rclpy.try_shutdown()
        assert stop_process(proc) in (0, -2), log.read_text()
    lat = [kv.value for a in d.diags for kv in a.status[0].values if kv.key == "latency_ms"]
    assert all(x == "" or x == "clock mismatch" or float(x) >= 0.0 for x in lat), lat
    assert int(v["clock_jumps_back"]) >= 1, v
    assert "jumped back" in log.read_text()
