"""FocusBEV (Zhao et al.): monocular BEV segmentation with a self-calibrated cycle view
transformation and ego-motion temporal fusion. The paper has no public code; this is built from
its text, and the blocks' docstrings (:mod:`.focusbev_blocks`) say which reading was chosen
where the paper leaves a detail open.

``FocusBEV(config, rig, grid)`` for a one-camera rig:

1. **Backbone + FPN** (:mod:`.resnet`): ResNet (paper: ResNet-50; default a CPU-sized
   ResNet-18 at width 32) and ``fpn_levels`` pyramid levels at strides 8, 16, ...
2. **PV -> BEV** per level: a :class:`~.focusbev_blocks.ColumnTransformer` from the level's
   image columns to polar rays of ``D_l`` depth bins over the level's depth range.
3. **Self-calibrated cycle** (``cycle``): BEV -> PV (a column transformer from the polar rays to
   an image-shaped query: the BEV-focusing image features), then the *same* PV -> BEV module
   again, plus the residual of the first polar result (Eq. 4-6).
4. **Polar -> Cartesian**: every level's polar map resampled onto the BEV feature grid with the
   calibration (:func:`~.focusbev_blocks.polar_grids`); each cell from the level covering its
   depth. Rebuilt on :meth:`FocusBEV.set_rig`; the weights do not depend on calibration.
5. **Ego-motion temporal fusion** (``window`` > 1): :class:`~.focusbev_blocks.EgoMotionFusion`
   of the reference feature with the warped history features (no gradient into them).
6. **Top-down network**: the project's BEV decoder (:class:`~.bimapper.BevDecoder`; the paper:
   PON's two residual bottleneck layers with upsampling) to per-class logits on the grid.
7. **segipm's prior** (``prior_skip``, not in the paper; issue #39): segipm's map of the same
   image (:mod:`~bev_mapper_core.nn.prior_skip`) enters the top-down network's head (whose last
   layer starts at zero) and is projected onto the logits (starting at ``8 p - 4``): the
   untrained model maps as segipm does, and the network learns the correction.

Single-frame use: :meth:`FocusBEV.forward` with no history (the reference feature stands in for
every history frame, as after a memory reset). The features to keep in a memory bank are the
``bev`` output (before fusion), as the paper's bank keeps the view transformation's output.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import torch
from torch import nn

from bev_mapper_core.errors import ConfigError
from bev_mapper_core.geometry.grid import BevGrid
from bev_mapper_core.geometry.projection import ground_tables
from bev_mapper_core.geometry.rig import Rig, scaled_camera
from bev_mapper_core.labels.classes import BEV_CLASS_NAMES, NUM_LABELS, resolve_classes
from bev_mapper_core.nn.config import MAX_CHANNELS, MAX_DOWNSAMPLE, MAX_WIDTH_PX, DictConfig, rgb_stats
from bev_mapper_core.nn.decoder import BevDecoder
from bev_mapper_core.nn.efficientnet import EfficientNet, EfficientNetConfig, downsampled_size
from bev_mapper_core.nn.inputs import preprocess_one_camera
from bev_mapper_core.nn.mono_geometry import check_same_camera, one_camera_input_size
from bev_mapper_core.nn.prior_skip import PriorProjection, check_prior
from bev_mapper_core.nn.resnet import FPN, RESNET_DEPTHS, ResNet

from ..segmenter.trunk import trunk_config
from .blocks import ColumnTransformer, EgoMotionFusion, depth_bins, depth_ranges, feature_grid, polar_grids, polar_to_cartesian

#: the image trunks FocusBEV can use (see :class:`FocusBEVConfig`)
BACKBONES = ("resnet", "efficientnet", "lite0")


class TrunkPyramid(nn.Module):
    """An EfficientNet trunk as the FPN's input: its endpoints from stride 4 on, in the ResNet's
    order (the FPN reads strides 8 and 16 of them and makes the coarser levels itself).

    Attributes:
        trunk: the EfficientNet; out_channels: the widths of the maps :meth:`forward` returns.
    """

    def __init__(self, trunk: EfficientNet) -> None:
        super().__init__()
        if tuple(trunk.endpoint_strides[1:3]) != (4, 8) or len(trunk.endpoint_strides) < 4:
            raise ConfigError(f"FocusBEV's FPN needs trunk endpoints at strides 4, 8, 16; got {trunk.endpoint_strides}")
        self.trunk = trunk
        self.out_channels = list(trunk.endpoint_channels[1:])

    def forward(self, x: torch.Tensor) -> list[torch.Tensor]:
        """``(B, C_in, h, w)`` -> the trunk's maps at strides 4, 8, 16 (, 32 ...)."""
        return self.trunk(x)[1:]


