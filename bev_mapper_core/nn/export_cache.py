"""The ONNX export cache, verified before use.

Beside each exported model ``<key>.onnx`` lies ``<key>.json``, a record of what the model was made
from and of the file itself::

    {"format": 1,
     "made_from": {"weights_sha256": ..., "calibration_sha256": ..., "inputs": [[shape, dtype], ...],
                   "exporter": {"torch": ..., "opset": 18}, "package": ...},
     "backend": "openvino",                 # the backend that asked for the export
     "runtimes": {"openvino": "2026.4.1"},  # runtimes (and versions) that loaded the file
     "onnx_sha256": ..., "onnx_bytes": ...}

``weights_sha256`` hashes the module's parameters, ``calibration_sha256`` its buffers (the
calibration-dependent tables live there), ``inputs`` the example inputs' shapes and dtypes. The key
(the file name) is a hash of ``made_from``. Before a cached model is used, its record must exist,
parse, carry the same ``made_from``, and the file's size and SHA-256 must match; then the runtime
loads it. Anything else (no or a damaged record, a record of other weights, a truncated, emptied,
overwritten or bit-flipped file, a directory in its place, a runtime that refuses the file) means
"export again", said once in the log (logger ``bev_mapper.export_cache``), never a traceback and
never a stale model. The ONNX file itself does not depend on the runtime, so both runtimes share
one export; each records its version in ``runtimes`` when it loads the file.

Files are written under a temporary name in the cache directory and renamed when complete
(:func:`part_path`: ``.<key>.<pid>.<random>.onnx.part``, records ``.json.part``), so an
interrupted export leaves no partial model under a model's name; its part file is removed by the
exporter, or, where the process was killed, by the next export in that directory
(:func:`remove_stale_parts`: part files of processes that no longer run, and the ``tmp*.onnx`` /
``tmp*.json`` files of earlier versions once they are :data:`LEGACY_TMP_AGE_S` old).
"""

from __future__ import annotations

import hashlib
import json
import logging
import os
import re
import shutil
import time
import uuid
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import TypeVar

import torch

from ..errors import ConfigError
from .export_process import ExportCancelled

log = logging.getLogger("bev_mapper.export_cache")

#: Version of the record's layout (a record of another format is re-exported).
CACHE_FORMAT = 1
#: ONNX opset of the exports.
OPSET = 18
#: Largest record read (bytes).
MAX_RECORD_BYTES = 1 << 16
#: Age (s) after which a ``tmp*.onnx`` / ``tmp*.json`` of an earlier version is stale.
LEGACY_TMP_AGE_S = 600.0
_RUNTIME_MODULES = {"onnxruntime": "onnxruntime", "openvino": "openvino"}
_PART = re.compile(r"\.[^/]*\.(\d+)\.[0-9a-f]+\.(onnx|json)\.part")
_LEGACY_TMP = re.compile(r"tmp[A-Za-z0-9_]+\.(onnx|json)")

T = TypeVar("T")


def _tensor_hash(tensors) -> str:
    h = hashlib.sha256()
    for name, t in tensors:
        h.update(name.encode())
        h.update(str((tuple(t.shape), t.dtype)).encode())
        h.update(t.detach().cpu().contiguous().numpy().tobytes())
    return h.hexdigest()


def package_version() -> str:
    """This package's version (``bev_mapper_core.__version__``, the one setup.py installs)."""
    from .. import __version__  # noqa: PLC0415

    return str(__version__)


def runtime_version(backend: str) -> str:
    """The version of ``backend``'s Python package ("unknown" when it says none)."""
    import importlib  # noqa: PLC0415

    try:
        return str(getattr(importlib.import_module(_RUNTIME_MODULES[backend]), "__version__", "unknown"))
    except (ImportError, KeyError):
        return "unknown"


