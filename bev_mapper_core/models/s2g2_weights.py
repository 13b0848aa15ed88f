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

import json
import os
from pathlib import Path

import torch
from safetensors.torch import save_file

from ..errors import BevMapperError, ConfigError
from ..grid import BevGrid
from ..rig import Rig
from .s2g2 import BRANCHES, S2G2, S2G2Config, check_monocular
from .weights import META_KEY, WeightsError, cached_tensors, check_model_document, read_document, standin_rig

FORMAT = "bev_mapper.s2g2"
VERSION = 1
_KEYS = ("method", "rig", "cameras", "input_kind", "classes", "grid", "input_size", "inference_branch", "config")


def s2g2_metadata(model: S2G2, inference_branch: str = "active") -> dict:
    """The metadata document of ``model`` (see the module docstring)."""
    if inference_branch not in BRANCHES:
        raise ConfigError(f"inference_branch must be one of {BRANCHES}, got {inference_branch!r}")
    cfg = model.config
    return {"format": FORMAT, "version": VERSION, "method": "s2g2", "rig": model.rig.name,
            "cameras": list(model.rig.names), "input_kind": cfg.input_kind, "classes": list(cfg.classes),
            "grid": model.grid.to_dict(), "input_size": list(model.input_size),
            "inference_branch": inference_branch, "config": cfg.to_dict()}


def save_s2g2(model: S2G2, path: str | os.PathLike, inference_branch: str = "active") -> Path:
    """Write ``model``'s parameters and buffers (both branches) and its metadata (atomically)."""
    path = Path(path)
    meta = s2g2_metadata(model, inference_branch)
    tensors = {k: v.detach().cpu().contiguous() for k, v in model.state_dict().items()}
    tmp = path.with_name(path.name + ".tmp")
    save_file(tensors, str(tmp), metadata={META_KEY: json.dumps(meta, sort_keys=True)})
    os.replace(tmp, path)
    return path


def _check_document(meta: dict, path: Path) -> None:
    """Schema and bounds of a metadata document (raises WeightsError)."""
    def bad(what: str) -> WeightsError:
        return WeightsError(f"{path}: metadata {what}")

    missing = sorted(set(_KEYS) - set(meta))
    if missing:
        raise bad(f"lacks {missing}")
    if meta["method"] != "s2g2":
        raise bad(f"is for method {meta['method']!r}, not 's2g2'")
    cams = meta["cameras"]
    if not isinstance(meta["rig"], str) or not isinstance(cams, list) or len(cams) != 1 \
            or not isinstance(cams[0], str) or not cams[0]:
        raise bad(f"must name a rig and exactly one camera, got rig {meta['rig']!r}, cameras {cams!r}")
    if meta["inference_branch"] not in BRANCHES:
        raise bad(f"'inference_branch' must be one of {BRANCHES}, got {meta['inference_branch']!r}")
    check_model_document(meta, path, S2G2Config)


def read_s2g2_metadata(path: str | os.PathLike) -> dict:
    """The checked metadata document of an S2G2 weights file (header only).

    Raises:
        WeightsError: missing file, not safetensors (e.g. a pickle), truncated or corrupt
            header, no or malformed S2G2 metadata.
    """
    path = Path(path)
    meta = read_document(path, FORMAT, VERSION, "S2G2")
    _check_document(meta, path)
    return meta


def validate_s2g2(path: str | os.PathLike) -> dict:
    """The full start-up check: the document, then the stored architecture built for a stand-in
    camera of the stored input size (tensor shapes do not depend on calibration) and every
    tensor checked against it. Returns the metadata document.

    Raises:
        WeightsError: the first problem found.
    """
    path = Path(path)
    meta = read_s2g2_metadata(path)
    h, w = meta["input_size"]
    try:
        model = S2G2(S2G2Config.from_dict(meta["config"]), standin_rig(meta["rig"], tuple(meta["cameras"]), (w, h)),
                     BevGrid.from_dict(meta["grid"]))
    except (BevMapperError, ValueError, RuntimeError) as e:
        raise WeightsError(f"{path}: cannot build the stored S2G2 model ({e})") from None
    load_state_s2g2(model, path, meta)
    return meta


def load_state_s2g2(model: S2G2, path: str | os.PathLike, meta: dict | None = None) -> None:
    """Load an S2G2 file into ``model`` after checking that it fits it exactly.

    Raises:
        WeightsError: another architecture, camera, input kind, classes, grid or input size;
            a missing, extra, misshapen or non-finite tensor; a corrupt file.
    """
    path = Path(path)
    meta = read_s2g2_metadata(path) if meta is None else meta
    if S2G2Config.from_dict(meta["config"]) != model.config:
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
    model.load_state_dict(cached_tensors(path, model.state_dict(), "S2G2"), strict=True)


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
    cfg, stored_grid = S2G2Config.from_dict(meta["config"]), BevGrid.from_dict(meta["grid"])
    if list(meta["cameras"]) != list(rig.names):
        raise WeightsError(f"{path}: weights were trained for camera {meta['cameras']}, the rig has {list(rig.names)}")
    try:
        model = S2G2(cfg, rig, grid or stored_grid)
    except ConfigError as e:
        raise WeightsError(f"{path}: cannot build the stored model for rig {rig.name!r} ({e})") from None
    load_state_s2g2(model, path, meta)
    return model.to(device).eval(), meta


__all__ = ["FORMAT", "load_s2g2", "load_state_s2g2", "read_s2g2_metadata", "s2g2_metadata", "save_s2g2",
           "validate_s2g2"]
