"""Benchmark: IPM ms/frame against its gather floor, cv2.remap, and naive ray casting.

surround6 label images (400x225 each) -> the default 200x400 grid at 0.15 m, 7 classes. Rows,
all measured in this run on the same frames:

* ``IpmMapper.map``, classical (``ipm_occlusion`` off), the default (occlusion reasoning on, its
  near edges found per image column, issue #28) and the occlusion reasoning as it was before
  (near edges searched along a polar raster of BEV rays, ``IpmMapper.occlusion_columns`` off);
* the six per-camera **gathers alone** of the seen cells' pixels with precomputed indices
  (``labels.ravel()[pixels]``): reading the input once, no class lookup, no sums, no output;
* ``cv2.remap`` of the six images alone: the warps the classical IPM did before its gather
  tables, without its accumulation (ratios are against this row);
* the classical IPM as it was before the gather tables (whole-image warps, masked accumulation;
  the same output, ``tests/bev_mapper_core/methods/ipm/test_ipm.py``);
* the naive baseline, which recomputes the geometry every frame: it unprojects every pixel of
  every camera, intersects the ray with the ground and splats the label into its cell.

    .venv/bin/python bench/bench_ipm.py [--frames 20] [--repeat 3]
"""

from __future__ import annotations

import argparse
import time

import numpy as np
from bench_rows import row, write_rows

from bev_mapper_core.geometry.grid import BevGrid
from bev_mapper_core.geometry.rig import preset_rig
from bev_mapper_core.labels.classes import label_lut
from bev_mapper_core.mapper import MapperConfig
from bev_mapper_core.methods.ipm.mapper import IpmMapper
from bev_mapper_core.synth import SynthConfig, generate_drive


def naive_ipm(rig, grid, images, lut):
    """Per-pixel forward ray casting, geometry recomputed each call (no lookup table)."""
    H, W = grid.shape
    acc = np.zeros((H * W, lut.shape[1]), np.float32)
    count = np.zeros(H * W, np.float32)
    for cam in rig.cameras:
        labels = images[cam.name]
        rays = cam.model.pixel_rays().reshape(-1, 3)  # (h*w, 3), recomputed every frame
        R = cam.ego_from_cam_array[:3, :3]
        o = cam.ego_from_cam_array[:3, 3]
        d = rays @ R.T
        down = d[:, 2] < -1e-9
        t = -o[2] / np.where(down, d[:, 2], -1.0)
        x = o[0] + t * d[:, 0]
        y = o[1] + t * d[:, 1]
        inside = down & grid.contains(x, y)
        row, col = grid.metric_to_cell(x[inside], y[inside])
        cell = row * W + col
        np.add.at(acc, cell, lut[labels.ravel()[inside]])
        np.add.at(count, cell, 1.0)
    known = count > 0
    probs = acc / np.maximum(count, 1.0)[:, None]
    return probs.T.reshape(-1, H, W), known.reshape(H, W)  # (H*W, C) -> (C, H, W)


def time_interleaved(fns, frames, repeat):
    """Milliseconds per frame of each of ``fns`` (name -> function of a frame), interleaved
    frame by frame (every function on a frame in turn, so all see the same load): ``(best,
    median)``, the mean over the frames of each frame's fastest and median of ``repeat`` runs."""
    times = {name: np.zeros((repeat, len(frames))) for name in fns}
    for r in range(repeat):
        for i, f in enumerate(frames):
            for name, fn in fns.items():
                t0 = time.perf_counter()
                fn(f)
                times[name][r, i] = (time.perf_counter() - t0) * 1000.0
    return {name: (float(t.min(axis=0).mean()), float(np.median(t, axis=0).mean())) for name, t in times.items()}


