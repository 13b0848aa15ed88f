"""FocusBEV weights: one safetensors file, its configuration in the metadata (never pickle).

The header's ``__metadata__`` holds ``bev_mapper``, a JSON document::

    {"format": "bev_mapper.focusbev", "version": 1, "method": "focusbev",
     "rig": "front1", "cameras": ["front"], "input_kind": "rgb", "classes": [...],
     "grid": {...}, "input_size": [h, w], "memory_interval_s": 0.3,
     "config": {FocusBEVConfig fields}}

``memory_interval_s`` is the time between the frames the temporal fusion was trained on; the
mapper's memory bank picks history frames that far apart. Reading and loading are the monocular
methods' shared :class:`~bev_mapper_core.nn.mono_weights.MonoWeightsFormat`: the document is
checked before anything is allocated, and every tensor's name, shape, dtype and finiteness
against the stored architecture. The polar tables and the frustum are not stored: they are
rebuilt from the rig the weights are used with.
"""

from __future__ import annotations

import math
import os
from pathlib import Path

from bev_mapper_core.nn.mono_weights import MonoWeightsFormat

from .model import FocusBEV, FocusBEVConfig

FORMAT = "bev_mapper.focusbev"
VERSION = 1
#: the longest history spacing a weights file may ask for (s)
MAX_INTERVAL_S = 10.0


def _check_interval(v) -> str | None:
    if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v) or not 0 < v <= MAX_INTERVAL_S:
        return f"must be in (0, {MAX_INTERVAL_S}] s, got {v!r}"
    return None


#: The FocusBEV weights file.
FOCUSBEV_WEIGHTS = MonoWeightsFormat(FORMAT, VERSION, "focusbev", "FocusBEV", FocusBEV, FocusBEVConfig,
                                     {"memory_interval_s": _check_interval})


def focusbev_metadata(model: FocusBEV, memory_interval_s: float) -> dict:
    """The metadata document of ``model`` (see the module docstring)."""
    return FOCUSBEV_WEIGHTS.metadata(model, memory_interval_s=float(memory_interval_s))


def save_focusbev(model: FocusBEV, path: str | os.PathLike, memory_interval_s: float) -> Path:
    """Write ``model``'s parameters and buffers and its metadata (atomically)."""
    return FOCUSBEV_WEIGHTS.save(model, path, memory_interval_s=float(memory_interval_s))


read_focusbev_metadata = FOCUSBEV_WEIGHTS.read_metadata
validate_focusbev = FOCUSBEV_WEIGHTS.validate
load_state_focusbev = FOCUSBEV_WEIGHTS.load_state
load_focusbev = FOCUSBEV_WEIGHTS.load

__all__ = ["FOCUSBEV_WEIGHTS", "FORMAT", "focusbev_metadata", "load_focusbev", "load_state_focusbev",
           "read_focusbev_metadata", "save_focusbev", "validate_focusbev"]
