"""Benchmark (issue #41): a learned node's cold start, and SIGINT / SIGTERM during its start-up.

Starts ``mapper_node`` with ``config/<params>.yaml`` (default ``front1_focusbev``) and its default
``backend`` (``auto``) on an **empty** export cache (``$BEV_MAPPER_CACHE`` in a fresh folder), in
its own process on a private loopback-only domain, and publishes the rig's CameraInfo and
full-size synthetic images at 10 Hz from the moment the process starts.

* default (timing): per run, the seconds from the process start and from the first complete
  camera set the node could receive (the first set published after every image and CameraInfo
  publisher matched the node's subscriptions) to its first ``/bev/drivable`` grid, and to the
  log line that says it switched to the exported backend.
* ``--signals N``: N starts, each stopped by SIGINT (``--signal term``: SIGTERM) at a moment
  drawn uniformly from ``[0, --max-delay]`` s after the process start (import, set-up, first
  frames, export); counts exit statuses other than 0 and files left in the cache folder other
  than complete ``<key>.onnx`` / ``<key>.json`` pairs.

    .venv/bin/python bench/bench_node_coldstart.py --runs 3
    .venv/bin/python bench/bench_node_coldstart.py --signals 50 --max-delay 40
"""

from __future__ import annotations

import argparse
import os
import pathlib
import random
import re
import signal
import statistics
import subprocess
import sys
import tempfile
import time

REPO = pathlib.Path(__file__).resolve().parents[1]
SWITCH = re.compile(r"inference: switched from torch to (\w+)")


def leftovers(cache: pathlib.Path) -> list[str]:
    """Files under ``cache`` that are not a complete ``<key>.onnx`` with its ``<key>.json``."""
    onnx = cache / "onnx"
    if not onnx.is_dir():
        return []
    names = sorted(p.name for p in onnx.iterdir())
    stems = {n[:-5] for n in names if n.endswith(".onnx")} & {n[:-5] for n in names if n.endswith(".json")}
    return [n for n in names if n.rsplit(".", 1)[0] not in stems]


class Feed:
    """Publishers of the rig's CameraInfo and images, and a subscription to the first grid."""

    def __init__(self, node, params_file: pathlib.Path) -> None:
        import yaml  # noqa: PLC0415
        from nav_msgs.msg import OccupancyGrid  # noqa: PLC0415
        from rclpy.qos import QoSProfile, ReliabilityPolicy  # noqa: PLC0415
        from sensor_msgs.msg import CameraInfo, Image  # noqa: PLC0415

        from bev_mapper_core.geometry.grid import BevGrid  # noqa: PLC0415
        from bev_mapper_core.geometry.rig import preset_rig  # noqa: PLC0415
        from bev_mapper_core.synth import SynthConfig, generate_drive  # noqa: PLC0415
        from msg_adapters import RclpyFactory  # noqa: PLC0415

        params = yaml.safe_load(params_file.read_text())["/**"]["ros__parameters"]
        self.rig, grid = preset_rig(params["rig"]), BevGrid.from_dict(params["grid"])
        rgb = params.get("input_kind") == "rgb"
        self.encoding = "rgb8" if rgb else "mono8"
        self.frames = [{n: (c.rgb if rgb else c.labels) for n, c in f.cameras.items()}
                       for f in generate_drive(self.rig, grid, SynthConfig(frames=3, seed=950_000_008))]
        topic = "/cameras/{}/image_raw" if rgb else "/cameras/{}/labels"
        qos = QoSProfile(depth=5, reliability=ReliabilityPolicy.RELIABLE)
        self.node, self.factory = node, RclpyFactory()
        self.pubs = {c: node.create_publisher(Image, topic.format(c), qos) for c in self.rig.names}
        self.infos = {c: node.create_publisher(CameraInfo, f"/cameras/{c}/camera_info", 10) for c in self.rig.names}
        self.grids: list[float] = []
        node.create_subscription(OccupancyGrid, "/bev/drivable", lambda m: self.grids.append(time.monotonic()), 10)

    def matched(self) -> bool:
        """Every image and CameraInfo publisher has the node's subscription."""
        return all(p.get_subscription_count() > 0 for p in (*self.pubs.values(), *self.infos.values()))

    def publish(self, k: int) -> None:
        """Set ``k`` (CameraInfo and image of every camera, stamped now)."""
        from msg_adapters import make_camera_info, make_image  # noqa: PLC0415

        stamp = time.time_ns()
        for cam in self.rig.cameras:
            self.infos[cam.name].publish(make_camera_info(self.factory, cam.model, stamp, cam.frame_id))
            self.pubs[cam.name].publish(make_image(self.factory, self.frames[k % len(self.frames)][cam.name],
                                                   self.encoding, stamp, cam.frame_id))


def start(params_file: pathlib.Path, cache: pathlib.Path, log: pathlib.Path) -> subprocess.Popen:
    env = dict(os.environ, PYTHONPATH=str(REPO), BEV_MAPPER_CACHE=str(cache), PYTHONUNBUFFERED="1")
    with open(log, "w") as out:
        return subprocess.Popen([sys.executable, "-m", "bev_mapper_ros.mapper_node", "--ros-args", "--params-file",
                                 str(params_file)], cwd=REPO, env=env, stdout=out, stderr=subprocess.STDOUT)