@dataclass(frozen=True)
class FocusBEVConfig(DictConfig):
    """FocusBEV architecture (saved with the weights and checked on load). The defaults are a
    CPU-sized network; :meth:`paper` gives the paper's sizes.

    Args:
        input_kind: ``rgb`` (the paper) or ``labels`` (one-hot label images).
        classes: BEV class names, in output layer order.
        input_width: model input width (px); the height follows the camera's aspect.
        backbone: ``resnet`` (the paper's ResNet, of ``backbone_depth`` / ``backbone_width``) or
            ``efficientnet`` (the shipped segmenter's EfficientNet trunk,
            :func:`~bev_mapper_core.methods.segmenter.trunk.trunk_config`: training starts from
            its weights, which have seen synthetic and real images; strides 4, 8, 16 feed the FPN,
            whose stride-32 level is then an extra convolution), or ``lite0`` (EfficientNet-Lite0
            with the trunk's stage count, which ``encoder_init imagenet`` starts from ImageNet).
        backbone_depth: ResNet depth (18, 34, 50, 101; paper 50).
        backbone_width: ResNet stem width (paper 64).
        fpn_levels: pyramid levels from stride 8 (paper: PON's, 5).
        channels: hidden dimension ``d`` of the FPN, the view transformers and the BEV features.
        decoder_layers: MHCA + MLP layers of each column transformer (paper 2; 0 = the MLP
            baseline of the ablation).
        heads: attention heads (paper 4).
        cycle: the self-calibrated cycle BEV -> PV -> BEV (False: the first PV -> BEV alone).
        window: frames fused by the ego-motion temporal fusion, the current one included
            (paper 2; 1 = no temporal fusion).
        bev_downsample: BEV feature map = grid / this (rounded up).
        min_depth: nearest depth of the polar rays (m; the paper's GT starts at 1 m).
        max_depth: farthest depth (m); ``None`` = the grid's farthest corner from the ego origin.
        decoder_channels: width of the top-down network at the BEV feature resolution.
        prior_skip: segipm's map of the same image, ``K`` class probabilities + the coverage
            channel on the full grid, enters the head and the logits (step 7 of the module
            docstring); RGB input only.
    """

    input_kind: str = "rgb"
    classes: tuple[str, ...] = BEV_CLASS_NAMES
    input_width: int = 192
    backbone: str = "resnet"
    backbone_depth: int = 18
    backbone_width: int = 32
    fpn_levels: int = 3
    channels: int = 64
    decoder_layers: int = 2
    heads: int = 4
    cycle: bool = True
    window: int = 2
    bev_downsample: int = 4
    min_depth: float = 1.0
    max_depth: float | None = None
    decoder_channels: int = 64
    prior_skip: bool = False

    def __post_init__(self) -> None:
        object.__setattr__(self, "classes", tuple(self.classes))
        if self.input_kind not in ("labels", "rgb"):
            raise ConfigError(f"input_kind must be 'labels' or 'rgb', got {self.input_kind!r}")
        resolve_classes(self.classes)
        if self.backbone not in BACKBONES:
            raise ConfigError(f"backbone must be one of {BACKBONES}, got {self.backbone!r}")
        if self.backbone_depth not in RESNET_DEPTHS or isinstance(self.backbone_depth, bool):
            raise ConfigError(f"backbone_depth must be one of {sorted(RESNET_DEPTHS)}, got {self.backbone_depth!r}")
        limits = {"input_width": (32, MAX_WIDTH_PX), "backbone_width": (4, 256), "fpn_levels": (1, 5),
                  "channels": (4, MAX_CHANNELS), "decoder_layers": (0, 8), "heads": (1, 16), "window": (1, 8),
                  "bev_downsample": (1, MAX_DOWNSAMPLE), "decoder_channels": (1, MAX_CHANNELS)}
        for name, (lo, hi) in limits.items():
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, int) or not lo <= v <= hi:
                raise ConfigError(f"{name} must be an integer in [{lo}, {hi}], got {v!r}")
        if self.channels % self.heads:
            raise ConfigError(f"channels ({self.channels}) must be a multiple of heads ({self.heads})")
        for name in ("cycle", "prior_skip"):
            if not isinstance(getattr(self, name), bool):
                raise ConfigError(f"{name} must be true or false, got {getattr(self, name)!r}")
        if self.prior_skip and self.input_kind != "rgb":
            raise ConfigError("prior_skip is segipm's map of an RGB image: it needs input_kind 'rgb'")
        for name in ("min_depth", "max_depth"):
            v = getattr(self, name)
            if v is None and name == "max_depth":
                continue
            if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v) or v <= 0:
                raise ConfigError(f"{name} must be a finite number > 0 (m), got {v!r}")
        if self.max_depth is not None and self.max_depth <= self.min_depth:
            raise ConfigError(f"max_depth ({self.max_depth}) must exceed min_depth ({self.min_depth})")

    @classmethod
    def paper(cls, **overrides) -> "FocusBEVConfig":
        """The paper's sizes: ResNet-50 at width 64, 5 FPN levels, d = 256, 2 decoder layers of
        4 heads, window 2, 800 px wide inputs (nuScenes' front images at half size).
        """
        base = dict(backbone_depth=50, backbone_width=64, fpn_levels=5, channels=256, decoder_layers=2, heads=4,
                    window=2, input_width=800, decoder_channels=128)
        base.update(overrides)
        return cls(**base)

    @property
    def in_channels(self) -> int:
        """Model input channels."""
        return NUM_LABELS if self.input_kind == "labels" else 3


