"""What the weights files of the monocular methods (S2G2, FocusBEV) share: one safetensors file
whose header metadata (``bev_mapper``) names the method, rig, its one camera, input kind,
classes, grid, input size and the model config; the checks of that document; and loading a
model after every tensor was checked against the stored architecture.

A method describes its file once, as a :class:`MonoWeightsFormat` (format id, model and config
types, its own extra keys with their checks); ``methods/s2g2/weights.py`` and
``methods/focusbev/weights.py`` are such descriptions.
"""

from __future__ import annotations

import os
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from pathlib import Path

import torch

from ..errors import BevMapperError, ConfigError
from ..geometry.grid import BevGrid
from ..geometry.rig import Rig
from .mono_geometry import check_one_camera
from .weights import WeightsError, cached_tensors, check_model_document, read_document, save_document, standin_rig

#: keys every monocular document has
COMMON_KEYS = ("method", "rig", "cameras", "input_kind", "classes", "grid", "input_size", "config")


def monocular_metadata(model, fmt: str, version: int, method: str) -> dict:
    """The common part of a monocular model's metadata document."""
    cfg = model.config
    return {"format": fmt, "version": version, "method": method, "rig": model.rig.name,
            "cameras": list(model.rig.names), "input_kind": cfg.input_kind, "classes": list(cfg.classes),
            "grid": model.grid.to_dict(), "input_size": list(model.input_size), "config": cfg.to_dict()}


def save_monocular(model, path: str | os.PathLike, meta: dict) -> Path:
    """Write ``model``'s parameters and buffers with the metadata ``meta`` (atomically)."""
    return save_document(model, path, meta)


def read_monocular_metadata(path: str | os.PathLike, fmt: str, version: int, method: str, title: str,
                            config_type: type, extra_keys: tuple[str, ...] = ()) -> dict:
    """The checked common document of a monocular weights file (header only).

    Raises:
        WeightsError: missing file, not safetensors (e.g. a pickle), truncated or corrupt header,
            no or malformed metadata, another method, not exactly one camera.
    """
    path = Path(path)
    meta = read_document(path, fmt, version, title)
    missing = sorted(set(COMMON_KEYS + extra_keys) - set(meta))
    if missing:
        raise WeightsError(f"{path}: metadata lacks {missing}")
    if meta["method"] != method:
        raise WeightsError(f"{path}: metadata is for method {meta['method']!r}, not {method!r}")
    cams = meta["cameras"]
    if not isinstance(meta["rig"], str) or not isinstance(cams, list) or len(cams) != 1 \
            or not isinstance(cams[0], str) or not cams[0]:
        raise WeightsError(f"{path}: metadata must name a rig and exactly one camera, got rig {meta['rig']!r}, "
                           f"cameras {cams!r}")
    check_model_document(meta, path, config_type)
    return meta


def load_state_monocular(model, path: Path, meta: dict, config_type: type, title: str) -> None:
    """Load a file into ``model`` after checking that it fits it exactly.

    Raises:
        WeightsError: another architecture, camera, grid or input size; a missing, extra,
            misshapen or non-finite tensor; a corrupt file.
    """
    if config_type.from_dict(meta["config"]) != model.config:
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
    model.load_state_dict(cached_tensors(path, model.state_dict(), title), strict=True)


def validate_monocular(path: Path, meta: dict, build: Callable[[Rig, BevGrid], torch.nn.Module],
                       load_state: Callable, title: str) -> None:
    """Build the stored architecture for a stand-in camera of the stored input size (tensor
    shapes do not depend on calibration) and check every tensor against it.

    Raises:
        WeightsError: the first problem found.
    """
    h, w = meta["input_size"]
    try:
        model = build(standin_rig(meta["rig"], tuple(meta["cameras"]), (w, h)), BevGrid.from_dict(meta["grid"]))
    except (BevMapperError, ValueError, RuntimeError) as e:
        raise WeightsError(f"{path}: cannot build the stored {title} model ({e})") from None
    load_state(model, path, meta)


def load_monocular(path: Path, meta: dict, rig: Rig, grid: BevGrid | None, device,
                   build: Callable[[Rig, BevGrid], torch.nn.Module], load_state: Callable):
    """The model a file describes, built for ``rig`` (its one camera, the stored one; the
    calibration may differ as long as the input size stays) and ``grid`` (default: the stored
    one), loaded and in eval mode on ``device``.

    Raises:
        WeightsError: another camera, a model that cannot be built for this rig, or see
            :func:`load_state_monocular`.
    """
    if list(meta["cameras"]) != list(rig.names):
        raise WeightsError(f"{path}: weights were trained for camera {meta['cameras']}, the rig has {list(rig.names)}")
    try:
        model = build(rig, grid or BevGrid.from_dict(meta["grid"]))
    except ConfigError as e:
        raise WeightsError(f"{path}: cannot build the stored model for rig {rig.name!r} ({e})") from None
    load_state(model, path, meta)
    return model.to(device).eval()


