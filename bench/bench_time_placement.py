"""Benchmark: what a new rig costs each method, the cost behind each camera at its own time (#38).

surround6 (400x225 label images), the default 200x400 grid at 0.15 m. Rows, per method:

* ``set_rig, every camera new``: a calibration no table was built for (what Bi-Mapper pays at
  every set_rig: its tables are rebuilt whatever changed);
* ``set_rig, one camera moved``: a time placement whose rounding changed for one camera (IPM
  rebuilds that camera's tables only, the others come from its per-camera cache);
* ``set_rig, back to a kept rig``: every camera's tables in the cache;
* with ``--onnx``: Bi-Mapper on onnxruntime, set_rig then the next frame's map (the re-export a
  new rig costs it; tens of seconds on 2 cores, with an empty export cache).

    .venv/bin/python bench/bench_time_placement.py [--repeat 3] [--onnx]
"""

from __future__ import annotations

import argparse
import os
import tempfile
import time
from dataclasses import replace

import numpy as np

from bev_mapper_core.geometry.grid import BevGrid
from bev_mapper_core.geometry.rig import preset_rig
from bev_mapper_core.geometry.transforms import make_transform
from bev_mapper_core.mapper import MapperConfig, create_mapper


def moved(rig, names, dx):
    """``rig`` with cameras ``names`` moved ``dx`` m forward (a placed rig)."""
    for n in names:
        cam = rig[n]
        rig = rig.with_camera(replace(cam, ego_from_cam=make_transform(np.eye(3), (dx, 0, 0)) @ cam.ego_from_cam_array))
    return rig


def timed(fn, repeat):
    out = []
    for i in range(repeat):
        t = time.perf_counter()
        fn(i)
        out.append((time.perf_counter() - t) * 1e3)
    return min(out)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--onnx", action="store_true", help="also Bi-Mapper on onnxruntime (a re-export per rig)")
    args = ap.parse_args()
    rig, grid = preset_rig("surround6"), BevGrid()
    configs = [("ipm", MapperConfig(method="ipm")), ("ipm classical", MapperConfig(method="ipm", ipm_occlusion=False)),
               ("bimapper torch", MapperConfig(method="bimapper", backend="torch"))]
    print(f"{'method':<16} {'every camera new':>18} {'one camera moved':>18} {'back to a kept rig':>20}  (ms, best of {args.repeat})")
    for label, cfg in configs:
        m = create_mapper(rig, grid, cfg)
        k = iter(range(1, 10_000))
        new = timed(lambda i, m=m, k=k: m.set_rig(moved(rig, rig.names, 0.01 * next(k))), args.repeat)
        one = timed(lambda i, m=m, k=k: m.set_rig(moved(rig, ("back",), 0.01 * next(k))), args.repeat)
        m.set_rig(rig)
        kept = timed(lambda i, m=m: m.set_rig(rig), args.repeat)
        print(f"{label:<16} {new:>18.1f} {one:>18.1f} {kept:>20.1f}")
    if args.onnx:
        os.environ["BEV_MAPPER_CACHE"] = tempfile.mkdtemp()
        m = create_mapper(rig, grid, MapperConfig(method="bimapper", backend="onnxruntime"))
        labels = {c.name: np.zeros(c.model.image_size[::-1], np.uint8) for c in rig.cameras}
        m.map(labels)
        t = time.perf_counter()
        m.set_rig(moved(rig, ("back",), 0.15))
        m.map(labels)
        print(f"bimapper onnxruntime: set_rig + the next map (its re-export): {(time.perf_counter() - t):.1f} s")


if __name__ == "__main__":
    main()
