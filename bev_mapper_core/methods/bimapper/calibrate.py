"""Per-class temperature scaling of Bi-Mapper weights (issue #11, calibration).

``T_k`` minimises the negative log-likelihood (binary cross-entropy) of ``sigmoid(z_k / T_k)``
over the **visible** cells of validation frames (the visibility mask; hidden cells have no
reliable label). It is fitted per class on ``log T`` (so ``T > 0``) with L-BFGS, stored in the
weights' ``BiMapperConfig.temperature`` (in the metadata) and applied by
:meth:`BiMapper.calibrated` in the mapper. A file without it keeps ``T = 1``.

    bev-train calibrate --rig surround6 --weights runs/X/last.safetensors --out runs/X/calibrated.safetensors
        [--val-seeds 900000000,...] [--cache data/cache]
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import replace

import numpy as np
import torch
from torch.nn import functional as F

from bev_mapper_core.geometry.grid import BevGrid
from bev_mapper_core.geometry.rig import Rig
from bev_mapper_core.training.data import FrameSet

from .model import BiMapper
from .weights import WeightsFile, save_weights

#: Bounds of a fitted temperature (the config accepts [0.01, 100]).
T_MIN, T_MAX = 0.05, 20.0
#: Visible cells per class kept for the fit (a random subset; the fit is one number per class).
MAX_CELLS = 2_000_000


def fit_temperature(logits: torch.Tensor, target: torch.Tensor, iters: int = 100) -> torch.Tensor:
    """Per-class temperatures minimising the mean BCE of ``sigmoid(logits / T)``.

    Args:
        logits: (M, K) class logits of M cells; target: (M, K) 0/1.

    Returns:
        (K,) temperatures in ``[T_MIN, T_MAX]``.
    """
    logits = logits.double()
    target = target.double()
    log_t = torch.zeros(logits.shape[1], dtype=torch.float64, requires_grad=True)
    opt = torch.optim.LBFGS([log_t], lr=0.5, max_iter=iters, line_search_fn="strong_wolfe")

    def closure() -> torch.Tensor:
        opt.zero_grad()
        loss = F.binary_cross_entropy_with_logits(logits / log_t.exp()[None], target, reduction="mean")
        loss.backward()
        return loss

    opt.step(closure)
    return log_t.detach().exp().clamp(T_MIN, T_MAX).float()


@torch.no_grad()
def collect_visible_logits(model: BiMapper, frames: FrameSet, batch: int = 2, seed: int = 0,
                           max_cells: int = MAX_CELLS) -> tuple[torch.Tensor, torch.Tensor]:
    """The model's raw class logits and targets on the visible cells of ``frames``.

    Returns ``(logits (M, K), target (M, K))``, at most ``max_cells`` cells (a seeded random subset).
    """
    model.eval()
    zs, ts = [], []
    for b in frames.batches(batch, seed, 0, shuffle=False):
        out = model(b["images"])
        z = out["logits"].permute(0, 2, 3, 1)  # (B, K, H, W) -> (B, H, W, K)
        t = b["target"].permute(0, 2, 3, 1)  # (B, K, H, W) -> (B, H, W, K)
        m = b["mask"].bool()  # (B, H, W)
        zs.append(z[m].float())  # (cells, K)
        ts.append(t[m].float())
    z, t = torch.cat(zs), torch.cat(ts)
    if len(z) > max_cells:
        idx = torch.from_numpy(np.random.default_rng(seed).choice(len(z), max_cells, replace=False))
        z, t = z[idx], t[idx]
    return z, t


def calibrate_weights(weights: str, out: str, rig: Rig, grid: BevGrid, frames: FrameSet,
                      log: Callable[[str], None] = print) -> tuple[float, ...]:
    """Fit the per-class temperatures of ``weights`` on ``frames`` (validation drives, camera-size
    images) and write the file with them to ``out``. Returns the temperatures.
    """
    wf = WeightsFile.open(weights)
    model = wf.build_model(rig, grid, input_kind=wf.input_kind)
    model.config = replace(model.config, temperature=None)  # fit the raw logits
    z, t = collect_visible_logits(model, frames)
    temps = fit_temperature(z, t)
    before = F.binary_cross_entropy_with_logits(z, t).item()
    after = F.binary_cross_entropy_with_logits(z / temps[None], t).item()
    names: Sequence[str] = model.config.classes
    log(f"temperatures {dict(zip(names, [round(float(v), 3) for v in temps]))}; visible-cell NLL "
        f"{before:.5f} -> {after:.5f} over {len(z)} cells")
    model.config = replace(model.config, temperature=tuple(round(float(v), 4) for v in temps))
    save_weights(model, out)
    return model.config.temperature


__all__ = ["calibrate_weights", "collect_visible_logits", "fit_temperature"]
