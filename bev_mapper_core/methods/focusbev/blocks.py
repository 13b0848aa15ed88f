"""FocusBEV's blocks: the column-wise view transformers, the polar -> Cartesian resampling and
the ego-motion temporal fusion (Zhao et al., "Focus on BEV: Self-calibrated Cycle View
Transformation for Monocular Birds-Eye-View Segmentation"; no public code exists, so each
reading of the paper is stated where it is made).

* :class:`ColumnTransformer`: each image column is a sequence (its pixels, bottom to top in
  feature rows) and each polar ray one (its depth bins); a grid-shaped learnable query
  cross-attends, column by column, to the keys of its own column only (Eq. 1-2). ``layers`` 0 is
  the ablation's MLP structure: a two-layer MLP along the column (shared by channels and
  columns), as PON's dense transformer without its channel bottleneck.
* :func:`depth_ranges` / :func:`polar_grids`: the polar BEV features of FPN level ``l`` cover
  depths ``[z_l, z_{l+1})`` along the camera's optical axis, the finest level the farthest
  range (PON). The paper gives no boundaries; here the range ``[min_depth, max_depth]`` is split
  geometrically. Every Cartesian BEV cell is projected into the camera with the project's own
  camera model (focal length, principal point and distortion from the calibration) to find its
  image column and depth: the cell samples ray ``u`` at depth ``z`` of the level covering ``z``.
* :class:`EgoMotionFusion`: the reference BEV feature and ``window - 1`` history features, each
  warped to the current pose (:func:`~bev_mapper_core.nn.bev_warp.warp_batch`; rotation and
  translation of the ego motion), concatenated along channels and fused by a 3x3 convolution
  (Eq. 8). A history cell is replaced by the reference feature where the history frame did not
  see it (its point lies outside that frame's grid) and a whole history frame where there is
  none (the memory was reset, or the drive just started): the paper's "inconsistent scene".
"""

from __future__ import annotations

import math

import numpy as np
import torch
from torch import nn
from torch.nn import functional as F

from bev_mapper_core.geometry.grid import BevGrid
from bev_mapper_core.geometry.rig import RigCamera
from bev_mapper_core.geometry.transforms import transform_points
from bev_mapper_core.nn.bev_warp import warp_batch


class ColumnTransformer(nn.Module):
    """Column-wise decoder-only transformer: keys ``(B, C, Lk, W)`` -> ``(B, C, Lq, W)``.

    Args:
        channels: feature width ``C``.
        key_len, query_len: sequence lengths along each column (keys, learnable queries).
        columns: number of columns ``W`` (each has its own queries and key positions).
        layers: MHCA + MLP layers (0: a column-wise two-layer MLP, the paper's ablation).
        heads: attention heads.
    """

    def __init__(self, channels: int, key_len: int, query_len: int, columns: int, layers: int, heads: int) -> None:
        super().__init__()
        self.key_len, self.query_len, self.columns, self.layers = key_len, query_len, columns, layers
        if layers == 0:
            hidden = max(query_len, key_len)
            self.mlp = nn.Sequential(nn.Linear(key_len, hidden), nn.ReLU(inplace=True), nn.Linear(hidden, query_len))
            return
        # grid-shaped learnable query and learnable key positions (Eq. 1)
        self.query = nn.Parameter(torch.randn(1, channels, query_len, columns) * 0.02)
        self.key_pos = nn.Parameter(torch.randn(1, channels, key_len, columns) * 0.02)
        self.key_norm = nn.LayerNorm(channels)
        self.attn = nn.ModuleList(nn.MultiheadAttention(channels, heads, batch_first=True) for _ in range(layers))
        self.norm1 = nn.ModuleList(nn.LayerNorm(channels) for _ in range(layers))
        self.norm2 = nn.ModuleList(nn.LayerNorm(channels) for _ in range(layers))
        self.ffn = nn.ModuleList(nn.Sequential(nn.Linear(channels, 2 * channels), nn.GELU(),
                                               nn.Linear(2 * channels, channels)) for _ in range(layers))

    def forward(self, keys: torch.Tensor) -> torch.Tensor:
        """``(B, C, Lk, W)`` -> ``(B, C, Lq, W)``; column ``j`` of the output reads column ``j`` only."""
        B, C, Lk, W = keys.shape
        if (Lk, W) != (self.key_len, self.columns):
            raise ValueError(f"column transformer expects (B, C, {self.key_len}, {self.columns}), got {tuple(keys.shape)}")
        if self.layers == 0:
            return self.mlp(keys.transpose(2, 3)).transpose(2, 3)  # (B, C, W, Lk) -> (B, C, W, Lq) -> (B, C, Lq, W)
        k = (keys + self.key_pos).permute(0, 3, 2, 1).reshape(B * W, Lk, C)  # (B, C, Lk, W) -> (B*W, Lk, C)
        k = self.key_norm(k)
        q = self.query.expand(B, -1, -1, -1).permute(0, 3, 2, 1).reshape(B * W, self.query_len, C)  # (B*W, Lq, C)
        for attn, n1, n2, ffn in zip(self.attn, self.norm1, self.norm2, self.ffn):
            q = q + attn(n1(q), k, k, need_weights=False)[0]
            q = q + ffn(n2(q))
        return q.reshape(B, W, self.query_len, C).permute(0, 3, 2, 1)  # (B*W, Lq, C) -> (B, C, Lq, W)


