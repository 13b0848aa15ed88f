"""S2G2 (Gao, Wang & Sun, RA-L 2022): semi-supervised semantic BEV grid maps from one front camera.

``S2G2(config, rig, grid)`` (config: :class:`S2G2Config`) holds, in one module (so that the
weights file keeps both branches):

* **Feature extractor**: the project's :class:`~.efficientnet.EfficientNet` trunk, shared by
  labeled and unlabeled frames (the paper: a pretrained B4, 448 channels at 1/32; here by default
  the trunk of the project's segmenter, width 1.0, depth 0.5, 5 stages, 112 channels at 1/16,
  from which training starts: see :mod:`~bev_mapper_core.methods.s2g2.train`), its last
  endpoint ``F_front`` ``(B, C, hf, wf)``.
* **Dual-attention view transformation** (:mod:`.s2g2_blocks`): ``F_BEV = H_B^F(F_front)``, the
  cycled ``F~_front = H_F^B(F_BEV)`` (cycle loss), the cross-view attention giving ``F_C`` and
  the inter-view attention giving ``F_I`` (tied by ``L_BEV``). An ablated attention
  (``cross_view_attention`` / ``inter_view_attention`` False) passes ``F_BEV`` through.
* **Double branch generator**: the ``active`` branch on ``F_C`` (trained by gradient descent)
  and the ``passive`` branch on ``F_I``, the same architecture, its parameters an EMA of the
  active ones (:func:`~.s2g2_losses.ema_update`; no gradient: ``requires_grad`` False). Each
  branch is the project's BEV decoder (:class:`~.bimapper.BevDecoder`: two 3x3 convs, x2
  upsampling stages with halved widths, a final resize to the grid, 3x3 + 1x1 head), close to
  the released code's branch (3 upsamplings 8 -> 64 with widths 64, 32, 16).

Output: per-class logits on the run's :class:`~bev_mapper_core.geometry.grid.BevGrid`, any grid (the
paper: a 64x64 grid ahead of the car; e.g. ``BevGrid(0, 30, -15, 15, 30 / 64)``); the BEV
feature map is the grid divided by ``bev_downsample`` (rounded up). Classes are multi-label
layers (a lane divider is also drivable), so each has its own sigmoid (the paper's 4 classes
are exclusive: softmax).

Input: the front camera image (RGB as in the paper, or a label image one-hot, as Bi-Mapper's),
resized to ``input_width`` wide with the camera's aspect (:meth:`S2G2.preprocess`). S2G2 is
monocular: rigs with more than one camera are refused.
"""

from __future__ import annotations

import copy
import math
from dataclasses import dataclass

import numpy as np
import torch
from torch import nn
from torch.nn import functional as F

from bev_mapper_core.errors import ConfigError
from bev_mapper_core.geometry.grid import BevGrid
from bev_mapper_core.geometry.projection import ground_tables
from bev_mapper_core.geometry.rig import Rig
from bev_mapper_core.labels.classes import BEV_CLASS_NAMES, NUM_LABELS, resolve_classes
from bev_mapper_core.nn.config import MAX_CHANNELS, MAX_DOWNSAMPLE, MAX_WIDTH_PX, DictConfig, rgb_stats
from bev_mapper_core.nn.decoder import BevDecoder
from bev_mapper_core.nn.efficientnet import EfficientNet, EfficientNetConfig, downsampled_size
from bev_mapper_core.nn.inputs import preprocess_one_camera
from bev_mapper_core.nn.mono_geometry import check_same_camera, one_camera_input_size
from bev_mapper_core.nn.prior_skip import PRIOR_LOGIT_SCALE, PriorProjection, check_prior

from .blocks import VIEW_TRANSFORMS, CrossViewAttention, InterViewAttention, ViewTransform

#: The two branches of the double branch generator.
BRANCHES = ("active", "passive")


