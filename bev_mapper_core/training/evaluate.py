"""Score any :class:`~bev_mapper_core.mapper.Mapper` (IPM, Bi-Mapper with weights, ...) over
held-out synthetic drives with :class:`~bev_mapper_core.metrics.MetricAccumulator`.

Every method goes through the same public path as the ROS node and ``bev-bag replay``:
``create_mapper(rig, grid, MapperConfig(...)).map({camera: full-size label image})``; the
result is compared with the drive's ground truth inside its ``visibility`` mask (cells some
camera sees, object cells included), with the mapper's ``known`` mask applied (unknown cells
count as negative). Range bands are 0-10, 10-20, 20-30, 30+ m.
"""

from __future__ import annotations

import json
import time
from pathlib import Path
from typing import Sequence

import numpy as np

from ..grid import BevGrid
from ..mapper import MapperConfig, create_mapper
from ..metrics import MetricAccumulator
from ..rig import Rig
from .data import FrameSet, synth_frameset

RANGE_BANDS = ((0.0, 10.0), (10.0, 20.0), (20.0, 30.0), (30.0, float("inf")))


def evaluate_mapper(mapper, frames: FrameSet, grid: BevGrid, mask: str = "visibility",
                    progress: bool = False) -> dict:
    """MetricAccumulator result of ``mapper`` over full-resolution ``frames`` (+ ``ms_per_frame``)."""
    acc = MetricAccumulator(grid, mapper.class_names, range_bands=RANGE_BANDS)
    names = frames.camera_names
    idx = range(len(frames))
    if progress:
        from tqdm import tqdm

        idx = tqdm(idx, desc=f"eval {mapper.name}", unit="frame", mininterval=5)
    t_map = 0.0
    for i in idx:
        images = {n: frames.labels[i, c] for c, n in enumerate(names)}
        t0 = time.perf_counter()
        pred = mapper.map(images)
        t_map += time.perf_counter() - t0
        vis = frames.mask[i] if mask == "visibility" else frames.ground_mask[i]
        acc.update(pred.probs, frames.target[i], vis, pred.known)
    res = acc.result()
    res["ms_per_frame"] = 1000.0 * t_map / max(len(frames), 1)
    return res


def held_out_frames(rig: Rig, grid: BevGrid, classes: Sequence[str], seeds: Sequence[int], frames: int = 20,
                    stride: int = 3, cache: str | None = "data/cache", progress: bool = False) -> FrameSet:
    """The held-out drives at full resolution (from the cache when present)."""
    return synth_frameset(rig, grid, classes, seeds, frames, stride, cache, None, progress=progress)


def evaluate(rig: Rig, grid: BevGrid, classes: Sequence[str], method: str, weights: str | None, seeds: Sequence[int],
             frames: int = 20, stride: int = 3, cache: str | None = "data/cache", device: str = "cpu",
             progress: bool = False) -> dict:
    """Build the mapper and score it on the held-out drives ``seeds``."""
    fs = held_out_frames(rig, grid, classes, seeds, frames, stride, cache, progress)
    mapper = create_mapper(rig, grid, MapperConfig(method=method, input_kind="labels", classes=tuple(classes),
                                                   weights=weights, device=device))
    res = evaluate_mapper(mapper, fs, grid, progress=progress)
    res.update(method=method, weights=weights, rig=rig.name, seeds=list(seeds), frames_per_drive=frames, stride=stride)
    return res


def save_result(res: dict, path: str | Path) -> None:
    Path(path).parent.mkdir(parents=True, exist_ok=True)
    Path(path).write_text(json.dumps(res, indent=1, allow_nan=False))


def summary_row(name: str, res: dict, classes: Sequence[str]) -> str:
    """One markdown table row: per-class IoU, mIoU, mean CD, IoU by range (percent / metres)."""
    def pct(v):
        return "-" if v is None else f"{100 * v:.1f}"

    ious = [pct(res["classes"][c]["iou"]) for c in classes]
    cds = [res["classes"][c]["cd"] for c in classes if res["classes"][c]["cd"] is not None]
    cd = f"{np.mean(cds):.2f}" if cds else "-"
    bands = [pct(row["miou"]) for row in res["iou_by_range"].values()]
    return f"| {name} | " + " | ".join(ious) + f" | **{pct(res['miou'])}** | {cd} | " + " | ".join(bands) + " |"


def summary_header(classes: Sequence[str], bands: Sequence[str]) -> str:
    cols = ["method"] + list(classes) + ["mIoU", "CD m"] + [f"mIoU {b} m" for b in bands]
    return "| " + " | ".join(cols) + " |\n|" + "---|" * len(cols)
