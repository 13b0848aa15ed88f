"""Benchmark: the mapper node's start-up, from process start to its first grid.

Starts ``mapper_node`` (``config/<params>.yaml``, ``method:=ipm`` unless ``--method``) in its own
process on a private loopback-only domain, publishes the rig's CameraInfo and full-size synthetic
images (labels or RGB, as the params say) at 10 Hz from the moment the process starts, and
measures the time until the first ``/bev/drivable`` grid arrives; it also reads the node's
``/proc/PID/maps`` then, to say whether torch was loaded. With ``--reference DIR`` (another
checkout of this package, e.g. a git worktree of an older commit) the runs alternate between the
two code trees in the same session.

``--methods`` (issue #28) instead times each learned method's params file with its default
``backend`` (``auto``: the fastest installed runtime) from a **cold** export cache (an empty
``$BEV_MAPPER_CACHE``: the first start exports) and then a **warm** one (the export of the cold
start reused), beside IPM and ``backend:=torch`` in the same session.

    .venv/bin/python bench/bench_node_startup.py --runs 5 --reference /tmp/ref
    .venv/bin/python bench/bench_node_startup.py --methods [--runs 2] [--json rows.json]
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


#: --methods: (label, params file, node arguments, export cache: None = the user's, "cold", "warm")
METHOD_RUNS = (
    ("ipm", "surround6", ["method:=ipm"], None),
    ("bimapper, backend:=torch", "surround6", ["backend:=torch"], None),
    ("bimapper, cold export cache", "surround6", [], "cold"),
    ("bimapper, warm export cache", "surround6", [], "warm"),
    ("s2g2, backend:=torch", "front1_s2g2", ["backend:=torch"], None),
    ("s2g2, cold export cache", "front1_s2g2", [], "cold"),
    ("s2g2, warm export cache", "front1_s2g2", [], "warm"),
    ("focusbev, backend:=torch", "front1_focusbev", ["backend:=torch"], None),
    ("focusbev, cold export cache", "front1_focusbev", [], "cold"),
    ("focusbev, warm export cache", "front1_focusbev", [], "warm"),
)


def one_run(code: pathlib.Path, params_file: pathlib.Path, node, pubs, infos, frames, rig, factory,
            node_args=("method:=ipm",), env_extra=None, encoding="mono8") -> tuple[float, bool]:
    """Seconds from the node's process start to its first grid, and whether torch was mapped."""
    import rclpy  # noqa: PLC0415

    from msg_adapters import make_camera_info, make_image  # noqa: PLC0415

    received: list[float] = []
    sub = node.create_subscription(__import__("nav_msgs.msg", fromlist=["OccupancyGrid"]).OccupancyGrid,
                                   "/bev/drivable", lambda m: received.append(time.monotonic()), 10)
    env = dict(os.environ, PYTHONPATH=str(code), **(env_extra or {}))
    args = [a for arg in node_args for a in ("-p", arg)]
    t0 = time.monotonic()
    proc = subprocess.Popen([sys.executable, "-m", "bev_mapper_ros.mapper_node", "--ros-args", "--params-file",
                             str(params_file), *args], cwd=code, env=env,
                            stdout=subprocess.DEVNULL, stderr=subprocess.STDOUT)
    try:
        k = 0
        while not received:
            if time.monotonic() - t0 > 300 or proc.poll() is not None:
                sys.exit(f"error: no grid from the node of {code}")
            stamp = time.time_ns()
            for cam in rig.cameras:
                infos[cam.name].publish(make_camera_info(factory, cam.model, stamp, cam.frame_id))
                pubs[cam.name].publish(make_image(factory, frames[k % len(frames)][cam.name], encoding, stamp,
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


def methods_session(args, node, factory) -> None:
    """``--methods``: every row of :data:`METHOD_RUNS`, ``args.runs`` rounds in turn."""
    import tempfile  # noqa: PLC0415

    import yaml  # noqa: PLC0415
    from bench_rows import row, write_rows  # noqa: PLC0415
    from rclpy.qos import QoSProfile, ReliabilityPolicy  # noqa: PLC0415
    from sensor_msgs.msg import CameraInfo, Image  # noqa: PLC0415

    from bev_mapper_core.geometry.grid import BevGrid  # noqa: PLC0415
    from bev_mapper_core.geometry.rig import preset_rig  # noqa: PLC0415
    from bev_mapper_core.nn.backends import resolve_backend  # noqa: PLC0415
    from bev_mapper_core.synth import SynthConfig, generate_drive  # noqa: PLC0415

    setups = {}
    for _, name, _, _ in METHOD_RUNS:
        if name in setups:
            continue
        params_file = REPO / "config" / f"{name}.yaml"
        params = yaml.safe_load(params_file.read_text())["/**"]["ros__parameters"]
        rig, grid = preset_rig(params["rig"]), BevGrid.from_dict(params["grid"])
        rgb = params.get("input_kind") == "rgb"
        frames = [{n: (c.rgb if rgb else c.labels) for n, c in f.cameras.items()}
                  for f in generate_drive(rig, grid, SynthConfig(frames=3, seed=950_000_008))]
        topic = "/cameras/{}/image_raw" if rgb else "/cameras/{}/labels"
        qos = QoSProfile(depth=5, reliability=ReliabilityPolicy.RELIABLE)
        pubs = {c: node.create_publisher(Image, topic.format(c), qos) for c in rig.names}
        infos = {c: node.create_publisher(CameraInfo, f"/cameras/{c}/camera_info", 10) for c in rig.names}
        setups[name] = (params_file, pubs, infos, frames, rig, "rgb8" if rgb else "mono8")
    times: dict[str, list[float]] = {label: [] for label, *_ in METHOD_RUNS}
    with tempfile.TemporaryDirectory(prefix="bench_startup_cache_") as tmp:
        for r in range(args.runs):
            cache = pathlib.Path(tmp) / f"round{r}"  # empty: cold; after the cold start: warm
            for label, name, node_args, which in METHOD_RUNS:
                params_file, pubs, infos, frames, rig, encoding = setups[name]
                env = {} if which is None else {"BEV_MAPPER_CACHE": str(cache / name)}
                t, _ = one_run(REPO, params_file, node, pubs, infos, frames, rig, factory, node_args, env, encoding)
                times[label].append(t)
                print(f"  round {r + 1}: {label}: {t:.2f} s", flush=True)
    backend = resolve_backend("auto")
    print(f"process start -> first /bev/drivable, median of {args.runs} round(s), the rows in turn; "
          f"backend auto = {backend} here")
    med = {label: statistics.median(ts) for label, ts in times.items()}
    for label, t in med.items():
        print(f"{label:32s}: {t:6.2f} s (min {min(times[label]):.2f}, max {max(times[label]):.2f})")
    rows = [row("node start -> first grid, IPM (surround6)", f"{med['ipm']:.1f} s", "", None, "method:=ipm")]
    for method in ("bimapper", "s2g2", "focusbev"):
        torch_t, cold, warm = (med[f"{method}, {k}"] for k in ("backend:=torch", "cold export cache", "warm export cache"))
        rows.append(row(f"node start -> first grid, {method}, backend auto ({backend})",
                        f"{cold:.1f} s cold export cache, {warm:.1f} s warm", f"{torch_t:.1f} s (backend:=torch)",
                        torch_t / warm, "cold: the first start exports the model; warm: it loads the cached export"))
    write_rows(args.json, "bench_node_startup.py", rows)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--methods", action="store_true", help="IPM and the learned methods, cold and warm export cache")
    ap.add_argument("--json", default=None, help="--methods: also write the rows for bench/bench_table.py here")
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

    if args.methods:
        rclpy.init()
        node = rclpy.create_node("bench_node_startup")
        try:
            methods_session(args, node, RclpyFactory())
        finally:
            node.destroy_node()
            rclpy.shutdown()
        return
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
