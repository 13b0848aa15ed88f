"""Bi-Mapper weights: one safetensors file with the configuration in its metadata.

Only safetensors is ever read (never ``torch.load`` / pickle). The header's ``__metadata__``
holds one key, ``bev_mapper``, a JSON document::

    {"format": "bev_mapper.bimapper", "version": 1, "method": "bimapper",
     "rig": "surround6", "cameras": [...], "input_kind": "labels", "classes": [...],
     "grid": {"x_min": ..., "x_max": ..., "y_min": ..., "y_max": ..., "resolution": ...},
     "input_size": [h, w], "config": {BiMapperConfig fields}}

Loading checks the document (method, rig name and camera order, input kind, classes, grid,
architecture) against what the caller expects and every tensor's name, shape and dtype against
the model built from it; any mismatch, a missing or extra tensor, a non-finite value, or a file
that is not valid safetensors raises :class:`WeightsError`. Calibration tables are not stored:
they are rebuilt from the rig the weights are used with.
"""

from __future__ import annotations

import json
import math
import os
from dataclasses import asdict
from pathlib import Path

import torch
from safetensors import safe_open
from safetensors.torch import save_file

from ..errors import BevMapperError, ConfigError
from ..grid import BevGrid
from ..rig import Rig
from .bimapper import BiMapper, BiMapperConfig

FORMAT = "bev_mapper.bimapper"
VERSION = 1
META_KEY = "bev_mapper"


class WeightsError(BevMapperError, ValueError):
    """A weights file is unreadable, corrupt, or does not fit the requested model."""


def model_metadata(model: BiMapper) -> dict:
    """The metadata document describing ``model`` (see the module docstring)."""
    cfg = model.config
    return {
        "format": FORMAT, "version": VERSION, "method": "bimapper",
        "rig": model.rig.name, "cameras": list(model.rig.names),
        "input_kind": cfg.input_kind, "classes": list(cfg.classes),
        "grid": asdict(model.grid), "input_size": list(model.input_size),
        "config": cfg.to_dict(),
    }


def save_weights(model: BiMapper, path: str | os.PathLike) -> Path:
    """Write ``model``'s parameters and buffers plus its metadata to ``path`` (atomically)."""
    path = Path(path)
    tensors = {k: v.detach().cpu().contiguous() for k, v in model.state_dict().items()}
    tmp = path.with_name(path.name + ".tmp")
    save_file(tensors, str(tmp), metadata={META_KEY: json.dumps(model_metadata(model), sort_keys=True)})
    os.replace(tmp, path)
    return path


def read_metadata(path: str | os.PathLike) -> dict:
    """Parse and sanity-check the metadata document of a weights file (tensors not loaded).

    Raises:
        WeightsError: missing file, not safetensors (e.g. a pickle), truncated/corrupt header,
            no or malformed Bi-Mapper metadata.
    """
    path = Path(path)
    if not path.is_file():
        raise WeightsError(f"weights file {path} does not exist")
    try:
        with safe_open(str(path), framework="pt") as f:
            raw = (f.metadata() or {}).get(META_KEY)
    except Exception as e:  # SafetensorError is not exported as a stable type
        raise WeightsError(f"{path} is not a valid safetensors file ({e})") from None
    if raw is None:
        raise WeightsError(f"{path} has no '{META_KEY}' metadata: not a bev_mapper weights file")
    try:
        meta = json.loads(raw)
    except json.JSONDecodeError as e:
        raise WeightsError(f"{path}: metadata is not valid JSON ({e})") from None
    if not isinstance(meta, dict) or meta.get("format") != FORMAT:
        raise WeightsError(f"{path}: metadata format is not {FORMAT!r}")
    if meta.get("version") != VERSION:
        raise WeightsError(f"{path}: metadata version {meta.get('version')!r}, this code reads {VERSION}")
    missing = {"method", "rig", "cameras", "input_kind", "classes", "grid", "input_size", "config"} - set(meta)
    if missing:
        raise WeightsError(f"{path}: metadata lacks {sorted(missing)}")
    if meta["method"] != "bimapper":
        raise WeightsError(f"{path}: weights are for method {meta['method']!r}, not 'bimapper'")
    return meta


def config_from_metadata(meta: dict, path: str | os.PathLike = "weights") -> tuple[BiMapperConfig, BevGrid]:
    """The architecture config and grid stored in a metadata document."""
    try:
        return BiMapperConfig.from_dict(meta["config"]), BevGrid(**meta["grid"])
    except (BevMapperError, TypeError, KeyError) as e:
        raise WeightsError(f"{path}: stored config/grid is invalid ({e})") from None


