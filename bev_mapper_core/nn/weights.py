"""Weights files of every learned model: safetensors only (never ``torch.load`` / pickle), with a
JSON document in the header's ``__metadata__`` under :data:`META_KEY`. Every document may carry a
model card (``card``, :mod:`bev_mapper_core.nn.card`); the shipped files do.

The generic steps each method's ``weights.py`` builds on: :func:`read_document` (header only:
format and version checked), :func:`check_model_document` (the fields every model document
shares, bounded before anything is allocated), :func:`read_checked_tensors` /
:func:`cached_tensors` (every tensor against the model's state dict: names, shapes, dtypes,
finite values), :func:`standin_rig` (to build a stored architecture before any CameraInfo is
known) and :func:`save_document` (atomic write). Every problem raises :class:`WeightsError`.
"""

from __future__ import annotations

import json
import os
import threading
from pathlib import Path

import torch
from safetensors import safe_open
from safetensors.torch import save_file

from bev_mapper_core.errors import BevMapperError, ConfigError
from bev_mapper_core.geometry.camera import CameraModel
from bev_mapper_core.geometry.grid import MAX_GRID_CELLS, BevGrid
from bev_mapper_core.geometry.rig import Rig, RigCamera
from bev_mapper_core.labels.classes import resolve_classes
from bev_mapper_core.labels.label_maps import file_kind

from .card import CARD_KEY, CardError, check_card, check_card_fits
from .config import MAX_WIDTH_PX

META_KEY = "bev_mapper"


class WeightsError(BevMapperError, ValueError):
    """A weights file is unreadable, corrupt, or does not fit the requested model."""


def weights_file_problem(path: str | os.PathLike) -> str | None:
    """None when ``path`` is a regular file (links followed), else what it is, as the end of a
    sentence that starts with the path: ``"does not exist"``, ``"is a directory, not a weights
    file"``, ``"is a FIFO, not a regular file"``, ``"is a device (a link to /dev/zero), not a
    regular file"``. Looked at with ``stat`` only: a FIFO or a device is never opened (a FIFO
    never blocks, ``/dev/zero`` is never read).
    """
    kind = file_kind(Path(path))
    if kind == "file":
        return None
    if kind is None:
        return "does not exist" if not os.path.lexists(path) else "does not exist (a broken link)"
    link = f" (a link to {os.path.realpath(path)})" if os.path.islink(path) else ""
    if kind == "directory":
        return f"is a directory{link}, not a weights file"
    return f"is a {kind}{link}, not a regular file"


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


def save_document(model: torch.nn.Module, path: str | os.PathLike, meta: dict) -> Path:
    """Write ``model``'s parameters and buffers with the document ``meta`` to ``path``, atomically
    (a temporary file beside it, then renamed).
    """
    path = Path(path)
    tensors = {k: v.detach().cpu().contiguous() for k, v in model.state_dict().items()}
    tmp = path.with_name(path.name + ".tmp")
    save_file(tensors, str(tmp), metadata={META_KEY: json.dumps(meta, sort_keys=True)})
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
            header, no metadata, not JSON, another format or version, a malformed model card
            (:mod:`~bev_mapper_core.nn.card`: the optional ``card`` object).
    """
    path = Path(path)
    problem = weights_file_problem(path)
    if problem is not None:
        raise WeightsError(f"{what} weights {path} {problem}")
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
    if CARD_KEY in meta:  # optional; a malformed one is refused (keys the format does not know are ignored)
        try:
            check_card_fits(check_card(meta[CARD_KEY]), meta)
        except CardError as e:
            raise WeightsError(f"{path}: bad model card ({e})") from None
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
            check_tensors(path, header, expected)
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


_DTYPES = {"F32": torch.float32, "F64": torch.float64, "F16": torch.float16, "BF16": torch.bfloat16,
           "I64": torch.int64, "I32": torch.int32, "I16": torch.int16, "I8": torch.int8, "U8": torch.uint8,
           "BOOL": torch.bool}


def check_tensors(path: Path, found: dict, expected: dict) -> None:
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
        check_tensors(path, {k: (tuple(t.shape), t.dtype) for k, t in state.items()}, expected)
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
