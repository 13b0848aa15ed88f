"""The BEV decoder head the learned BEV models share (Bi-Mapper, S2G2, FocusBEV)."""

from __future__ import annotations

import torch
from torch import nn
from torch.nn import functional as F

from .layers import conv_bn_relu

#: Width of the visibility head's 3x3 layer (``BiMapperConfig.visibility_head``).
VIS_CHANNELS = 16


class BevDecoder(nn.Module):
    """Conv + upsampling decoder from the BEV feature map to per-class logits on the full grid.

    With ``skip_channels`` > 0 the head also takes a full-resolution skip input (the IPM
    prior of ``ipm_skip``), concatenated before two 3x3 conv stages; its last 1x1 layer starts
    at zero, so an ``ipm_skip`` model's logits start as the prior's projection alone.
    """

    def __init__(self, cin: int, channels: int, num_classes: int, in_hw: tuple[int, int], out_hw: tuple[int, int],
                 skip_channels: int = 0, visibility_head: bool = False, min_channels: int = 16) -> None:
        super().__init__()
        self.out_hw = tuple(out_hw)
        self.stem = nn.Sequential(conv_bn_relu(cin, channels), conv_bn_relu(channels, channels))
        ups = []
        h, w = in_hw
        c = channels
        while h * 2 <= out_hw[0] and w * 2 <= out_hw[1]:
            ups.append(conv_bn_relu(c, max(min_channels, c // 2)))
            c = max(min_channels, c // 2)
            h, w = h * 2, w * 2
        self.ups = nn.ModuleList(ups)
        self.skip_channels = skip_channels
        if skip_channels:
            last = nn.Conv2d(c, num_classes, 1)
            nn.init.zeros_(last.weight)
            nn.init.zeros_(last.bias)
            self.head = nn.Sequential(conv_bn_relu(c + skip_channels, c), conv_bn_relu(c, c), last)
        else:
            self.head = nn.Sequential(conv_bn_relu(c, c), nn.Conv2d(c, num_classes, 1))
        #: optional visibility logit (:data:`VIS_CHANNELS`-wide 3x3 conv + 1x1) on the head's input
        #: (upsampled features [+ the skip input, whose coverage channel is the cameras' frustum])
        self.vis_head = (nn.Sequential(conv_bn_relu(c + skip_channels, VIS_CHANNELS), nn.Conv2d(VIS_CHANNELS, 1, 1))
                         if visibility_head else None)

    def forward(self, x: torch.Tensor, skip: torch.Tensor | None = None) -> tuple[torch.Tensor, torch.Tensor | None]:
        """``x`` (B, cin, h, w) [+ ``skip`` (B, skip_channels, H, W)] -> ``(logits (B, classes, H, W),
        visibility logits (B, 1, H, W) or None without the visibility head)``.
        """
        x = self.stem(x)
        for up in self.ups:
            x = up(F.interpolate(x, scale_factor=2.0, mode="bilinear", align_corners=False))
        if tuple(x.shape[-2:]) != self.out_hw:
            x = F.interpolate(x, size=self.out_hw, mode="bilinear", align_corners=False)
        if self.skip_channels:
            if skip is None:
                raise ValueError("this decoder needs its full-resolution skip input")
            x = torch.cat([x, skip], dim=1)  # (B, c + skip_channels, H, W)
        return self.head(x), (None if self.vis_head is None else self.vis_head(x))
