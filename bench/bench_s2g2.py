"""Benchmark: S2G2 inference ms/frame on CPU through the Mapper interface.

The shipped configuration: ``create_mapper(front1, grid_preset("ahead"), MapperConfig(method="s2g2",
input_kind="rgb"))`` (the shipped weights ``bev_mapper_core/weights/s2g2_front1_rgb.safetensors``),
batch 1, one 400x225 RGB image per frame; the time covers ``mapper.map`` in full: resize and
normalization, encoder, view transform and attentions, the inference branch, sigmoid and the
copy back to numpy. For reference, measured in the same run on the same frames: ``segipm`` (the
shipped segmenter, then IPM) on the RGB images, and IPM on the true label images.

    .venv/bin/python bench/bench_s2g2.py [--frames 20] [--repeat 3] [--threads N] [--weights FILE]
"""

from __future__ import annotations

import argparse
import os
import platform
import statistics
import time


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--frames", type=int, default=20)
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--threads", type=int, default=None, help="torch threads (default: every CPU but one, as the node)")
    ap.add_argument("--weights", default=None, help="S2G2 weights file (default: the shipped one)")
    args = ap.parse_args()
    if args.threads:
        os.environ["BEV_MAPPER_TORCH_THREADS"] = str(args.threads)

    import torch

    from bev_mapper_core.geometry.grid import grid_preset
    from bev_mapper_core.geometry.rig import preset_rig
    from bev_mapper_core.mapper import MapperConfig, create_mapper
    from bev_mapper_core.synth import SynthConfig, generate_drive

    rig, grid = preset_rig("front1"), grid_preset("ahead")
    drive = list(generate_drive(rig, grid, SynthConfig(frames=args.frames, seed=7)))
    rgb = [{n: c.rgb for n, c in f.cameras.items()} for f in drive]
    labels = [{n: c.labels for n, c in f.cameras.items()} for f in drive]
    t0 = time.perf_counter()
    s2g2 = create_mapper(rig, grid, MapperConfig(method="s2g2", input_kind="rgb", weights=args.weights))
    s2g2.map(rgb[0])  # the model loads on first use; warm-up (allocations, oneDNN kernels)
    setup_ms = (time.perf_counter() - t0) * 1000.0
    segipm = create_mapper(rig, grid, MapperConfig(method="segipm", input_kind="rgb", classes=s2g2.class_names))
    ipm = create_mapper(rig, grid, MapperConfig(method="ipm", classes=s2g2.class_names))
    segipm.map(rgb[0])

    def per_frame(m, frames):
        runs = []
        for _ in range(args.repeat):
            t = time.perf_counter()
            for f in frames:
                m.map(f)
            runs.append((time.perf_counter() - t) * 1000.0 / len(frames))
        return min(runs), statistics.median(runs)

    rows = [("S2G2 (rgb)", per_frame(s2g2, rgb)), ("segipm (rgb)", per_frame(segipm, rgb)),
            ("IPM (true labels)", per_frame(ipm, labels))]
    model = s2g2.model
    n_params = sum(p.numel() for p in model.parameters() if p.requires_grad)
    w, h = rig.cameras[0].model.image_size
    print(f"{platform.processor() or platform.machine()}, {os.cpu_count()} CPUs, torch {torch.__version__}, "
          f"{torch.get_num_threads()} torch thread(s)")
    print(f"front1 1x{w}x{h} RGB -> {grid.describe()}, {len(rgb)} frames, batch 1")
    print(f"weights {s2g2.weights_file.name}: {n_params / 1e6:.2f} M trainable parameters, model input "
          f"{model.input_size[1]}x{model.input_size[0]}, maps with the {s2g2.branch} branch; "
          f"load + first frame {setup_ms:.0f} ms")
    for name, (best, med) in rows:
        print(f"{name:18s} (Mapper.map): {best:7.1f} ms/frame = {1000.0 / best:6.1f} FPS "
              f"(best of {args.repeat}; median {med:.1f} ms)")


if __name__ == "__main__":
    main()
