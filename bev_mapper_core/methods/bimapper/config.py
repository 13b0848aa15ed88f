"""Bi-Mapper architecture configuration (saved with the weights and checked on load)."""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass, fields

from bev_mapper_core.errors import ConfigError
from bev_mapper_core.labels.classes import BEV_CLASS_NAMES, NUM_LABELS, resolve_classes
from bev_mapper_core.nn.config import MAX_CHANNELS, MAX_DOWNSAMPLE, MAX_WIDTH_PX
from bev_mapper_core.nn.efficientnet import EfficientNetConfig

from .geometry import PlaneSpec

STREAMS = ("gv", "lv", "both", "none")
MAX_PLANE_CELLS = 4096 * 4096  # plane_shape[0] * plane_shape[1] (paper: 800 x 400)
FUSIONS = ("sum", "concat")


@dataclass(frozen=True)
class BiMapperConfig:
    """Architecture hyperparameters (all saved with the weights and checked on load).

    The defaults are the CPU-trainable configuration; :meth:`paper` gives the paper's sizes.

    Args:
        input_kind: ``labels`` (one-hot of ``NUM_LABELS`` label ids) or ``rgb``.
        classes: BEV class names, in output layer order.
        input_width: model input width per camera (px); the height follows the camera aspect.
        encoder_variant: EfficientNet variant ``b0`` .. ``b7``.
        width_mult, depth_mult: override the variant's multipliers (``None`` = the variant's).
        encoder_stages: EfficientNet stages kept (7 = full).
        drop_connect_rate: EfficientNet stochastic depth.
        neck_channels: camera-encoder neck width (HDMapNet 512).
        bev_channels: channels C of F_g and F_l (HDMapNet 64).
        bev_downsample: BEV feature grid = full grid / this (paper/HDMapNet 5: 40x80).
        gv_hidden: hidden width of the GV MLPs, ``None`` = BEV feature cells (HDMapNet).
        streams: ``both`` | ``gv`` | ``lv`` (ablations); ``none`` (with ``ipm_skip`` only): no
            stream at all, the control that shows what the streams add to the IPM prior.
        fusion: ``sum`` (weighted) | ``concat``.
        gv_weight, lv_weight: fusion weights (paper 1.0, 0.1).
        plane_x_range, plane_z_range, plane_shape, plane_height: the camera plane
            (:class:`~.geometry.PlaneSpec`; ``plane_height`` None = camera height above ground).
        lv_full_res: the LV stream's IPM samples the camera images at their delivered resolution
            (as the paper warps the original image) instead of the encoder's resized input.
        ipm_skip: **not in the paper.** The decoder head also receives the camera-size input
            warped onto the full-resolution ego grid by the core's ground IPM (the classical
            baseline's geometry), and the logits start from that IPM result (a residual 1x1
            projection initialised to the class table, the learned refinement zero-initialised).
            The streams then only have to learn corrections (occlusion, object footprints, far
            range) instead of re-deriving 0.15 m detail from 1.2 m features.
        prior_skip: **not in the paper** (issue #39; RGB input). As ``ipm_skip``, but the prior is
            segipm's map of the same camera images (the shipped segmenter, then IPM with its
            occlusion reasoning: :mod:`~bev_mapper_core.methods.segipm.prior`), ``K`` class
            probabilities + a coverage channel, and the logits start from it through
            :class:`~bev_mapper_core.nn.prior_skip.PriorProjection` (``8 p - 4``): the untrained
            model maps as segipm does, and the streams learn the correction from the images.
        unet_channels: U-Net expanding-path width.
        decoder_channels: BEV decoder width at the feature resolution.
        decoder_min_channels: **not in the paper** (issue #15). The decoder halves its width at
            each 2x upsampling down to this; the last stages and the head run at the full grid
            resolution at this width (16 = 1.4 of the shipped surround6 model's 3.3 GFLOP).
        visibility_head: **not in the paper** (issue #11). One extra logit per BEV cell, a small
            head (3x3 conv + BN + ReLU, 16 channels, then 1x1) on the decoder head's input (the
            upsampled features and, with ``ipm_skip``, the IPM prior), trained with BCE on the visibility mask
            (cells some camera sees); the mapper publishes cells it calls unobservable as unknown
            (``MapperConfig.unknown_below``). Off for files saved before it existed.
        temperature: per-class temperature ``T_k`` dividing the class logits at inference
            (temperature scaling fitted on validation drives by ``bev-train calibrate``);
            ``None`` = 1 for every class (uncalibrated, files saved before it existed).
    """

    input_kind: str = "labels"
    classes: tuple[str, ...] = BEV_CLASS_NAMES
    input_width: int = 112
    encoder_variant: str = "b0"
    width_mult: float | None = 0.5
    depth_mult: float | None = 0.5
    encoder_stages: int = 5
    drop_connect_rate: float = 0.2
    neck_channels: int = 64
    bev_channels: int = 32
    bev_downsample: int = 8
    gv_hidden: int | None = None
    streams: str = "both"
    fusion: str = "sum"
    gv_weight: float = 1.0
    lv_weight: float = 0.1
    plane_x_range: tuple[float, float] = (-5.0, 5.0)
    plane_z_range: tuple[float, float] = (3.0, 29.0)
    plane_shape: tuple[int, int] = (104, 40)
    plane_height: float | None = None
    lv_full_res: bool = False
    ipm_skip: bool = False
    prior_skip: bool = False
    unet_channels: int = 32
    decoder_channels: int = 64
    decoder_min_channels: int = 16
    visibility_head: bool = False
    temperature: tuple[float, ...] | None = None

    def __post_init__(self) -> None:
        for name in ("classes", "plane_x_range", "plane_z_range", "plane_shape"):
            object.__setattr__(self, name, tuple(getattr(self, name)))
        if self.temperature is not None:
            t = tuple(self.temperature)
            if (len(t) != len(self.classes) or any(isinstance(v, bool) or not isinstance(v, (int, float))
                                                   or not math.isfinite(v) or not 0.01 <= v <= 100 for v in t)):
                raise ConfigError(f"temperature must be one number in [0.01, 100] per class "
                                  f"({len(self.classes)}), got {self.temperature!r}")
            object.__setattr__(self, "temperature", tuple(float(v) for v in t))
        for name in ("visibility_head", "ipm_skip", "prior_skip", "lv_full_res"):
            if not isinstance(getattr(self, name), bool):
                raise ConfigError(f"{name} must be true or false, got {getattr(self, name)!r}")
        if self.input_kind not in ("labels", "rgb"):
            raise ConfigError(f"input_kind must be 'labels' or 'rgb', got {self.input_kind!r}")
        resolve_classes(self.classes)
        if self.streams not in STREAMS:
            raise ConfigError(f"streams must be one of {STREAMS}, got {self.streams!r}")
        if self.prior_skip and self.input_kind != "rgb":
            raise ConfigError("prior_skip is segipm's map of the RGB images: it needs input_kind 'rgb'")
        if self.prior_skip and self.ipm_skip:
            raise ConfigError("ipm_skip and prior_skip are two priors for the same place: choose one")
        if self.streams == "none" and not (self.ipm_skip or self.prior_skip):
            raise ConfigError("streams 'none' leaves the model without input: it needs ipm_skip or prior_skip")
        if self.fusion not in FUSIONS:
            raise ConfigError(f"fusion must be one of {FUSIONS}, got {self.fusion!r}")
        limits = {"input_width": MAX_WIDTH_PX, "neck_channels": MAX_CHANNELS, "bev_channels": MAX_CHANNELS,
                  "bev_downsample": MAX_DOWNSAMPLE, "unet_channels": MAX_CHANNELS, "decoder_channels": MAX_CHANNELS,
                  "decoder_min_channels": MAX_CHANNELS}
        for name, hi in limits.items():
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, int) or not 1 <= v <= hi:
                raise ConfigError(f"{name} must be an integer in [1, {hi}], got {v!r}")
        if self.gv_hidden is not None and (isinstance(self.gv_hidden, bool) or not isinstance(self.gv_hidden, int)
                                           or not 1 <= self.gv_hidden <= MAX_CHANNELS):
            raise ConfigError(f"gv_hidden must be an integer in [1, {MAX_CHANNELS}] or None, got {self.gv_hidden!r}")
        shape = self.plane_shape
        if (len(shape) != 2 or any(isinstance(v, bool) or not isinstance(v, int) or v < 1 for v in shape)
                or shape[0] * shape[1] > MAX_PLANE_CELLS):
            raise ConfigError(f"plane_shape must be two integers >= 1 with at most {MAX_PLANE_CELLS} cells, "
                              f"got {list(shape)!r}")
        for name in ("plane_x_range", "plane_z_range"):
            v = getattr(self, name)
            if len(v) != 2 or not all(isinstance(x, (int, float)) and not isinstance(x, bool) and math.isfinite(x)
                                      for x in v):
                raise ConfigError(f"{name} must be two finite numbers, got {list(v)!r}")
        for name in ("gv_weight", "lv_weight", "drop_connect_rate"):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v) or v < 0:
                raise ConfigError(f"{name} must be a finite number >= 0, got {v!r}")
        self.plane_spec()  # validates the plane
        self.encoder_config(3)  # validates the encoder

    @classmethod
    def paper(cls, **overrides) -> "BiMapperConfig":
        """The paper-size network: full EfficientNet-B0, HDMapNet neck (512) and BEV width (64),
        40x80 BEV features on the 200x400 grid, 352 px wide inputs (HDMapNet's 352x128 on
        nuScenes), the 1 m camera plane at the paper's 400x800 IPM resolution.
        """
        base = dict(
            width_mult=None, depth_mult=None, encoder_stages=7, neck_channels=512, bev_channels=64,
            bev_downsample=5, input_width=352, plane_shape=(800, 400), plane_height=1.0,
            unet_channels=64, decoder_channels=128,
        )
        base.update(overrides)
        return cls(**base)

    @property
    def in_channels(self) -> int:
        """Model input channels."""
        return NUM_LABELS if self.input_kind == "labels" else 3

    def encoder_config(self, in_channels: int) -> EfficientNetConfig:
        """EfficientNet config of both streams' encoders."""
        over = {"num_stages": self.encoder_stages, "in_channels": in_channels, "drop_connect_rate": self.drop_connect_rate}
        if self.width_mult is not None:
            over["width_mult"] = self.width_mult
        if self.depth_mult is not None:
            over["depth_mult"] = self.depth_mult
        return EfficientNetConfig.variant(self.encoder_variant, **over)

    def plane_spec(self) -> PlaneSpec:
        """The camera plane of the LV stream."""
        return PlaneSpec(self.plane_x_range, self.plane_z_range, self.plane_shape, self.plane_height)

    def to_dict(self) -> dict:
        """JSON-ready dict (tuples as lists)."""
        return {k: list(v) if isinstance(v, tuple) else v for k, v in asdict(self).items()}

    @classmethod
    def from_dict(cls, d: dict) -> "BiMapperConfig":
        """Inverse of :meth:`to_dict`; unknown keys raise ConfigError."""
        names = {f.name for f in fields(cls)}
        extra = set(d) - names
        if extra:
            raise ConfigError(f"unknown BiMapperConfig fields {sorted(extra)}")
        return cls(**d)
