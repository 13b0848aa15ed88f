"""S2G2 weights: one safetensors file, its configuration in the metadata (never pickle).

The header's ``__metadata__`` holds ``bev_mapper``, a JSON document::

    {"format": "bev_mapper.s2g2", "version": 1, "method": "s2g2",
     "rig": "front1", "cameras": ["front"], "input_kind": "rgb", "classes": [...],
     "grid": {"x_min": ..., "x_max": ..., "y_min": ..., "y_max": ..., "resolution": ...},
     "input_size": [h, w], "inference_branch": "active", "config": {S2G2Config fields}}

Both branches are stored (the passive one is the EMA of the active one);
``inference_branch`` says which one maps. Reading and loading are the monocular methods' shared
:class:`~bev_mapper_core.nn.mono_weights.MonoWeightsFormat`: the document is checked (schema,
bounds, the stored architecture) before anything is allocated, and every tensor's name, shape,
dtype and finiteness against the stored architecture before the model is used. The frustum is
not stored: it is rebuilt from the rig the weights are used with.
"""

from __future__ import annotations

import os
from pathlib import Path

from bev_mapper_core.nn.mono_weights import MonoWeightsFormat

from .model import BRANCHES, S2G2, S2G2Config

FORMAT = "bev_mapper.s2g2"
VERSION = 1


def _check_branch(value) -> str | None:
    return None if value in BRANCHES else f"must be one of {BRANCHES}, got {value!r}"


#: The S2G2 weights file.
S2G2_WEIGHTS = MonoWeightsFormat(FORMAT, VERSION, "s2g2", "S2G2", S2G2, S2G2Config,
                                 {"inference_branch": _check_branch})


def s2g2_metadata(model: S2G2, inference_branch: str = "active") -> dict:
    """The metadata document of ``model`` (see the module docstring)."""
    return S2G2_WEIGHTS.metadata(model, inference_branch=inference_branch)


def save_s2g2(model: S2G2, path: str | os.PathLike, inference_branch: str = "active") -> Path:
    """Write ``model``'s parameters and buffers (both branches) and its metadata (atomically)."""
    return S2G2_WEIGHTS.save(model, path, inference_branch=inference_branch)


read_s2g2_metadata = S2G2_WEIGHTS.read_metadata
validate_s2g2 = S2G2_WEIGHTS.validate
load_state_s2g2 = S2G2_WEIGHTS.load_state
load_s2g2 = S2G2_WEIGHTS.load

__all__ = ["FORMAT", "S2G2_WEIGHTS", "load_s2g2", "load_state_s2g2", "read_s2g2_metadata", "s2g2_metadata",
           "save_s2g2", "validate_s2g2"]
