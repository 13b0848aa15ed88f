"""S2G2's objective (paper Eq. 1, 4-6) and the passive branch's EMA update.

``L = L_seg + alpha * L_cycle + beta * L_BEV + gamma(t) * L_con`` (paper: alpha = beta = 1,
gamma ramped to 1 over 100 steps):

* ``L_seg``: the active branch's per-class BCE against the BEV ground truth of the labeled
  frames, over the cells inside the visibility mask (as Bi-Mapper's ego loss,
  :func:`~.losses.masked_bce`, with the same optional per-class positive weights). The paper
  names a cross-entropy over 4 exclusive classes; this package's layers overlap (a lane divider
  is also drivable), so it is a two-class cross-entropy per layer.
* ``L_cycle`` (Eq. 1): ``mean |H_F^B(H_B^F(F_front)) - F_front|`` (L1), on every frame.
* ``L_BEV``: ties ``F_I`` and ``F_C``. The paper names a cross-entropy between the two attention
  outputs, which are real-valued feature maps; the released code uses an L1 distance. ``l1``
  (default) is that; ``ce`` is the soft cross-entropy between the per-cell channel
  distributions, ``-sum_c softmax(F_I)_c log softmax(F_C)_c``, averaged over cells. Gradient
  reaches both maps, as in the released code.
* ``L_con`` (Eq. 4): mean squared difference between the active and passive branches' class
  probabilities (sigmoid per layer: the multi-label counterpart of Mean Teacher's softmax MSE)
  on labeled and unlabeled frames; the passive prediction is a target (no gradient), as in
  the released code.
* ``gamma(t) = weight * exp(-5 (1 - t)^2)``, ``t = clip(step / ramp_steps, 0, 1)``: Mean
  Teacher's sigmoid ramp-up (:func:`sigmoid_rampup`).

The passive branch follows the active one by ``w_p <- lambda w_p + (1 - lambda) w_a`` after each
optimizer step (Eq. 5, :func:`ema_update`, lambda 0.999).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
from torch import nn
from torch.nn import functional as F

from bev_mapper_core.errors import ConfigError
from bev_mapper_core.nn.losses import class_cells, masked_bce

#: ``S2G2LossConfig.bev_tie`` choices.
BEV_TIES = ("l1", "ce")


def sigmoid_rampup(step: float, ramp_steps: float) -> float:
    """Mean Teacher's ramp-up ``exp(-5 (1 - t)^2)``, ``t = clip(step / ramp_steps, 0, 1)``;
    1 from ``ramp_steps`` on (and always, for ``ramp_steps`` 0).
    """
    if ramp_steps <= 0:
        return 1.0
    t = min(max(float(step) / float(ramp_steps), 0.0), 1.0)
    return float(math.exp(-5.0 * (1.0 - t) ** 2))


@torch.no_grad()
def ema_update(passive: nn.Module, active: nn.Module, decay: float) -> None:
    """``p <- decay * p + (1 - decay) * a`` for every parameter pair (Eq. 5), in place.

    Parameters only, matched by name: buffers (BatchNorm running statistics) stay the passive
    module's own, which it gathers from its own input in train mode, as Mean Teacher's teacher.

    Raises:
        ValueError: ``decay`` outside [0, 1], or modules whose parameters differ.
    """
    if not 0.0 <= decay <= 1.0:
        raise ValueError(f"EMA decay must be in [0, 1], got {decay}")
    a = dict(active.named_parameters())
    p = dict(passive.named_parameters())
    if a.keys() != p.keys() or any(a[k].shape != p[k].shape for k in a):
        raise ValueError("the passive and active modules must have the same parameters")
    for k, pp in p.items():
        pp.mul_(decay).add_(a[k].detach(), alpha=1.0 - decay)


def ema_decay_at(step: int, decay: float, warmup: bool) -> float:
    """The EMA decay after ``step`` optimizer steps: ``decay``, or with ``warmup``
    ``min(decay, 1 - 1 / (step + 1))`` (Mean Teacher's and the released S2G2 code's: the passive
    branch is the plain average of the active weights while that is the closer estimate).
    """
    return min(decay, 1.0 - 1.0 / (step + 1)) if warmup else decay


@dataclass(frozen=True)
class S2G2LossConfig:
    """Weights of Eq. 6 and the consistency ramp.

    Args:
        cycle_weight: alpha (paper 1; 0 ablates the cycle loss).
        bev_weight: beta (paper 1; 0 ablates L_BEV).
        bev_tie: ``l1`` (released code) or ``ce`` (the paper's wording), see the module docstring.
        consistency_weight: gamma's final value (paper 1; 0 = supervised only).
        consistency_ramp_steps: optimizer steps of the ramp-up (paper 100).
        pos_weight: optional per-class positive weights of L_seg.
    """

    cycle_weight: float = 1.0
    bev_weight: float = 1.0
    bev_tie: str = "l1"
    consistency_weight: float = 1.0
    consistency_ramp_steps: int = 100
    pos_weight: tuple[float, ...] | None = None

    def __post_init__(self) -> None:
        for name in ("cycle_weight", "bev_weight", "consistency_weight"):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v) or v < 0:
                raise ConfigError(f"{name} must be a finite number >= 0, got {v!r}")
        if self.bev_tie not in BEV_TIES:
            raise ConfigError(f"bev_tie must be one of {BEV_TIES}, got {self.bev_tie!r}")
        v = self.consistency_ramp_steps
        if isinstance(v, bool) or not isinstance(v, int) or v < 0:
            raise ConfigError(f"consistency_ramp_steps must be an integer >= 0, got {v!r}")

    def gamma(self, step: int) -> float:
        """The consistency weight after ``step`` optimizer steps."""
        return self.consistency_weight * sigmoid_rampup(step, self.consistency_ramp_steps)


def cycle_loss(front: torch.Tensor, front_cycled: torch.Tensor) -> torch.Tensor:
    """Eq. 1: mean absolute difference of ``(B, C, hf, wf)`` maps."""
    return F.l1_loss(front_cycled, front)


def bev_tie_loss(f_i: torch.Tensor, f_c: torch.Tensor, kind: str = "l1") -> torch.Tensor:
    """L_BEV between ``F_I`` and ``F_C`` ``(B, C, hb, wb)`` (``kind``: see the module docstring)."""
    if kind == "l1":
        return F.l1_loss(f_c, f_i)
    if kind == "ce":
        return -(F.softmax(f_i, dim=1) * F.log_softmax(f_c, dim=1)).sum(1).mean()  # sum over C, mean over cells
    raise ConfigError(f"bev_tie must be one of {BEV_TIES}, got {kind!r}")


def consistency_loss(active_logits: torch.Tensor, passive_logits: torch.Tensor) -> torch.Tensor:
    """Eq. 4: mean squared difference of the class probabilities ``(B, K, H, W)``; the passive
    prediction is detached (a target).
    """
    return F.mse_loss(torch.sigmoid(active_logits), torch.sigmoid(passive_logits.detach()))


def s2g2_loss(outputs: dict, labeled: int, target: torch.Tensor, mask: torch.Tensor | None, step: int,
              config: S2G2LossConfig | None = None,
              class_mask: torch.Tensor | None = None) -> tuple[torch.Tensor, dict[str, float]]:
    """Eq. 6 over a batch whose first ``labeled`` frames have ground truth.

    Args:
        outputs: :meth:`~.s2g2.S2G2.forward` of the whole batch (labeled frames first, then
            the unlabeled ones).
        labeled: number of labeled frames (>= 1) at the front of the batch.
        target: ``(labeled, K, H, W)`` class layers; mask: ``(labeled, H, W)`` bool visibility,
            None = every cell.
        step: optimizer steps so far (the ramp).
        config: loss weights; default :class:`S2G2LossConfig`.
        class_mask: ``(labeled, K, H, W)`` bool, each class's known cells (None: all of ``mask``).

    Returns:
        ``(total, parts)``: floats ``seg``, ``cycle``, ``bev``, ``con``, ``gamma``, ``total``.
    """
    cfg = config or S2G2LossConfig()
    logits = outputs["active_logits"]
    if not 1 <= labeled <= logits.shape[0]:
        raise ValueError(f"labeled frames must be in 1..{logits.shape[0]}, got {labeled}")
    pw = None if cfg.pos_weight is None else torch.tensor(cfg.pos_weight, dtype=logits.dtype, device=logits.device)
    m = class_cells(None if mask is None else mask.to(logits.device),
                    None if class_mask is None else class_mask.to(logits.device))  # (B_l, 1 or K, H, W)
    seg = masked_bce(logits[:labeled], target.to(logits.device), m, pw)
    cyc = cycle_loss(outputs["front"], outputs["front_cycled"])
    tie = bev_tie_loss(outputs["f_i"], outputs["f_c"], cfg.bev_tie)
    con = consistency_loss(logits, outputs["passive_logits"])
    gamma = cfg.gamma(step)
    total = seg + cfg.cycle_weight * cyc + cfg.bev_weight * tie + gamma * con
    parts = {"seg": float(seg.detach()), "cycle": float(cyc.detach()), "bev": float(tie.detach()),
             "con": float(con.detach()), "gamma": gamma, "total": float(total.detach())}
    return total, parts


__all__ = ["BEV_TIES", "S2G2LossConfig", "bev_tie_loss", "consistency_loss", "cycle_loss", "ema_decay_at",
           "ema_update", "s2g2_loss", "sigmoid_rampup"]
