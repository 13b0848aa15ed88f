"""Benchmark (issue #41): surround6 RGB (6 cameras of 400x225) at camera rate on the CPU: frames
per second of ``Mapper.map`` for the default chained Bi-Mapper (the segmenter per camera, then the
shipped label Bi-Mapper), for ``segipm`` and (``e2e``, issue #39) for the shipped end-to-end RGB
Bi-Mapper (``bimapper_surround6_rgb_e2e.safetensors``: segipm's map as its prior, then both view
streams on the RGB images), in each segmenter precision (``MapperConfig.segmenter_precision``), in
the same run.

Rows, per method: ``f32`` (the segmenter on onnxruntime in f32: the default before #41), ``auto``
(the default: OpenVINO in bf16 where the CPU has it, else f32), ``bf16`` and ``int8``
(:mod:`bev_mapper_core.methods.segmenter.int8`), with ``backend auto`` and the default threads.
The configurations take turns frame by frame (``--repeat`` rounds over ``--frames`` frames of a
held-out drive, seed 950000010), so a busy shared machine slows them alike; the figure is the
median ``map`` time and its frames per second. The segmenter stage alone is timed the same way
(its six cameras), so the rest (Bi-Mapper or IPM, Python) is the difference.

``--node``: then the node itself (``bench/bench_node_rate.py``, RGB input at ``--hz``), once per
precision, in turns; frames published per second on ``/bev/drivable``. The export cache is the
usual one (``$BEV_MAPPER_CACHE``); the first run of a precision exports (int8: exports and
quantizes, about 20 s), not timed.

    .venv/bin/python bench/bench_rgb_rate.py [--frames 6] [--repeat 5] [--methods bimapper segipm e2e]
        [--node [--hz 10] [--seconds 15]]
"""

from __future__ import annotations

import argparse
import os
import pathlib
import re
import statistics
import subprocess
import sys
import time

import numpy as np
import torch

REPO = pathlib.Path(__file__).resolve().parents[1]
PRECISIONS = ("f32", "auto", "bf16", "int8")
#: the shipped end-to-end RGB Bi-Mapper (``--methods e2e``)
E2E = "bimapper_surround6_rgb_e2e.safetensors"


def _mapper_rows(args) -> None:
    from bev_mapper_core.geometry.grid import BevGrid
    from bev_mapper_core.geometry.rig import preset_rig
    from bev_mapper_core.labels.classes import BEV_CLASS_NAMES
    from bev_mapper_core.mapper import MapperConfig, create_mapper
    from bev_mapper_core.methods import WEIGHTS_DIR
    from bev_mapper_core.training.data import render_drive

    rig, grid = preset_rig("surround6"), BevGrid()
    drive = render_drive(rig, grid, BEV_CLASS_NAMES, 950000010, args.frames, 3, rgb=(225, 400))
    frames = [{n: np.ascontiguousarray(drive["rgb"][k, i]) for i, n in enumerate(rig.names)}
              for k in range(args.frames)]
    print(f"torch {torch.__version__}, {os.cpu_count()} CPUs; surround6 RGB 6 x 400x225; medians of "
          f"{args.repeat} x {args.frames} frames, configurations in turns")
    for method in args.methods:
        mappers = {}
        for p in args.precisions:
            e2e = {"method": "bimapper", "weights": str(WEIGHTS_DIR / E2E)} if method == "e2e" else {"method": method}
            m = create_mapper(rig, grid, MapperConfig(input_kind="rgb", segmenter_precision=p, **e2e))
            m.map(frames[0])  # export / cache read, not timed
            mappers[p] = m
        t_map = {p: [] for p in mappers}
        t_seg = {p: [] for p in mappers}
        for _ in range(args.repeat):
            for f in frames:
                for p, m in mappers.items():
                    t = time.perf_counter()
                    m.map(f)
                    t_map[p].append(time.perf_counter() - t)
                    t = time.perf_counter()
                    (m.stage or m.prior.mapper.stage).segment(f)  # e2e: the prior's segmenter
                    t_seg[p].append(time.perf_counter() - t)
        name = {"bimapper": "chained Bi-Mapper", "e2e": f"end-to-end RGB Bi-Mapper ({E2E})"}.get(method, method)
        print(f"\n{name}: precision, what runs, map ms, frames/s, segmenter stage ms (6 cameras), rest ms")
        for p, m in mappers.items():
            ms, seg = 1000 * statistics.median(t_map[p]), 1000 * statistics.median(t_seg[p])
            print(f"  {p:5} {m.backend_state:40} {ms:7.1f} {1000 / ms:6.2f} {seg:7.1f} {ms - seg:7.1f}", flush=True)


def _node_rows(args) -> None:
    rates: dict[str, list[str]] = {p: [] for p in args.precisions}
    for _ in range(args.node_repeat):
        for p in args.precisions:
            cmd = [sys.executable, str(REPO / "bench" / "bench_node_rate.py"), "--input", "rgb", "--hz", str(args.hz),
                   "--seconds", str(args.seconds), "--settle", "3", "--node-arg", f"segmenter_precision:={p}",
                   "--domain-id", str(args.domain_id)]
            res = subprocess.run(cmd, cwd=REPO, capture_output=True, text=True, check=False)
            out = res.stdout
            if res.returncode != 0:
                print(f"  node, precision {p}: failed ({(res.stderr or out).strip().splitlines()[-1:]})")
            m = re.search(r"output rate\s*: ([\d.]+)", out)
            d = re.search(r"processing_ms (\S+)", out)
            rates[p].append(f"{m.group(1) if m else '?'} grids/s (processing {d.group(1) if d else '?'} ms)")
            print(f"  node, precision {p}: {rates[p][-1]}", flush=True)
    print(f"\nnode, chained Bi-Mapper, surround6 RGB at {args.hz:g} Hz, {args.seconds:g} s a run:")
    for p, r in rates.items():
        print(f"  {p:5} " + "; ".join(r))


def main() -> None:
    """Print the tables (see the module docstring)."""
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--frames", type=int, default=6)
    ap.add_argument("--repeat", type=int, default=5)
    ap.add_argument("--methods", nargs="+", default=["bimapper", "segipm", "e2e"],
                    choices=["bimapper", "segipm", "e2e"])
    ap.add_argument("--precisions", nargs="+", default=list(PRECISIONS), choices=PRECISIONS)
    ap.add_argument("--node", action="store_true", help="also the node's published grids per second")
    ap.add_argument("--node-only", action="store_true", help="only the node's rows")
    ap.add_argument("--node-repeat", type=int, default=1)
    ap.add_argument("--hz", type=float, default=10.0)
    ap.add_argument("--seconds", type=float, default=15.0)
    ap.add_argument("--domain-id", type=int, default=int(os.environ.get("ROS_DOMAIN_ID") or 150 + os.getpid() % 50))
    args = ap.parse_args()
    if not args.node_only:
        _mapper_rows(args)
    if args.node or args.node_only:
        _node_rows(args)


if __name__ == "__main__":
    main()
