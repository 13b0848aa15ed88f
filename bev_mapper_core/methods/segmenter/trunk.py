"""Where another method's image encoder starts: the trunk of a segmenter (issue #26: every RGB
method starts from a backbone that has seen synthetic and real images), or the ImageNet
EfficientNet-Lite checkpoint (issue #37, ``imagenet``).

:func:`trunk_config` is the trunk architecture of the segmenter the methods' encoders were built
for (:data:`~.stage.TRUNK_SEGMENTER`, :class:`~.model.SegmenterConfig`'s defaults: one source),
:func:`encoder_source` resolves a method's ``encoder_init`` setting to a segmenter file, and
:func:`init_encoder` copies that file's trunk, or the ImageNet weights, into the method's encoder.
An ``imagenet`` start needs a Lite encoder of a published variant's multipliers
(``encoder_variant lite0`` for S2G2 and Bi-Mapper with their width and depth multipliers unset
or 1.0; FocusBEV's ``backbone lite0``).
"""

from __future__ import annotations

from pathlib import Path

import torch

from bev_mapper_core.errors import ConfigError
from bev_mapper_core.nn.efficientnet import EfficientNetConfig
from bev_mapper_core.nn.pretrained import CHECKPOINTS, checkpoint_path, load_lite_imagenet
from bev_mapper_core.nn.weights import weights_file_problem

from .. import WEIGHTS_DIR
from .model import SegmenterConfig
from .stage import TRUNK_SEGMENTER
from .weights import load_segmenter_trunk

#: what ``encoder_init`` may say (besides a segmenter weights path)
ENCODER_INITS = ("auto", "none", "segmenter", "imagenet")


def trunk_config(in_channels: int = 3) -> EfficientNetConfig:
    """The EfficientNet configuration of the shipped segmenter's trunk (width, depth and stages
    of :class:`~.model.SegmenterConfig`'s defaults): an encoder built with it takes the trunk.
    """
    return SegmenterConfig().trunk_config(in_channels)


def check_encoder_init(spec) -> None:
    """Raise :class:`ConfigError` unless ``spec`` is one of :data:`ENCODER_INITS` or a non-empty path."""
    if not isinstance(spec, str) or not spec:
        raise ConfigError(f"encoder_init must be one of {', '.join(ENCODER_INITS)} or a file path, got {spec!r}")


def encoder_source(spec: str, input_kind: str, rig_name: str) -> Path | None:
    """The segmenter file whose trunk initializes a method's encoder (``None``: from scratch, or
    ``imagenet``, which :func:`init_encoder` reads); the shipped one is
    :data:`~.stage.TRUNK_SEGMENTER`, whose trunk has :func:`trunk_config`'s sizes.

    ``auto``: the shipped trunk on RGB input, none on label input; ``none``; ``segmenter``:
    the shipped trunk; ``imagenet``: see :func:`init_encoder`; else a segmenter weights path.

    Raises:
        ConfigError: a segmenter asked for on label input (its first layer reads RGB), no shipped
            segmenter, or a path that is not a file.
    """
    check_encoder_init(spec)
    if spec == "none" or (spec == "auto" and input_kind != "rgb"):
        return None
    if input_kind != "rgb":
        raise ConfigError(f"encoder_init {spec!r}: a segmenter's trunk and ImageNet weights: both read RGB images, the "
                          f"model's input is {input_kind!r} (use auto or none)")
    if spec == "imagenet":
        return None
    if spec in ("auto", "segmenter"):
        path = WEIGHTS_DIR / TRUNK_SEGMENTER
        if not path.is_file():
            raise ConfigError(f"encoder_init: the shipped trunk {TRUNK_SEGMENTER} is missing; use --encoder-init "
                              "none, imagenet or a path")
        return path
    path = Path(spec)
    problem = weights_file_problem(path)
    if problem is not None:
        raise ConfigError(f"encoder_init: segmenter weights {spec} {problem}")
    return path


def init_encoder(encoder: torch.nn.Module, spec: str, input_kind: str, rig_name: str) -> Path | None:
    """Copy the trunk of :func:`encoder_source`'s segmenter into ``encoder`` (an
    :class:`~bev_mapper_core.nn.efficientnet.EfficientNet` of :func:`trunk_config`'s sizes), or
    with ``imagenet`` the ImageNet EfficientNet-Lite checkpoint of ``encoder``'s multipliers
    (:func:`~bev_mapper_core.nn.pretrained.load_lite_imagenet`); the file used, or ``None``
    (left as initialized).

    Raises:
        ConfigError: see :func:`encoder_source`.
        WeightsError: a bad segmenter file, or a trunk of other sizes than ``encoder``'s.
        PretrainedError: ``imagenet`` for an encoder that is not a published Lite variant, the
            checkpoint's package missing, or another file behind its name.
    """
    if spec == "imagenet" and input_kind == "rgb":
        variant = load_lite_imagenet(encoder)["variant"]
        return checkpoint_path(variant) if variant in CHECKPOINTS else None
    path = encoder_source(spec, input_kind, rig_name)
    if path is not None:
        load_segmenter_trunk(encoder, path)
    return path


__all__ = ["ENCODER_INITS", "check_encoder_init", "encoder_source", "init_encoder", "trunk_config"]
