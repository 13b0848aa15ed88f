"""Benchmark: the mapper node's end-to-end rate and latency with a real method, over DDS.

Starts ``mapper_node`` in its own process (a shipped parameter file, default ``surround6``;
loopback-only discovery, a private domain), publishes the file's rig's full-size synthetic images
(label images, or RGB where the file sets ``input_kind: rgb``) at ``--hz`` with stamps = now,
and measures on ``/bev/drivable``: grids per second and latency (receive time - image stamp).
When the method is slower than the input, the node drops stale sets (that is the design), so
the output rate is the method's sustainable rate.

    .venv/bin/python bench/bench_node_rate.py --method bimapper [--hz 20] [--seconds 20]
    .venv/bin/python bench/bench_node_rate.py --params front1_s2g2      # S2G2 on one RGB camera
"""

from __future__ import annotations

import argparse
import os
import pathlib
import statistics
import subprocess
import sys
import time

from bench_rows import row, write_rows

REPO = pathlib.Path(__file__).resolve().parents[1]


#: seconds allowed for the node's first grid (backend auto: the first start exports the model)
FIRST_GRID_S = 300.0

def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--params", default="surround6", help="config/<NAME>.yaml (default: %(default)s)")
    ap.add_argument("--method", default=None, help="override the file's method (bimapper, ipm, s2g2, ...)")
    ap.add_argument("--hz", type=float, default=20.0, help="input rate of synchronized sets")
    ap.add_argument("--seconds", type=float, default=20.0)
    ap.add_argument("--publishers", choices=("reliable", "best_effort"), default="reliable",
                    help="QoS reliability of the cameras' image publishers (the node's image_reliability "
                         "stays auto: it follows them)")
    ap.add_argument("--node-arg", action="append", default=[], metavar="NAME:=VALUE",
                    help="another node parameter, e.g. backend:=openvino (repeatable)")
    ap.add_argument("--json", default=None, help="also write the row for bench/bench_table.py here")
    ap.add_argument("--input", choices=("labels", "rgb"), default=None,
                    help="override the file's input_kind (rgb: the cameras' RGB images, the segmenter in front)")
    ap.add_argument("--settle", type=float, default=0.0,
                    help="seconds after the first grid before the measured window (a background export's switch)")
    ap.add_argument("--domain-id", type=int, default=150 + os.getpid() % 50)
    args = ap.parse_args()
    os.environ["ROS_AUTOMATIC_DISCOVERY_RANGE"] = "LOCALHOST"
    os.environ["ROS_DOMAIN_ID"] = str(args.domain_id)

    import rclpy  # noqa: PLC0415 - after the environment is set
    import yaml  # noqa: PLC0415
    from diagnostic_msgs.msg import DiagnosticArray  # noqa: PLC0415
    from nav_msgs.msg import OccupancyGrid  # noqa: PLC0415
    from rclpy.qos import QoSProfile, ReliabilityPolicy, qos_profile_sensor_data  # noqa: PLC0415
    from sensor_msgs.msg import CameraInfo, Image  # noqa: PLC0415

    from bev_mapper_core.geometry.grid import BevGrid  # noqa: PLC0415
    from bev_mapper_core.geometry.rig import preset_rig  # noqa: PLC0415
    from bev_mapper_core.synth import SynthConfig, generate_drive  # noqa: PLC0415
    from msg_adapters import RclpyFactory, make_camera_info, make_image  # noqa: PLC0415

    params_file = REPO / "config" / f"{args.params}.yaml"
    params = yaml.safe_load(params_file.read_text())["/**"]["ros__parameters"]
    rig, kind = preset_rig(params["rig"]), args.input or params.get("input_kind", "labels")
    method = args.method or params["method"]
    grid = BevGrid.from_dict(params["grid"])
    frames = [{n: (c.labels if kind == "labels" else c.rgb) for n, c in f.cameras.items()}
              for f in generate_drive(rig, grid, SynthConfig(frames=10, seed=950_000_008))]
    node_proc = subprocess.Popen(
        [sys.executable, "-m", "bev_mapper_ros.mapper_node", "--ros-args", "--params-file",
         str(params_file), "-p", f"method:={method}", "-p", f"input_kind:={kind}", *(a for p in args.node_arg for a in ("-p", p))],
        cwd=REPO, stdout=subprocess.DEVNULL, stderr=subprocess.STDOUT, env=dict(os.environ))
    rclpy.init()
    node = rclpy.create_node("bench_node_rate")
    factory = RclpyFactory()
    topic = "labels" if kind == "labels" else "image_raw"
    encoding = "mono8" if kind == "labels" else "rgb8"
    image_qos = (QoSProfile(depth=5, reliability=ReliabilityPolicy.RELIABLE) if args.publishers == "reliable"
                 else qos_profile_sensor_data)
    pubs = {c: node.create_publisher(Image, f"/cameras/{c}/{topic}", image_qos) for c in rig.names}
    infos = {c: node.create_publisher(CameraInfo, f"/cameras/{c}/camera_info", 10) for c in rig.names}
    received: list[tuple[float, int]] = []

    def on_grid(msg):
        received.append((time.time(), msg.header.stamp.sec * 1_000_000_000 + msg.header.stamp.nanosec))

    node.create_subscription(OccupancyGrid, "/bev/drivable", on_grid, 50)
    diag: dict[str, str] = {}
    node.create_subscription(
        DiagnosticArray, "/diagnostics",
        lambda m: diag.update({kv.key: kv.value for st in m.status for kv in st.values}), 10)
    try:
        deadline = time.monotonic() + 60
        while any(p.get_subscription_count() == 0 for p in pubs.values()):
            rclpy.spin_once(node, timeout_sec=0.05)
            if time.monotonic() > deadline or node_proc.poll() is not None:
                sys.exit("error: mapper_node did not come up")
        period = 1.0 / args.hz
        start = time.monotonic()
        k = 0
        warm = None
        # the window is --seconds from the first grid: the first start with backend auto exports the
        # model first (FIRST_GRID_S at most; a warm export cache loads it)
        while (time.monotonic() - start < FIRST_GRID_S) if warm is None else (time.time() - warm[1] < args.seconds):
            stamp = time.time_ns()
            for cam in rig.cameras:
                infos[cam.name].publish(make_camera_info(factory, cam.model, stamp, cam.frame_id))
                pubs[cam.name].publish(make_image(factory, frames[k % len(frames)][cam.name], encoding,
                                                  stamp, cam.frame_id))
            k += 1
            if warm is None and received and time.time() - received[0][0] >= args.settle:
                warm = len(received), time.time()
            next_t = start + k * period
            while time.monotonic() < next_t:
                rclpy.spin_once(node, timeout_sec=max(0.0, next_t - time.monotonic()))
        end_wall = time.time()
        if not received or warm is None:
            sys.exit("error: no grid received")
        steady = [r for r in received if r[0] >= warm[1]]
        rate = (len(steady) - 1) / (steady[-1][0] - steady[0][0]) if len(steady) > 1 else 0.0
        lat = [(t - s / 1e9) * 1000.0 for t, s in steady]
        w, h = rig.cameras[0].model.image_size
        print(f"{args.params}.yaml, method {method} {' '.join(args.node_arg)}: input {args.hz:.1f} sets/s of "
              f"{len(rig.cameras)} x {w}x{h} {kind} for {args.seconds:.0f} s, {args.publishers} publishers")
        print(f"output rate      : {rate:.1f} grids/s on /bev/drivable ({len(steady)} after warm-up)")
        p95 = sorted(lat)[int(0.95 * (len(lat) - 1))]
        print(f"latency (recv - stamp): p50 {statistics.median(lat):.1f} ms, p95 {p95:.1f} ms")
        print(f"sets published {k}, grids received {len(received)} ({end_wall - steady[0][0]:.1f} s steady)")
        keys = ("mapped_sets", "dropped_sets", "sets_with_missing_cameras", "bad_input", "processing_ms")
        print("node diagnostics : " + ", ".join(f"{key} {diag.get(key, '?')}" for key in keys))
        extra = f" {' '.join(args.node_arg)}" if args.node_arg else ""
        write_rows(args.json, "bench_node_rate.py", [row(
            f"node, {method}{extra}, {len(rig.cameras)} cameras at {args.hz:.0f} Hz, {args.publishers} publishers",
            f"{rate:.1f} sets/s mapped, p95 latency {p95:.0f} ms", f"{args.hz:.1f} sets/s published", rate / args.hz,
            f"fraction mapped; sets with a camera missing: {diag.get('sets_with_missing_cameras', '?')}, "
            f"processing {diag.get('processing_ms', '?')} ms")])
    finally:
        node.destroy_node()
        rclpy.shutdown()
        node_proc.send_signal(2)
        try:
            node_proc.wait(10)
        except subprocess.TimeoutExpired:
            node_proc.kill()


if __name__ == "__main__":
    main()
