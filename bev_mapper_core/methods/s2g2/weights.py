"""S2G2 weights: one safetensors file, its configuration in the metadata (never pickle).

The header's ``__metadata__`` holds ``bev_mapper``, a JSON document::

    {"format": "bev_mapper.s2g2", "version": 1, "method": "s2g2",
     "rig": "front1", "cameras": ["front"], "input_kind": "rgb", "classes": [...],
     "grid": {"x_min": ..., "x_max": ..., "y_min": ..., "y_max": ..., "resolution": ...},
     "input_size": [h, w], "inference_branch": "active", "config": {S2G2Config fields}}

Both branches are stored (the passive one is the EMA of the active one);
``inference_branch`` says which one maps. Reading checks the document (schema, bounds, the
stored architecture) before anything is allocated (:func:`read_s2g2_metadata`), and
:func:`load_s2g2` checks every tensor's name, shape, dtype and finiteness against the stored
architecture before the model is used; checked tensors are cached per file version, as
Bi-Mapper's :class:`~.weights.WeightsFile` does. The frustum is not stored: it is rebuilt from
the rig the weights are used with.
"""

from __future__ import annotations

import os
from pathlib import Path

import torch

from bev_mapper_core.errors import ConfigError
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
from .model import BRANCHES, S2G2, S2G2Config, check_monocular

FORMAT = "bev_mapper.s2g2"
VERSION = 1


def s2g2_metadata(model: S2G2, inference_branch: str = "active") -> dict:
    """The metadata document of ``model`` (see the module docstring)."""
    if inference_branch not in BRANCHES:
        raise ConfigError(f"inference_branch must be one of {BRANCHES}, got {inference_branch!r}")
    return {**monocular_metadata(model, FORMAT, VERSION, "s2g2"), "inference_branch": inference_branch}


def save_s2g2(model: S2G2, path: str | os.PathLike, inference_branch: str = "active") -> Path:
    """Write ``model``'s parameters and buffers (both branches) and its metadata (atomically)."""
    return save_monocular(model, path, s2g2_metadata(model, inference_branch))


def read_s2g2_metadata(path: str | os.PathLike) -> dict:
    """The checked metadata document of an S2G2 weights file (header only).

    Raises:
        WeightsError: missing file, not safetensors (e.g. a pickle), truncated or corrupt
            header, no or malformed S2G2 metadata.
    """
    path = Path(path)
    meta = read_monocular_metadata(path, FORMAT, VERSION, "s2g2", "S2G2", S2G2Config, ("inference_branch",))
    if meta["inference_branch"] not in BRANCHES:
        raise WeightsError(f"{path}: metadata 'inference_branch' must be one of {BRANCHES}, "
                           f"got {meta['inference_branch']!r}")
    return meta


def _build(meta: dict):
    return lambda rig, grid: S2G2(S2G2Config.from_dict(meta["config"]), rig, grid)


def validate_s2g2(path: str | os.PathLike) -> dict:
    """The full start-up check: the document, then the stored architecture built for a stand-in
    camera of the stored input size (tensor shapes do not depend on calibration) and every
    tensor checked against it. Returns the metadata document.

    Raises:
        WeightsError: the first problem found.
    """
    path = Path(path)
    meta = read_s2g2_metadata(path)
    validate_monocular(path, meta, _build(meta), load_state_s2g2, "S2G2")
    return meta


def load_state_s2g2(model: S2G2, path: str | os.PathLike, meta: dict | None = None) -> None:
    """Load an S2G2 file into ``model`` after checking that it fits it exactly.

    Raises:
        WeightsError: another architecture, camera, input kind, classes, grid or input size;
            a missing, extra, misshapen or non-finite tensor; a corrupt file.
    """
    path = Path(path)
    load_state_monocular(model, path, read_s2g2_metadata(path) if meta is None else meta, S2G2Config, "S2G2")


def load_s2g2(path: str | os.PathLike, rig: Rig, grid: BevGrid | None = None,
              device: str | torch.device = "cpu") -> tuple[S2G2, dict]:
    """Build the model an S2G2 file describes for ``rig`` (one camera, the stored one; its
    calibration may differ as long as the input size stays) and ``grid`` (default: the stored
    grid; another one is refused), load it; returns ``(model in eval mode, metadata)``.

    Raises:
        ConfigError: a rig with more than one camera.
        WeightsError: see :func:`load_state_s2g2`.
    """
    check_monocular(rig)
    path = Path(path)
    meta = read_s2g2_metadata(path)
    return load_monocular(path, meta, rig, grid, device, _build(meta), load_state_s2g2), meta


__all__ = ["FORMAT", "load_s2g2", "load_state_s2g2", "read_s2g2_metadata", "s2g2_metadata", "save_s2g2",
           "validate_s2g2"]
