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
import json
import os
import threading
from collections import OrderedDict
from pathlib import Path

import torch
from safetensors import safe_open
from safetensors.torch import save_file

from bev_mapper_core.errors import BevMapperError, ConfigError
from bev_mapper_core.geometry.camera import CameraModel
from bev_mapper_core.geometry.grid import MAX_GRID_CELLS, BevGrid
from bev_mapper_core.geometry.rig import Rig, RigCamera
from bev_mapper_core.labels.classes import resolve_classes

from .config import MAX_WIDTH_PX
from .model import BiMapper, BiMapperConfig

FORMAT = "bev_mapper.bimapper"
VERSION = 1
META_KEY = "bev_mapper"




class WeightsError(BevMapperError, ValueError):
    """A weights file is unreadable, corrupt, or does not fit the requested model."""


def check_model_document(meta: dict, path: Path, config_type: type) -> tuple:
    """The part of a model weights document every method shares: ``input_kind``, ``classes``,
    ``input_size``, ``config`` (built as ``config_type``, whose own bounds apply) and ``grid``
    (at most :data:`~bev_mapper_core.geometry.grid.MAX_GRID_CELLS` cells), and their agreement.
    Returns ``(config, grid)``.

    Raises:
        WeightsError: the first problem found.
    """
    def bad(what: str) -> WeightsError:
        return WeightsError(f"{path}: metadata {what}")

    if meta["input_kind"] not in ("labels", "rgb"):
        raise bad(f"'input_kind' must be 'labels' or 'rgb', got {meta['input_kind']!r}")
    classes = meta["classes"]
    if not isinstance(classes, list) or not classes or any(not isinstance(c, str) for c in classes):
        raise bad(f"'classes' must be a list of class names, got {classes!r}")
    try:
        resolve_classes(tuple(classes))
    except ConfigError as e:
        raise bad(f"names an unknown class ({e})") from None
    size = meta["input_size"]
    if (not isinstance(size, list) or len(size) != 2
            or any(isinstance(v, bool) or not isinstance(v, int) or not 1 <= v <= MAX_WIDTH_PX for v in size)):
        raise bad(f"'input_size' must be [height, width] in 1..{MAX_WIDTH_PX}, got {size!r}")
    if not isinstance(meta["config"], dict) or not isinstance(meta["grid"], dict):
        raise bad("'config' and 'grid' must be mappings")
    try:  # bounded by the config's and BevGrid's own checks
        cfg, grid = config_type.from_dict(meta["config"]), BevGrid.from_dict(meta["grid"])
    except (BevMapperError, TypeError, KeyError, ValueError, OverflowError) as e:
        raise WeightsError(f"{path}: stored config/grid is invalid ({e})") from None
    if grid.width * grid.height > MAX_GRID_CELLS:
        raise bad(f"grid has {grid.width} x {grid.height} cells, more than {MAX_GRID_CELLS}")
    if cfg.input_kind != meta["input_kind"] or list(cfg.classes) != list(classes):
        raise bad("'input_kind' / 'classes' differ from the stored architecture's")
    if size[1] != cfg.input_width:
        raise bad(f"'input_size' width {size[1]} differs from the architecture's input_width {cfg.input_width}")
    return cfg, grid


def _check_schema(meta: dict, path: Path) -> None:
    """Types and bounds of a Bi-Mapper metadata document (see the module docstring)."""
    if not isinstance(meta["rig"], str):
        raise WeightsError(f"{path}: metadata 'rig' must be a string, got {meta['rig']!r}")
    cams = meta["cameras"]
    if (not isinstance(cams, list) or not cams or any(not isinstance(c, str) or not c for c in cams)
            or len(set(cams)) != len(cams)):
        raise WeightsError(f"{path}: metadata 'cameras' must be a list of distinct camera names, got {cams!r}")
    check_model_document(meta, path, BiMapperConfig)


