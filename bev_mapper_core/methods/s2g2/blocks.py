"""The building blocks of S2G2's dual-attention view transformation (DVT, paper Sec. III-C).

* :class:`ViewTransform`: the view-transformation block ``H_B^F`` (front -> BEV) and, built the
  other way round, its inverse ``H_F^B`` (BEV -> front); two layers each (paper: "double
  convolutional layers"), ``conv`` or ``fc`` (see the class).
* :class:`CrossViewAttention`: PYVA's cross-view transformer (Yang et al., CVPR 2021), which
  S2G2 keeps unchanged: it relates the front features, the BEV features and the cycled front
  features.
* :class:`InterViewAttention`: S2G2's inter-view attention (paper Fig. 2, Eq. 2-3): two
  depthwise convolutions and a 1x1 convolution with max-pooling, a sigmoid score multiplied
  into the BEV features.

Feature layouts: front features ``(B, C, hf, wf)`` in image layout (row 0 = image top = far,
column 0 = image left); BEV features ``(B, C, hb, wb)`` in the :class:`~bev_mapper_core.geometry.grid.BevGrid`
layout (row along +y, row 0 at ``y_min``; column along +x, column 0 at ``x_min``).
"""

from __future__ import annotations

import torch
from torch import nn
from torch.nn import functional as F

#: ``S2G2Config.view_transform`` choices.
VIEW_TRANSFORMS = ("conv", "fc")


def image_to_grid_layout(x: torch.Tensor, out_hw: tuple[int, int]) -> torch.Tensor:
    """Front-view layout ``(B, C, hf, wf)`` -> BEV-grid layout ``(B, C, *out_hw)``, a fixed
    re-orientation and a bilinear resize (no parameters).

    The image's bottom row (near) becomes grid column 0 (``x_min``), its top row the far
    column; its right column (``-y``) becomes grid row 0 (``y_min``). This is the layout the
    released S2G2 code gives its branches (front-shaped features whose rows run from far to
    near, then a strided convolution that changes the aspect ratio), written in the grid's axes.
    """
    y = x.flip(-2, -1).transpose(-1, -2)  # (B, C, hf, wf) -> (B, C, wf, hf): row = image column, col = image row
    if tuple(y.shape[-2:]) != tuple(out_hw):
        y = F.interpolate(y, size=tuple(out_hw), mode="bilinear", align_corners=False)
    return y


def grid_to_image_layout(x: torch.Tensor, out_hw: tuple[int, int]) -> torch.Tensor:
    """Inverse of :func:`image_to_grid_layout`: BEV-grid layout ``(B, C, hb, wb)`` -> front-view
    layout ``(B, C, *out_hw)``.
    """
    hf, wf = out_hw
    if tuple(x.shape[-2:]) != (wf, hf):
        x = F.interpolate(x, size=(wf, hf), mode="bilinear", align_corners=False)
    return x.transpose(-1, -2).flip(-2, -1)  # (B, C, wf, hf) -> (B, C, hf, wf)


class ViewTransform(nn.Module):
    """One view-transformation block: ``(B, C, *in_hw)`` -> ``(B, C, *out_hw)``.

    Two layers, the first followed by BatchNorm + ReLU, the second linear (its output is
    compared with the encoder's signed features by the cycle loss, so it must be able to reach
    negative values; the released code ends with a ReLU, on encoder features that are nearly
    non-negative).

    * ``conv`` (the paper): two 3x3 convolutions at the front resolution, the BEV side
      re-oriented into the grid layout and resized (:func:`image_to_grid_layout`); the inverse
      does the re-orientation first, then its two convolutions.
    * ``fc`` (PYVA's transform): two fully connected layers over the flattened spatial cells,
      shared by all channels (``hf*wf -> hb*wb -> hb*wb`` and back), so any front cell can reach
      any BEV cell.

    Args:
        channels: C, the same on both sides.
        in_hw, out_hw: spatial sizes of the input and output.
        kind: ``conv`` or ``fc``.
        to_bev: True for ``H_B^F`` (front -> BEV), False for the inverse ``H_F^B``.
    """

    def __init__(self, channels: int, in_hw: tuple[int, int], out_hw: tuple[int, int], kind: str,
                 to_bev: bool) -> None:
        super().__init__()
        if kind not in VIEW_TRANSFORMS:
            raise ValueError(f"view transform must be one of {VIEW_TRANSFORMS}, got {kind!r}")
        self.kind, self.to_bev = kind, to_bev
        self.in_hw, self.out_hw = tuple(in_hw), tuple(out_hw)
        C = channels
        if kind == "conv":
            self.layer1 = nn.Conv2d(C, C, 3, padding=1, bias=False)
            self.norm = nn.BatchNorm2d(C)
            self.layer2 = nn.Conv2d(C, C, 3, padding=1)
        else:
            n_in, n_out = in_hw[0] * in_hw[1], out_hw[0] * out_hw[1]
            self.layer1 = nn.Linear(n_in, n_out, bias=False)
            self.norm = nn.BatchNorm1d(C)
            self.layer2 = nn.Linear(n_out, n_out)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        """``x`` ``(B, C, *in_hw)`` -> ``(B, C, *out_hw)``."""
        if self.kind == "fc":
            B, C = x.shape[:2]
            y = F.relu(self.norm(self.layer1(x.flatten(2))))  # (B, C, hi, wi) -> (B, C, hi*wi) -> (B, C, ho*wo)
            return self.layer2(y).view(B, C, *self.out_hw)  # (B, C, ho*wo) -> (B, C, ho, wo)
        if not self.to_bev:  # BEV -> front: into the image layout first, then the convolutions
            x = grid_to_image_layout(x, self.out_hw)
        y = self.layer2(F.relu(self.norm(self.layer1(x))))
        return image_to_grid_layout(y, self.out_hw) if self.to_bev else y