#: an extra key's check: the problem with a value (``"must be ..., got ..."``), or None when it is fine
ExtraCheck = Callable[[object], "str | None"]


@dataclass(frozen=True)
class MonoWeightsFormat:
    """The weights file of one monocular method: the common document plus its own keys.

    Args:
        fmt, version: the document's ``format`` id and ``version``.
        method: the method name stored in the document.
        title: the method's name in messages (``S2G2``).
        model_type: the network class, built as ``model_type(config, rig, grid)``.
        config_type: its architecture config (a frozen dataclass with ``from_dict``).
        extra: the method's own document keys -> their checks (:data:`ExtraCheck`).
    """

    fmt: str
    version: int
    method: str
    title: str
    model_type: type
    config_type: type
    extra: Mapping[str, ExtraCheck] = field(default_factory=dict)

    def metadata(self, model, **extra) -> dict:
        """The document of ``model`` with the method's ``extra`` keys.

        Raises:
            ConfigError: an extra key missing, unknown or failing its check.
        """
        if set(extra) != set(self.extra):
            raise ConfigError(f"{self.title} weights need the keys {sorted(self.extra)}, got {sorted(extra)}")
        for key, value in extra.items():
            problem = self.extra[key](value)
            if problem:
                raise ConfigError(f"{key} {problem}")
        return {**monocular_metadata(model, self.fmt, self.version, self.method), **extra}

    def save(self, model, path: str | os.PathLike, **extra) -> Path:
        """Write ``model``'s parameters and buffers and its document (atomically)."""
        return save_monocular(model, path, self.metadata(model, **extra))

    def read_metadata(self, path: str | os.PathLike) -> dict:
        """The checked document of a weights file (header only).

        Raises:
            WeightsError: missing file, not safetensors (e.g. a pickle), truncated or corrupt
                header, no or malformed metadata of this method.
        """
        path = Path(path)
        meta = read_monocular_metadata(path, self.fmt, self.version, self.method, self.title, self.config_type,
                                       tuple(self.extra))
        for key, check in self.extra.items():
            problem = check(meta[key])
            if problem:
                raise WeightsError(f"{path}: metadata {key!r} {problem}")
        return meta

    def build(self, meta: dict) -> Callable[[Rig, BevGrid], torch.nn.Module]:
        """``(rig, grid) -> model`` of the architecture a document stores."""
        return lambda rig, grid: self.model_type(self.config_type.from_dict(meta["config"]), rig, grid)

    def load_state(self, model, path: str | os.PathLike, meta: dict | None = None) -> None:
        """Load a file into ``model`` after checking that it fits it exactly.

        Raises:
            WeightsError: another architecture, camera, input kind, classes, grid or input size;
                a missing, extra, misshapen or non-finite tensor; a corrupt file.
        """
        path = Path(path)
        load_state_monocular(model, path, self.read_metadata(path) if meta is None else meta, self.config_type,
                             self.title)

    def validate(self, path: str | os.PathLike) -> dict:
        """The full start-up check: the document, then the stored architecture built for a
        stand-in camera of the stored input size (tensor shapes do not depend on calibration) and
        every tensor checked against it. Returns the document.

        Raises:
            WeightsError: the first problem found.
        """
        path = Path(path)
        meta = self.read_metadata(path)
        validate_monocular(path, meta, self.build(meta), self.load_state, self.title)
        return meta

    def load(self, path: str | os.PathLike, rig: Rig, grid: BevGrid | None = None,
             device: str | torch.device = "cpu") -> tuple:
        """Build the model a file describes for ``rig`` (one camera, the stored one; its
        calibration may differ as long as the input size stays) and ``grid`` (default: the
        stored grid; another one is refused), load it; returns ``(model in eval mode, document)``.

        Raises:
            ConfigError: a rig with more than one camera.
            WeightsError: see :meth:`load_state`.
        """
        check_one_camera(rig, self.title)
        path = Path(path)
        meta = self.read_metadata(path)
        return load_monocular(path, meta, rig, grid, device, self.build(meta), self.load_state), meta


__all__ = ["COMMON_KEYS", "MonoWeightsFormat", "load_monocular", "load_state_monocular", "monocular_metadata", "read_monocular_metadata",
           "save_monocular", "validate_monocular"]
