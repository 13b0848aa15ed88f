"""U-Net of the LV stream, with an EfficientNet encoder.

The paper segments each IPM image with "a basic semantic segmentation network, U-Net" and says
"the encoder of two streams is EfficientNet-B0"; the simplest reading that satisfies both is a
U-Net whose contracting path is an EfficientNet trunk (as ``segmentation_models_pytorch``'s
``Unet('efficientnet-b0')``): its endpoints at strides 2, 4, 8, ... are the skip connections;
the expanding path upsamples to each skip's size, concatenates and applies two 3x3 conv-BN-ReLU
layers; a last stage returns to the input resolution, concatenating the input itself. The
encoder has its own weights (its input is the IPM image, not the perspective image).
"""

from __future__ import annotations

import torch
from torch import nn
from torch.nn import functional as F

from .efficientnet import EfficientNet, EfficientNetConfig
from .layers import conv_bn_relu


class EffUNet(nn.Module):
    """U-Net producing per-pixel features and per-class logits at the input resolution.

    Args:
        cfg: EfficientNet trunk config (its ``in_channels`` is the input's).
        channels: width of every expanding-path stage.
        out_channels: feature channels returned (merged into the ego grid by the LV stream).
        num_classes: channels of the segmentation head (the ASL is computed on them).
    """

    def __init__(self, cfg: EfficientNetConfig, channels: int, out_channels: int, num_classes: int) -> None:
        super().__init__()
        self.encoder = EfficientNet(cfg)
        enc = self.encoder.endpoint_channels
        ups = []
        cin = enc[-1]
        for skip in reversed(enc[:-1]):
            ups.append(nn.Sequential(conv_bn_relu(cin + skip, channels), conv_bn_relu(channels, channels)))
            cin = channels
        self.ups = nn.ModuleList(ups)
        self.final = conv_bn_relu(cin + cfg.in_channels, out_channels)
        self.head = nn.Conv2d(out_channels, num_classes, 1)

    def forward(self, x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """``x`` (B, C_in, Hp, Wp) -> features (B, out_channels, Hp, Wp), logits (B, classes, Hp, Wp)."""
        ends = self.encoder(x)
        y = ends[-1]
        for up, skip in zip(self.ups, reversed(ends[:-1])):
            y = F.interpolate(y, size=skip.shape[-2:], mode="bilinear", align_corners=False)
            y = up(torch.cat([y, skip], dim=1))
        y = F.interpolate(y, size=x.shape[-2:], mode="bilinear", align_corners=False)
        feats = self.final(torch.cat([y, x], dim=1))
        return feats, self.head(feats)