def feed_until(feed: Feed, proc: subprocess.Popen, t0: float, done, timeout: float) -> float | None:
    """Publish at 10 Hz until ``done()``; the time the first set went out after the node matched."""
    import rclpy  # noqa: PLC0415

    k, first_matched = 0, None
    while not done() and time.monotonic() - t0 < timeout and proc.poll() is None:
        if first_matched is None and feed.matched():
            first_matched = time.monotonic()
        feed.publish(k)
        k += 1
        end = t0 + 0.1 * k
        while time.monotonic() < end and not done():
            rclpy.spin_once(feed.node, timeout_sec=max(0.0, end - time.monotonic()))
    return first_matched


def timing_run(feed: Feed, params_file: pathlib.Path, work: pathlib.Path) -> dict:
    cache, log = work / "cache", work / "node.log"
    feed.grids.clear()
    t0 = time.monotonic()
    proc = start(params_file, cache, log)
    try:
        first_set = feed_until(feed, proc, t0, lambda: bool(feed.grids), 300)
        if not feed.grids:
            sys.exit(f"error: no grid from the node (log: {log})")
        grid = feed.grids[0]
        feed_until(feed, proc, t0, lambda: SWITCH.search(log.read_text()) is not None, 300)
        switched = time.monotonic() if SWITCH.search(log.read_text()) else None
    finally:
        proc.send_signal(signal.SIGINT)
        code = proc.wait(30)
    return {"grid_from_start": grid - t0, "grid_from_first_set": grid - (first_set or t0),
            "switch_from_start": None if switched is None else switched - t0, "exit": code,
            "left": leftovers(cache), "log": log.read_text()}


def signal_run(feed: Feed, params_file: pathlib.Path, work: pathlib.Path, delay: float, sig: int) -> tuple[int, list]:
    cache, log = work / "cache", work / "node.log"
    t0 = time.monotonic()
    proc = start(params_file, cache, log)
    try:
        feed_until(feed, proc, t0, lambda: time.monotonic() - t0 >= delay, delay + 1)
    finally:
        proc.send_signal(sig)
        try:
            code = proc.wait(60)
        except subprocess.TimeoutExpired:
            proc.kill()
            code = proc.wait()
    time.sleep(0.2)
    return code, leftovers(cache)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--params", default="front1_focusbev", help="config/<NAME>.yaml (default: %(default)s)")
    ap.add_argument("--runs", type=int, default=3, help="timing: cold starts")
    ap.add_argument("--signals", type=int, default=0, help="instead: this many starts stopped by a signal")
    ap.add_argument("--signal", choices=("int", "term"), default="int")
    ap.add_argument("--max-delay", type=float, default=40.0, help="--signals: latest moment of the signal (s)")
    ap.add_argument("--seed", type=int, default=41)
    ap.add_argument("--domain-id", type=int, default=150 + os.getpid() % 50)
    args = ap.parse_args()
    os.environ["ROS_AUTOMATIC_DISCOVERY_RANGE"] = "LOCALHOST"
    os.environ["ROS_DOMAIN_ID"] = str(args.domain_id)
    import rclpy  # noqa: PLC0415 - after the environment is set

    params_file = REPO / "config" / f"{args.params}.yaml"
    rclpy.init()
    node = rclpy.create_node("bench_node_coldstart")
    feed = Feed(node, params_file)
    try:
        with tempfile.TemporaryDirectory(prefix="bench_coldstart_") as tmp:
            if args.signals:
                rng = random.Random(args.seed)
                sig = signal.SIGINT if args.signal == "int" else signal.SIGTERM
                bad = []
                for i in range(args.signals):
                    delay = rng.uniform(0.0, args.max_delay)
                    work = pathlib.Path(tmp) / f"run{i}"
                    work.mkdir()
                    code, left = signal_run(feed, params_file, work, delay, sig)
                    print(f"  run {i + 1}: SIG{args.signal.upper()} at {delay:5.1f} s: exit {code}, left in the cache: "
                          f"{left or 'nothing'}", flush=True)
                    if code != 0 or left:
                        bad.append((i + 1, delay, code, left))
                print(f"{args.params}: {args.signals} starts stopped by SIG{args.signal.upper()} at 0-{args.max_delay:g} s: "
                      f"{sum(1 for b in bad if b[2] != 0)} exit status(es) other than 0, "
                      f"{sum(1 for b in bad if b[3])} with files left in the cache")
                return
            runs = []
            for i in range(args.runs):
                work = pathlib.Path(tmp) / f"run{i}"
                work.mkdir()
                r = timing_run(feed, params_file, work)
                runs.append(r)
                sw = "never" if r["switch_from_start"] is None else f"{r['switch_from_start']:.1f} s"
                print(f"  run {i + 1}: first grid {r['grid_from_start']:.1f} s after the process start, "
                      f"{r['grid_from_first_set']:.1f} s after the first complete set; switched to the exported "
                      f"backend at {sw}; exit {r['exit']}; left in the cache: {r['left'] or 'nothing'}", flush=True)
            med = {k: statistics.median(r[k] for r in runs) for k in ("grid_from_start", "grid_from_first_set")}
            print(f"{args.params}, cold export cache, median of {len(runs)}: first grid {med['grid_from_start']:.1f} s "
                  f"after the process start, {med['grid_from_first_set']:.1f} s after the first complete set")
    finally:
        node.destroy_node()
        rclpy.shutdown()


if __name__ == "__main__":
    main()