def input_size(config: FocusBEVConfig, rig: Rig) -> tuple[int, int]:
    """Model input ``(h, w)`` of the rig's camera at ``config.input_width``."""
    return one_camera_input_size(rig, config.input_width, "FocusBEV")


def max_depth(config: FocusBEVConfig, grid: BevGrid) -> float:
    """The polar rays' farthest depth: ``config.max_depth`` or the grid's farthest corner."""
    if config.max_depth is not None:
        return float(config.max_depth)
    return float(max(math.hypot(x, y) for x in (grid.x_min, grid.x_max) for y in (grid.y_min, grid.y_max)))


class FocusBEV(nn.Module):
    """The FocusBEV network for one monocular rig and BEV grid (see the module docstring).

    Attributes:
        input_size: ``(h, w)`` model input; fgrid: the BEV feature grid; ranges: each level's
            depth range; level_hw: each level's feature size ``(H_l, W_l)``; depths: ``D_l``.
    """

    def __init__(self, config: FocusBEVConfig, rig: Rig, grid: BevGrid) -> None:
        super().__init__()
        self.config, self.grid, self.rig = config, grid, rig
        self.input_size = input_size(config, rig)
        self.num_classes = len(config.classes)
        C = config.channels
        if config.backbone == "resnet":
            self.backbone = ResNet(config.backbone_depth, config.backbone_width, config.in_channels)
        elif config.backbone == "efficientnet":
            self.backbone = TrunkPyramid(EfficientNet(trunk_config(config.in_channels)))
        else:  # lite0: EfficientNet-Lite0 at the trunk's stage count (output stride 16), ImageNet-startable
            stages = trunk_config().num_stages
            self.backbone = TrunkPyramid(EfficientNet(EfficientNetConfig.variant(
                "lite0", num_stages=stages, in_channels=config.in_channels)))
        self.fpn = FPN(self.backbone.out_channels, C, config.fpn_levels)
        self.fgrid = feature_grid(grid, config.bev_downsample)
        if max_depth(config, grid) <= config.min_depth:
            raise ConfigError(f"the grid reaches {max_depth(config, grid):.1f} m, not beyond min_depth {config.min_depth} m")
        self.ranges = depth_ranges(config.min_depth, max_depth(config, grid), config.fpn_levels)
        h, w = self.input_size
        self.level_hw = []
        for lvl in range(config.fpn_levels):
            s = 8 * 2 ** lvl
            self.level_hw.append((downsampled_size(h, s), downsampled_size(w, s)))
        self.depths = [depth_bins(z0, z1, self.fgrid.resolution) for z0, z1 in self.ranges]
        L, heads = config.decoder_layers, config.heads
        self.to_bev = nn.ModuleList(ColumnTransformer(C, hl, d, wl, L, heads)
                                    for (hl, wl), d in zip(self.level_hw, self.depths))
        self.to_pv = nn.ModuleList(ColumnTransformer(C, d, hl, wl, L, heads)
                                   for (hl, wl), d in zip(self.level_hw, self.depths)) if config.cycle else None
        self.temporal = EgoMotionFusion(C, config.window, self.fgrid) if config.window > 1 else None
        #: channels of the ``prior_skip`` input: K class probabilities + coverage (0 without it)
        self.prior_channels = self.num_classes + 1 if config.prior_skip else 0
        self.head = BevDecoder(C, config.decoder_channels, self.num_classes, self.fgrid.shape, grid.shape,
                               skip_channels=self.prior_channels)
        if config.prior_skip:
            self.prior_proj = PriorProjection(self.num_classes)  # logits start as the prior's: 8 p - 4 per class
        mean, std = rgb_stats(config.backbone == "lite0")  # a Lite trunk reads ImageNet-Lite's scaling
        self.register_buffer("rgb_mean", torch.tensor(mean), persistent=False)
        self.register_buffer("rgb_std", torch.tensor(std), persistent=False)
        grids, valid, frustum = self._tables(rig)
        self.register_buffer("polar_grid", grids, persistent=False)
        self.register_buffer("polar_valid", valid, persistent=False)
        self.register_buffer("frustum", frustum, persistent=False)

    # ------------------------------------------------------------ calibration
    def _tables(self, rig: Rig) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        cam = scaled_camera(rig.cameras[0], self.config.input_width)
        grids, valid = polar_grids(cam, self.fgrid, self.ranges)
        frustum = np.ascontiguousarray(ground_tables(rig, self.grid)[rig.names[0]].valid)
        return torch.from_numpy(grids), torch.from_numpy(valid), torch.from_numpy(frustum)

    def set_rig(self, rig: Rig) -> None:
        """Adopt a new calibration of the same camera (polar tables and frustum rebuilt).

        Raises:
            ConfigError: another camera, more than one camera, or another model input size.
        """
        check_same_camera(self.rig, rig, self.config.input_width, self.input_size, "FocusBEV")
        grids, valid, frustum = self._tables(rig)
        self.polar_grid.copy_(grids)
        self.polar_valid.copy_(valid)
        self.frustum.copy_(frustum)
        self.rig = rig

    # ---------------------------------------------------------- preprocessing
    def preprocess(self, images: torch.Tensor) -> torch.Tensor:
        """Camera images ``(B, 1, H, W)`` label ids or ``(B, 1, H, W, 3)`` RGB -> model input
        ``(B, C_in, h, w)`` (:func:`~.inputs.preprocess_images`).
        """
        return preprocess_one_camera(images, self.config.input_kind, self.input_size, self.rgb_mean, self.rgb_std,
                                     "FocusBEV")

    # ---------------------------------------------------------------- forward
    def bev_features(self, x: torch.Tensor) -> torch.Tensor:
        """Model inputs ``(B, C_in, h, w)`` -> the calibrated Cartesian BEV feature ``(B, C, hb, wb)``
        of this frame (steps 1-4 of the module docstring).
        """
        if tuple(x.shape[-2:]) != tuple(self.input_size):
            raise ValueError(f"input {tuple(x.shape)} does not match the model input size {self.input_size}")
        return self.bev_from_trunk(self.backbone(x))

    def bev_from_trunk(self, feats) -> torch.Tensor:
        """:meth:`bev_features` from the backbone's maps ``feats`` (e.g. cached ones of a frozen
        trunk; the FPN reads those from stride 8 on, the first may be None).
        """
        levels = self.fpn(feats)  # each (B, C, H_l, W_l)
        polar = [t(f) for t, f in zip(self.to_bev, levels)]  # each (B, C, D_l, W_l)
        if self.to_pv is not None:
            focused = [t(p) for t, p in zip(self.to_pv, polar)]  # BEV-focusing PV, each (B, C, H_l, W_l)
            polar = [t(f) + p for t, f, p in zip(self.to_bev, focused, polar)]  # weight-shared PV->BEV + residual
        return polar_to_cartesian(polar, self.polar_grid, self.polar_valid)

    def forward(self, x: torch.Tensor, history=None, prior: torch.Tensor | None = None) -> dict[str, torch.Tensor]:
        """Model inputs ``(B, C_in, h, w)`` and optional ``history`` (see
        :meth:`~.focusbev_blocks.EgoMotionFusion.forward`: newest first, ``(feature, prev_from_cur,
        present)``) -> ``{"bev": this frame's feature (B, C, hb, wb), "logits": (B, K, H, W)}``;
        ``prior``: see :meth:`logits`.
        """
        return self.decode(self.bev_features(x), history, prior)

    def decode(self, bev: torch.Tensor, history=None, prior: torch.Tensor | None = None) -> dict[str, torch.Tensor]:
        """:meth:`forward` from this frame's BEV feature ``bev`` ``(B, C, hb, wb)``."""
        fused = bev if self.temporal is None else self.temporal(bev, history or [])
        return {"bev": bev, "logits": self.logits(fused, prior)}

    def logits(self, fused: torch.Tensor, prior: torch.Tensor | None = None) -> torch.Tensor:
        """The top-down network on the (fused) BEV feature ``(B, C, hb, wb)`` -> logits ``(B, K, H, W)``;
        ``prior`` ``(B, K + 1, H, W)`` (:mod:`~bev_mapper_core.methods.segipm.prior`) is required
        by ``prior_skip`` models.
        """
        if not self.prior_channels:
            return self.head(fused)[0]
        check_prior(prior, self.prior_channels, self.grid.shape)
        prior = prior.to(fused.dtype)
        return self.head(fused, prior)[0] + self.prior_proj(prior)

    def known(self) -> torch.Tensor:
        """(H, W) bool: grid cells on the ground inside the camera's image."""
        return self.frustum


__all__ = ["BACKBONES", "FocusBEV", "FocusBEVConfig", "TrunkPyramid", "input_size", "max_depth"]
