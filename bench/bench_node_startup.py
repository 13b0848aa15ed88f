"""Benchmark: the mapper node's start-up, from process start to its first grid, with IPM.

Starts ``mapper_node`` (``config/<params>.yaml``, ``method:=ipm``) in its own process on a
private loopback-only domain, publishes the rig's CameraInfo and full-size synthetic label images
at 10 Hz from the moment the process starts, and measures the time until the first
``/bev/drivable`` grid arrives; it also reads the node's ``/proc/PID/maps`` then, to say whether
torch was loaded. With ``--reference DIR`` (another checkout of this package, e.g. a git worktree
of an older commit) the runs alternate between the two code trees in the same session.

    .venv/bin/python bench/bench_node_startup.py --runs 5 --reference /tmp/ref
"""

from __future__ import annotations

import argparse
import os
import pathlib
import statistics
import subprocess
import sys
import time

REPO = pathlib.Path(__file__).resolve().parents[1]


def _torch_mapped(pid: int) -> bool:
    try:
        with open(f"/proc/{pid}/maps") as f:
            return any("/torch/" in line for line in f)
    except OSError:
        return False


def one_run(code: pathlib.Path, params_file: pathlib.Path, node, pubs, infos, frames, rig, factory) -> tuple[float, bool]:
    """Seconds from the node's process start to its first grid, and whether torch was mapped."""
    import rclpy  # noqa: PLC0415

    from msg_adapters import make_camera_info, make_image  # noqa: PLC0415

    received: list[float] = []
    sub = node.create_subscription(__import__("nav_msgs.msg", fromlist=["OccupancyGrid"]).OccupancyGrid,
                                   "/bev/drivable", lambda m: received.append(time.monotonic()), 10)
    env = dict(os.environ, PYTHONPATH=str(code))
    t0 = time.monotonic()
    proc = subprocess.Popen([sys.executable, "-m", "bev_mapper_ros.mapper_node", "--ros-args", "--params-file",
                             str(params_file), "-p", "method:=ipm"], cwd=code, env=env,
                            stdout=subprocess.DEVNULL, stderr=subprocess.STDOUT)
    try:
        k = 0
        while not received:
            if time.monotonic() - t0 > 120 or proc.poll() is not None:
                sys.exit(f"error: no grid from the node of {code}")
            stamp = time.time_ns()
            for cam in rig.cameras:
                infos[cam.name].publish(make_camera_info(factory, cam.model, stamp, cam.frame_id))
                pubs[cam.name].publish(make_image(factory, frames[k % len(frames)][cam.name], "mono8", stamp,
                                                  cam.frame_id))
            k += 1
            end = t0 + 0.1 * k
            while time.monotonic() < end and not received:
                rclpy.spin_once(node, timeout_sec=max(0.0, end - time.monotonic()))
        return received[0] - t0, _torch_mapped(proc.pid)
    finally:
        node.destroy_subscription(sub)
        proc.send_signal(2)
        try:
            proc.wait(10)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait()


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--params", default="surround6", help="config/<NAME>.yaml (default: %(default)s)")
    ap.add_argument("--runs", type=int, default=5, help="start-ups per code tree")
    ap.add_argument("--reference", type=pathlib.Path, default=None, help="another checkout to compare with")
    ap.add_argument("--domain-id", type=int, default=150 + os.getpid() % 50)
    args = ap.parse_args()
    os.environ["ROS_AUTOMATIC_DISCOVERY_RANGE"] = "LOCALHOST"
    os.environ["ROS_DOMAIN_ID"] = str(args.domain_id)

    import rclpy  # noqa: PLC0415 - after the environment is set
    import yaml  # noqa: PLC0415
    from rclpy.qos import QoSProfile, ReliabilityPolicy  # noqa: PLC0415
    from sensor_msgs.msg import CameraInfo, Image  # noqa: PLC0415

    from bev_mapper_core.geometry.grid import BevGrid  # noqa: PLC0415
    from bev_mapper_core.geometry.rig import preset_rig  # noqa: PLC0415
    from bev_mapper_core.synth import SynthConfig, generate_drive  # noqa: PLC0415
    from msg_adapters import RclpyFactory  # noqa: PLC0415

    params_file = REPO / "config" / f"{args.params}.yaml"
    params = yaml.safe_load(params_file.read_text())["/**"]["ros__parameters"]
    rig, grid = preset_rig(params["rig"]), BevGrid.from_dict(params["grid"])
    frames = [{n: c.labels for n, c in f.cameras.items()}
              for f in generate_drive(rig, grid, SynthConfig(frames=3, seed=950_000_008))]
    rclpy.init()
    node = rclpy.create_node("bench_node_startup")
    qos = QoSProfile(depth=5, reliability=ReliabilityPolicy.RELIABLE)
    pubs = {c: node.create_publisher(Image, f"/cameras/{c}/labels", qos) for c in rig.names}
    infos = {c: node.create_publisher(CameraInfo, f"/cameras/{c}/camera_info", 10) for c in rig.names}
    trees = [("this checkout", REPO)] + ([("reference", args.reference.resolve())] if args.reference else [])
    times: dict[str, list[float]] = {name: [] for name, _ in trees}
    torch_seen: dict[str, set[bool]] = {name: set() for name, _ in trees}
    try:
        for _ in range(args.runs):
            for name, code in trees:
                t, has_torch = one_run(code, params_file, node, pubs, infos, frames, rig, RclpyFactory())
                times[name].append(t)
                torch_seen[name].add(has_torch)
    finally:
        node.destroy_node()
        rclpy.shutdown()
    print(f"{args.params}.yaml, method ipm, {len(rig.cameras)} cameras at 10 Hz: process start -> first /bev/drivable")
    for name, code in trees:
        ts = times[name]
        print(f"{name:14s} ({code}): median {statistics.median(ts):.2f} s, min {min(ts):.2f}, max {max(ts):.2f} "
              f"over {len(ts)} runs; torch loaded: {sorted(torch_seen[name])}")


if __name__ == "__main__":
    main()
