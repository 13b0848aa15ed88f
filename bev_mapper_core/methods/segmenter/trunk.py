"""The shipped segmenter's EfficientNet trunk as the pretrained start of another method's image
encoder (issue #26: every RGB method starts from the backbone that has seen synthetic and real
images).

:func:`trunk_config` is the segmenter's trunk architecture (from :class:`~.model.SegmenterConfig`'s
defaults: one source), :func:`encoder_source` resolves a method's ``encoder_init`` setting to a
segmenter file, and :func:`init_encoder` copies that file's trunk into the method's encoder.
"""

from __future__ import annotations

from pathlib import Path

import torch

from bev_mapper_core.errors import ConfigError
from bev_mapper_core.nn.efficientnet import EfficientNetConfig
from bev_mapper_core.nn.weights import weights_file_problem

from .model import SegmenterConfig
from .stage import shipped_segmenter
from .weights import load_segmenter_trunk

#: what ``encoder_init`` may say (besides a segmenter weights path)
ENCODER_INITS = ("auto", "none", "segmenter")


def trunk_config(in_channels: int = 3) -> EfficientNetConfig:
    """The EfficientNet configuration of the shipped segmenter's trunk (width, depth and stages
    of :class:`~.model.SegmenterConfig`'s defaults): an encoder built with it takes the trunk.
    """
    seg = SegmenterConfig()
    return EfficientNetConfig(width_mult=seg.width_mult, depth_mult=seg.depth_mult, num_stages=seg.encoder_stages,
                              in_channels=in_channels)


def check_encoder_init(spec) -> None:
    """Raise :class:`ConfigError` unless ``spec`` is one of :data:`ENCODER_INITS` or a non-empty path."""
    if not isinstance(spec, str) or not spec:
        raise ConfigError(f"encoder_init must be one of {', '.join(ENCODER_INITS)} or a file path, got {spec!r}")


def encoder_source(spec: str, input_kind: str, rig_name: str) -> Path | None:
    """The segmenter file whose trunk initializes a method's encoder (``None``: from scratch);
    the shipped one is the rig's (:func:`~.stage.shipped_segmenter`).

    ``auto``: the shipped segmenter on RGB input, none on label input; ``none``; ``segmenter``:
    the shipped one; else a segmenter weights path.

    Raises:
        ConfigError: a segmenter asked for on label input (its first layer reads RGB), no shipped
            segmenter, or a path that is not a file.
    """
    check_encoder_init(spec)
    if spec == "none" or (spec == "auto" and input_kind != "rgb"):
        return None
    if input_kind != "rgb":
        raise ConfigError(f"encoder_init {spec!r}: a segmenter's trunk reads RGB images, the model's input is "
                          f"{input_kind!r} (use auto or none)")
    if spec in ("auto", "segmenter"):
        path = shipped_segmenter(rig_name)
        if path is None:
            raise ConfigError("encoder_init: no segmenter ships with the package; use --encoder-init none or a path")
        return path
    path = Path(spec)
    problem = weights_file_problem(path)
    if problem is not None:
        raise ConfigError(f"encoder_init: segmenter weights {spec} {problem}")
    return path


def init_encoder(encoder: torch.nn.Module, spec: str, input_kind: str, rig_name: str) -> Path | None:
    """Copy the trunk of :func:`encoder_source`'s segmenter into ``encoder`` (an
    :class:`~bev_mapper_core.nn.efficientnet.EfficientNet` of :func:`trunk_config`'s sizes); the
    file used, or ``None`` (left as initialized).

    Raises:
        ConfigError: see :func:`encoder_source`.
        WeightsError: a bad segmenter file, or a trunk of other sizes than ``encoder``'s.
    """
    path = encoder_source(spec, input_kind, rig_name)
    if path is not None:
        load_segmenter_trunk(encoder, path)
    return path


__all__ = ["ENCODER_INITS", "check_encoder_init", "encoder_source", "init_encoder", "trunk_config"]
