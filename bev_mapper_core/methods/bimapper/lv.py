"""Local-self View (LV) stream of Bi-Mapper: IPM to each camera's plane, U-Net, merge to ego.

Per camera, the input image is warped onto its camera plane by the precomputed IPM table
(:class:`~bev_mapper_core.methods.bimapper.geometry.BiMapperGeometry`), segmented there by a U-Net whose
per-class logits are supervised by the Across-Space Loss, and the U-Net's features are merged
into the reduced ego BEV grid with the extrinsics: each ego feature cell samples (bilinearly)
every camera plane it falls in, and the seen plane cells of the cameras covering it are
averaged.

The functions below take the tables as tensors, so they can be tested on their own; cameras are
put on ``grid_sample``'s batch axis (each camera has its own table) and the batch is folded into
channels.
"""

from __future__ import annotations

import torch
from torch import nn
from torch.nn import functional as F

from bev_mapper_core.nn.efficientnet import EfficientNetConfig
from bev_mapper_core.nn.unet import EffUNet


def warp_to_planes(images: torch.Tensor, ipm_grid: torch.Tensor, ipm_valid: torch.Tensor, mode: str) -> torch.Tensor:
    """IPM of each camera's input onto its plane.

    Args:
        images: (B, N, C, h, w) model inputs.
        ipm_grid: (N, Hp, Wp, 2) normalised pixel coordinates; ipm_valid: (N, Hp, Wp) bool.
        mode: ``nearest`` (one-hot labels) or ``bilinear`` (RGB).

    Returns:
        (B, N, C, Hp, Wp), zero where the plane cell is not seen.
    """
    B, N, C, h, w = images.shape
    x = images.permute(1, 0, 2, 3, 4).reshape(N, B * C, h, w)  # (B, N, C, h, w) -> (N, B*C, h, w)
    out = F.grid_sample(x, ipm_grid, mode=mode, padding_mode="zeros", align_corners=False)  # (N, B*C, Hp, Wp)
    out = out * ipm_valid[:, None].to(out.dtype)
    Hp, Wp = ipm_grid.shape[1:3]
    return out.view(N, B, C, Hp, Wp).permute(1, 0, 2, 3, 4)  # (N, B*C, Hp, Wp) -> (B, N, C, Hp, Wp)


def merge_planes_to_ego(planes: torch.Tensor, merge_grid: torch.Tensor, merge_weight: torch.Tensor,
                        cam_mask: torch.Tensor | None = None, eps: float = 1e-3) -> tuple[torch.Tensor, torch.Tensor]:
    """Merge per-camera plane maps into the ego feature grid (normalised bilinear average).

    Each ego cell samples every camera plane bilinearly; ``merge_weight`` is the same bilinear
    sample of the plane's "seen" mask, so with unseen plane cells zeroed beforehand,
    ``sum_n S_n(planes) / sum_n w_n`` averages the seen plane cells of all covering cameras
    (one camera fully covering a cell contributes weight 1; two overlapping cameras are averaged).

    Args:
        planes: (B, N, C, Hp, Wp), zero on plane cells the camera does not see.
        merge_grid: (N, h, w, 2) normalised plane coordinates of each ego feature cell.
        merge_weight: (N, h, w) seen fraction of each cell's bilinear footprint (0 off the plane).
        cam_mask: (B, N) cameras present, or None for all.
        eps: total weight below which a cell counts as uncovered (left at 0).

    Returns:
        ego (B, C, h, w) and coverage (B, 1, h, w) float (1 where some present camera covers).
    """
    B, N, C, Hp, Wp = planes.shape
    x = planes.permute(1, 0, 2, 3, 4).reshape(N, B * C, Hp, Wp)  # (B, N, C, Hp, Wp) -> (N, B*C, Hp, Wp)
    s = F.grid_sample(x, merge_grid, mode="bilinear", padding_mode="zeros", align_corners=False)  # (N, B*C, h, w)
    h, w = merge_grid.shape[1:3]
    s = s.view(N, B, C, h, w)  # (N, B*C, h, w) -> (N, B, C, h, w)
    wgt = merge_weight[:, None].to(s.dtype).expand(N, B, h, w)  # (N, B, h, w)
    if cam_mask is not None:
        cm = cam_mask.t().to(s.dtype)[:, :, None, None]  # (B, N) -> (N, B, 1, 1)
        wgt = wgt * cm
        s = s * cm[:, :, None]
    total = wgt.sum(0)  # (B, h, w)
    covered = total > eps
    ego = s.sum(0) / torch.where(covered, total, torch.ones_like(total))[:, None]  # (B, C, h, w)
    ego = ego * covered[:, None].to(s.dtype)
    return ego, covered[:, None].to(s.dtype)


class LVStream(nn.Module):
    """IPM -> U-Net -> merge. Output channels equal the GV stream's, for the weighted sum."""

    def __init__(self, cfg: EfficientNetConfig, unet_channels: int, out_channels: int, num_classes: int,
                 interpolation: str) -> None:
        super().__init__()
        self.unet = EffUNet(cfg, unet_channels, out_channels, num_classes)
        self.interpolation = interpolation

    def forward(self, images: torch.Tensor, tables: dict[str, torch.Tensor],
                cam_mask: torch.Tensor | None = None) -> dict[str, torch.Tensor]:
        """Run the stream.

        Args:
            images: (B, N, C_in, h, w) model inputs.
            tables: ``ipm_grid``, ``ipm_valid``, ``merge_grid``, ``merge_weight`` tensors.
            cam_mask: (B, N) cameras present.

        Returns:
            ``feat`` (B, C, hb, wb) merged ego features; ``plane_logits`` (B, N, K, Hp, Wp);
            ``fg_logits`` (B, 1, hb, wb) the merged plane logits' max over classes (the stream's
            foreground/background prediction for mutual learning); ``coverage`` (B, 1, hb, wb).
        """
        B, N = images.shape[:2]
        planes = warp_to_planes(images, tables["ipm_grid"], tables["ipm_valid"], self.interpolation)
        feats, logits = self.unet(planes.flatten(0, 1))  # (B*N, C_in, Hp, Wp) -> (B*N, C, Hp, Wp), (B*N, K, Hp, Wp)
        feats = feats.view(B, N, *feats.shape[1:])  # (B*N, C, Hp, Wp) -> (B, N, C, Hp, Wp)
        logits = logits.view(B, N, *logits.shape[1:])  # (B*N, K, Hp, Wp) -> (B, N, K, Hp, Wp)
        both = torch.cat([feats, logits], dim=2)  # (B, N, C + K, Hp, Wp): one merge for both
        both = both * tables["ipm_valid"][None, :, None].to(both.dtype)  # unseen plane cells -> 0
        ego, coverage = merge_planes_to_ego(both, tables["merge_grid"], tables["merge_weight"], cam_mask)
        C = feats.shape[2]
        fg = ego[:, C:].amax(dim=1, keepdim=True)  # (B, K, hb, wb) -> (B, 1, hb, wb)
        return {"feat": ego[:, :C], "plane_logits": logits, "fg_logits": fg, "coverage": coverage}
