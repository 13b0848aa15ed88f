"""Segmenter weights: one safetensors file, its configuration in the metadata (never pickle).

The header's ``__metadata__`` holds ``bev_mapper``, a JSON document::

    {"format": "bev_mapper.segmenter", "version": 1, "method": "segmenter",
     "rig": "surround6", "config": {SegmenterConfig fields}}

``rig`` only records what the weights were trained on: a segmenter works per camera image, so
it runs on any camera (its quality is best on cameras like those it saw). Loading checks the
document, builds the stored architecture, and checks every tensor's name, shape, dtype and
finiteness before the model is used (:func:`load_segmenter`); files are read once per file
version (cached), as Bi-Mapper's :class:`~.weights.WeightsFile`.
"""

from __future__ import annotations

import os
import threading
from pathlib import Path

import torch

from bev_mapper_core.errors import BevMapperError, ConfigError
from bev_mapper_core.nn.weights import (
    WeightsError,
    read_checked_tensors,
    read_document,
    save_document,
    weights_file_problem,
)

from .model import Segmenter, SegmenterConfig

FORMAT = "bev_mapper.segmenter"
VERSION = 1

_CACHE: dict[tuple, Segmenter] = {}
_LOCK = threading.Lock()


def save_segmenter(model: Segmenter, path: str | os.PathLike, rig_name: str = "") -> Path:
    """Write ``model``'s tensors and metadata to ``path`` (atomically)."""
    path = Path(path)
    meta = {"format": FORMAT, "version": VERSION, "method": "segmenter", "rig": rig_name,
            "config": model.config.to_dict()}
    return save_document(model, path, meta)


def read_segmenter_metadata(path: str | os.PathLike) -> dict:
    """The checked metadata document of a segmenter file (header only).

    Raises:
        WeightsError: missing file, not safetensors, no or malformed segmenter metadata.
    """
    meta = read_document(path, FORMAT, VERSION, "segmenter")
    if not isinstance(meta.get("config"), dict) or not isinstance(meta.get("rig", ""), str):
        raise WeightsError(f"{path}: metadata lacks a config")
    try:
        SegmenterConfig.from_dict(meta["config"])
    except (ConfigError, TypeError) as e:
        raise WeightsError(f"{path}: bad segmenter config ({e})") from None
    return meta


def load_segmenter(path: str | os.PathLike, device: str | torch.device = "cpu") -> Segmenter:
    """The segmenter stored in ``path``, checked tensor by tensor, in eval mode.

    The checked model is cached per file version (path, size, mtime); each call returns a copy
    on ``device`` only when the device differs, so callers must not train the returned model.

    Raises:
        WeightsError: the first problem found (see :func:`read_segmenter_metadata`; missing,
            extra, misshapen or non-finite tensors).
    """
    path = Path(path)
    problem = weights_file_problem(path)
    if problem is not None:
        raise WeightsError(f"segmenter weights {path} {problem}")
    try:
        st = path.stat()
    except OSError as e:
        raise WeightsError(f"segmenter weights {path}: {e.strerror or e}") from None
    key = (str(path.resolve()), st.st_size, st.st_mtime_ns, str(device))
    with _LOCK:
        if key in _CACHE:
            return _CACHE[key]
    meta = read_segmenter_metadata(path)
    try:
        model = Segmenter(SegmenterConfig.from_dict(meta["config"]))
    except (BevMapperError, ValueError, RuntimeError) as e:
        raise WeightsError(f"{path}: cannot build the stored segmenter ({e})") from None
    state = read_checked_tensors(path, model.state_dict())
    model.load_state_dict(state, strict=True)
    model = model.to(device).eval()
    with _LOCK:
        _CACHE[key] = model
    return model


def load_segmenter_trunk(encoder: torch.nn.Module, path: str | os.PathLike) -> None:
    """Copy the EfficientNet trunk of the segmenter in ``path`` into ``encoder`` (another model's
    :class:`~.efficientnet.EfficientNet`, e.g. S2G2's feature extractor: a pretrained start).

    Raises:
        WeightsError: a bad segmenter file (see :func:`load_segmenter`), or a trunk whose tensors
            differ in name or shape from ``encoder``'s (another width, depth or stage count).
    """
    trunk = {k[len("encoder."):]: v for k, v in load_segmenter(path).state_dict().items() if k.startswith("encoder.")}
    own = encoder.state_dict()
    missing, extra = sorted(set(own) - set(trunk)), sorted(set(trunk) - set(own))
    wrong = [k for k in own if k in trunk and tuple(own[k].shape) != tuple(trunk[k].shape)]
    if missing or extra or wrong:
        first = (missing or extra or wrong)[0]
        raise WeightsError(f"{path}: the segmenter's encoder does not fit this encoder ({len(missing)} missing, "
                           f"{len(extra)} extra, {len(wrong)} misshapen tensors, e.g. {first!r}); the trunk sizes "
                           "(width, depth, stages) must be the segmenter's")
    with torch.no_grad():
        for k, v in own.items():
            v.copy_(trunk[k])


__all__ = ["FORMAT", "load_segmenter", "load_segmenter_trunk", "read_segmenter_metadata", "save_segmenter"]
