"""Training across label spaces (torch): the partial-label loss and the evaluation helpers.

A dataset's classes are sets of this package's fine labels
(:class:`~bev_mapper_core.labels.spaces.LabelSpace`, numpy, in :mod:`bev_mapper_core.labels.spaces`
with the CamVid mapping decisions). The loss of a coarse label is the **marginal (partial-label)
negative log-likelihood**

    loss = -log( sum_{j in cover(c)} softmax(z)_j )

so a pixel labelled ``Road`` asks for "road or lane divider or crossing" and never teaches "not
lane divider" on a marking (the gradient on every covered logit is <= 0; see
:func:`marginal_nll`). With singleton covers the loss is the ordinary cross-entropy, so synthetic
frames (the ``FINE`` space) and real frames train through the same function, also in one
mixed batch (:func:`joint_cover`). Predictions map back for evaluation with
:func:`coarse_predict` (fine argmax, then each fine label's home class).
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
import torch

from ..errors import ConfigError
from ..labels.spaces import IGNORE, LabelSpace


def joint_cover(spaces: Sequence[LabelSpace]) -> tuple[torch.Tensor, tuple[int, ...]]:
    """Stack several spaces into one target code space: ``(cover (sum K, NUM_LABELS) bool,
    offsets)``; a target of class ``k`` of ``spaces[i]`` is coded ``offsets[i] + k`` (ignored
    pixels stay :data:`IGNORE`), so one :func:`marginal_nll` call trains a mixed batch.
    """
    mats, offsets, n = [], [], 0
    for s in spaces:
        offsets.append(n)
        mats.append(s.cover_matrix())
        n += s.num_classes
    if n >= IGNORE:
        raise ConfigError(f"{n} classes in all: the joint code space holds at most {IGNORE - 1}")
    return torch.from_numpy(np.concatenate(mats)), tuple(offsets)


def marginal_nll(logits: torch.Tensor, target: torch.Tensor, cover: torch.Tensor,
                 weight: torch.Tensor | None = None, ignore_index: int = IGNORE,
                 hard_fraction: float = 1.0) -> torch.Tensor:
    """Partial-label loss: mean over labelled pixels of ``-log sum_{j in cover[t]} p_j``.

    Args:
        logits: ``(B, L, H, W)`` fine-label logits (any float dtype; computed in float32).
        target: ``(B, H, W)`` integer class codes (rows of ``cover``), ``ignore_index`` ignored.
        cover: ``(K, L)`` bool, the fine labels each code covers.
        weight: ``(K,)`` per-code weights (a weighted mean, as ``F.cross_entropy``), or None.
        hard_fraction: online hard example mining (OHEM): below 1, only that fraction of the
            labelled pixels, those of the highest loss, count (a weighted mean over them).

    The gradient w.r.t. a covered logit ``z_j`` is ``p_j (1 - 1/S)`` <= 0 (``S`` the covered
    probability sum), so descent never lowers a covered label; with singleton covers this is
    exactly the cross-entropy.
    """
    if logits.dim() != 4 or target.shape != (logits.shape[0], *logits.shape[2:]):
        raise ValueError(f"logits (B, L, H, W) and target (B, H, W) expected, got {tuple(logits.shape)} "
                         f"and {tuple(target.shape)}")
    cover = cover.to(logits.device)
    valid = target != ignore_index
    t = torch.where(valid, target, torch.zeros_like(target)).long()
    logp = logits.float().log_softmax(1)  # (B, L, H, W)
    mask = cover[t].permute(0, 3, 1, 2)  # (B, H, W, L) -> (B, L, H, W)
    nll = -logp.masked_fill(~mask, float("-inf")).logsumexp(1)  # (B, H, W)
    w = valid.float() if weight is None else weight.to(logits.device).float()[t] * valid
    nll = nll.masked_fill(~valid, 0.0)
    if hard_fraction < 1.0:
        k = max(1, int(hard_fraction * int(valid.sum())))
        hard = torch.zeros_like(valid).flatten()
        hard[nll.detach().masked_fill(~valid, -1.0).flatten().topk(k).indices] = True
        w = w * hard.view_as(valid)
    return (nll * w).sum() / w.sum().clamp(min=1e-6)


def coarse_predict(logits: torch.Tensor, space: LabelSpace) -> torch.Tensor:
    """``(B, L, H, W)`` fine logits -> ``(B, H, W)`` uint8 class ids of ``space`` (fine argmax,
    then each label's home class; :data:`IGNORE` for labels the space does not cover).
    """
    home = torch.from_numpy(space.coarse_of_fine()).to(logits.device)
    return home[logits.argmax(1)]


def confusion(pred: torch.Tensor, target: torch.Tensor, num_classes: int,
              ignore_index: int = IGNORE) -> torch.Tensor:
    """``(K, K + 1)`` int64 confusion on the CPU (rows: truth, columns: prediction; the last
    column counts predictions outside ``0..K-1``) of the pixels whose truth is a class.
    """
    t, p = target.reshape(-1).long(), pred.reshape(-1).long()
    keep = (t != ignore_index) & (t < num_classes)
    t, p = t[keep], p[keep]
    p = torch.where(p < num_classes, p, torch.full_like(p, num_classes))
    conf = torch.bincount(t * (num_classes + 1) + p, minlength=num_classes * (num_classes + 1))
    return conf.view(num_classes, num_classes + 1).cpu()


def iou_from_confusion(conf: torch.Tensor) -> np.ndarray:
    """Per-class IoU ``(K,)`` (NaN where a class is in neither truth nor prediction) of a
    :func:`confusion` ``(K, K + 1)``.
    """
    c = conf.double().numpy()
    if c.ndim != 2 or c.shape[1] != c.shape[0] + 1:
        raise ValueError(f"a (K, K + 1) confusion expected, got {c.shape}")
    k = c.shape[0]
    inter = np.diag(c[:, :k])
    union = c[:, :k].sum(0) + c.sum(1) - inter
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.where(union > 0, inter / np.maximum(union, 1), np.nan)


__all__ = ["coarse_predict", "confusion", "iou_from_confusion", "joint_cover", "marginal_nll"]
