"""Benchmark: Bi-Mapper inference ms/frame on CPU through the Mapper interface.

The shipped configuration: ``create_mapper(surround6, BevGrid(), MapperConfig(method="bimapper"))``
(the shipped weights ``bev_mapper_core/weights/bimapper_surround6_labels.safetensors``), batch 1,
six 400x225 label images per frame; the time covers ``mapper.map`` in full: preprocessing
(resize + one-hot), the IPM prior of the skip, both streams, fusion, decoder, sigmoid and the
copy back to numpy. IPM is timed on the same frames for reference.

    .venv/bin/python bench/bench_bimapper.py [--frames 20] [--repeat 3] [--threads N] [--weights FILE]
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
    ap.add_argument("--weights", default=None, help="weights file (default: the shipped one)")
    ap.add_argument("--rig", default="surround6")
    args = ap.parse_args()
    if args.threads:
        os.environ["BEV_MAPPER_TORCH_THREADS"] = str(args.threads)

    import torch

    from bev_mapper_core.geometry.grid import BevGrid
    from bev_mapper_core.geometry.rig import preset_rig
    from bev_mapper_core.mapper import MapperConfig, create_mapper
    from bev_mapper_core.synth import SynthConfig, generate_drive

    rig, grid = preset_rig(args.rig), BevGrid()
    frames = [{n: c.labels for n, c in f.cameras.items()}
              for f in generate_drive(rig, grid, SynthConfig(frames=args.frames, seed=7))]
    t0 = time.perf_counter()
    mapper = create_mapper(rig, grid, MapperConfig(method="bimapper", weights=args.weights))
    setup_ms = (time.perf_counter() - t0) * 1000.0
    ipm = create_mapper(rig, grid, MapperConfig(method="ipm", classes=mapper.class_names))
    mapper.map(frames[0])  # warm-up (allocations, oneDNN kernels)

    def per_frame(m):
        runs = []
        for _ in range(args.repeat):
            t = time.perf_counter()
            for f in frames:
                m.map(f)
            runs.append((time.perf_counter() - t) * 1000.0 / len(frames))
        return min(runs), statistics.median(runs)

    bi_best, bi_med = per_frame(mapper)
    ipm_best, ipm_med = per_frame(ipm)
    model = mapper.model
    n_params = sum(p.numel() for p in model.parameters())
    w, h = rig.cameras[0].model.image_size
    print(f"{platform.processor() or platform.machine()}, {os.cpu_count()} CPUs, torch {torch.__version__}, "
          f"{torch.get_num_threads()} torch thread(s)")
    print(f"{rig.name} {len(rig.cameras)}x{w}x{h} labels -> {grid.describe()}, {len(frames)} frames, batch 1")
    print(f"weights {mapper.weights_path.name}: {n_params / 1e6:.2f} M parameters, model input "
          f"{model.input_size[1]}x{model.input_size[0]} per camera; load {setup_ms:.0f} ms")
    print(f"Bi-Mapper (Mapper.map): {bi_best:8.1f} ms/frame (best of {args.repeat}; median {bi_med:.1f})")
    print(f"IPM       (Mapper.map): {ipm_best:8.1f} ms/frame (best of {args.repeat}; median {ipm_med:.1f})")
    print("forward pass by part (ms, best of 5 on the first frame):")
    for name, ms in profile_parts(model, rig, frames[0]).items():
        print(f"  {name:28s} {ms:7.1f}")


def profile_parts(model, rig, frame: dict) -> dict[str, float]:
    """Time each part of the forward pass on one frame: what limits the rate."""
    import numpy as np
    import torch

    raw = torch.from_numpy(np.stack([frame[n] for n in rig.names]))[None]  # (1, N, H, W)

    def best(fn, n=5):
        fn()
        times = []
        for _ in range(n):
            t = time.perf_counter()
            fn()
            times.append((time.perf_counter() - t) * 1000.0)
        return min(times)

    out = {}
    with torch.inference_mode():
        x = model.preprocess(raw)
        out["preprocess (resize, one-hot)"] = best(lambda: model.preprocess(raw))
        prior = None
        if model.config.ipm_skip:
            prior = model.ipm_prior(raw)
            out["IPM prior (skip)"] = best(lambda: model.ipm_prior(raw))
        res = model.forward_preprocessed(x, None, None, prior)
        if model.use_gv:
            def gv():
                f = model.cam_encoder(x.flatten(0, 1))  # (N, C, hf, wf)
                return model.gv(f.view(1, model.num_cameras, *f.shape[1:]), None)
            out["GV stream"] = best(gv)
        if model.use_lv:
            out["LV stream"] = best(lambda: model.lv(x, model.tables(), None))
        fused = res["gv_feat"] if res["gv_feat"] is not None else res["lv_feat"]
        if fused is None:  # streams "none"
            fused = x.new_zeros(1, model.config.bev_channels, *model.feat_hw)
        out["BEV decoder (+ skip head)"] = best(lambda: model.decoder(fused, prior))
        out["whole forward"] = best(lambda: model(raw))
    return out


if __name__ == "__main__":
    main()