def model_metadata(model: BiMapper) -> dict:
    """The metadata document describing ``model`` (see the module docstring)."""
    cfg = model.config
    return {
        "format": FORMAT, "version": VERSION, "method": "bimapper",
        "rig": model.rig.name, "cameras": list(model.rig.names),
        "input_kind": cfg.input_kind, "classes": list(cfg.classes),
        "grid": model.grid.to_dict(), "input_size": list(model.input_size),
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


def read_document(path: str | os.PathLike, fmt: str, version: int, what: str) -> dict:
    """The ``bev_mapper`` metadata document of a safetensors weights file (header only), with
    its ``format`` and ``version`` checked; the shared first step of every weights reader.

    Args:
        fmt, version: the document's expected ``format`` / ``version``.
        what: the kind of weights, for messages (``Bi-Mapper``, ``segmenter``, ...).

    Raises:
        WeightsError: missing file, not safetensors (e.g. a pickle), truncated or corrupt
            header, no metadata, not JSON, another format or version.
    """
    path = Path(path)
    if not path.is_file():
        raise WeightsError(f"{what} weights {path} do not exist")
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
    if not isinstance(meta, dict) or meta.get("format") != fmt:
        got = meta.get("format") if isinstance(meta, dict) else None
        raise WeightsError(f"{path}: not {what} weights (format {got!r}, expected {fmt!r})")
    if meta.get("version") != version:
        raise WeightsError(f"{path}: metadata version {meta.get('version')!r}, this code reads {version}")
    return meta


def read_checked_tensors(path: str | os.PathLike, expected: dict) -> dict:
    """Every tensor of ``path`` after its header matched ``expected`` (a model's state dict:
    names, shapes, dtypes; nothing is read for a file that does not fit), each checked for
    non-finite values.

    Raises:
        WeightsError: the first mismatch, a non-finite value, or an unreadable file.
    """
    path = Path(path)
    try:
        with safe_open(str(path), framework="pt") as f:
            header = {k: (tuple(f.get_slice(k).get_shape()), _DTYPES.get(f.get_slice(k).get_dtype()))
                      for k in f.keys()}
            _check_tensors(path, header, expected)
            state = {}
            for k in expected:
                t = f.get_tensor(k)
                if t.is_floating_point() and not torch.isfinite(t).all():
                    raise WeightsError(f"{path}: tensor {k!r} has non-finite values")
                state[k] = t
    except WeightsError:
        raise
    except Exception as e:
        raise WeightsError(f"{path}: cannot read tensors ({e})") from None
    return state


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
    if rig is not None:
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
        if st is None or not path.is_file():
            raise WeightsError(f"weights file {path} does not exist")
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
              classes: tuple[str, ...] | None = None) -> None:
        """Start-up checks against a configuration; ``None`` (or an empty rig name) is not checked.

        ``classes`` must be among the weights' classes (a subset, any order); ``cameras`` must
        be the stored names in the stored order; ``grid`` must be the stored grid
        (:meth:`BevGrid.isclose`).

        Raises:
            WeightsError: naming the first mismatch (input kind, rig, classes, cameras, grid).
        """
        path, meta = self.path, self.meta
        if input_kind is not None and meta["input_kind"] != input_kind:
            raise WeightsError(f"{path} is for input {meta['input_kind']!r}, configured input is {input_kind!r}")
        if rig_name and meta["rig"] != rig_name:
            raise WeightsError(f"{path} was trained for rig {meta['rig']!r}, not {rig_name!r}")
        unknown = [c for c in classes or () if c not in meta["classes"]]
        if unknown:
            raise WeightsError(f"{path}: classes {unknown} are not among the weights' classes {list(meta['classes'])}")
        if cameras is not None and list(cameras) != list(meta["cameras"]):
            raise WeightsError(f"{path}: weights were trained for cameras {list(meta['cameras'])} (in this "
                               f"order), but {list(cameras)} are configured; or use method 'ipm'")
        if grid is not None:
            try:
                check_metadata(meta, path, grid=grid)
            except WeightsError as e:
                raise WeightsError(f"{e}; use weights trained for this grid, or method 'ipm'") from None

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
        if list(meta["input_size"]) != list(model.input_size):
            raise WeightsError(f"{path}: weights expect input size {meta['input_size']}, the model has {list(model.input_size)}")
        expected = model.state_dict()
        state = self._entry["state"]
        if state is None:
            state = self._read_tensors(expected)
            self._entry["state"] = state
        else:
            _check_tensors(path, {k: (tuple(t.shape), t.dtype) for k, t in state.items()}, expected)
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
            model = BiMapper(cfg, standin_rig(self.meta["rig"], tuple(self.meta["cameras"]), (w, h)), grid)
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


