"""FocusBEV weights: one safetensors file, its configuration in the metadata (never pickle).

The header's ``__metadata__`` holds ``bev_mapper``, a JSON document::

    {"format": "bev_mapper.focusbev", "version": 1, "method": "focusbev",
     "rig": "front1", "cameras": ["front"], "input_kind": "rgb", "classes": [...],
     "grid": {...}, "input_size": [h, w], "memory_interval_s": 0.3,
     "config": {FocusBEVConfig fields}}

``memory_interval_s`` is the time between the frames the temporal fusion was trained on; the
mapper's memory bank picks history frames that far apart. Reading checks the document before
anything is allocated (:func:`read_focusbev_metadata`) and every tensor's name, shape, dtype and
finiteness against the stored architecture (:func:`load_state_focusbev`). The polar tables and
the frustum are not stored: they are rebuilt from the rig the weights are used with.
"""

from __future__ import annotations

import json
import math
import os
from pathlib import Path

import torch
from safetensors.torch import save_file

from ..errors import BevMapperError, ConfigError
from ..grid import BevGrid
from ..rig import Rig
from .focusbev import FocusBEV, FocusBEVConfig, check_monocular
from .weights import META_KEY, WeightsError, cached_tensors, check_model_document, read_document, standin_rig

FORMAT = "bev_mapper.focusbev"
VERSION = 1
_KEYS = ("method", "rig", "cameras", "input_kind", "classes", "grid", "input_size", "memory_interval_s", "config")
#: the longest history spacing a weights file may ask for (s)
MAX_INTERVAL_S = 10.0


def focusbev_metadata(model: FocusBEV, memory_interval_s: float) -> dict:
    """The metadata document of ``model`` (see the module docstring)."""
    cfg = model.config
    return {"format": FORMAT, "version": VERSION, "method": "focusbev", "rig": model.rig.name,
            "cameras": list(model.rig.names), "input_kind": cfg.input_kind, "classes": list(cfg.classes),
            "grid": model.grid.to_dict(), "input_size": list(model.input_size),
            "memory_interval_s": float(memory_interval_s), "config": cfg.to_dict()}


def save_focusbev(model: FocusBEV, path: str | os.PathLike, memory_interval_s: float) -> Path:
    """Write ``model``'s parameters and buffers and its metadata (atomically)."""
    path = Path(path)
    meta = focusbev_metadata(model, memory_interval_s)
    tensors = {k: v.detach().cpu().contiguous() for k, v in model.state_dict().items()}
    tmp = path.with_name(path.name + ".tmp")
    save_file(tensors, str(tmp), metadata={META_KEY: json.dumps(meta, sort_keys=True)})
    os.replace(tmp, path)
    return path


def read_focusbev_metadata(path: str | os.PathLike) -> dict:
    """The checked metadata document of a FocusBEV weights file (header only).

    Raises:
        WeightsError: missing file, not safetensors (e.g. a pickle), truncated or corrupt
            header, no or malformed FocusBEV metadata.
    """
    path = Path(path)
    meta = read_document(path, FORMAT, VERSION, "FocusBEV")
    missing = sorted(set(_KEYS) - set(meta))
    if missing:
        raise WeightsError(f"{path}: metadata lacks {missing}")
    if meta["method"] != "focusbev":
        raise WeightsError(f"{path}: metadata is for method {meta['method']!r}, not 'focusbev'")
    cams = meta["cameras"]
    if not isinstance(meta["rig"], str) or not isinstance(cams, list) or len(cams) != 1 \
            or not isinstance(cams[0], str) or not cams[0]:
        raise WeightsError(f"{path}: metadata must name a rig and exactly one camera, got {meta['rig']!r}, {cams!r}")
    v = meta["memory_interval_s"]
    if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v) or not 0 < v <= MAX_INTERVAL_S:
        raise WeightsError(f"{path}: metadata 'memory_interval_s' must be in (0, {MAX_INTERVAL_S}] s, got {v!r}")
    check_model_document(meta, path, FocusBEVConfig)
    return meta


def validate_focusbev(path: str | os.PathLike) -> dict:
    """The full start-up check: the document, then the stored architecture built for a stand-in
    camera of the stored input size and every tensor checked against it. Returns the document.

    Raises:
        WeightsError: the first problem found.
    """
    path = Path(path)
    meta = read_focusbev_metadata(path)
    h, w = meta["input_size"]
    try:
        model = FocusBEV(FocusBEVConfig.from_dict(meta["config"]),
                         standin_rig(meta["rig"], tuple(meta["cameras"]), (w, h)), BevGrid.from_dict(meta["grid"]))
    except (BevMapperError, ValueError, RuntimeError) as e:
        raise WeightsError(f"{path}: cannot build the stored FocusBEV model ({e})") from None
    load_state_focusbev(model, path, meta)
    return meta


def load_state_focusbev(model: FocusBEV, path: str | os.PathLike, meta: dict | None = None) -> None:
    """Load a FocusBEV file into ``model`` after checking that it fits it exactly.

    Raises:
        WeightsError: another architecture, camera, classes, grid or input size; a missing,
            extra, misshapen or non-finite tensor; a corrupt file.
    """
    path = Path(path)
    meta = read_focusbev_metadata(path) if meta is None else meta
    if FocusBEVConfig.from_dict(meta["config"]) != model.config:
        stored = meta["config"]
        diff = [k for k, v in model.config.to_dict().items() if stored.get(k) != v]
        raise WeightsError(f"{path}: architecture differs from the model's in {diff}")
    if list(meta["cameras"]) != list(model.rig.names):
        raise WeightsError(f"{path}: weights were trained for camera {meta['cameras']}, the rig has {list(model.rig.names)}")
    if not BevGrid.from_dict(meta["grid"]).isclose(model.grid):
        raise WeightsError(f"{path}: weights were trained for grid {BevGrid.from_dict(meta['grid']).describe()}, "
                           f"the model maps {model.grid.describe()}")
    if list(meta["input_size"]) != list(model.input_size):
        raise WeightsError(f"{path}: weights expect input size {meta['input_size']}, the model has {list(model.input_size)}")
    model.load_state_dict(cached_tensors(path, model.state_dict(), "FocusBEV"), strict=True)


def load_focusbev(path: str | os.PathLike, rig: Rig, grid: BevGrid | None = None,
                  device: str | torch.device = "cpu") -> tuple[FocusBEV, dict]:
    """Build the model a FocusBEV file describes for ``rig`` (its one camera, the stored one;
    the calibration may differ as long as the input size stays) and ``grid`` (default: the
    stored one); returns ``(model in eval mode, metadata)``.

    Raises:
        ConfigError: a rig with more than one camera.
        WeightsError: see :func:`load_state_focusbev`.
    """
    check_monocular(rig)
    path = Path(path)
    meta = read_focusbev_metadata(path)
    if list(meta["cameras"]) != list(rig.names):
        raise WeightsError(f"{path}: weights were trained for camera {meta['cameras']}, the rig has {list(rig.names)}")
    try:
        model = FocusBEV(FocusBEVConfig.from_dict(meta["config"]), rig, grid or BevGrid.from_dict(meta["grid"]))
    except ConfigError as e:
        raise WeightsError(f"{path}: cannot build the stored model for rig {rig.name!r} ({e})") from None
    load_state_focusbev(model, path, meta)
    return model.to(device).eval(), meta


__all__ = ["FORMAT", "focusbev_metadata", "load_focusbev", "load_state_focusbev", "read_focusbev_metadata",
           "save_focusbev", "validate_focusbev"]
