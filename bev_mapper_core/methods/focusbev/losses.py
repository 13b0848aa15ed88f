"""FocusBEV's objective (Eq. 9-10): weighted BCE on visible cells + ``lambda_u`` x PON's
uncertainty loss on the other cells + ``lambda_iou`` x the occupancy-agnostic IoU loss on all
cells (paper: 0.001 and 0.01).

* **Weighted BCE** (PON): per-class positive weights (the project's ``class_pos_weight``, as
  Bi-Mapper's), averaged over visible cells.
* **Uncertainty loss** (PON): where the ground truth is not observed, predictions are pushed
  towards maximum entropy: ``1 - H2(p)``, ``H2`` the binary entropy in bits, averaged over the
  unobserved cells and classes.
* **Occupancy-agnostic IoU loss**: ``1 - soft IoU`` per sample and class over *all* cells
  (``sum(p g) / sum(p + g - p g)``; the visibility mask plays no part, hence "occupancy
  agnostic"), averaged over classes and samples. A class (nearly) absent from both a sample's
  ground truth and its prediction contributes 0: its IoU is undefined there, and the paper does
  not say what it takes.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
from torch.nn import functional as F

from bev_mapper_core.errors import ConfigError
from bev_mapper_core.nn.losses import class_cells

#: A class whose ground truth and prediction both sum below this has no IoU term in a sample.
EMPTY = 1.0


@dataclass(frozen=True)
class FocusBEVLossConfig:
    """Loss weights (paper: ``uncertainty_weight`` 0.001, ``iou_weight`` 0.01)."""

    uncertainty_weight: float = 0.001
    iou_weight: float = 0.01

    def __post_init__(self) -> None:
        for name in ("uncertainty_weight", "iou_weight"):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v) or v < 0:
                raise ConfigError(f"{name} must be a finite number >= 0, got {v!r}")


def weighted_bce(logits: torch.Tensor, target: torch.Tensor, mask: torch.Tensor,
                 pos_weight: torch.Tensor | None = None, class_mask: torch.Tensor | None = None) -> torch.Tensor:
    """Mean BCE of ``logits`` / ``target`` ``(B, K, H, W)`` over the cells of ``mask`` ``(B, H, W)``
    (every class; with ``class_mask`` ``(B, K, H, W)`` only each class's known cells), positives
    weighted by ``pos_weight`` ``(K,)``.
    """
    pw = None if pos_weight is None else pos_weight.view(1, -1, 1, 1).to(logits)
    per = F.binary_cross_entropy_with_logits(logits, target, pos_weight=pw, reduction="none")  # (B, K, H, W)
    m = class_cells(mask, class_mask).to(per.dtype).expand_as(per)  # (B, 1 or K, H, W) -> (B, K, H, W)
    return (per * m).sum() / m.sum().clamp(min=1.0)


def uncertainty_loss(logits: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
    """PON's uncertainty loss: mean ``1 - H2(sigmoid(logits))`` over the cells *outside* ``mask``."""
    p = torch.sigmoid(logits)
    logp, log1mp = F.logsigmoid(logits), F.logsigmoid(-logits)
    entropy_bits = -(p * logp + (1 - p) * log1mp) / math.log(2.0)  # (B, K, H, W), 0..1
    m = (~mask)[:, None].to(p.dtype)  # (B, 1, H, W)
    return ((1.0 - entropy_bits) * m).sum() / (m.sum() * logits.shape[1]).clamp(min=1.0)


def occupancy_agnostic_iou_loss(logits: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
    """``1 - soft IoU`` per sample and class over all cells, averaged (see the module docstring)."""
    p = torch.sigmoid(logits)
    inter = (p * target).sum((2, 3))  # (B, K)
    union = (p + target - p * target).sum((2, 3))
    present = (target.sum((2, 3)) + p.sum((2, 3))) >= EMPTY
    iou = inter / union.clamp(min=1e-6)
    return torch.where(present, 1.0 - iou, torch.zeros_like(iou)).mean()


def focusbev_loss(logits: torch.Tensor, target: torch.Tensor, mask: torch.Tensor, cfg: FocusBEVLossConfig,
                  pos_weight: torch.Tensor | None = None,
                  class_mask: torch.Tensor | None = None) -> tuple[torch.Tensor, dict[str, float]]:
    """Eq. 10: ``(total, parts)`` for logits / target ``(B, K, H, W)`` and the visible mask ``(B, H, W)``
    (``class_mask`` ``(B, K, H, W)``: each class's known cells, for the BCE term).
    """
    bce = weighted_bce(logits, target, mask, pos_weight, class_mask)
    unc = uncertainty_loss(logits, mask)
    iou = occupancy_agnostic_iou_loss(logits, target)
    total = bce + cfg.uncertainty_weight * unc + cfg.iou_weight * iou
    parts = {"bce": bce, "uncertainty": unc, "iou": iou, "total": total}
    return total, {k: float(v.detach()) for k, v in parts.items()}


__all__ = ["FocusBEVLossConfig", "focusbev_loss", "occupancy_agnostic_iou_loss", "uncertainty_loss", "weighted_bce"]
