"""Benchmark: ``bev-bag evaluate`` throughput with 1 and 2 Ray workers, Ray's overhead per bag,
the size of a bag's result and the driver's cost per bag; then Ray alone on simulated
multi-node clusters (``ray.cluster_utils.Cluster``) for the scaling model of docs/SCALING.md.

Writes ``--bags`` synthetic surround6 drives (full-size cameras, the standard 400x200 grid at
0.15 m) of ``--frames`` frames, then, in one process:

1. replays them one after the other in-process with :func:`bags.replay.replay` (IPM, the
   evaluate defaults: pictures of every 10th frame, report.html): seconds per bag and frame;
2. evaluates them with :func:`bags.fleet.evaluate.evaluate` with 1 and 2 workers (a local Ray
   runtime each): wall time, frames/s, the ratio; Ray's overhead per bag = (task phase with
   1 worker - in-process replay time) / bags;
3. the result of one bag as sent back (JSON bytes, and per frame), and the driver's cost per bag:
   :func:`bags.fleet.replay_tasks.aggregate` over 1,000 copies of a record and one ``evaluate.json`` write;
4. ``--nodes`` simulated clusters of N nodes with 2 CPUs each, running ``--sim-tasks`` tasks that
   sleep ``--sim-sleep`` s and return a bag-sized result through the same windowed submit loop
   shape (at most 2 x N in flight): wall vs ideal, and with 0 s tasks the most tasks per second
   the driver and Ray's scheduler sustain here.

    nice -n 19 .venv/bin/python bench/bench_evaluate.py [--bags 8] [--frames 10] [--nodes 1 2 4]
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import shutil
import tempfile
import time
from dataclasses import replace
from pathlib import Path

os.environ.setdefault("OMP_NUM_THREADS", "1")

from bench_rows import machine  # noqa: E402

from bags.cli.synth import SynthBagOptions, synth_bag  # noqa: E402
from bags.files import write_atomic  # noqa: E402
from bags.fleet.evaluate import EvaluateOptions, evaluate  # noqa: E402
from bags.fleet.replay_tasks import aggregate, evaluate_bag  # noqa: E402
from bags.replay import ReplayOptions, replay  # noqa: E402
from bev_mapper_core.mapper import MapperConfig  # noqa: E402
from bev_mapper_core.synth.config import SynthConfig  # noqa: E402


def simulated(nodes: int, tasks: int, sleep_s: float, payload: dict) -> tuple[float, float]:
    """``(wall s, start s)`` of ``tasks`` sleeping tasks on a simulated ``nodes``-node cluster."""
    import ray  # noqa: PLC0415
    from ray.cluster_utils import Cluster  # noqa: PLC0415

    t0 = time.perf_counter()
    cluster = Cluster(initialize_head=True, head_node_args={"num_cpus": 2, "include_dashboard": False})
    for _ in range(nodes - 1):
        cluster.add_node(num_cpus=2)
    ray.init(address=cluster.address, log_to_driver=False, logging_level="WARNING")
    cluster.wait_for_nodes()

    @ray.remote(num_cpus=1, max_retries=0)
    def task(i: int, sleep_s: float) -> dict:
        time.sleep(sleep_s)
        return payload

    ray.get([task.remote(i, 0.0) for i in range(2 * nodes)])  # workers started
    start = time.perf_counter() - t0
    window = 2 * nodes
    t = time.perf_counter()
    pending, i, records = set(), 0, []
    while i < tasks or pending:
        while i < tasks and len(pending) < window:
            pending.add(task.remote(i, sleep_s))
            i += 1
        ready, _ = ray.wait(list(pending), num_returns=1)
        for ref in ready:
            pending.discard(ref)
            records.append(ray.get(ref))
    wall = time.perf_counter() - t
    ray.shutdown()
    cluster.shutdown()
    return wall, start


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--bags", type=int, default=8)
    ap.add_argument("--frames", type=int, default=10)
    ap.add_argument("--nodes", type=int, nargs="*", default=[1, 2, 4])
    ap.add_argument("--sim-tasks", type=int, default=64)
    ap.add_argument("--sim-sleep", type=float, default=0.25)
    ap.add_argument("--keep", type=Path, default=None)
    args = ap.parse_args()
    print(f"machine: {machine()} usable, Python {platform.python_version()}; load average "
          f"{os.getloadavg()[0]:.2f}")
    tmp = Path(tempfile.mkdtemp(prefix="bench_evaluate_"))
    try:
        bags = []
        t0 = time.perf_counter()
        for i in range(args.bags):
            bag = tmp / "drives" / f"drive{i}"
            synth_bag(SynthBagOptions(out=bag, synth=SynthConfig(frames=args.frames, seed=100 + i)))
            bags.append(bag)
        size = sum(p.stat().st_size for p in (tmp / "drives").rglob("*") if p.is_file()) / len(bags)
        print(f"{args.bags} surround6 drives of {args.frames} frames ({size / 1e6:.1f} MB each) "
              f"written in {time.perf_counter() - t0:.1f} s")
        base = ReplayOptions(bag=Path(), out=Path(), mapper=MapperConfig(method="ipm"))

        # 1. in-process, one after the other
        t0 = time.perf_counter()
        seconds = []
        for i, bag in enumerate(bags):
            t = time.perf_counter()
            replay(replace(base, bag=bag, out=tmp / "seq" / f"b{i}"))
            seconds.append(time.perf_counter() - t)
        seq = time.perf_counter() - t0
        frames = args.bags * args.frames
        print(f"in-process replay(): {seq:.2f} s, {frames / seq:.2f} frames/s, "
              f"{seq / args.bags:.3f} s per bag ({min(seconds):.3f}..{max(seconds):.3f})")
        t = time.perf_counter()
        for i, bag in enumerate(bags):
            replay(replace(base, bag=bag, out=tmp / "seq2" / f"b{i}", max_frames=2))
        short = (time.perf_counter() - t) / args.bags
        per_frame = (seq / args.bags - short) / (args.frames - 2)
        out_size = sum(p.stat().st_size for p in (tmp / "seq").rglob("*") if p.is_file()) / args.bags
        print(f"in-process, the same bags stopped after 2 frames: {short:.3f} s per bag: a bag costs "
              f"{short - 2 * per_frame:.3f} s + {per_frame * 1000:.0f} ms per frame; outputs "
              f"{out_size / 1e6:.2f} MB per {args.frames}-frame bag")

        # 2. evaluate with 1 and 2 workers (and 1 worker on half the bags, for the per-bag gap)
        runs = {}
        half = bags[: args.bags // 2]
        for key, w, these in (("1", 1, bags), ("2", 2, bags), ("1/2", 1, half)):
            t = time.perf_counter()
            res = evaluate(EvaluateOptions(bags=tuple(these), out=tmp / f"ev{len(runs)}", replay=base,
                                           workers=w))
            wall = time.perf_counter() - t
            tm = res.summary["timing"]
            assert res.summary["complete"], res.summary["per_bag"]
            in_task = sum(e["seconds"] for e in res.summary["per_bag"])
            cpu = sum(e["cpu_seconds"] for e in res.summary["per_bag"])
            runs[key] = (wall, tm, in_task)
            n = len(these) * args.frames
            print(f"evaluate --workers {w} on {len(these)} bags: {wall:.2f} s wall = Ray start "
                  f"{tm['ray_start_s']:.2f} + tasks {tm['tasks_s']:.2f} + Ray stop {tm['ray_stop_s']:.2f} "
                  f"+ rest; {n / wall:.2f} frames/s wall, {n / tm['tasks_s']:.2f} frames/s in the task "
                  f"phase; replay() inside the tasks {in_task:.2f} s ({cpu:.2f} s CPU)")
        r_wall = runs["1"][0] / runs["2"][0]
        r_tasks = runs["1"][1]["tasks_s"] / runs["2"][1]["tasks_s"]
        print(f"2 workers / 1 worker: x{r_wall:.2f} on wall time, x{r_tasks:.2f} in the task phase")
        overhead = (runs["1"][1]["tasks_s"] - seq) / args.bags
        print(f"Ray overhead per bag, (1-worker task phase - in-process replays) / bags: {overhead * 1000:.0f} ms")
        # task phase - replay() time inside the tasks = worker start-up + gap per bag x bags
        g_all = runs["1"][1]["tasks_s"] - runs["1"][2]
        g_half = runs["1/2"][1]["tasks_s"] - runs["1/2"][2]
        gap = (g_all - g_half) / (args.bags - len(half))
        print(f"  outside replay(): {g_all:.2f} s over {args.bags} bags, {g_half:.2f} s over {len(half)}: "
              f"{gap * 1000:.0f} ms per bag + {g_all - gap * args.bags:.2f} s worker start-up (per run); "
              f"replay() in a task vs in-process: {(runs['1'][2] - seq) / args.bags * 1000:+.0f} ms per bag")

        # 3. a bag's result and the driver's cost per bag
        record = evaluate_bag(replace(base, bag=bags[0], out=tmp / "one"), "drive0")
        blob = json.dumps(record).encode()
        lat = json.dumps(record["latencies_ms"]).encode()
        print(f"result of one bag: {len(blob) / 1e3:.1f} kB JSON ({len(lat) / args.frames:.0f} B per frame "
              f"of latencies + {(len(blob) - len(lat)) / 1e3:.1f} kB fixed)")
        many = [{**record, "name": f"b{i}"} for i in range(1000)]
        t = time.perf_counter()
        aggregate(many)
        agg = (time.perf_counter() - t) / len(many)
        t = time.perf_counter()
        for _ in range(50):
            write_atomic(tmp / "rec.json", blob)
        write = (time.perf_counter() - t) / 50
        print(f"driver per bag: aggregate {agg * 1e6:.0f} us (1,000 records), evaluate.json write "
              f"{write * 1e6:.0f} us")

        # 4. simulated clusters
        payload = {k: v for k, v in record.items()}
        for n in args.nodes:
            wall, start = simulated(n, args.sim_tasks, args.sim_sleep, payload)
            ideal = args.sim_tasks * args.sim_sleep / (2 * n)
            print(f"simulated {n} node(s) x 2 CPUs: {args.sim_tasks} tasks of {args.sim_sleep} s in "
                  f"{wall:.2f} s (ideal {ideal:.2f} s, +{(wall - ideal) / args.sim_tasks * 1000:.1f} ms "
                  f"per task; cluster start {start:.1f} s)")
        for n in args.nodes[-1:]:
            wall, _ = simulated(n, 4 * args.sim_tasks, 0.0, payload)
            print(f"simulated {n} node(s), 0 s tasks: {4 * args.sim_tasks / wall:.0f} tasks/s "
                  f"through the driver ({wall / (4 * args.sim_tasks) * 1000:.1f} ms per task)")
        print(f"load average at the end: {os.getloadavg()[0]:.2f}")
        if args.keep:
            shutil.copytree(tmp, args.keep, dirs_exist_ok=True)
    finally:
        shutil.rmtree(tmp, ignore_errors=True)


if __name__ == "__main__":
    main()
