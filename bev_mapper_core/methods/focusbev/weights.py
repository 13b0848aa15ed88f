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

import math
import os
from pathlib import Path

import torch

from bev_mapper_core.geometry.grid import BevGrid
from bev_mapper_core.geometry.rig import Rig
from bev_mapper_core.nn.mono_weights import (
    load_monocular,
    load_state_monocular,
    monocular_metadata,
    read_monocular_metadata,
    save_monocular,
    validate_monocular,
)

from ..bimapper.weights import WeightsError
from .model import FocusBEV, FocusBEVConfig, check_monocular

FORMAT = "bev_mapper.focusbev"
VERSION = 1
#: the longest history spacing a weights file may ask for (s)
MAX_INTERVAL_S = 10.0


def focusbev_metadata(model: FocusBEV, memory_interval_s: float) -> dict:
    """The metadata document of ``model`` (see the module docstring)."""
    return {**monocular_metadata(model, FORMAT, VERSION, "focusbev"), "memory_interval_s": float(memory_interval_s)}


def save_focusbev(model: FocusBEV, path: str | os.PathLike, memory_interval_s: float) -> Path:
    """Write ``model``'s parameters and buffers and its metadata (atomically)."""
    return save_monocular(model, path, focusbev_metadata(model, memory_interval_s))


def read_focusbev_metadata(path: str | os.PathLike) -> dict:
    """The checked metadata document of a FocusBEV weights file (header only).

    Raises:
        WeightsError: missing file, not safetensors (e.g. a pickle), truncated or corrupt
            header, no or malformed FocusBEV metadata.
    """
    path = Path(path)
    meta = read_monocular_metadata(path, FORMAT, VERSION, "focusbev", "FocusBEV", FocusBEVConfig,
                                   ("memory_interval_s",))
    v = meta["memory_interval_s"]
    if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v) or not 0 < v <= MAX_INTERVAL_S:
        raise WeightsError(f"{path}: metadata 'memory_interval_s' must be in (0, {MAX_INTERVAL_S}] s, got {v!r}")
    return meta


def _build(meta: dict):
    return lambda rig, grid: FocusBEV(FocusBEVConfig.from_dict(meta["config"]), rig, grid)


def validate_focusbev(path: str | os.PathLike) -> dict:
    """The full start-up check: the document, then the stored architecture built for a stand-in
    camera of the stored input size and every tensor checked against it. Returns the document.

    Raises:
        WeightsError: the first problem found.
    """
    path = Path(path)
    meta = read_focusbev_metadata(path)
    validate_monocular(path, meta, _build(meta), load_state_focusbev, "FocusBEV")
    return meta


def load_state_focusbev(model: FocusBEV, path: str | os.PathLike, meta: dict | None = None) -> None:
    """Load a FocusBEV file into ``model`` after checking that it fits it exactly.

    Raises:
        WeightsError: another architecture, camera, classes, grid or input size; a missing,
            extra, misshapen or non-finite tensor; a corrupt file.
    """
    path = Path(path)
    load_state_monocular(model, path, read_focusbev_metadata(path) if meta is None else meta, FocusBEVConfig,
                         "FocusBEV")


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
    return load_monocular(path, meta, rig, grid, device, _build(meta), load_state_focusbev), meta


__all__ = ["FORMAT", "focusbev_metadata", "load_focusbev", "load_state_focusbev", "read_focusbev_metadata",
           "save_focusbev", "validate_focusbev"]