class CrossViewAttention(nn.Module):
    """PYVA's cross-view transformer: ``F_C = F_BEV + f([F_BEV, T]) * S``.

    Query: a 1x1 projection (C -> C/8) of the BEV features ``F_BEV``; key: the same of the front
    features ``F_front``; value: a 1x1 projection (C -> C) of the cycled front features
    ``F~_front = H_F^B(H_B^F(F_front))``. For every BEV cell, the front cell of highest
    correlation is selected (hard arg-max over the front cells): ``S`` is that correlation and
    ``T`` the value there; ``f`` a 3x3 convolution over ``[F_BEV, T]``. PYVA's front and BEV maps
    have one size; here they may differ (the energy is ``(front cells x BEV cells)``), and the
    residual is on the BEV features, as in PYVA (the released S2G2 code, whose two maps share a
    shape, adds the front features instead).
    """

    def __init__(self, channels: int) -> None:
        super().__init__()
        c8 = max(1, channels // 8)
        self.query = nn.Conv2d(channels, c8, 1)
        self.key = nn.Conv2d(channels, c8, 1)
        self.value = nn.Conv2d(channels, channels, 1)
        self.fuse = nn.Conv2d(2 * channels, channels, 3, padding=1)

    def forward(self, front: torch.Tensor, bev: torch.Tensor, front_cycled: torch.Tensor) -> torch.Tensor:
        """``front``, ``front_cycled`` ``(B, C, hf, wf)``, ``bev`` ``(B, C, hb, wb)`` -> ``F_C`` ``(B, C, hb, wb)``."""
        B, C, hb, wb = bev.shape
        q = self.query(bev).flatten(2)  # (B, C/8, hb, wb) -> (B, C/8, Nb)
        k = self.key(front).flatten(2).transpose(1, 2)  # (B, C/8, hf, wf) -> (B, Nf, C/8)
        energy = torch.bmm(k, q)  # (B, Nf, Nb)
        score, arg = energy.max(dim=1)  # (B, Nb) each: best front cell per BEV cell
        v = self.value(front_cycled).flatten(2)  # (B, C, hf, wf) -> (B, C, Nf)
        t = torch.gather(v, 2, arg[:, None, :].expand(B, C, arg.shape[1]))  # (B, C, Nb)
        t = t.view(B, C, hb, wb)  # (B, C, Nb) -> (B, C, hb, wb)
        s = score.view(B, 1, hb, wb)  # (B, Nb) -> (B, 1, hb, wb)
        return bev + self.fuse(torch.cat([bev, t], dim=1)) * s  # cat: (B, 2C, hb, wb)


class InterViewAttention(nn.Module):
    """S2G2's inter-view attention: ``F_I = F_BEV * sigmoid(C_1[C_d(F_BEV)])`` (Eq. 2-3).

    ``C_d``: two depthwise 3x3 convolutions (one kernel per channel, depth unchanged), each with
    BatchNorm + ReLU and a 2x2 max-pooling (ceil mode) that halves the resolution, so the score
    sees salient features over a neighbourhood; ``C_1``: a 1x1 convolution across channels. The
    score map, at a quarter of the BEV resolution per side, is brought back by nearest
    upsampling and multiplied in, element by element: a spatial and channel attention. (Fig. 2
    puts a max-pooling after both kinds of convolution; the released code pools after the
    depthwise ones only, there down to 1x1, i.e. a channel attention; we pool after the
    depthwise ones and keep a coarse spatial map, as the paper describes both.)
    """

    def __init__(self, channels: int) -> None:
        super().__init__()
        C = channels
        self.depthwise = nn.ModuleList(
            nn.Sequential(nn.Conv2d(C, C, 3, padding=1, groups=C, bias=False), nn.BatchNorm2d(C), nn.ReLU(inplace=True),
                          nn.MaxPool2d(2, ceil_mode=True))
            for _ in range(2))
        self.pointwise = nn.Conv2d(C, C, 1)

    def forward(self, bev: torch.Tensor) -> torch.Tensor:
        """``bev`` ``(B, C, hb, wb)`` -> ``F_I`` of the same shape."""
        s = bev
        for block in self.depthwise:
            s = block(s)  # (B, C, h, w) -> (B, C, ceil(h/2), ceil(w/2))
        s = torch.sigmoid(self.pointwise(s))
        s = F.interpolate(s, size=bev.shape[-2:], mode="nearest")  # (B, C, hb/4, wb/4) -> (B, C, hb, wb)
        return bev * s


__all__ = ["VIEW_TRANSFORMS", "CrossViewAttention", "InterViewAttention", "ViewTransform",
           "grid_to_image_layout", "image_to_grid_layout"]
