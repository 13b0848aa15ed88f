"""Benchmark: FocusBEV inference ms/frame on CPU through the Mapper interface, with and without
its memory bank.

The shipped configuration: ``create_mapper(front1, grid_preset("ahead"),
MapperConfig(method="focusbev", input_kind="rgb"))`` (``weights/focusbev_front1_rgb.safetensors``),
batch 1, one 400x225 RGB image per frame of a 10 Hz drive; the time covers ``mapper.map`` in full
(resize, backbone + FPN, column transformers and the cycle, polar -> Cartesian, fusion, top-down
network, sigmoid, copy back). "with memory": every frame with its stamp and ego pose, so from the
third frame on a kept feature is warped and fused; "without": no pose, every frame mapped alone
(the fusion still runs, with the reference in every slot). The file shipped since issue #39 has
window 1 (segipm's map as its prior, each frame alone): both rows then time the same work, and
``--weights`` names a file with a window to time the bank. For reference, in the same run on the
same frames: segipm (the prior's own cost), S2G2 (the shipped weights) and IPM on the true label
images.

    .venv/bin/python bench/bench_focusbev.py [--frames 20] [--repeat 3] [--threads N] [--weights FILE]
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
    ap.add_argument("--weights", default=None, help="FocusBEV weights file (default: the shipped one)")
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
    rgb = [({n: c.rgb for n, c in f.cameras.items()}, f.world_from_ego, f.stamp_ns) for f in drive]
    labels = [({n: c.labels for n, c in f.cameras.items()}, None, None) for f in drive]
    t0 = time.perf_counter()
    fb = create_mapper(rig, grid, MapperConfig(method="focusbev", input_kind="rgb", weights=args.weights))
    fb.map(rgb[0][0])  # the model loads on first use; warm-up
    setup_ms = (time.perf_counter() - t0) * 1000.0
    s2g2 = create_mapper(rig, grid, MapperConfig(method="s2g2", input_kind="rgb", classes=fb.class_names))
    segipm = create_mapper(rig, grid, MapperConfig(method="segipm", input_kind="rgb", classes=fb.class_names))
    ipm = create_mapper(rig, grid, MapperConfig(method="ipm", classes=fb.class_names))
    s2g2.map(rgb[0][0])
    segipm.map(rgb[0][0])

    def per_frame(m, frames, memory: bool):
        runs, fused = [], 0
        for _ in range(args.repeat):
            m.reset()
            t = time.perf_counter()
            for images, pose, stamp in frames:
                pred = m.map(images, pose, stamp) if memory else m.map(images)
                fused += pred.frames > 1
            runs.append((time.perf_counter() - t) * 1000.0 / len(frames))
        return min(runs), statistics.median(runs), fused // args.repeat

    rows = [("FocusBEV, with memory", per_frame(fb, rgb, True)), ("FocusBEV, no memory", per_frame(fb, rgb, False)),
            ("segipm (rgb)", per_frame(segipm, rgb, False)), ("S2G2 (rgb)", per_frame(s2g2, rgb, False)),
            ("IPM (true labels)", per_frame(ipm, labels, False))]
    n_params = sum(p.numel() for p in fb.model.parameters())
    w, h = rig.cameras[0].model.image_size
    print(f"{platform.processor() or platform.machine()}, {os.cpu_count()} CPUs, torch {torch.__version__}, "
          f"{torch.get_num_threads()} torch thread(s)")
    print(f"front1 1x{w}x{h} RGB at 10 Hz -> {grid.describe()}, {len(rgb)} frames, batch 1")
    print(f"weights {fb.weights_file.name}: {n_params / 1e6:.2f} M parameters, model input "
          f"{fb.model.input_size[1]}x{fb.model.input_size[0]}, window {fb.window}, memory interval "
          f"{fb.interval_ns / 1e9:.1f} s; load + first frame {setup_ms:.0f} ms")
    for name, (best, med, fused) in rows:
        print(f"{name:22s} (Mapper.map): {best:7.1f} ms/frame = {1000.0 / best:6.1f} FPS "
              f"(best of {args.repeat}; median {med:.1f} ms; {fused} frames fused with memory)")


if __name__ == "__main__":
    main()
