"""The node's clocks (issue #29): latency is never negative and a clock jump back is counted;
``/diagnostics`` keep their period under sim time that stops and loops. (The node under abused
odometry is in test_node_temporal.py: the same node run as the temporal fusion's check.)"""

from __future__ import annotations

from dataclasses import replace

from ros_helpers import REPO, rclpy, spin_until, start_process, stop_process
from test_node import Driver

from bev_mapper_core.geometry.grid import grid_preset
from bev_mapper_core.geometry.rig import preset_rig
from bev_mapper_core.synth import SynthConfig, generate_drive

PARAMS = REPO / "config" / "front1.yaml"
CLASSES = ("drivable", "lane_divider")
S = 1_000_000_000


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