@dataclass(frozen=True)
class S2G2Config(DictConfig):
    """S2G2 architecture (saved with the weights and checked on load).

    The defaults are a CPU-trainable network; :meth:`paper` gives the paper's sizes.

    Args:
        input_kind: ``rgb`` (the paper) or ``labels`` (one-hot of ``NUM_LABELS`` label ids).
        classes: BEV class names, in output layer order.
        input_width: model input width (px); the height follows the camera's aspect ratio.
        encoder_variant: EfficientNet variant ``b0`` .. ``b7`` (paper: ``b4``).
        width_mult, depth_mult: override the variant's multipliers (``None`` = the variant's).
        encoder_stages: EfficientNet stages kept (7 = the full trunk, output stride 32).
        drop_connect_rate: EfficientNet stochastic depth.
        view_transform: ``conv`` (the paper's two convolutions) or ``fc`` (PYVA's two fully
            connected layers), see :class:`~.s2g2_blocks.ViewTransform`.
        bev_downsample: BEV feature map = grid / this, rounded up (paper: 64 / 8 = 8).
        cross_view_attention, inter_view_attention: the two attentions (ablations OIVA / OCVA:
            the ablated one passes ``F_BEV`` through).
        decoder_channels: width of each branch at the BEV feature resolution.
        prior_skip: a strong prior the branches correct (not in the paper; issue #39): segipm's
            map of the same image (the 2-D segmenter's labels projected by IPM,
            :mod:`~bev_mapper_core.methods.segipm.prior`, :mod:`~bev_mapper_core.nn.prior_skip`),
            ``K`` class probabilities + the coverage channel on the full grid, enters each
            branch's head (:class:`~bev_mapper_core.nn.decoder.BevDecoder`'s skip input, whose
            last layer starts at zero) and is projected onto the logits by ``prior_proj``, which
            starts at ``8 p - 4`` per class: the untrained model maps as segipm does.
        prior_pool: with ``prior_skip``, the prior also enters each branch's first layer,
            average-pooled to the BEV feature map (the branch then sees the whole prior, not only
            the head's 5 x 5 cells).
    """

    input_kind: str = "rgb"
    classes: tuple[str, ...] = BEV_CLASS_NAMES
    input_width: int = 192
    encoder_variant: str = "b0"
    width_mult: float | None = 1.0
    depth_mult: float | None = 0.5
    encoder_stages: int = 5
    drop_connect_rate: float = 0.2
    view_transform: str = "conv"
    bev_downsample: int = 8
    cross_view_attention: bool = True
    inter_view_attention: bool = True
    decoder_channels: int = 32
    prior_skip: bool = False
    prior_pool: bool = False

    def __post_init__(self) -> None:
        object.__setattr__(self, "classes", tuple(self.classes))
        if self.input_kind not in ("labels", "rgb"):
            raise ConfigError(f"input_kind must be 'labels' or 'rgb', got {self.input_kind!r}")
        resolve_classes(self.classes)
        if self.view_transform not in VIEW_TRANSFORMS:
            raise ConfigError(f"view_transform must be one of {VIEW_TRANSFORMS}, got {self.view_transform!r}")
        limits = {"input_width": (16, MAX_WIDTH_PX), "bev_downsample": (1, MAX_DOWNSAMPLE),
                  "decoder_channels": (1, MAX_CHANNELS), "encoder_stages": (1, 7)}
        for name, (lo, hi) in limits.items():
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, int) or not lo <= v <= hi:
                raise ConfigError(f"{name} must be an integer in [{lo}, {hi}], got {v!r}")
        for name in ("cross_view_attention", "inter_view_attention", "prior_skip", "prior_pool"):
            if not isinstance(getattr(self, name), bool):
                raise ConfigError(f"{name} must be true or false, got {getattr(self, name)!r}")
        v = self.drop_connect_rate
        if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v) or v < 0:
            raise ConfigError(f"drop_connect_rate must be a finite number >= 0, got {v!r}")
        if self.prior_skip and self.input_kind != "rgb":
            raise ConfigError("prior_skip is segipm's map of an RGB image: it needs input_kind 'rgb'")
        if self.prior_pool and not self.prior_skip:
            raise ConfigError("prior_pool pools the prior_skip input: it needs prior_skip")
        self.encoder_config()  # validates the encoder (variant, multipliers, sanity bounds)

    @classmethod
    def paper(cls, **overrides) -> "S2G2Config":
        """The paper's sizes: the full EfficientNet-B4 trunk (448 channels at output stride 32),
        512 px wide inputs (the paper's 256x512 Cityscapes frames), 8x8 BEV features for a 64x64
        grid, branches 128 wide at 8x8 (the released code: 128 -> 64, 32, 16 over 3 upsamplings).
        """
        base = dict(encoder_variant="b4", width_mult=None, depth_mult=None, encoder_stages=7, input_width=512,
                    bev_downsample=8, decoder_channels=128)
        base.update(overrides)
        return cls(**base)

    @property
    def in_channels(self) -> int:
        """Model input channels."""
        return NUM_LABELS if self.input_kind == "labels" else 3

    def encoder_config(self) -> EfficientNetConfig:
        """The feature extractor's EfficientNet config."""
        over = {"num_stages": self.encoder_stages, "in_channels": self.in_channels,
                "drop_connect_rate": self.drop_connect_rate}
        if self.width_mult is not None:
            over["width_mult"] = self.width_mult
        if self.depth_mult is not None:
            over["depth_mult"] = self.depth_mult
        return EfficientNetConfig.variant(self.encoder_variant, **over)