def made_from(module: torch.nn.Module, inputs: Sequence[torch.Tensor]) -> dict:
    """What an export of ``module`` on ``inputs`` depends on (JSON-ready): the weights, the
    calibration tables (buffers), the inputs' shapes and dtypes, the exporter and this package.
    """
    return {
        "weights_sha256": _tensor_hash(module.named_parameters()),
        "calibration_sha256": _tensor_hash(module.named_buffers()),
        "inputs": [[list(t.shape), str(t.dtype)] for t in inputs],
        "exporter": {"torch": torch.__version__, "opset": OPSET},
        "package": package_version(),
    }


def cache_key(made: dict) -> str:
    """The file name stem of an export made from ``made``."""
    return hashlib.sha256(json.dumps(made, sort_keys=True).encode()).hexdigest()[:32]


def file_sha256(path: Path) -> str:
    """SHA-256 of a file's bytes."""
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for block in iter(lambda: f.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()


def record_path(model: Path) -> Path:
    """The record beside an exported model."""
    return model.with_suffix(".json")


def _read_record(path: Path) -> dict | str:
    """The record at ``path``, or why it cannot be used."""
    try:
        with open(path, "rb") as f:
            data = f.read(MAX_RECORD_BYTES + 1)
    except FileNotFoundError:
        return "it has no record of what it was made from"
    except OSError as exc:
        return f"its record is unreadable ({exc.strerror or exc})"
    if len(data) > MAX_RECORD_BYTES:
        return "its record is too large"
    try:
        record = json.loads(data.decode("utf-8"))
    except (UnicodeDecodeError, ValueError):
        return "its record is damaged (not JSON)"
    if not isinstance(record, dict) or record.get("format") != CACHE_FORMAT:
        return "its record is of another format"
    return record


def check_cached(model: Path, made: dict) -> str | None:
    """None when ``model`` is a usable export made from ``made``, else why not (a short phrase)."""
    if not model.exists():
        return "absent"
    if not model.is_file():
        return "it is not a regular file"
    record = _read_record(record_path(model))
    if isinstance(record, str):
        return record
    if record.get("made_from") != made:
        return "it was made from other weights, calibration, inputs or versions"
    try:
        size = model.stat().st_size
        if size != record.get("onnx_bytes"):
            return f"it has {size} bytes, its record says {record.get('onnx_bytes')}"
        if file_sha256(model) != record.get("onnx_sha256"):
            return "its contents differ from its record (damaged or replaced)"
    except OSError as exc:
        return f"it is unreadable ({exc.strerror or exc})"
    return None


def part_path(final: Path) -> Path:
    """A temporary name for ``final`` in its directory, unique to this process and call, that
    :func:`remove_stale_parts` recognises once this process is gone.
    """
    return final.parent / f".{final.stem}.{os.getpid()}.{uuid.uuid4().hex[:12]}{final.suffix}.part"


def _pid_alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except OSError:  # another user's process: alive
        return True
    return True


def remove_stale_parts(directory: Path) -> list[Path]:
    """Remove the part files of exports whose process no longer runs, and the ``tmp*.onnx`` /
    ``tmp*.json`` files earlier versions left when interrupted (once :data:`LEGACY_TMP_AGE_S`
    old); returns what was removed. Best effort: an unreadable directory removes nothing.
    """
    removed = []
    try:
        entries = list(os.scandir(directory))
    except OSError:
        return removed
    now = time.time()
    for entry in entries:
        m = _PART.fullmatch(entry.name)
        try:
            if m is not None:
                stale = int(m.group(1)) != os.getpid() and not _pid_alive(int(m.group(1)))
            elif _LEGACY_TMP.fullmatch(entry.name):
                stale = now - entry.stat(follow_symlinks=False).st_mtime > LEGACY_TMP_AGE_S
            else:
                continue
            if stale and not entry.is_dir(follow_symlinks=False):
                os.unlink(entry.path)
                removed.append(Path(entry.path))
        except OSError:
            continue
    if removed:
        log.warning("export cache: removed %d partial file(s) of interrupted exports in %s", len(removed), directory)
    return removed


def _write_json(path: Path, record: dict) -> None:
    tmp = part_path(path)
    try:
        with open(tmp, "w") as f:
            json.dump(record, f, indent=1, sort_keys=True)
        os.replace(tmp, path)
    finally:
        if os.path.lexists(tmp):
            os.unlink(tmp)


def _remove(model: Path) -> None:
    for p in (model, record_path(model)):
        try:
            if p.is_dir() and not p.is_symlink():
                shutil.rmtree(p)
            elif p.exists() or p.is_symlink():
                p.unlink()
        except OSError:
            pass  # the export's os.replace will say what is wrong


def _short(exc: BaseException) -> str:
    text = " ".join(str(exc).split()) or type(exc).__name__
    return text if len(text) <= 200 else text[:200] + "..."


def load_cached(module: torch.nn.Module, inputs: Sequence[torch.Tensor], backend: str, directory: Path,
                export: Callable[[torch.nn.Module, Sequence[torch.Tensor], Path], Path],
                load: Callable[[Path], T], fresh: bool = False) -> tuple[T, Path]:
    """``load(path)`` of the verified export of ``module`` on ``inputs`` in ``directory``: the
    cached file when its record and hash match and ``backend`` loads it, else exported again
    (``export(module, inputs, path)``, said once in the log) and loaded. ``fresh``: export again
    whatever the cache holds (a cached model that failed at run time).

    Raises:
        ExportCancelled: ``export`` was stopped (the program stops); nothing was written.
        ConfigError: the export failed, or the runtime refuses even a fresh export.
    """
    made = made_from(module, inputs)
    model = directory / f"{cache_key(made)}.onnx"
    reason = "a fresh export was asked for (the cached model failed)" if fresh else check_cached(model, made)
    if reason is None:
        try:
            loaded = load(model)
        except Exception as exc:  # noqa: BLE001 - every runtime raises its own kinds
            reason = f"{backend} refused to load it ({_short(exc)})"
        else:
            _note_runtime(model, backend)
            return loaded, model
    if reason != "absent":
        log.warning("export cache: %s is not used: %s; exporting again", model, reason)
    _remove(model)
    directory.mkdir(parents=True, exist_ok=True)
    remove_stale_parts(directory)
    log.warning("export cache: exporting the model to ONNX for %s (once per weights and calibration; "
                "later starts reuse %s) ...", backend, model)
    started = time.perf_counter()
    part = part_path(model)
    try:
        export(module, inputs, part)  # complete, or nothing under the model's name
        record = {"format": CACHE_FORMAT, "made_from": made, "backend": backend, "runtimes": {},
                  "onnx_sha256": file_sha256(part), "onnx_bytes": part.stat().st_size}
        os.replace(part, model)
        _write_json(record_path(model), record)
        log.warning("export cache: exported in %.1f s", time.perf_counter() - started)
    except ExportCancelled:
        raise
    except Exception as exc:  # noqa: BLE001 - the exporter raises many kinds
        raise ConfigError(f"could not export the model to ONNX for backend {backend!r} in {directory} "
                          f"({_short(exc)}); use backend 'torch'") from None
    finally:
        if os.path.lexists(part):
            try:
                os.unlink(part)
            except OSError:
                pass
    try:
        loaded = load(model)
    except Exception as exc:  # noqa: BLE001
        raise ConfigError(f"backend {backend!r} cannot load the freshly exported model {model} ({_short(exc)}); "
                          "use backend 'torch'") from None
    _note_runtime(model, backend)
    return loaded, model


def _note_runtime(model: Path, backend: str) -> None:
    """Record ``backend``'s version in the model's record (best effort: a read-only cache is fine)."""
    record = _read_record(record_path(model))
    if isinstance(record, str):
        return
    version = runtime_version(backend)
    runtimes = record.get("runtimes") if isinstance(record.get("runtimes"), dict) else {}
    if runtimes.get(backend) == version:
        return
    record["runtimes"] = {**runtimes, backend: version}
    try:
        _write_json(record_path(model), record)
    except OSError:
        pass


__all__ = ["CACHE_FORMAT", "LEGACY_TMP_AGE_S", "OPSET", "cache_key", "check_cached", "file_sha256", "load_cached",
           "made_from", "package_version", "part_path", "record_path", "remove_stale_parts", "runtime_version"]
