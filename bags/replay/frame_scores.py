"""Per-frame IoU of a replay, for the picture captions and the HTML report.

:meth:`FrameScores.add` scores one frame exactly as the drive-level scorer does (same threshold,
``known`` mask and scope masks, see :meth:`~bev_mapper_core.metrics.MetricAccumulator.update`),
but keeps the frame's own IoU per class instead of summing counts over the drive.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np

from bev_mapper_core.metrics import iou, mean_iou, scope_masks


@dataclass
class FrameScore:
    """IoU per scored class of one frame (None: class absent from prediction and GT)."""

    index: int
    stamp_ns: int
    ious: dict[str, float | None]

    @property
    def miou(self) -> float | None:
        """Mean IoU over the classes defined in this frame (None if none is)."""
        m = mean_iou([np.nan if v is None else v for v in self.ious.values()])
        return None if math.isnan(m) else m


@dataclass
class FrameScores:
    """The :class:`FrameScore` of every scored frame of a replay, in frame order."""

    frames: list[FrameScore] = field(default_factory=list)

    def add(self, index: int, stamp_ns: int, probs: np.ndarray, known: np.ndarray,
            pred_names: Sequence[str], gt: np.ndarray, gt_names: Sequence[str],
            visible: np.ndarray, ground: np.ndarray | None = None, scope: str | None = "visible",
            threshold: float = 0.5) -> FrameScore:
        """Score one frame and keep it.

        Args:
            index, stamp_ns: the frame's index and stamp.
            probs, known: the prediction ``(C, H, W)`` and its known mask ``(H, W)``.
            pred_names: class names of ``probs``' layers.
            gt: ``(C', H, W)`` bool ground truth of the scored classes ``gt_names``.
            visible, ground, scope: as for :func:`~bev_mapper_core.metrics.scope_masks`.
            threshold: a cell is predicted positive where ``probs >= threshold``.
        """
        names = list(gt_names)
        masks = scope_masks(names, visible, ground, scope or "visible")
        ious: dict[str, float | None] = {}
        for ci, name in enumerate(names):
            if name not in pred_names:
                ious[name] = None
                continue
            pred = (probs[list(pred_names).index(name)] >= threshold) & known
            v = float(iou(pred[None], gt[ci:ci + 1], masks[ci])[0])
            ious[name] = None if math.isnan(v) else v
        score = FrameScore(int(index), int(stamp_ns), ious)
        self.frames.append(score)
        return score

    def add_ious(self, index: int, stamp_ns: int, names: Sequence[str], ious) -> FrameScore:
        """Keep a frame already scored: ``ious`` ``(C',)`` the frame's own IoU per class of
        ``names`` (NaN: undefined), as :meth:`MetricAccumulator.update
        <bev_mapper_core.metrics.MetricAccumulator.update>` returns it for the frame; the same
        numbers :meth:`add` computes from the layers, without scoring the frame twice.
        """
        score = FrameScore(int(index), int(stamp_ns),
                           {n: (None if math.isnan(float(v)) else float(v)) for n, v in zip(names, ious)})
        self.frames.append(score)
        return score


def caption(index: int, stamp_ns: int, score: FrameScore | None) -> str:
    """A picture's footer: frame index, stamp and the frame's mIoU over the classes defined in
    it (``score`` None: the frame was not scored).
    """
    text = f"frame {index}  stamp {stamp_ns / 1e9:.3f} s"
    if score is None:
        return text + "  (no GT: not scored)"
    defined = [v for v in score.ious.values() if v is not None]
    miou = "-" if score.miou is None else f"{100 * score.miou:.1f}%"
    return text + f"  mIoU {miou} over {len(defined)} class(es)"
