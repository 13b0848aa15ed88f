"""Soak: the mapper node for a long run on a looping bag; its memory must stay flat.

Starts ``mapper_node`` (default: the shipped surround6 Bi-Mapper, ``temporal_window`` 3,
``use_sim_time``) and ``bev-bag play --loop --clock`` of a drive (default: the demo drive,
``data/demo_drive``; ``bash scripts/demo.sh`` writes it), both in their own processes on a private
domain, and samples every ``--every`` seconds: the node's resident memory (``VmRSS``), the grids
received on ``/bev/drivable``, the ``/diagnostics`` messages and the last one (level, rate, latency, temporal
resets, clock jumps back). Prints one row per sample and a summary: RSS after the warm-up (the
first sample past ``--warmup``) against the last, and its largest step.

    .venv/bin/python bench/soak_node.py                        # 30 min (the issue's soak)
    .venv/bin/python bench/soak_node.py --minutes 2 --every 10 # a quick check that it works
"""

from __future__ import annotations

import argparse
import os
import pathlib
import signal
import subprocess
import sys
import tempfile
import time

REPO = pathlib.Path(__file__).resolve().parents[1]


def rss_mb(pid: int) -> float | None:
    """Resident memory of process ``pid`` (MB), None when it is gone."""
    try:
        for line in pathlib.Path(f"/proc/{pid}/status").read_text().splitlines():
            if line.startswith("VmRSS:"):
                return int(line.split()[1]) / 1024.0
    except OSError:
        return None
    return None


def _stop(proc: subprocess.Popen) -> int | None:
    if proc.poll() is None:
        os.killpg(proc.pid, signal.SIGINT)
        try:
            proc.wait(30)
        except subprocess.TimeoutExpired:
            os.killpg(proc.pid, signal.SIGKILL)
            proc.wait(10)
    return proc.returncode


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--minutes", type=float, default=30.0)
    ap.add_argument("--every", type=float, default=30.0, help="seconds between samples")
    ap.add_argument("--warmup", type=float, default=60.0, help="seconds before the reference RSS sample")
    ap.add_argument("--bag", type=pathlib.Path, default=REPO / "data" / "demo_drive")
    ap.add_argument("--params", default="surround6", help="config/<NAME>.yaml (default: %(default)s)")
    ap.add_argument("--method", default="bimapper")
    ap.add_argument("--temporal-window", type=int, default=3)
    ap.add_argument("--node-arg", action="append", default=[], metavar="NAME:=VALUE")
    ap.add_argument("--domain-id", type=int, default=200 + os.getpid() % 30)
    args = ap.parse_args()
    if not (args.bag / "metadata.yaml").is_file() and not args.bag.is_file():
        print(f"error: no bag at {args.bag} (bash scripts/demo.sh writes the demo drive)", file=sys.stderr)
        return 1
    os.environ["ROS_AUTOMATIC_DISCOVERY_RANGE"] = "LOCALHOST"
    os.environ["ROS_DOMAIN_ID"] = str(args.domain_id)

    import rclpy  # noqa: PLC0415 - after the environment is set
    from diagnostic_msgs.msg import DiagnosticArray  # noqa: PLC0415
    from nav_msgs.msg import OccupancyGrid  # noqa: PLC0415

    logs = pathlib.Path(tempfile.mkdtemp(prefix="soak_node_"))
    node_cmd = [sys.executable, "-m", "bev_mapper_ros.mapper_node", "--ros-args", "--params-file",
                str(REPO / "config" / f"{args.params}.yaml"), "-p", f"method:={args.method}",
                "-p", f"temporal_window:={args.temporal_window}", "-p", "use_sim_time:=true",
                *(a for p in args.node_arg for a in ("-p", p))]
    play_cmd = [sys.executable, "-m", "bags.cli.main", "play", str(args.bag), "--loop", "--clock", "--quiet"]
    with open(logs / "node.log", "w") as nlog, open(logs / "play.log", "w") as plog:
        node_proc = subprocess.Popen(node_cmd, cwd=REPO, stdout=nlog, stderr=subprocess.STDOUT,
                                     start_new_session=True)
        play_proc = subprocess.Popen(play_cmd, cwd=REPO, stdout=plog, stderr=subprocess.STDOUT,
                                     start_new_session=True)
    rclpy.init()
    node = rclpy.create_node("soak_node_bench")
    grids = [0]
    diag_count = [0]
    diag: dict = {}
    node.create_subscription(OccupancyGrid, "/bev/drivable", lambda m: grids.__setitem__(0, grids[0] + 1), 10)

    def on_diag(msg) -> None:
        for st in msg.status:
            if "bev mapper" in st.name:
                diag_count[0] += 1
                diag.clear()
                diag.update({kv.key: kv.value for kv in st.values}, level=int.from_bytes(st.level, "little"))

    node.create_subscription(DiagnosticArray, "/diagnostics", on_diag, 10)
    print(f"soak: {args.method} temporal_window {args.temporal_window} on {args.bag} looping with /clock, "
          f"{args.minutes:g} min (logs in {logs})")
    print(f"{'t_s':>7}  {'rss_MB':>7}  {'grids':>6}  {'level':>5}  {'rate_hz':>7}  {'lat_ms':>7}  "
          f"{'resets':>6}  {'clk_back':>8}")
    samples: list[tuple[float, float]] = []
    t0 = time.monotonic()
    end = t0 + args.minutes * 60.0
    next_sample = t0 + args.every
    try:
        while time.monotonic() < end:
            rclpy.spin_once(node, timeout_sec=0.1)
            if node_proc.poll() is not None or play_proc.poll() is not None:
                print("error: the node or the player stopped early; see the logs", file=sys.stderr)
                return 1
            if time.monotonic() >= next_sample:
                next_sample += args.every
                t, rss = time.monotonic() - t0, rss_mb(node_proc.pid)
                samples.append((t, rss))
                print(f"{t:7.0f}  {rss:7.1f}  {grids[0]:6d}  {diag.get('level', '-'):>5}  "
                      f"{diag.get('rate_hz', '-'):>7}  {diag.get('latency_ms', '-') or '-':>7}  "
                      f"{diag.get('temporal_resets', '-'):>6}  {diag.get('clock_jumps_back', '-'):>8}", flush=True)
    finally:
        node.destroy_node()
        rclpy.try_shutdown()
        play_rc, node_rc = _stop(play_proc), _stop(node_proc)
    after = [r for t, r in samples if t >= args.warmup] or [r for _, r in samples]
    if len(after) >= 2:
        steps = [b - a for a, b in zip(after, after[1:])]
        print(f"RSS after warm-up {after[0]:.1f} MB -> last {after[-1]:.1f} MB ({after[-1] - after[0]:+.1f} MB), "
              f"largest step {max(steps, key=abs):+.1f} MB; {grids[0]} grids; {diag_count[0]} /diagnostics messages "
              f"in {samples[-1][0]:.0f} s; node exit {node_rc}, player exit {play_rc}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
