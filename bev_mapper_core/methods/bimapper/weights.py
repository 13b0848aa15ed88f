"""Bi-Mapper weights: one safetensors file with the configuration in its metadata.

Only safetensors is ever read (never ``torch.load`` / pickle). The header's ``__metadata__``
holds one key, ``bev_mapper``, a JSON document::

    {"format": "bev_mapper.bimapper", "version": 1, "method": "bimapper",
     "rig": "surround6", "cameras": [...], "input_kind": "labels", "classes": [...],
     "grid": {"x_min": ..., "x_max": ..., "y_min": ..., "y_max": ..., "resolution": ...},
     "input_size": [h, w], "config": {BiMapperConfig fields}}

:class:`WeightsFile` reads a file's header and document once (cached per file version) and
offers the start-up checks (:meth:`~WeightsFile.check`, :meth:`~WeightsFile.validate`) and the
model (:meth:`~WeightsFile.build_model`).

* Opening checks the document's schema and bounds (types, known classes, a grid of at most
  :data:`~bev_mapper_core.geometry.grid.MAX_GRID_CELLS` cells, an architecture within ``BiMapperConfig``'s sanity bounds) before
  anything is allocated.
* :meth:`~WeightsFile.validate` (the mapper's preflight runs it) builds the stored architecture
  for a stand-in rig of the stored cameras and loads every tensor into it: names, shapes, dtypes
  and finite values are checked before a node starts, not at its first frame. The checked
  tensors stay cached with the document, so the model built later reads no file again.
* Loading checks the document (rig name and camera order, input kind, classes, grid,
  architecture) against what the caller expects.

Any mismatch, a missing or extra tensor, a non-finite value, or a file that is not valid
safetensors raises :class:`WeightsError`. Calibration tables are not stored: they are rebuilt
from the rig the weights are used with.
"""

from __future__ import annotations

import copy
import os
import threading
from collections import OrderedDict
from pathlib import Path

import torch

from bev_mapper_core.errors import BevMapperError, ConfigError
from bev_mapper_core.geometry.grid import BevGrid
from bev_mapper_core.geometry.rig import Rig
from bev_mapper_core.nn.weights import (
    WeightsError,
    check_model_document,
    check_tensors,
    read_checked_tensors,
    read_document,
    save_document,
    standin_rig,
    weights_file_problem,
)

from .. import ANY_RIG as _ANY_RIG
from .model import BiMapper, BiMapperConfig

FORMAT = "bev_mapper.bimapper"
VERSION = 1
#: The ``rig`` of weights that map any rig (:data:`bev_mapper_core.methods.ANY_RIG`): a rig-free
#: model (:attr:`BiMapper.rig_free`, no GV stream) trained on many rigs (``bev-train --rig
#: random``); its ``cameras`` are ``[]``.
ANY_RIG = _ANY_RIG


def _check_schema(meta: dict, path: Path) -> None:
    """Types and bounds of a Bi-Mapper metadata document (see the module docstring)."""
    if not isinstance(meta["rig"], str):
        raise WeightsError(f"{path}: metadata 'rig' must be a string, got {meta['rig']!r}")
    cams = meta["cameras"]
    if meta["rig"] == ANY_RIG:
        if cams != []:
            raise WeightsError(f"{path}: weights for any rig name no cameras, got {cams!r}")
        check_model_document(meta, path, BiMapperConfig)
        if meta["config"].get("streams") not in ("lv", "none"):
            raise WeightsError(f"{path}: weights for any rig need a model without the GV stream (streams 'lv'), "
                               f"got streams {meta['config'].get('streams')!r}")
        return
    if (not isinstance(cams, list) or not cams or any(not isinstance(c, str) or not c for c in cams)
            or len(set(cams)) != len(cams)):
        raise WeightsError(f"{path}: metadata 'cameras' must be a list of distinct camera names, got {cams!r}")
    check_model_document(meta, path, BiMapperConfig)


