"""Benchmark: Bi-Mapper's ``Mapper.map`` with each inference backend, against torch eager in the
same run.

The shipped surround6 weights on 6 x 400x225 label images -> the 400x200 grid, batch 1, all of
``Mapper.map`` (the occlusion reasoning on label input included, the same for every backend).
Backends not installed are reported as such. The first frame of an ONNX backend exports the
model (or reads it from the cache, ``$BEV_MAPPER_CACHE``); that time is printed apart.

    .venv/bin/python bench/bench_backends.py [--frames 10] [--repeat 3] [--threads 1,2]
"""

from __future__ import annotations

import argparse
import os
import platform
import statistics
import time


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--frames", type=int, default=10)
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--threads", default="1,2", help="comma list of thread counts")
    args = ap.parse_args()

    import torch

    from bev_mapper_core.grid import BevGrid
    from bev_mapper_core.mapper import MapperConfig, create_mapper
    from bev_mapper_core.models.backends import AUTO_ORDER, installed_backends
    from bev_mapper_core.rig import preset_rig
    from bev_mapper_core.synth import SynthConfig, generate_drive

    rig, grid = preset_rig("surround6"), BevGrid()
    frames = [{n: c.labels for n, c in f.cameras.items()}
              for f in generate_drive(rig, grid, SynthConfig(frames=args.frames, seed=7))]
    have = installed_backends()
    print(f"{platform.processor() or platform.machine()}, {os.cpu_count()} CPUs, torch {torch.__version__}; "
          f"installed backends: {', '.join(have)}")
    print(f"Bi-Mapper (shipped surround6) Mapper.map, {len(frames)} frames, batch 1")
    for threads in (int(t) for t in args.threads.split(",")):
        rows = []
        for backend in ("torch",) + AUTO_ORDER:
            if backend not in have:
                rows.append((backend, None, None, None))
                continue
            m = create_mapper(rig, grid, MapperConfig(threads=threads, backend=backend))
            t0 = time.perf_counter()
            m.map(frames[0])  # load, export or cache read, warm-up
            first_s = time.perf_counter() - t0
            runs = []
            for _ in range(args.repeat):
                t = time.perf_counter()
                for f in frames:
                    m.map(f)
                runs.append((time.perf_counter() - t) * 1000.0 / len(frames))
            rows.append((backend, min(runs), statistics.median(runs), first_s))
        ref = rows[0][1]
        for backend, best, med, first_s in rows:
            if best is None:
                print(f"  {threads} thread(s) {backend:12s}: not installed")
                continue
            print(f"  {threads} thread(s) {backend:12s}: {best:7.1f} ms/frame (best of {args.repeat}; median "
                  f"{med:.1f}) = {ref / best:4.2f}x torch eager; first frame {first_s:.1f} s")


if __name__ == "__main__":
    main()
