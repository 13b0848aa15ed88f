"""Moving BEV feature maps between ego poses in torch, batched with one motion per sample: the
ego-motion fusion of FocusBEV trains and runs with it. The geometry is
:mod:`bev_mapper_core.geometry.bev_warp`'s (whose numpy :func:`~bev_mapper_core.geometry.bev_warp.warp_layers`
the published maps' temporal fusion uses, without torch).
"""

from __future__ import annotations

from functools import lru_cache

import torch
from torch.nn import functional as F

from bev_mapper_core.geometry.grid import BevGrid


@lru_cache(maxsize=16)
def _centers(grid: BevGrid, device: str) -> tuple[torch.Tensor, torch.Tensor]:
    """The grid's cell centres ``(xs, ys)`` as float64 tensors on ``device`` (built once)."""
    return tuple(torch.tensor(a, device=device) for a in grid.centers)


def warp_batch(layers: torch.Tensor, grid: BevGrid, prev_from_cur: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Earlier layers ``(B, C, H, W)`` on ``grid`` with one motion per sample, ``prev_from_cur``
    ``(B, 4, 4)`` (rigid, not checked here: :func:`warp_layers` and the callers' poses are) ->
    warped ``(B, C, H, W)`` (bilinear, 0 outside) and ``valid`` ``(B, H, W)`` bool: current cells
    whose earlier point lies inside the grid.

    Raises:
        ValueError: layers not of ``grid``'s shape.
    """
    if layers.dim() != 4 or tuple(layers.shape[-2:]) != grid.shape:
        raise ValueError(f"layers must be (B, C, {grid.height}, {grid.width}), got {tuple(layers.shape)}")
    T = prev_from_cur.to(device=layers.device, dtype=torch.float64)
    xs, ys = _centers(grid, str(layers.device))  # (H, W) float64 each; the cells lie at z = 0
    px = T[:, 0, 0, None, None] * xs + T[:, 0, 1, None, None] * ys + T[:, 0, 3, None, None]  # (B, H, W)
    py = T[:, 1, 0, None, None] * xs + T[:, 1, 1, None, None] * ys + T[:, 1, 3, None, None]
    u = 2.0 * (px - grid.x_min) / (grid.x_max - grid.x_min) - 1.0  # along columns (x)
    v = 2.0 * (py - grid.y_min) / (grid.y_max - grid.y_min) - 1.0  # along rows (y)
    g = torch.stack([u, v], dim=-1).to(layers.dtype)  # (B, H, W, 2)
    out = F.grid_sample(layers, g, mode="bilinear", padding_mode="zeros", align_corners=False)  # (B, C, H, W)
    valid = (px >= grid.x_min) & (px < grid.x_max) & (py >= grid.y_min) & (py < grid.y_max)
    return out, valid


__all__ = ["warp_batch"]