def model_metadata(model: BiMapper, any_rig: bool = False) -> dict:
    """The metadata document describing ``model`` (see the module docstring); ``any_rig``: for
    every rig (:data:`ANY_RIG`; a :attr:`BiMapper.rig_free` model only).
    """
    cfg = model.config
    if any_rig and not model.rig_free:
        raise ConfigError("only a model without the GV stream (streams 'lv') maps any rig")
    return {
        "format": FORMAT, "version": VERSION, "method": "bimapper",
        "rig": ANY_RIG if any_rig else model.rig.name, "cameras": [] if any_rig else list(model.rig.names),
        "input_kind": cfg.input_kind, "classes": list(cfg.classes),
        "grid": model.grid.to_dict(), "input_size": list(model.input_size),
        "config": cfg.to_dict(),
    }


def save_weights(model: BiMapper, path: str | os.PathLike, any_rig: bool = False) -> Path:
    """Write ``model``'s parameters and buffers plus its metadata to ``path`` (atomically);
    ``any_rig``: as weights for every rig (:func:`model_metadata`).
    """
    return save_document(model, path, model_metadata(model, any_rig))


def _parse_metadata(path: Path) -> dict:
    """Open ``path`` with safetensors (header only), parse and sanity-check its Bi-Mapper document."""
    try:
        meta = read_document(path, FORMAT, VERSION, "Bi-Mapper")
    except WeightsError as e:
        if "not Bi-Mapper weights" in str(e):  # the message older callers and tests know
            raise WeightsError(f"{path}: metadata format is not {FORMAT!r}") from None
        raise
    missing = {"method", "rig", "cameras", "input_kind", "classes", "grid", "input_size", "config"} - set(meta)
    if missing:
        raise WeightsError(f"{path}: metadata lacks {sorted(missing)}")
    if meta["method"] != "bimapper":
        raise WeightsError(f"{path}: weights are for method {meta['method']!r}, not 'bimapper'")
    _check_schema(meta, path)
    return meta


def read_metadata(path: str | os.PathLike) -> dict:
    """Parse and sanity-check the metadata document of a weights file (tensors not loaded).

    A copy of :attr:`WeightsFile.meta` (the file is read once, see :meth:`WeightsFile.open`).

    Raises:
        WeightsError: missing file, not safetensors (e.g. a pickle), truncated/corrupt header,
            no or malformed Bi-Mapper metadata.
    """
    return copy.deepcopy(WeightsFile.open(path).meta)


def config_from_metadata(meta: dict, path: str | os.PathLike = "weights") -> tuple[BiMapperConfig, BevGrid]:
    """The architecture config and grid stored in a metadata document."""
    try:
        return BiMapperConfig.from_dict(meta["config"]), BevGrid.from_dict(meta["grid"])
    except (BevMapperError, TypeError, KeyError, ValueError, OverflowError) as e:
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
    if rig is not None and meta["rig"] != ANY_RIG:
        if meta["rig"] != rig.name:
            fail("rig", rig.name, meta["rig"])
        if list(meta["cameras"]) != list(rig.names):
            fail("cameras", list(rig.names), meta["cameras"])
    if input_kind is not None and meta["input_kind"] != input_kind:
        fail("input kind", input_kind, meta["input_kind"])
    if classes is not None and list(meta["classes"]) != list(classes):
        fail("classes", list(classes), meta["classes"])
    if grid is not None and not grid.isclose(stored_grid):
        fail("grid", grid.describe(), stored_grid.describe())
    if config is not None and config != stored_cfg:
        diff = [k for k, v in config.to_dict().items() if stored_cfg.to_dict()[k] != v]
        raise WeightsError(f"{path}: architecture differs from the requested one in {diff}")


