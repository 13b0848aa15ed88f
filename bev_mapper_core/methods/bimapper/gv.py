"""Global-cross View (GV) stream of Bi-Mapper: image encoder and per-view MLP view transform.

Paper Eq. (2): ``F_g = sum_n phi2_n(ReLU(phi1_n(F_p_n)))``. Each camera's pixel-layer feature
map ``F_p_n`` (C, h, w) is flattened over its spatial dimensions; the two linear layers act on
that ``h * w`` axis with the channels shared (HDMapNet's view relation module), mapping it
straight to the ego BEV feature map ``(hb, wb)``; every camera has its own ``phi1_n, phi2_n``
(same architecture, separate weights) and the views are summed. As in the formula, there is no
activation after ``phi2`` (HDMapNet adds one). The hidden width defaults to ``hb * wb``
(HDMapNet's choice; the paper does not give it).
"""

from __future__ import annotations

import math

import torch
from torch import nn

from bev_mapper_core.nn.efficientnet import EfficientNet, EfficientNetConfig
from bev_mapper_core.nn.layers import conv_bn_relu


class CamEncoder(nn.Module):
    """EfficientNet trunk + HDMapNet-style neck: the two deepest endpoints fused at the shallower
    one's stride (B0 full: stride 32 and 16 fused at 16, 320 + 112 -> 512 -> C).

    Output: ``(B, out_channels, ceil(H / stride), ceil(W / stride))`` with :attr:`stride`.
    """

    def __init__(self, cfg: EfficientNetConfig, neck_channels: int, out_channels: int) -> None:
        super().__init__()
        self.trunk = EfficientNet(cfg)
        if len(self.trunk.endpoint_channels) < 2:
            raise ValueError("the camera encoder needs at least two EfficientNet endpoints (num_stages >= 2)")
        c_deep, c_skip = self.trunk.endpoint_channels[-1], self.trunk.endpoint_channels[-2]
        self.stride = self.trunk.endpoint_strides[-2]
        self.neck = nn.Sequential(conv_bn_relu(c_deep + c_skip, neck_channels), conv_bn_relu(neck_channels, neck_channels))
        self.out = nn.Conv2d(neck_channels, out_channels, 1)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        """``x`` (B, C_in, H, W) -> features (B, out_channels, h, w)."""
        ends = self.trunk(x)
        deep, skip = ends[-1], ends[-2]
        deep = nn.functional.interpolate(deep, size=skip.shape[-2:], mode="bilinear", align_corners=False)
        return self.out(self.neck(torch.cat([deep, skip], dim=1)))


class GVTransform(nn.Module):
    """Per-view two-layer MLPs from flattened image features to the ego BEV feature map.

    Weights are stored batched over views (``w1`` (N, hidden, fv), ``w2`` (N, bv, hidden)) so
    one ``einsum`` runs all cameras; view ``n`` only ever uses slice ``n``.
    """

    def __init__(self, n_views: int, fv_hw: tuple[int, int], bv_hw: tuple[int, int], hidden: int | None = None) -> None:
        super().__init__()
        self.fv_hw, self.bv_hw = tuple(fv_hw), tuple(bv_hw)
        fv = fv_hw[0] * fv_hw[1]
        bv = bv_hw[0] * bv_hw[1]
        hidden = hidden or bv
        self.w1 = nn.Parameter(torch.empty(n_views, hidden, fv))
        self.b1 = nn.Parameter(torch.empty(n_views, hidden))
        self.w2 = nn.Parameter(torch.empty(n_views, bv, hidden))
        self.b2 = nn.Parameter(torch.empty(n_views, bv))
        for w, b, fan_in in ((self.w1, self.b1, fv), (self.w2, self.b2, hidden)):
            bound = 1.0 / math.sqrt(fan_in)  # nn.Linear's default initialisation
            nn.init.uniform_(w, -bound, bound)
            nn.init.uniform_(b, -bound, bound)

    def forward(self, feats: torch.Tensor, cam_mask: torch.Tensor | None = None) -> torch.Tensor:
        """``feats`` (B, N, C, h, w), ``cam_mask`` (B, N) bool/float or None -> F_g (B, C, hb, wb).

        Cameras with ``cam_mask`` 0 contribute nothing to the sum.
        """
        B, N, C = feats.shape[:3]
        x = feats.flatten(3)  # (B, N, C, h, w) -> (B, N, C, h*w)
        x = torch.einsum("bncf,nkf->bnck", x, self.w1) + self.b1[None, :, None, :]  # (B, N, C, hidden)
        x = torch.relu(x)
        x = torch.einsum("bnck,nvk->bncv", x, self.w2) + self.b2[None, :, None, :]  # (B, N, C, hb*wb)
        if cam_mask is not None:
            x = x * cam_mask.to(x.dtype)[:, :, None, None]
        return x.sum(1).view(B, C, *self.bv_hw)  # (B, C, hb*wb) -> (B, C, hb, wb)
