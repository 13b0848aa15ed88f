"""Benchmark: the segmenter stage per backend (issue #37), the shipped segmenters against the one
shipped before (``segmenter_w320``), in the same run.

Rows:

* ``SegmenterStage.segment`` of one 480x360 RGB frame (CamVid's size; resize, network, labels at
  the frame's size), 1 thread, for torch, onnxruntime and OpenVINO (those installed), and
  OpenVINO in bf16 and int8 (``segmenter_precision``, issue #41; int8's first call quantizes);
* the whole ``Mapper.map`` of ``segipm`` and of chained Bi-Mapper (the shipped surround6 label
  weights behind the segmenter) on one surround6 frame (6 RGB cameras of 400x225), at the
  machine's default threads, per backend (``MapperConfig.backend``).

Median of ``--frames`` calls after a warm-up call (an ONNX backend's first call exports the model
or reads it from the cache, ``$BEV_MAPPER_CACHE``; not counted). The frames are rendered by the
synthetic town (seed 950000010, a test seed), so the labels vary as on a real drive.

    .venv/bin/python bench/bench_segmenter.py [--frames 10] [--skip-maps]
"""

from __future__ import annotations

import argparse
import statistics
import time

import numpy as np
import torch


def _median_ms(fn, frames: int) -> float:
    fn()  # warm-up (export or cache read)
    ts = []
    for _ in range(frames):
        t = time.perf_counter()
        fn()
        ts.append(time.perf_counter() - t)
    return 1000 * statistics.median(ts)


def main() -> None:
    """Print the table (see the module docstring)."""
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--frames", type=int, default=10)
    ap.add_argument("--skip-maps", action="store_true", help="only the 480x360 stage rows")
    a = ap.parse_args()
    from bev_mapper_core.geometry.grid import BevGrid
    from bev_mapper_core.geometry.rig import preset_rig
    from bev_mapper_core.labels.classes import BEV_CLASS_NAMES
    from bev_mapper_core.mapper import MapperConfig, create_mapper
    from bev_mapper_core.methods import WEIGHTS_DIR
    from bev_mapper_core.methods.segmenter.stage import SegmenterStage
    from bev_mapper_core.nn.backends import installed_backends
    from bev_mapper_core.training.data import render_drive

    rig, grid = preset_rig("surround6"), BevGrid()
    drive = render_drive(rig, grid, BEV_CLASS_NAMES, 950000010, 2, 3, rgb=(225, 400))
    cams = {n: np.ascontiguousarray(drive["rgb"][0, i]) for i, n in enumerate(rig.names)}
    frame = np.ascontiguousarray(np.asarray(  # one 480x360 frame: the front camera, scaled
        torch.nn.functional.interpolate(torch.from_numpy(cams[rig.names[0]]).permute(2, 0, 1)[None].float(),
                                        size=(360, 480), mode="bilinear")[0].permute(1, 2, 0).round().byte()))
    backends = installed_backends()
    files = {"camvid (default)": "segmenter.safetensors", "open": "segmenter_open.safetensors",
             "w320 (before #37)": "segmenter_w320.safetensors"}
    print(f"torch {torch.__version__}, backends {backends}; ms, median of {a.frames}")
    default_threads = torch.get_num_threads()
    torch.set_num_threads(1)
    # columns: each backend in f32, then OpenVINO's bf16 and int8 (issue #41) where installed
    columns = [(b, "f32") for b in backends] + [("openvino", p) for p in ("bf16", "int8") if "openvino" in backends]
    print("\nSegmenterStage.segment, one 480x360 frame, 1 thread (precision after the backend)")
    print(f"{'segmenter':20}" + "".join(f"{b + ('' if p == 'f32' else ' ' + p):>16}" for b, p in columns))
    for label, name in files.items():
        cells = []
        for b, p in columns:
            stage = SegmenterStage(WEIGHTS_DIR / name, backend=b, threads=1, precision=p)
            cells.append(_median_ms(lambda s=stage: s.segment({"f": frame}), a.frames))
        print(f"{label:20}" + "".join(f"{c:16.1f}" for c in cells), flush=True)
    torch.set_num_threads(default_threads)
    if a.skip_maps:
        return
    print("\nMapper.map, one surround6 frame (6 x 400x225 RGB), default threads")
    print(f"{'method, segmenter':34}" + "".join(f"{b:>14}" for b in backends))
    for method in ("segipm", "bimapper"):
        for label, name in files.items():
            cells = []
            for b in backends:
                cfg = MapperConfig(method=method, input_kind="rgb", backend=b, segmenter=str(WEIGHTS_DIR / name),
                                   segmenter_precision="f32",
                                   weights=str(WEIGHTS_DIR / "bimapper_surround6_labels.safetensors")
                                   if method == "bimapper" else None)
                mapper = create_mapper(rig, grid, cfg)
                cells.append(_median_ms(lambda m=mapper: m.map(cams), a.frames))
            name_ = "chained Bi-Mapper" if method == "bimapper" else method
            print(f"{name_ + ', ' + label:34}" + "".join(f"{c:14.1f}" for c in cells), flush=True)


if __name__ == "__main__":
    main()
