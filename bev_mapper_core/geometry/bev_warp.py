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

import numpy as np

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


def warp_layers(layers: np.ndarray, grid: BevGrid, prev_from_cur) -> tuple[np.ndarray, np.ndarray]:
    """Earlier layers ``(B, C, H, W)`` (or ``(C, H, W)``) on ``grid`` -> the same layers seen from the
    current pose, and ``valid`` ``(H, W)`` bool: current cells whose earlier point lies inside the
    grid (elsewhere the warped layers are 0). Numpy, no torch: bilinear sampling as
    ``torch.nn.functional.grid_sample(mode="bilinear", padding_mode="zeros", align_corners=False)``
    computes it (its CPU kernel's unnormalization and corner weights, in the layers' float dtype;
    the batched torch version the learned methods train with is
    :func:`bev_mapper_core.nn.bev_warp.warp_batch`).

    Raises:
        ConfigError: ``prev_from_cur`` is not a finite rigid 4x4 transform.
        ValueError: layers not of ``grid``'s shape.
    """
    x = np.asarray(layers)
    if x.ndim not in (3, 4) or tuple(x.shape[-2:]) != grid.shape:
        raise ValueError(f"layers must be (B, C, {grid.height}, {grid.width}) or (C, ...), got {tuple(x.shape)}")
    px, py = source_points(grid, prev_from_cur)  # (H, W) float64 each
    dtype = x.dtype if np.issubdtype(x.dtype, np.floating) else np.dtype(np.float32)
    x = x.astype(dtype, copy=False)
    u = (2.0 * (px - grid.x_min) / (grid.x_max - grid.x_min) - 1.0).astype(dtype)  # along columns (x)
    v = (2.0 * (py - grid.y_min) / (grid.y_max - grid.y_min) - 1.0).astype(dtype)  # along rows (y)
    H, W = grid.shape
    ix = (u + dtype.type(1)) * dtype.type(W / 2) - dtype.type(0.5)  # pixel coordinates, torch's kernel order
    iy = (v + dtype.type(1)) * dtype.type(H / 2) - dtype.type(0.5)
    x0, y0 = np.floor(ix), np.floor(iy)
    we, wn = ix - x0, iy - y0  # distances to the west / north neighbour
    ee, es = dtype.type(1) - we, dtype.type(1) - wn
    c0, r0 = x0.astype(np.int64), y0.astype(np.int64)
    out = np.zeros(x.shape, dtype)
    # corners nw, ne, sw, se in torch's summation order; a corner outside the grid adds 0
    for dr, dc, weight in ((0, 0, es * ee), (0, 1, es * we), (1, 0, wn * ee), (1, 1, wn * we)):
        r, c = r0 + dr, c0 + dc
        inside = (r >= 0) & (r < H) & (c >= 0) & (c < W)
        vals = x[..., np.clip(r, 0, H - 1), np.clip(c, 0, W - 1)]  # (..., H, W)
        out += np.where(inside, vals, dtype.type(0)) * weight
    valid = (px >= grid.x_min) & (px < grid.x_max) & (py >= grid.y_min) & (py < grid.y_max)
    return out, valid


__all__ = ["source_points", "warp_layers"]