class WeightsFile:
    """A Bi-Mapper weights file whose header and metadata document were read and checked once.

    Get one with :meth:`open`. The parsed metadata is cached per file (resolved path, inode,
    modification time and size), so the start-up checks (:meth:`check`, from the mapper's
    preflight) and the model construction (:meth:`build_model`) share one read of the header; a
    file replaced on disk is read again. Tensors are read only by :meth:`load_into` /
    :meth:`build_model`, once per call.

    Attributes:
        path: the path as the caller gave it (error messages name it).
        meta: the metadata document (see the module docstring); shared, do not modify.
    """

    _CACHE_SIZE = 8
    #: file version -> {"meta": document, "state": checked tensors or None, "validated": bool}
    _cache: "OrderedDict[tuple, dict]" = OrderedDict()
    _lock = threading.Lock()

    def __init__(self, path: str | os.PathLike, meta: dict, entry: dict | None = None) -> None:
        self.path = Path(path)
        self.meta = meta
        self._entry = entry if entry is not None else {"meta": meta, "state": None, "validated": False}

    @classmethod
    def open(cls, path: str | os.PathLike) -> "WeightsFile":
        """The weights file at ``path``, its metadata read at most once per file version.

        Raises:
            WeightsError: missing file, not safetensors (e.g. a pickle), truncated/corrupt
                header, no or malformed Bi-Mapper metadata.
        """
        path = Path(path)
        try:
            st = path.stat()
        except OSError:
            st = None
        problem = weights_file_problem(path)
        if st is None or problem is not None:
            raise WeightsError(f"weights file {path} {problem or 'does not exist'}")
        key = (str(path.resolve()), st.st_ino, st.st_mtime_ns, st.st_size)
        with cls._lock:
            entry = cls._cache.get(key)
            if entry is not None:
                cls._cache.move_to_end(key)
        if entry is None:
            entry = {"meta": _parse_metadata(path), "state": None, "validated": False}
            with cls._lock:
                cls._cache[key] = entry
                while len(cls._cache) > cls._CACHE_SIZE:
                    cls._cache.popitem(last=False)
        return cls(path, entry["meta"], entry)

    @classmethod
    def clear_cache(cls) -> None:
        """Forget every parsed metadata document (the next :meth:`open` reads the file)."""
        with cls._lock:
            cls._cache.clear()

    # ------------------------------------------------------------ metadata
    @property
    def rig_name(self) -> str:
        """Name of the rig the weights were trained for."""
        return self.meta["rig"]

    @property
    def cameras(self) -> tuple[str, ...]:
        """Camera names of that rig, in its order."""
        return tuple(self.meta["cameras"])

    @property
    def input_kind(self) -> str:
        """``labels`` or ``rgb``."""
        return self.meta["input_kind"]

    @property
    def classes(self) -> tuple[str, ...]:
        """Output classes of the model, in layer order."""
        return tuple(self.meta["classes"])

    @property
    def grid(self) -> BevGrid:
        """The BEV grid the weights were trained for."""
        return config_from_metadata(self.meta, self.path)[1]

    @property
    def config(self) -> BiMapperConfig:
        """The stored architecture."""
        return config_from_metadata(self.meta, self.path)[0]

    def check(self, *, rig_name: str | None = None, cameras: tuple[str, ...] | None = None,
              grid: BevGrid | None = None, input_kind: str | None = None,
              classes: tuple[str, ...] | None = None, hint: str = "") -> None:
        """Start-up checks against a configuration; ``None`` (or an empty rig name) is not checked.
        ``hint``: what a camera or grid refusal adds (the methods that run instead,
        :func:`~bev_mapper_core.methods.alternatives`).

        ``classes`` must be among the weights' classes (a subset, any order); ``cameras`` must
        be the stored names in the stored order; ``grid`` must be the stored grid
        (:meth:`BevGrid.isclose`).

        Raises:
            WeightsError: naming the first mismatch (input kind, rig, classes, cameras, grid).
        """
        path, meta = self.path, self.meta
        if input_kind is not None and meta["input_kind"] != input_kind:
            raise WeightsError(f"{path} is for input {meta['input_kind']!r}, configured input is {input_kind!r}")
        any_rig = meta["rig"] == ANY_RIG
        if rig_name and meta["rig"] != rig_name and not any_rig:
            raise WeightsError(f"{path} was trained for rig {meta['rig']!r}, not {rig_name!r}")
        unknown = [c for c in classes or () if c not in meta["classes"]]
        if unknown:
            raise WeightsError(f"{path}: classes {unknown} are not among the weights' classes {list(meta['classes'])}")
        if cameras is not None and list(cameras) != list(meta["cameras"]) and not any_rig:
            raise WeightsError(f"{path}: weights were trained for cameras {list(meta['cameras'])} (in this "
                               f"order), but {list(cameras)} are configured" + (f"; {hint}" if hint else ""))
        if grid is not None:
            try:
                check_metadata(meta, path, grid=grid)
            except WeightsError as e:
                raise WeightsError(f"{e}; use weights trained for this grid" + (f"; {hint}" if hint else "")) from None

    # ------------------------------------------------------------- tensors
    def load_into(self, model: BiMapper) -> None:
        """Load the tensors into an existing model after checking that they fit it exactly.

        Raises:
            WeightsError: metadata mismatch (rig, cameras, input kind, classes, grid, config,
                input size), a missing/extra tensor, a shape/dtype mismatch, non-finite values,
                corruption.
        """
        path, meta = self.path, self.meta
        check_metadata(meta, path, rig=model.rig, grid=model.grid, input_kind=model.config.input_kind,
                       classes=model.config.classes, config=model.config)
        if meta["rig"] != ANY_RIG and list(meta["input_size"]) != list(model.input_size):
            raise WeightsError(f"{path}: weights expect input size {meta['input_size']}, the model has {list(model.input_size)}")
        expected = model.state_dict()
        state = self._entry["state"]
        if state is None:
            state = self._read_tensors(expected)
            self._entry["state"] = state
        else:
            check_tensors(path, {k: (tuple(t.shape), t.dtype) for k, t in state.items()}, expected)
        model.load_state_dict(state, strict=True)

    def _read_tensors(self, expected: dict) -> dict:
        """Every tensor of the file, checked against ``expected`` (:func:`read_checked_tensors`)."""
        return read_checked_tensors(self.path, expected)

    def validate(self) -> None:
        """The full check a node needs before it starts: build the stored architecture for a
        stand-in rig of the stored cameras (the tensors' shapes do not depend on calibration)
        and load every tensor into it (names, shapes, dtypes, finite values). Done once per file
        version; the checked tensors are kept for :meth:`build_model`.

        Raises:
            WeightsError: the first problem found.
        """
        if self._entry["validated"]:
            return
        cfg, grid = config_from_metadata(self.meta, self.path)
        h, w = self.meta["input_size"]
        try:
            cams = tuple(self.meta["cameras"]) or ("cam0",)  # weights for any rig: one camera stands in
            model = BiMapper(cfg, standin_rig(self.meta["rig"], cams, (w, h)), grid)
        except (BevMapperError, ValueError, RuntimeError) as e:
            raise WeightsError(f"{self.path}: cannot build the stored model ({e})") from None
        self.load_into(model)
        self._entry["validated"] = True

    def build_model(self, rig: Rig, grid: BevGrid | None = None, *, input_kind: str | None = None,
                    classes: tuple[str, ...] | None = None,
                    device: str | torch.device = "cpu") -> BiMapper:
        """Build the model the file describes for ``rig``, load it, return it in eval mode.

        ``grid``, ``input_kind`` and ``classes`` (exact list) are checked when given. The rig
        must have the stored name and camera order; its calibration may differ (tables are
        rebuilt) as long as the model input size stays the same.
        """
        path = self.path
        check_metadata(self.meta, path, rig=rig, grid=grid, input_kind=input_kind, classes=classes)
        cfg, stored_grid = config_from_metadata(self.meta, path)
        try:
            model = BiMapper(cfg, rig, grid or stored_grid)
        except ConfigError as e:
            raise WeightsError(f"{path}: cannot build the stored model for rig {rig.name!r} ({e})") from None
        self.load_into(model)
        return model.to(device).eval()


def load_state(model: BiMapper, path: str | os.PathLike) -> None:
    """Load a weights file into an existing model after checking that it fits it exactly
    (:meth:`WeightsFile.load_into`).

    Raises:
        WeightsError: metadata mismatch (rig, cameras, input kind, classes, grid, config, input
            size), a missing/extra tensor, a shape/dtype mismatch, non-finite values, corruption.
    """
    WeightsFile.open(path).load_into(model)


def load_bimapper(path: str | os.PathLike, rig: Rig, grid: BevGrid | None = None, *,
                  input_kind: str | None = None, classes: tuple[str, ...] | None = None,
                  device: str | torch.device = "cpu") -> BiMapper:
    """Build the model a weights file describes for ``rig``, load it, and return it in eval mode
    (:meth:`WeightsFile.build_model`).

    ``grid``, ``input_kind`` and ``classes`` are checked when given. The rig must have the
    stored name and camera order; its calibration may differ (tables are rebuilt) as long as
    the model input size stays the same.
    """
    return WeightsFile.open(path).build_model(rig, grid, input_kind=input_kind, classes=classes, device=device)
