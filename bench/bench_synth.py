"""Benchmark: synthetic drive generation, ms per frame (all cameras + ground truth), one thread.

    OMP_NUM_THREADS=1 .venv/bin/python bench/bench_synth.py [--rig surround6] [--frames 20] [--seed 0]
        [--style mixed]
"""

from __future__ import annotations

import argparse
import os
import time

os.environ.setdefault("OMP_NUM_THREADS", "1")
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import cv2  # noqa: E402
import numpy as np  # noqa: E402

from bev_mapper_core.geometry.grid import BevGrid  # noqa: E402
from bev_mapper_core.geometry.rig import preset_rig  # noqa: E402
from bev_mapper_core.synth import DriveRenderer, SynthConfig, build_world  # noqa: E402
from bev_mapper_core.synth.styles import STYLE_CHOICES  # noqa: E402


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--rig", default="surround6")
    ap.add_argument("--frames", type=int, default=20)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--style", default=SynthConfig.style, choices=STYLE_CHOICES,
                    help="appearance style (default: SynthConfig's)")
    args = ap.parse_args()
    cv2.setNumThreads(1)
    rig, grid = preset_rig(args.rig), BevGrid()
    t0 = time.perf_counter()
    world = build_world(SynthConfig(frames=args.frames, seed=args.seed, style=args.style))
    t1 = time.perf_counter()
    renderer = DriveRenderer(world, rig, grid)
    t2 = time.perf_counter()
    times = []
    for k in range(args.frames):
        t = time.perf_counter()
        renderer.frame(k)
        times.append(time.perf_counter() - t)
    w, h = rig.cameras[0].model.image_size
    ms = np.array(times) * 1000.0
    print(f"{args.rig}: {len(rig.cameras)} cameras at {w}x{h}, grid {grid.describe()}, "
          f"style {args.style} ({renderer.style})")
    print(f"world build {1000 * (t1 - t0):.0f} ms, renderer set-up {1000 * (t2 - t1):.0f} ms")
    print(f"first frame {ms[0]:.0f} ms (builds ground tiles)")
    print(f"frames 1..: median {np.median(ms[1:]):.0f} ms, mean {ms[1:].mean():.0f} ms,"
          f" max {ms[1:].max():.0f} ms per frame")


if __name__ == "__main__":
    main()
