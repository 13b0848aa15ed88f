"""Score any :class:`~bev_mapper_core.mapper.Mapper` (IPM, Bi-Mapper with weights, ...) over
held-out synthetic drives with :class:`~bev_mapper_core.metrics.MetricAccumulator`.

Every method goes through the same public path as the ROS node and ``bev-bag replay``:
``create_mapper(rig, grid, MapperConfig(...)).map({camera: full-size label image})``; the
result is compared with the drive's ground truth inside its ``visibility`` mask (cells some
camera sees, object cells included), with the mapper's ``known`` mask applied (unknown cells
count as negative). Every score goes through :func:`score_frameset`, which uses the one
:class:`~bev_mapper_core.metrics.MetricAccumulator` with its default range bands (the same as
``bev-bag replay``'s) and per-class scope masks.
"""

from __future__ import annotations

import json
import time
from collections.abc import Callable, Sequence
from pathlib import Path

import numpy as np

from ..errors import ConfigError
from ..geometry.grid import BevGrid
from ..geometry.rig import Rig
from ..mapper import MapperConfig, create_mapper
from ..metrics import MetricAccumulator, scope_masks
from ..temporal import TemporalConfig, TemporalFusion
from .data import FrameSet, synth_frameset


def score_frameset(predict: Callable[[dict], tuple[np.ndarray, np.ndarray]], frames: FrameSet,
                   grid: BevGrid, class_names: Sequence[str], batch: int = 1, limit: int | None = None,
                   scope: str = "visible", progress: str | None = None) -> dict:
    """The one scoring loop over a :class:`FrameSet` (``bev-train eval`` and validation).

    Args:
        predict: a batch of :meth:`FrameSet.batch` (``images`` (B, N, h, w) uint8 tensor, ...)
            ``-> (probs (B, C, H, W) float, known (B, H, W) bool)`` numpy; a training method's
            :meth:`~.method.TrainMethod.predict` is one.
        frames: the frames, in order; the first ``limit`` are scored (None = all).
        scope: ``visible`` (the drive's ``visibility``) or ``ground`` (flat classes where the
            ground is seen), see :func:`~bev_mapper_core.metrics.scope_masks`.
        progress: a tqdm description, or None for no bar.

    Returns:
        :meth:`MetricAccumulator.result` (default range bands, the same as ``bev-bag replay``)
        plus ``ms_per_frame`` of ``predict``.
    """
    acc = MetricAccumulator(grid, class_names)
    n = len(frames) if limit is None else min(limit, len(frames))
    # frames of several rigs (MultiRigFrames) batch within one rig
    groups = (frames.scoring_batches(batch, n) if hasattr(frames, "scoring_batches")
              else (np.arange(s, min(s + batch, n)) for s in range(0, n, batch)))
    if progress:
        from tqdm import tqdm

        groups = tqdm(groups, total=-(-n // batch), desc=progress, unit="batch", mininterval=5)
    t_pred = 0.0
    for idx in groups:
        t0 = time.perf_counter()
        probs, known = predict(frames.batch(idx))
        t_pred += time.perf_counter() - t0
        for j, i in enumerate(idx):
            masks = scope_masks(class_names, frames.mask[i], frames.ground_mask[i], scope)
            if frames.class_mask is not None:
                masks &= frames.class_mask[i]  # a class unknown in a cell is not scored there
            acc.update(probs[j], frames.target[i], masks, known[j])
    res = acc.result()
    res["ms_per_frame"] = 1000.0 * t_pred / max(n, 1)
    return res


def evaluate_mapper(mapper, frames: FrameSet, grid: BevGrid, scope: str = "visible",
                    progress: bool = False, temporal: TemporalConfig | None = None) -> dict:
    """:func:`score_frameset` of a :class:`~bev_mapper_core.mapper.Mapper` over full-resolution
    ``frames``, one frame at a time through ``mapper.map`` (as the node and replay call it). A
    mapper on RGB input (``mapper.config.input_kind == "rgb"``) gets the frames' camera images.
    Frames with poses are mapped as drives: in order, with each frame's stamp and ego pose, and
    :meth:`~bev_mapper_core.mapper.Mapper.reset` at the start of every drive (a temporal
    method's memory never crosses drives). ``temporal`` (window > 1): the method-independent
    fusion of the published maps (:class:`~bev_mapper_core.temporal.TemporalFusion`) over each
    drive's frames, as ``bev-bag replay --temporal-window`` and the node's ``temporal_window``.
    """
    names = frames.camera_names
    fusion = TemporalFusion(grid, temporal) if temporal is not None and temporal.window > 1 else None
    if fusion is not None and frames.poses is None:
        raise ConfigError("temporal fusion needs frames with poses")
    rgb = mapper.config.input_kind == "rgb"
    if rgb and frames.rgb is None:
        raise ConfigError("an RGB mapper needs frames with camera images (load them with rgb=...)")

    drive = None  # the drive of the last frame mapped

    def predict(batch: dict):  # images (1, N, H, W[, 3]) -> (1, C, H, W), (1, H, W)
        nonlocal drive
        images = (batch["rgb"] if rgb else batch["images"]).numpy()
        pose = stamp = None
        if "poses" in batch:  # a sequence: a temporal method gets stamps and poses, and a new drive resets it
            pose, stamp = batch["poses"][0].numpy(), int(batch["stamps"][0])
            if int(batch["drives"][0]) != drive:
                mapper.reset()
                if fusion is not None:
                    fusion.reset()
                drive = int(batch["drives"][0])
        pred = mapper.map({n: images[0, c] for c, n in enumerate(names)}, ego_pose=pose, stamp_ns=stamp)
        if fusion is not None:
            pred = fusion.update(pred, stamp, pose).prediction
        return pred.probs[None], pred.known[None]

    return score_frameset(predict, frames, grid, mapper.class_names, scope=scope,
                          progress=f"eval {mapper.name}" if progress else None)


def held_out_frames(rig: Rig, grid: BevGrid, classes: Sequence[str], seeds: Sequence[int], frames: int = 20,
                    stride: int = 3, cache: str | None = "data/cache", progress: bool = False,
                    rgb: bool = False, style: str | None = None) -> FrameSet:
    """The held-out drives at full resolution (from the cache when present); ``rgb``: with the
    camera images (full size) in appearance ``style`` (default ``SynthConfig.style``).
    """
    size = None
    if rgb:
        w, h = rig.cameras[0].model.image_size
        size = (h, w)
    return synth_frameset(rig, grid, classes, seeds, frames, stride, cache, None, progress=progress,
                          rgb=size, style=style)


def evaluate(rig: Rig, grid: BevGrid, classes: Sequence[str], method: str, weights: str | None, seeds: Sequence[int],
             frames: int = 20, stride: int = 3, cache: str | None = "data/cache", device: str = "cpu",
             progress: bool = False, ipm_occlusion: bool = MapperConfig.ipm_occlusion,
             unknown_below: float = MapperConfig.unknown_below, input_kind: str = "labels",
             style: str | None = None, temporal_window: int = TemporalConfig.window) -> dict:
    """Build the mapper and score it on the held-out drives ``seeds`` (``ipm_occlusion``, ``unknown_below``: see
    :class:`~bev_mapper_core.mapper.MapperConfig`; False = the classical IPM). ``input_kind``
    ``rgb``: the mapper reads the drives' camera images, rendered in ``style``.
    ``temporal_window`` > 1: the method-independent temporal fusion over that many frames.
    """
    fs = held_out_frames(rig, grid, classes, seeds, frames, stride, cache, progress, rgb=input_kind == "rgb",
                         style=style)
    mapper = create_mapper(rig, grid, MapperConfig(method=method, input_kind=input_kind, classes=tuple(classes),
                                                   weights=weights, device=device,
                                                   ipm_occlusion=ipm_occlusion, unknown_below=unknown_below))
    res = evaluate_mapper(mapper, fs, grid, progress=progress, temporal=TemporalConfig(window=temporal_window))
    res.update(method=method, weights=weights, temporal_window=temporal_window, rig=rig.name, seeds=list(seeds),
               frames_per_drive=frames, stride=stride,
               input_kind=input_kind, style=style if input_kind == "rgb" else None, grid=grid.to_dict())
    return res


def save_result(res: dict, path: str | Path) -> None:
    """Write a result document as strict JSON (creating the directory)."""
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
    """The markdown header (and rule) of :func:`summary_row`'s table."""
    cols = ["method"] + list(classes) + ["mIoU", "CD m"] + [f"mIoU {b} m" for b in bands]
    return "| " + " | ".join(cols) + " |\n|" + "---|" * len(cols)
