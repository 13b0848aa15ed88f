"""Losses more than one method trains with."""

from __future__ import annotations

import torch
from torch.nn import functional as F


def class_cells(mask: torch.Tensor | None, class_mask: torch.Tensor | None) -> torch.Tensor | None:
    """The cells each class is trained on: ``mask`` (B, H, W) as (B, 1, H, W), narrowed by a
    batch's ``class_mask`` (B, K, H, W) where it has one (then (B, K, H, W)); None: every cell.
    """
    if class_mask is None:
        return None if mask is None else mask.bool()[:, None]
    class_mask = class_mask.bool()
    return class_mask if mask is None else mask.bool().to(class_mask.device)[:, None] & class_mask


def masked_bce(logits: torch.Tensor, target: torch.Tensor, mask: torch.Tensor | None = None,
               pos_weight: torch.Tensor | None = None) -> torch.Tensor:
    """Mean binary cross-entropy with logits over the elements where ``mask`` is true.

    ``logits``/``target`` (B, K, ...); ``mask`` broadcastable to them (e.g. (B, 1, ...)) or None.
    ``pos_weight`` (K,) multiplies the positive term per class. Returns 0 if nothing is masked in.
    """
    pw = None if pos_weight is None else pos_weight.view(1, -1, *([1] * (logits.dim() - 2)))
    loss = F.binary_cross_entropy_with_logits(logits, target.to(logits.dtype), pos_weight=pw, reduction="none")
    if mask is None:
        return loss.mean()
    m = mask.to(loss.dtype).expand_as(loss)
    return (loss * m).sum() / m.sum().clamp(min=1.0)
