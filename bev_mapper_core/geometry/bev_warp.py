"""Moving BEV layers between ego poses: the geometry of temporal fusion (issue #14).

A layer computed at an earlier ego pose shows the world in that pose's ``base_link`` frame. To
combine it with the current frame, each *current* cell centre is carried into the earlier frame
(``prev_from_cur``, a 4x4 rigid transform, e.g. ``inv(odom_from_prev) @ odom_from_cur``) and
the earlier layer is sampled there, bilinearly. The ground is taken as the plane ``z = 0`` of
both frames, so only the planar part of the motion matters (x, y and yaw; roll, pitch and z move
the sample point only through their effect on ``(x, y)``).

Everything goes through the one :class:`~bev_mapper_core.geometry.grid.BevGrid`: cell ``(row, col)`` is
the point :meth:`~bev_mapper_core.geometry.grid.BevGrid.cell_to_metric` names, in both frames.
"""

from __future__ import annotations

from functools import lru_cache

import numpy as np
import torch
from torch.nn import functional as F

from ..errors import CalibrationError, ConfigError
from .grid import BevGrid
from .transforms import validate_transform


def _check_transform(T) -> np.ndarray:
    """``T`` as float64 after :func:`~bev_mapper_core.geometry.transforms.validate_transform` (a bad one:
    ConfigError).
    """
    try:
        return validate_transform(T, "prev_from_cur")
    except CalibrationError as exc:
        raise ConfigError(str(exc)) from None


def source_points(grid: BevGrid, prev_from_cur) -> tuple[np.ndarray, np.ndarray]:
    """Where each current cell centre lies in the earlier frame: ``(xs, ys)``, each ``(H, W)``.

    Raises:
        ConfigError: ``prev_from_cur`` is not a finite rigid 4x4 transform.
    """
    T = _check_transform(prev_from_cur)
    xs, ys = grid.centers  # (H, W) each, cached by the grid; the cells lie at z = 0
    return T[0, 0] * xs + T[0, 1] * ys + T[0, 3], T[1, 0] * xs + T[1, 1] * ys + T[1, 3]


def warp_layers(layers: torch.Tensor, grid: BevGrid, prev_from_cur) -> tuple[torch.Tensor, torch.Tensor]:
    """Earlier layers ``(B, C, H, W)`` (or ``(C, H, W)``) on ``grid`` -> the same layers seen from the
    current pose, and ``valid`` ``(H, W)`` bool: current cells whose earlier point lies inside the
    grid (elsewhere the warped layers are 0). One motion for the whole batch (:func:`warp_batch`).

    Raises:
        ConfigError: ``prev_from_cur`` is not a finite rigid 4x4 transform.
        ValueError: layers not of ``grid``'s shape.
    """
    T = torch.from_numpy(_check_transform(prev_from_cur))
    squeeze = layers.dim() == 3
    x = layers[None] if squeeze else layers  # (B, C, H, W)
    out, valid = warp_batch(x, grid, T[None].expand(x.shape[0], -1, -1))  # (4, 4) -> (B, 4, 4)
    return (out[0] if squeeze else out), valid[0]


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


__all__ = ["source_points", "warp_batch", "warp_layers"]