_DTYPES = {"F32": torch.float32, "F64": torch.float64, "F16": torch.float16, "BF16": torch.bfloat16,
           "I64": torch.int64, "I32": torch.int32, "I16": torch.int16, "I8": torch.int8, "U8": torch.uint8,
           "BOOL": torch.bool}


def _check_tensors(path: Path, found: dict, expected: dict) -> None:
    """``found`` (name -> (shape, dtype)) against a model's ``expected`` state dict."""
    missing, extra = sorted(set(expected) - set(found)), sorted(set(found) - set(expected))
    if missing or extra:
        raise WeightsError(f"{path}: tensors missing {missing[:5]}{'...' if len(missing) > 5 else ''}, "
                           f"unexpected {extra[:5]}{'...' if len(extra) > 5 else ''}")
    for k, ref in expected.items():
        shape, dtype = found[k]
        if shape != tuple(ref.shape):
            raise WeightsError(f"{path}: tensor {k!r} has shape {shape}, the model needs {tuple(ref.shape)}")
        if dtype != ref.dtype:
            raise WeightsError(f"{path}: tensor {k!r} is {dtype}, the model needs {ref.dtype}")


#: (what, file version) -> checked tensors (name -> tensor): the last file of each format
_CACHED: dict[tuple, dict[str, torch.Tensor]] = {}
_CACHED_LOCK = threading.Lock()


def cached_tensors(path: Path, expected: dict, what: str) -> dict[str, torch.Tensor]:
    """Every tensor of ``path`` after its header matched ``expected`` (nothing is read for a
    file that does not fit), each checked for non-finite values; cached per file version, the
    last file of each ``what`` (``S2G2``, ``FocusBEV``: a node loads one).

    Raises:
        WeightsError: an unreadable file, or tensors that do not fit ``expected``.
    """
    try:
        st = path.stat()
    except OSError as e:
        raise WeightsError(f"{what} weights {path}: {e.strerror or e}") from None
    key = (what, str(path.resolve()), st.st_ino, st.st_size, st.st_mtime_ns)
    with _CACHED_LOCK:
        state = _CACHED.get(key)
    if state is not None:
        _check_tensors(path, {k: (tuple(t.shape), t.dtype) for k, t in state.items()}, expected)
        return state
    state = read_checked_tensors(path, expected)
    with _CACHED_LOCK:
        for k in [k for k in _CACHED if k[0] == what]:
            del _CACHED[k]
        _CACHED[key] = state
    return state


def standin_rig(name: str, cameras: tuple[str, ...], size: tuple[int, int]) -> Rig:
    """A rig of forward-looking pinhole cameras delivering ``size`` = (width, height) images.

    The model's tensors depend on the number of cameras and the input size only, so this rig
    lets :meth:`WeightsFile.validate` build the stored architecture before any CameraInfo is known.
    """
    w, h = size
    K = ((w / 2.0, 0.0, w / 2.0), (0.0, w / 2.0, h / 2.0), (0.0, 0.0, 1.0))
    # optical z forward = ego x, optical x right = ego -y, optical y down = ego -z; 1.5 m up
    ego_from_cam = ((0.0, 0.0, 1.0, 0.0), (-1.0, 0.0, 0.0, 0.0), (0.0, -1.0, 0.0, 1.5), (0.0, 0.0, 0.0, 1.0))
    model = CameraModel(K=K, D=(0.0,) * 5, width=w, height=h)
    return Rig(name or "standin", tuple(RigCamera(c, model, ego_from_cam) for c in cameras))


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
