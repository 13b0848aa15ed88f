"""Bi-Mapper training losses (paper Eq. 3-5): ``BCE + ASL + alpha * mutual``.

* **BCE** on the ego grid, per class (the BEV classes are multi-label: a lane divider is also
  drivable), averaged over the cells inside the visibility mask.
* **Across-Space Loss (ASL)**: each camera's LV camera-plane logits against the ground truth
  warped into that camera's plane with the model's precomputed tables (nearest cell; plane
  cells outside the grid, unseen by the camera or outside the visibility mask are ignored),
  averaged per view and summed over views (Eq. 3). The paper names cross-entropy; since the
  classes overlap, a softmax over classes cannot express the targets, so the loss is the
  per-class binary cross-entropy, i.e. a two-class (present / absent) cross-entropy per class.
* **Asynchronous mutual learning (AML)**: each stream predicts foreground/background on the ego
  feature grid (GV: a 1x1 head on F_g; LV: the max over classes of its merged plane logits).
  The teacher's prediction is thresholded into a hard mask and detached; the student is trained
  toward it with (binary) cross-entropy, the best loss of Table VI. Before epoch N only LV
  teaches GV; from epoch N both teach each other (Eq. 4). The loss is restricted to feature
  cells some camera plane covers: LV says nothing elsewhere.

* **Visibility** (not in the paper; issue #11): BCE of the visibility head's logit against the
  visibility mask (cells some camera sees) over every grid cell, weight ``visibility_weight``.
* **Uncertainty** (PON, Roddick & Cipolla 2020, used by FocusBEV with weight 0.001): on cells
  *not* visible, the mean over cells and classes of ``KL(Bernoulli(p) || Bernoulli(0.5)) =
  log 2 - H(p)``, which pushes each class probability towards 0.5 (maximum entropy) where the
  cameras have no evidence; weight ``uncertainty_weight``.

Epochs are counted from 0; the paper's "5th epoch" is ``mutual_start_epoch = 4``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
from torch.nn import functional as F

from bev_mapper_core.errors import ConfigError
from bev_mapper_core.nn.losses import class_cells, masked_bce

MUTUAL_MODES = ("async", "sync", "lv", "gv", "none")


@dataclass(frozen=True)
class BiMapperLossConfig:
    """Loss weights and the mutual-learning schedule.

    Args:
        asl_weight: weight of the Across-Space Loss (paper 1).
        mutual_weight: alpha of Eq. 5 (paper 0.1).
        mutual_start_epoch: N of Eq. 4, 0-based (paper: the 5th epoch -> 4).
        mutual_mode: ``async`` (paper), ``sync`` (both from the start), ``lv`` (LV teacher only),
            ``gv`` (GV teacher only), ``none`` (Table IV ablations).
        pos_weight: optional per-class positive weights of the ego BCE.
        visibility_weight: weight of the visibility head's BCE (0 = off; needs the head).
        uncertainty_weight: weight of the PON uncertainty loss on hidden cells (0 = off;
            FocusBEV 0.001).
    """

    asl_weight: float = 1.0
    mutual_weight: float = 0.1
    mutual_start_epoch: int = 4
    mutual_mode: str = "async"
    pos_weight: tuple[float, ...] | None = None
    visibility_weight: float = 0.0
    uncertainty_weight: float = 0.0

    def __post_init__(self) -> None:
        for name in ("visibility_weight", "uncertainty_weight"):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, (int, float)) or not v >= 0 or v == float("inf"):
                raise ConfigError(f"{name} must be a finite number >= 0, got {v!r}")
        if self.mutual_mode not in MUTUAL_MODES:
            raise ConfigError(f"mutual_mode must be one of {MUTUAL_MODES}, got {self.mutual_mode!r}")
        if self.mutual_start_epoch < 0:
            raise ConfigError(f"mutual_start_epoch must be >= 0, got {self.mutual_start_epoch}")


def mutual_teachers(epoch: int, start_epoch: int = 4, mode: str = "async") -> tuple[bool, bool]:
    """Who teaches at ``epoch`` (0-based): ``(lv_teaches_gv, gv_teaches_lv)``.

    ``async``: LV always teaches; GV teaches from ``start_epoch`` on (paper Eq. 4).
    """
    if mode == "async":
        return True, epoch >= start_epoch
    if mode == "sync":
        return True, True
    if mode == "lv":
        return True, False
    if mode == "gv":
        return False, True
    if mode == "none":
        return False, False
    raise ConfigError(f"unknown mutual_mode {mode!r}")


def uncertainty_loss(logits: torch.Tensor, hidden: torch.Tensor) -> torch.Tensor:
    """PON's uncertainty loss: mean ``KL(Bernoulli(p) || Bernoulli(0.5)) = log 2 - H(p)`` over
    the hidden cells and all classes, ``p = sigmoid(logits)``.

    ``logits`` (B, K, H, W); ``hidden`` (B, H, W) bool, cells no camera sees. 0 when every
    hidden probability is 0.5, ``log 2`` when they are all certain; 0 if nothing is hidden.
    """
    p = torch.sigmoid(logits)
    # H(p) from the logits, stable: -p log p - (1-p) log(1-p) = softplus(x) - p x
    entropy = F.softplus(logits) - p * logits
    kl = math.log(2.0) - entropy  # (B, K, H, W)
    m = hidden[:, None].to(kl.dtype).expand_as(kl)
    return (kl * m).sum() / m.sum().clamp(min=1.0)


def warp_target_to_planes(target: torch.Tensor, gt_grid: torch.Tensor, gt_valid: torch.Tensor,
                          mask: torch.Tensor | None = None,
                          class_mask: torch.Tensor | None = None) -> tuple[torch.Tensor, torch.Tensor]:
    """Ground truth of the ego grid warped into every camera plane (nearest cell).

    Args:
        target: (B, K, H, W) ego-grid class layers; mask: (B, H, W) visibility or None.
        gt_grid: (N, Hp, Wp, 2) normalised ego-grid coordinates of each plane cell;
        gt_valid: (N, Hp, Wp) bool.
        class_mask: (B, K, H, W) bool, each class's known cells, or None.

    Returns:
        targets (B, N, K, Hp, Wp) and valid (B, N, Hp, Wp) bool; with ``class_mask`` valid is
        per class, (B, N, K, Hp, Wp).
    """
    B, K, H, W = target.shape
    N, Hp, Wp, _ = gt_grid.shape
    layers = target.to(gt_grid.dtype)
    if mask is not None:
        layers = torch.cat([layers, mask[:, None].to(gt_grid.dtype)], dim=1)  # (B, K+1, H, W)
    if class_mask is not None:
        layers = torch.cat([layers, class_mask.to(gt_grid.dtype)], dim=1)  # (B, K[+1]+K, H, W)
    Kx = layers.shape[1]
    grid = gt_grid.reshape(1, N * Hp, Wp, 2).expand(B, N * Hp, Wp, 2)  # (N, Hp, Wp, 2) -> (B, N*Hp, Wp, 2)
    s = F.grid_sample(layers, grid, mode="nearest", padding_mode="zeros", align_corners=False)  # (B, Kx, N*Hp, Wp)
    s = s.view(B, Kx, N, Hp, Wp).permute(0, 2, 1, 3, 4)  # (B, Kx, N*Hp, Wp) -> (B, N, Kx, Hp, Wp)
    valid = gt_valid[None].expand(B, N, Hp, Wp)
    if mask is not None:
        valid = valid & (s[:, :, K] > 0.5)
    if class_mask is not None:
        valid = valid[:, :, None] & (s[:, :, Kx - K:] > 0.5)  # (B, N, Hp, Wp) -> (B, N, K, Hp, Wp)
    return s[:, :, :K], valid


def across_space_loss(plane_logits: torch.Tensor, target: torch.Tensor, gt_grid: torch.Tensor,
                      gt_valid: torch.Tensor, mask: torch.Tensor | None = None,
                      cam_mask: torch.Tensor | None = None,
                      class_mask: torch.Tensor | None = None) -> torch.Tensor:
    """ASL (Eq. 3): per-view mean per-class BCE in the camera planes, summed over views.

    ``plane_logits`` (B, N, K, Hp, Wp); other arguments as :func:`warp_target_to_planes`;
    ``cam_mask`` (B, N) drops absent cameras.
    """
    tgt, valid = warp_target_to_planes(target, gt_grid, gt_valid, mask, class_mask)
    if valid.dim() == 4:
        valid = valid[:, :, None]  # (B, N, Hp, Wp) -> (B, N, 1, Hp, Wp)
    if cam_mask is not None:
        valid = valid & cam_mask.bool()[:, :, None, None, None]
    loss = F.binary_cross_entropy_with_logits(plane_logits, tgt, reduction="none")  # (B, N, K, Hp, Wp)
    v = valid.to(loss.dtype).expand_as(loss)
    per_view = (loss * v).sum((0, 2, 3, 4)) / v.sum((0, 2, 3, 4)).clamp(min=1.0)  # (N,)
    return per_view.sum()


def mutual_loss(gv_fg: torch.Tensor, lv_fg: torch.Tensor, coverage: torch.Tensor,
                lv_teaches: bool, gv_teaches: bool) -> torch.Tensor:
    """AML (Eq. 4): cross-entropy of each student's foreground logit against the teacher's
    detached hard foreground mask, over covered feature cells. Inputs (B, 1, hb, wb).
    """
    loss = gv_fg.new_zeros(())
    if lv_teaches:
        loss = loss + masked_bce(gv_fg, (lv_fg.detach() > 0).to(gv_fg.dtype), coverage > 0)
    if gv_teaches:
        loss = loss + masked_bce(lv_fg, (gv_fg.detach() > 0).to(lv_fg.dtype), coverage > 0)
    return loss


def bimapper_loss(outputs: dict, batch: dict, epoch: int,
                  config: BiMapperLossConfig | None = None) -> tuple[torch.Tensor, dict[str, float]]:
    """Total Bi-Mapper loss ``BCE + asl_weight * ASL + mutual_weight * mutual`` (Eq. 5).

    Args:
        outputs: :meth:`BiMapper.forward` output.
        batch: ``target`` (B, K, H, W) ego class layers (bool/float), optional ``mask``
            (B, H, W) bool visibility (None/missing = every cell) and ``class_mask`` (B, K, H, W)
            bool, the cells each class's ground truth is known in (BCE and ASL leave the others out).
        epoch: current epoch, 0-based (drives the mutual-learning schedule).
        config: weights and schedule; default :class:`BiMapperLossConfig`.

    Returns:
        ``(total, parts)``, parts = floats ``bce``, ``asl``, ``mutual``, ``total`` (plus
        ``visibility`` / ``uncertainty`` when their weights are > 0). Terms of a disabled stream
        are 0.
    """
    cfg = config or BiMapperLossConfig()
    logits = outputs["logits"]
    target = batch["target"].to(logits.device)
    mask = batch.get("mask")
    if mask is not None:
        mask = mask.to(logits.device).bool()
    pw = None if cfg.pos_weight is None else torch.tensor(cfg.pos_weight, dtype=logits.dtype, device=logits.device)
    class_mask = batch.get("class_mask")
    if class_mask is not None:
        class_mask = class_mask.to(logits.device).bool()
    bce = masked_bce(logits, target, class_cells(mask, class_mask), pw)
    zero = logits.new_zeros(())
    asl = zero
    if outputs.get("lv_plane_logits") is not None:
        asl = across_space_loss(outputs["lv_plane_logits"], target, outputs["gt_grid"], outputs["gt_valid"],
                                mask, outputs.get("cam_mask"), class_mask)
    mutual = zero
    if outputs.get("gv_fg_logits") is not None and outputs.get("lv_fg_logits") is not None:
        lv_t, gv_t = mutual_teachers(epoch, cfg.mutual_start_epoch, cfg.mutual_mode)
        mutual = mutual_loss(outputs["gv_fg_logits"], outputs["lv_fg_logits"], outputs["lv_coverage"], lv_t, gv_t)
    total = bce + cfg.asl_weight * asl + cfg.mutual_weight * mutual
    parts = {"bce": float(bce.detach()), "asl": float(asl.detach()), "mutual": float(mutual.detach())}
    if cfg.visibility_weight > 0:
        vis_logits = outputs.get("visibility_logits")
        if vis_logits is None:
            raise ConfigError("visibility_weight > 0 needs a model with the visibility head")
        if mask is None:
            raise ConfigError("visibility_weight > 0 needs the visibility mask in the batch")
        vis = masked_bce(vis_logits, mask[:, None])
        total = total + cfg.visibility_weight * vis
        parts["visibility"] = float(vis.detach())
    if cfg.uncertainty_weight > 0:
        if mask is None:
            raise ConfigError("uncertainty_weight > 0 needs the visibility mask in the batch")
        unc = uncertainty_loss(logits, ~mask)
        total = total + cfg.uncertainty_weight * unc
        parts["uncertainty"] = float(unc.detach())
    parts["total"] = float(total.detach())
    return total, parts