def check_metadata(meta: dict, path: str | os.PathLike = "weights", *, rig: Rig | None = None,
                   grid: BevGrid | None = None, input_kind: str | None = None,
                   classes: tuple[str, ...] | None = None, config: BiMapperConfig | None = None) -> None:
    """Compare a metadata document with what the caller needs; ``None`` arguments are not checked.

    Raises:
        WeightsError: naming the first field that differs.
    """
    def fail(what, want, got):
        raise WeightsError(f"{path}: weights were trained for {what} {got!r}, but {want!r} is required")

    stored_cfg, stored_grid = config_from_metadata(meta, path)
    if rig is not None:
        if meta["rig"] != rig.name:
            fail("rig", rig.name, meta["rig"])
        if list(meta["cameras"]) != list(rig.names):
            fail("cameras", list(rig.names), meta["cameras"])
    if input_kind is not None and meta["input_kind"] != input_kind:
        fail("input kind", input_kind, meta["input_kind"])
    if classes is not None and list(meta["classes"]) != list(classes):
        fail("classes", list(classes), meta["classes"])
    if grid is not None:
        a, b = asdict(grid), asdict(stored_grid)
        if any(not math.isclose(a[k], b[k], rel_tol=0, abs_tol=1e-9) for k in a):
            fail("grid", grid.describe(), stored_grid.describe())
    if config is not None and config != stored_cfg:
        diff = [k for k, v in config.to_dict().items() if stored_cfg.to_dict()[k] != v]
        raise WeightsError(f"{path}: architecture differs from the requested one in {diff}")


def load_state(model: BiMapper, path: str | os.PathLike) -> None:
    """Load a weights file into an existing model after checking that it fits it exactly.

    Raises:
        WeightsError: metadata mismatch (rig, cameras, input kind, classes, grid, config, input
            size), a missing/extra tensor, a shape/dtype mismatch, non-finite values, corruption.
    """
    meta = read_metadata(path)
    check_metadata(meta, path, rig=model.rig, grid=model.grid, input_kind=model.config.input_kind,
                   classes=model.config.classes, config=model.config)
    if list(meta["input_size"]) != list(model.input_size):
        raise WeightsError(f"{path}: weights expect input size {meta['input_size']}, the model has {list(model.input_size)}")
    expected = model.state_dict()
    try:
        with safe_open(str(path), framework="pt") as f:
            keys = set(f.keys())
            missing, extra = sorted(set(expected) - keys), sorted(keys - set(expected))
            if missing or extra:
                raise WeightsError(f"{path}: tensors missing {missing[:5]}{'...' if len(missing) > 5 else ''}, "
                                   f"unexpected {extra[:5]}{'...' if len(extra) > 5 else ''}")
            state = {}
            for k, ref in expected.items():
                shape = tuple(f.get_slice(k).get_shape())
                if shape != tuple(ref.shape):
                    raise WeightsError(f"{path}: tensor {k!r} has shape {shape}, the model needs {tuple(ref.shape)}")
                t = f.get_tensor(k)
                if t.dtype != ref.dtype:
                    raise WeightsError(f"{path}: tensor {k!r} is {t.dtype}, the model needs {ref.dtype}")
                if t.is_floating_point() and not torch.isfinite(t).all():
                    raise WeightsError(f"{path}: tensor {k!r} has non-finite values")
                state[k] = t
    except WeightsError:
        raise
    except Exception as e:
        raise WeightsError(f"{path}: cannot read tensors ({e})") from None
    model.load_state_dict(state, strict=True)


def load_bimapper(path: str | os.PathLike, rig: Rig, grid: BevGrid | None = None, *,
                  input_kind: str | None = None, classes: tuple[str, ...] | None = None,
                  device: str | torch.device = "cpu") -> BiMapper:
    """Build the model a weights file describes for ``rig``, load it, and return it in eval mode.

    ``grid``, ``input_kind`` and ``classes`` are checked when given. The rig must have the
    stored name and camera order; its calibration may differ (tables are rebuilt) as long as
    the model input size stays the same.
    """
    meta = read_metadata(path)
    check_metadata(meta, path, rig=rig, grid=grid, input_kind=input_kind, classes=classes)
    cfg, stored_grid = config_from_metadata(meta, path)
    try:
        model = BiMapper(cfg, rig, grid or stored_grid)
    except ConfigError as e:
        raise WeightsError(f"{path}: cannot build the stored model for rig {rig.name!r} ({e})") from None
    load_state(model, path)
    return model.to(device).eval()
