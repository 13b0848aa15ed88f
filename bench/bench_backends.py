"""Benchmark: Bi-Mapper's ``Mapper.map`` with each inference backend, against torch eager in the
same run.

The shipped surround6 weights on 6 x 400x225 label images -> the 400x200 grid, batch 1, all of
``Mapper.map`` (the occlusion reasoning on label input included, the same for every backend).
Backends not installed are reported as such. The first frame of an ONNX backend exports the
model (or reads it from the cache, ``$BEV_MAPPER_CACHE``); that time is printed apart.

``--competitor``: every row again while another process keeps one CPU busy (a shared robot
computer), beside the quiet figures of the same run: what the thread default
(:func:`~bev_mapper_core.nn.runtime.inference_threads`, every CPU but one) is chosen for.

    .venv/bin/python bench/bench_backends.py [--frames 10] [--repeat 3] [--threads 1,2] [--competitor]
"""

from __future__ import annotations

import argparse
import contextlib
import os
import platform
import statistics
import subprocess
import sys
import time

from bench_rows import row, write_rows


@contextlib.contextmanager
def busy_competitor(on: bool):
    """A process spinning on one CPU while the block runs (nothing when ``on`` is False)."""
    if not on:
        yield
        return
    proc = subprocess.Popen([sys.executable, "-c", "while True: pass"])
    try:
        time.sleep(0.5)
        yield
    finally:
        proc.kill()
        proc.wait()


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--frames", type=int, default=10)
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--threads", default="1,2", help="comma list of thread counts")
    ap.add_argument("--competitor", action="store_true",
                    help="also measure every row with a busy process on one CPU")
    ap.add_argument("--json", default=None, help="also write the rows for bench/bench_table.py here")
    args = ap.parse_args()

    import torch

    from bev_mapper_core.geometry.grid import BevGrid
    from bev_mapper_core.geometry.rig import preset_rig
    from bev_mapper_core.nn.backends import AUTO_ORDER, installed_backends
    from bev_mapper_core.synth import SynthConfig, generate_drive

    rig, grid = preset_rig("surround6"), BevGrid()
    frames = [{n: c.labels for n, c in f.cameras.items()}
              for f in generate_drive(rig, grid, SynthConfig(frames=args.frames, seed=7))]
    have = installed_backends()
    print(f"{platform.processor() or platform.machine()}, {os.cpu_count()} CPUs, torch {torch.__version__}; "
          f"installed backends: {', '.join(have)}")
    print(f"Bi-Mapper (shipped surround6) Mapper.map, {len(frames)} frames, batch 1")
    from bev_mapper_core.nn.runtime import inference_threads

    print(f"default threads (every CPU but one): {inference_threads()}")
    quiet: dict[tuple[int, str], float] = {}
    loaded: dict[tuple[int, str], float] = {}
    for load in (False, True) if args.competitor else (False,):
        print("with one busy competing process:" if load else "quiet:")
        with busy_competitor(load):
            for threads in (int(t) for t in args.threads.split(",")):
                rows = [measure(backend, threads, have, rig, grid, frames, args.repeat)
                        for backend in ("torch",) + AUTO_ORDER]
                ref = rows[0][1]
                for backend, best, med, first_s in rows:
                    if best is None:
                        print(f"  {threads} thread(s) {backend:12s}: not installed")
                        continue
                    extra = "" if not load else f"; {med / quiet[threads, backend]:4.2f}x its quiet median"
                    (loaded if load else quiet)[threads, backend] = med
                    print(f"  {threads} thread(s) {backend:12s}: {best:7.1f} ms/frame (best of {args.repeat}; median "
                          f"{med:.1f}) = {ref / best:4.2f}x torch eager; first frame {first_s:.1f} s{extra}")
    rows = []
    for (threads, backend), med in quiet.items():
        if backend != "torch" and (threads, "torch") in quiet:
            rows.append(row(f"Bi-Mapper, {backend}, {threads} thread(s)", f"{med:.1f} ms",
                            f"{quiet[threads, 'torch']:.1f} ms (torch eager)", quiet[threads, "torch"] / med,
                            "median of the repeats"))
    default = inference_threads()
    for backend in ("torch",) + AUTO_ORDER:
        others = [t for t, b in loaded if b == backend and t != default]
        if (default, backend) in loaded and others:
            t = others[-1]
            rows.append(row(f"Bi-Mapper, {backend}, one busy competing process", f"{loaded[default, backend]:.1f} ms "
                            f"({default} thread(s), the default)", f"{loaded[t, backend]:.1f} ms ({t} threads)",
                            loaded[t, backend] / loaded[default, backend],
                            f"quiet: {quiet[default, backend]:.1f} / {quiet[t, backend]:.1f} ms"))
    write_rows(args.json, "bench_backends.py", rows)


def measure(backend, threads, have, rig, grid, frames, repeat):
    """``(backend, best ms/frame, median ms/frame, first-frame s)``; None figures if not installed."""
    from bev_mapper_core.mapper import MapperConfig, create_mapper

    if backend not in have:
        return backend, None, None, None
    m = create_mapper(rig, grid, MapperConfig(threads=threads, backend=backend))
    t0 = time.perf_counter()
    m.map(frames[0])  # load, export or cache read, warm-up
    first_s = time.perf_counter() - t0
    runs = []
    for _ in range(repeat):
        t = time.perf_counter()
        for f in frames:
            m.map(f)
        runs.append((time.perf_counter() - t) * 1000.0 / len(frames))
    return backend, min(runs), statistics.median(runs), first_s

if __name__ == "__main__":
    main()