def input_size(config: S2G2Config, rig: Rig) -> tuple[int, int]:
    """Model input ``(h, w)`` of the rig's camera at ``config.input_width``."""
    return one_camera_input_size(rig, config.input_width, "S2G2")


class S2G2(nn.Module):
    """The S2G2 network for one monocular rig and BEV grid (see the module docstring).

    Attributes:
        input_size: ``(h, w)`` model input; front_hw / bev_hw: feature map sizes.
        active, passive: the two branches (``passive`` has ``requires_grad`` False).
    """

    def __init__(self, config: S2G2Config, rig: Rig, grid: BevGrid) -> None:
        super().__init__()
        self.config, self.grid = config, grid
        self.input_size = input_size(config, rig)
        self.rig = rig
        self.num_classes = len(config.classes)
        self.encoder = EfficientNet(config.encoder_config())
        C = self.encoder.out_channels
        stride = self.encoder.endpoint_strides[-1]
        self.front_hw = (downsampled_size(self.input_size[0], stride), downsampled_size(self.input_size[1], stride))
        ds = config.bev_downsample
        self.bev_hw = (math.ceil(grid.height / ds), math.ceil(grid.width / ds))
        self.to_bev = ViewTransform(C, self.front_hw, self.bev_hw, config.view_transform, to_bev=True)
        self.to_front = ViewTransform(C, self.bev_hw, self.front_hw, config.view_transform, to_bev=False)
        self.cross_view = CrossViewAttention(C) if config.cross_view_attention else None
        self.inter_view = InterViewAttention(C) if config.inter_view_attention else None
        #: channels of the ``prior_skip`` input: K class probabilities + coverage (0 without it)
        self.prior_channels = self.num_classes + 1 if config.prior_skip else 0
        self._pool = self.prior_channels if config.prior_pool else 0  # prior channels into the stem
        self.active = BevDecoder(C + self._pool, config.decoder_channels, self.num_classes, self.bev_hw, grid.shape,
                                 skip_channels=self.prior_channels)
        self.passive = copy.deepcopy(self.active)  # starts equal to the active branch
        self.passive.requires_grad_(False)
        if config.prior_skip:
            self.prior_proj = PriorProjection(self.num_classes)  # logits start as the prior's: 8 p - 4 per class
        mean, std = rgb_stats(config.encoder_config().lite)  # a Lite encoder reads ImageNet-Lite's scaling
        self.register_buffer("rgb_mean", torch.tensor(mean), persistent=False)
        self.register_buffer("rgb_std", torch.tensor(std), persistent=False)
        self.register_buffer("frustum", self._frustum(rig), persistent=False)

    # ------------------------------------------------------------ calibration
    def _frustum(self, rig: Rig) -> torch.Tensor:
        """(H, W) bool: grid cells on the ground inside the camera's image."""
        return torch.from_numpy(np.ascontiguousarray(ground_tables(rig, self.grid)[rig.names[0]].valid))

    def set_rig(self, rig: Rig) -> None:
        """Adopt a new calibration of the same camera (the frustum is rebuilt).

        Raises:
            ConfigError: another camera, more than one camera, or another model input size.
        """
        check_same_camera(self.rig, rig, self.config.input_width, self.input_size, "S2G2")
        self.frustum.copy_(self._frustum(rig))
        self.rig = rig

    def trainable_parameters(self) -> list[nn.Parameter]:
        """Every parameter but the passive branch's (an EMA, never a gradient step)."""
        return [p for n, p in self.named_parameters() if not n.startswith("passive.")]

    # ---------------------------------------------------------- preprocessing
    def preprocess(self, images: torch.Tensor) -> torch.Tensor:
        """Camera images ``(B, 1, H, W)`` label ids or ``(B, 1, H, W, 3)`` RGB (the rig's one
        camera) -> model input ``(B, C_in, h, w)`` (:func:`~.inputs.preprocess_images`).
        """
        return preprocess_one_camera(images, self.config.input_kind, self.input_size, self.rgb_mean, self.rgb_std,
                                     "S2G2")

    # ---------------------------------------------------------------- forward
    def features(self, x: torch.Tensor, frozen_encoder: bool = False) -> dict[str, torch.Tensor]:
        """The DVT module on model inputs ``x`` ``(B, C_in, h, w)`` (``frozen_encoder``: the
        encoder runs without gradient, so losses on these outputs train only what follows it).

        Returns dict: ``front`` ``F_front`` and ``front_cycled`` ``H_F^B(H_B^F(F_front))``
        ``(B, C, hf, wf)``; ``bev`` ``F_BEV``, ``f_c`` ``F_C`` and ``f_i`` ``F_I`` ``(B, C, hb, wb)``.
        """
        if tuple(x.shape[-2:]) != tuple(self.input_size):
            raise ValueError(f"input {tuple(x.shape)} does not match the model input size {self.input_size}")
        with torch.set_grad_enabled(torch.is_grad_enabled() and not frozen_encoder):
            front = self.encoder(x)[-1]  # (B, C, hf, wf)
        return self.from_front(front)

    def from_front(self, front: torch.Tensor) -> dict[str, torch.Tensor]:
        """:meth:`features` from the encoder's features ``front`` ``(B, C, hf, wf)`` (e.g. cached
        ones of a frozen encoder).
        """
        bev = self.to_bev(front)  # (B, C, hb, wb)
        front_cycled = self.to_front(bev)  # (B, C, hf, wf)
        f_c = bev if self.cross_view is None else self.cross_view(front, bev, front_cycled)
        f_i = bev if self.inter_view is None else self.inter_view(bev)
        return {"front": front, "front_cycled": front_cycled, "bev": bev, "f_c": f_c, "f_i": f_i}

    def forward(self, x: torch.Tensor, frozen_encoder: bool = False,
                prior: torch.Tensor | None = None) -> dict[str, torch.Tensor]:
        """Model inputs ``(B, C_in, h, w)`` -> :meth:`features` (``frozen_encoder``: see there) plus ``active_logits`` (B, K, H, W)
        of the active branch on ``F_C`` and ``passive_logits`` (B, K, H, W) of the passive branch
        on ``F_I``, computed without gradient (the consistency target). ``prior``: see :meth:`heads`.
        """
        return self.heads(self.features(x, frozen_encoder), prior)

    def heads(self, out: dict[str, torch.Tensor], prior: torch.Tensor | None = None) -> dict[str, torch.Tensor]:
        """:meth:`features`' outputs ``out`` with both branches' logits added (see :meth:`forward`);
        ``prior`` ``(B, K + 1, H, W)`` (:mod:`~bev_mapper_core.methods.segipm.prior`) is required by ``prior_skip`` models.
        """
        out["active_logits"] = self._branch(self.active, out["f_c"], prior)
        with torch.no_grad():
            out["passive_logits"] = self._branch(self.passive, out["f_i"], prior)
        return out

    def _branch(self, branch: nn.Module, f: torch.Tensor, prior: torch.Tensor | None) -> torch.Tensor:
        """One branch's logits ``(B, K, H, W)`` on BEV features ``f`` (+ the prior's skip and projection)."""
        if not self.prior_channels:
            return branch(f)[0]
        check_prior(prior, self.prior_channels, self.grid.shape)
        prior = prior.to(f.dtype)
        if self._pool:
            f = torch.cat([f, F.adaptive_avg_pool2d(prior, f.shape[-2:])], dim=1)  # (B, C + K + 1, hb, wb)
        return branch(f, prior)[0] + self.prior_proj(prior)

    def logits(self, x: torch.Tensor, branch: str = "active", prior: torch.Tensor | None = None) -> torch.Tensor:
        """Per-class logits ``(B, K, H, W)`` of one branch (inference: only what it needs runs;
        ``prior``: see :meth:`heads`).
        """
        if branch not in BRANCHES:
            raise ConfigError(f"branch must be one of {BRANCHES}, got {branch!r}")
        if tuple(x.shape[-2:]) != tuple(self.input_size):
            raise ValueError(f"input {tuple(x.shape)} does not match the model input size {self.input_size}")
        front = self.encoder(x)[-1]  # (B, C, hf, wf)
        bev = self.to_bev(front)  # (B, C, hb, wb)
        if branch == "passive":
            return self._branch(self.passive, bev if self.inter_view is None else self.inter_view(bev), prior)
        if self.cross_view is not None:
            bev = self.cross_view(front, bev, self.to_front(bev))
        return self._branch(self.active, bev, prior)

    def known(self) -> torch.Tensor:
        """(H, W) bool: grid cells on the ground inside the camera's image."""
        return self.frustum


__all__ = ["BRANCHES", "PRIOR_LOGIT_SCALE", "S2G2", "S2G2Config", "input_size"]