def depth_ranges(min_depth: float, max_depth: float, levels: int) -> list[tuple[float, float]]:
    """Depth range ``(z0, z1)`` (m, along the optical axis) of each FPN level, finest level first
    (it sees farthest): ``[min_depth, max_depth]`` split geometrically into ``levels`` parts.
    """
    edges = [min_depth * (max_depth / min_depth) ** (i / levels) for i in range(levels + 1)]
    return [(edges[levels - 1 - i], edges[levels - i]) for i in range(levels)]


def depth_bins(z0: float, z1: float, cell: float) -> int:
    """Polar depth bins of a range, one per BEV feature cell length ``cell`` (at least 2)."""
    return max(2, math.ceil((z1 - z0) / cell))


def feature_grid(grid: BevGrid, downsample: int) -> BevGrid:
    """The BEV feature map's grid: ``grid``'s cells ``downsample`` times larger, the extent
    rounded up to whole cells (same origin corner).
    """
    res = grid.resolution * downsample
    h, w = math.ceil(grid.height / downsample), math.ceil(grid.width / downsample)
    return BevGrid(grid.x_min, grid.x_min + w * res, grid.y_min, grid.y_min + h * res, res)


def polar_grids(camera: RigCamera, fgrid: BevGrid, ranges: list[tuple[float, float]]) -> tuple[np.ndarray, np.ndarray]:
    """Where each Cartesian cell of ``fgrid`` reads the polar features of each level.

    Args:
        camera: the camera at the model's input size (:func:`~.geometry.scaled_camera`).
        fgrid: the BEV feature grid.
        ranges: :func:`depth_ranges`.

    Returns:
        ``grids`` ``(L, h, w, 2)`` float32 ``grid_sample`` coordinates (``align_corners=False``)
        into a level's polar map ``(D_l, W_l)``: x = the cell's image column (pixel centres at
        integers), y = its depth within the level's range; ``valid`` ``(L, h, w)`` bool: the cell
        is in front of the camera, inside the image's width and inside the level's range.
    """
    W_in = camera.model.image_size[0]
    p = transform_points(camera.cam_from_ego, fgrid.points(0.0))  # (h*w, 3) ground cell centres, optical frame
    uv, in_front = camera.model.project(p)
    u = np.where(in_front, uv[:, 0], -1e6)
    z = p[:, 2]
    x_norm = (2.0 * u + 1.0) / W_in - 1.0
    inside = in_front & (u >= -0.5) & (u < W_in - 0.5)
    grids, valid = [], []
    for z0, z1 in ranges:
        y_norm = 2.0 * (z - z0) / (z1 - z0) - 1.0
        grids.append(np.stack([x_norm, y_norm], axis=1).reshape(*fgrid.shape, 2))  # (h*w, 2) -> (h, w, 2)
        valid.append((inside & (z >= z0) & (z < z1)).reshape(fgrid.shape))
    return np.stack(grids).astype(np.float32), np.stack(valid)


def polar_to_cartesian(polar: list[torch.Tensor], grids: torch.Tensor, valid: torch.Tensor) -> torch.Tensor:
    """Polar features of every level ``(B, C, D_l, W_l)`` -> Cartesian ``(B, C, h, w)``: each cell
    from the one level whose depth range holds it (the levels' ranges, concatenated along depth).
    """
    B = polar[0].shape[0]
    out = 0
    for lvl, feat in enumerate(polar):
        g = grids[lvl][None].expand(B, -1, -1, -1)  # (B, h, w, 2)
        s = F.grid_sample(feat, g, mode="bilinear", padding_mode="border", align_corners=False)  # (B, C, h, w)
        out = out + s * valid[lvl].to(s.dtype)
    return out


class EgoMotionFusion(nn.Module):
    """Ego-motion temporal fusion of ``window`` BEV features (see the module docstring)."""

    def __init__(self, channels: int, window: int, fgrid: BevGrid) -> None:
        super().__init__()
        self.window, self.fgrid = window, fgrid
        self.fuse = nn.Sequential(nn.Conv2d(channels * window, channels, 3, 1, 1, bias=False),
                                  nn.BatchNorm2d(channels), nn.ReLU(inplace=True))

    def forward(self, current: torch.Tensor, history: list[tuple[torch.Tensor, torch.Tensor, torch.Tensor]]) -> torch.Tensor:
        """``current`` ``(B, C, h, w)``; ``history``: up to ``window - 1`` entries, newest first,
        each ``(feature (B, C, h, w), prev_from_cur (B, 4, 4), present (B,) bool)``; features are
        used without gradient. Returns the fused ``(B, C, h, w)``.
        """
        aligned = [current]
        for feat, prev_from_cur, present in history[: self.window - 1]:
            moved, inside = warp_batch(feat.detach(), self.fgrid, prev_from_cur)
            keep = (inside & present.to(inside.device)[:, None, None])[:, None]  # (B, 1, h, w)
            aligned.append(torch.where(keep, moved, current))
        while len(aligned) < self.window:  # no history frame: the reference stands in
            aligned.append(current)
        return self.fuse(torch.cat(aligned, dim=1))  # (B, C * window, h, w) -> (B, C, h, w)


__all__ = ["ColumnTransformer", "EgoMotionFusion", "depth_bins", "depth_ranges", "feature_grid", "polar_grids",
           "polar_to_cartesian"]