class PolarIpmMapper(IpmMapper):
    """The occlusion reasoning before #28: near edges along the polar raster's BEV rays."""

    occlusion_columns = False


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--frames", type=int, default=20)
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--json", default=None, help="also write the rows for bench/bench_table.py here")
    args = ap.parse_args()
    rig, grid = preset_rig("surround6"), BevGrid()
    frames = [
        {n: c.labels for n, c in f.cameras.items()}
        for f in generate_drive(rig, grid, SynthConfig(frames=args.frames, seed=7))
    ]
    t0 = time.perf_counter()
    mapper = IpmMapper(rig, grid, MapperConfig(method="ipm", ipm_occlusion=False))
    setup_ms = (time.perf_counter() - t0) * 1000.0
    occluding = IpmMapper(rig, grid, MapperConfig(method="ipm"))
    polar = PolarIpmMapper(rig, grid, MapperConfig(method="ipm"))
    lut = label_lut(mapper.classes).astype(np.float32)
    gathers = [(n, g.pixels) for n, g in mapper.gathers.items()]

    def floor(f):
        for n, pixels in gathers:
            f[n].reshape(-1)[pixels]

    def remaps(f):
        for n, t in mapper.tables.items():
            t.warp(f[n])

    def whole_image_ipm(f):  # the classical IPM before its gather tables: warp, masked accumulation
        H, W = grid.shape
        acc, count = np.zeros((H, W, lut.shape[1]), np.float32), np.zeros((H, W), np.float32)
        for n, t in mapper.tables.items():
            warped = t.warp(f[n])
            warped = np.where(warped < lut.shape[0], warped, 0)
            acc[t.valid] += lut[warped[t.valid]]
            count += t.valid
        return np.ascontiguousarray(np.moveaxis(acc / np.maximum(count, 1.0)[..., None], -1, 0)), count > 0

    timed = time_interleaved({
        "IPM, classical (ours)": mapper.map,
        "gathers alone": floor,
        "cv2.remap x6 alone": remaps,
        "IPM, classical, warps": whole_image_ipm,
        "IPM, occlusion (default)": occluding.map,
        "IPM, occlusion, polar rays": polar.map,
        "naive ray casting": lambda f: naive_ipm(rig, grid, f, lut),
    }, frames, args.repeat)
    rows = list(timed.items())
    w, h = rig.cameras[0].model.image_size
    print(f"surround6 {len(rig.cameras)}x{w}x{h} labels -> {grid.describe()}, {len(frames)} frames, "
          f"{len(mapper.classes)} classes")
    print(f"IPM lookup and gather tables: set-up {setup_ms:.1f} ms once per calibration")
    ref_ms = rows[2][1][0]
    for name, (best, med) in rows:
        print(f"{name:26s}: {best:8.2f} ms/frame (fastest of {args.repeat} per frame; median {med:.2f}) = "
              f"{best / ref_ms:6.2f}x the six cv2.remap warps alone")
    ms = {name: best for name, (best, _) in rows}
    classical, default = ms["IPM, classical (ours)"], ms["IPM, occlusion (default)"]
    before = ms["IPM, occlusion, polar rays"]
    print(f"occlusion reasoning: {default / classical:.2f}x the classical IPM per image column (default), "
          f"{before / classical:.2f}x along the polar raster's rays (before #28); the rows interleaved")
    write_rows(args.json, "bench_ipm.py", [
        row("IPM, classical (6 x 400x225 labels -> 400x200)", f"{classical:.2f} ms",
            f"{ms['IPM, classical, warps']:.2f} ms (whole-image warps + masked sums, same output)",
            ms["IPM, classical, warps"] / classical,
            f"{classical / ms['cv2.remap x6 alone']:.1f}x the six cv2.remap alone, {classical / ms['gathers alone']:.0f}x "
            "the bare gathers"),
        row("IPM, default (occlusion reasoning on)", f"{default:.2f} ms = {default / classical:.2f}x classical",
            f"{classical:.2f} ms (classical)", classical / default,
            f"near edges per image column; before #28 (polar rays): {before:.2f} ms = {before / classical:.2f}x classical"),
    ])

if __name__ == "__main__":
    main()
