"""Benchmark: full-resolution cameras (1600 x 900) against the 400 x 225 ones, on RGB input.

A drive recorded elsewhere delivers its cameras at full size (nuScenes: 1600 x 900), the
shipped rigs at 400 x 225 (binning 4). The segmenter decides its labels at most at twice its
input width and nearest-upsamples them (:meth:`Segmenter.segment`), so the full-size camera
should cost about what the small one does. Rows, measured in this run, interleaved (each
repeat times every variant once, in turn; medians over the repeats):

* the segmenter stage on one camera image: 400 x 225, 1600 x 900, and 1600 x 900 the way it
  was (class scores upsampled to every pixel before the argmax: the reference);
* ``segipm`` on a six-camera surround6 frame at both sizes;
* chained Bi-Mapper (the shipped label weights behind the segmenter) at both sizes.

    .venv/bin/python bench/bench_full_resolution.py [--repeat 7] [--threads 1]
"""

from __future__ import annotations

import argparse
import statistics
import time

import cv2
import numpy as np
import torch
from bench_rows import machine, row, write_rows

from bev_mapper_core.geometry.camera import CameraModel
from bev_mapper_core.geometry.grid import BevGrid
from bev_mapper_core.geometry.rig import Rig, RigCamera, preset_rig
from bev_mapper_core.mapper import MapperConfig, create_mapper
from bev_mapper_core.methods.segmenter.stage import SegmenterStage, shipped_segmenter
from bev_mapper_core.synth import SynthConfig, generate_drive


def full_resolution(rig: Rig) -> Rig:
    """The rig's cameras delivered unbinned (1600 x 900 for surround6)."""
    cams = []
    for c in rig.cameras:
        m = c.model
        cams.append(RigCamera(c.name, CameraModel(K=m.K, D=m.D, width=m.width, height=m.height),
                              c.ego_from_cam_array, c.frame_id))
    return Rig(rig.name, tuple(cams))


def old_segment(stage: SegmenterStage, image: np.ndarray) -> np.ndarray:
    """The segmenter before full-resolution support: scores upsampled to every pixel, then argmax."""
    model = stage.model
    x = torch.from_numpy(image[None])
    with torch.inference_mode():
        return model(model.preprocess(x), size=image.shape[:2]).argmax(dim=1).to(torch.uint8)[0].numpy()


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--repeat", type=int, default=7)
    p.add_argument("--threads", type=int, default=1, help="torch threads (default 1: one core)")
    p.add_argument("--json", default=None, help="write the rows for bench_table.py here")
    args = p.parse_args()
    torch.set_num_threads(args.threads)
    cv2.setNumThreads(args.threads)

    small = preset_rig("surround6")
    full = full_resolution(small)
    grid = BevGrid()
    frame = next(iter(generate_drive(small, grid, SynthConfig(frames=1, seed=950000008))))
    rgb_small = {n: c.rgb for n, c in frame.cameras.items()}
    W, H = full.cameras[0].model.image_size
    rgb_full = {n: cv2.resize(img, (W, H), interpolation=cv2.INTER_LINEAR) for n, img in rgb_small.items()}
    stage = SegmenterStage(shipped_segmenter("surround6"))
    cfg = MapperConfig(method="segipm", input_kind="rgb", threads=args.threads)
    segipm = {"small": create_mapper(small, grid, cfg), "full": create_mapper(full, grid, cfg)}
    chained_cfg = MapperConfig(method="bimapper", input_kind="rgb", threads=args.threads, backend="torch")
    chained = {"small": create_mapper(small, grid, chained_cfg), "full": create_mapper(full, grid, chained_cfg)}

    variants = {
        "segment 400x225": lambda: stage.segment({"front": rgb_small["front"]}),
        "segment 1600x900": lambda: stage.segment({"front": rgb_full["front"]}),
        "segment 1600x900, scores upsampled (before)": lambda: old_segment(stage, rgb_full["front"]),
        "segipm 6 x 400x225": lambda: segipm["small"].map(rgb_small),
        "segipm 6 x 1600x900": lambda: segipm["full"].map(rgb_full),
        "chained Bi-Mapper 6 x 400x225": lambda: chained["small"].map(rgb_small),
        "chained Bi-Mapper 6 x 1600x900": lambda: chained["full"].map(rgb_full),
    }
    for fn in variants.values():  # warm-up: tables, allocations
        fn()
    times: dict[str, list[float]] = {k: [] for k in variants}
    for _ in range(args.repeat):
        for name, fn in variants.items():
            t0 = time.perf_counter()
            fn()
            times[name].append((time.perf_counter() - t0) * 1e3)
    med = {k: statistics.median(v) for k, v in times.items()}
    print(f"# {machine()}; torch threads {args.threads}; medians of {args.repeat} interleaved repeats")
    print(f"{'variant':48s} {'ms':>8s}")
    for k, v in med.items():
        print(f"{k:48s} {v:8.1f}")
    pairs = [("segment 1600x900", "segment 400x225"), ("segment 1600x900, scores upsampled (before)", "segment 1600x900"),
             ("segipm 6 x 1600x900", "segipm 6 x 400x225"),
             ("chained Bi-Mapper 6 x 1600x900", "chained Bi-Mapper 6 x 400x225")]
    rows = []
    for a, b in pairs:
        print(f"{a} / {b}: {med[a] / med[b]:.2f}x")
        rows.append(row("full resolution", f"{a}: {med[a]:.1f} ms", f"{b}: {med[b]:.1f} ms", med[a] / med[b]))
    write_rows(args.json, "bench_full_resolution", rows)


if __name__ == "__main__":
    main()
