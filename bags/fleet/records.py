"""A finished bag's record (``evaluate.json``) and what ``--resume`` checks before trusting it.

The record carries the bag's *identity* (:func:`bag_identity`: its files' sizes and modification
times and a SHA-256 of ``metadata.yaml`` and of the first and last MiB of every storage file),
the options that define its results, and its own SHA-256 (``record_sha256``, over the rest of
the record). :func:`resumable` gives back a record only when it parses, holds every key with the
right type, hashes to its own ``record_sha256`` (a hand-edited count is not trusted), names the
same bag with the same identity (a bag replaced since is replayed again) and the bag's
``metrics.json`` is there; otherwise it says why, and the bag is replayed again.
"""

from __future__ import annotations

import hashlib
import json
import os
from pathlib import Path

from ..errors import BagError

#: Bytes hashed at each end of a storage file (its header and first chunk, its summary/index).
EDGE_BYTES = 1 << 20
#: Largest record read back (bytes): records hold a latency per frame.
MAX_RECORD_BYTES = 64 << 20
#: Keys of a record and their JSON types (``None`` allowed where the tuple says so).
RECORD_TYPES: dict[str, tuple[type, ...]] = {
    "name": (str,), "bag": (str,), "status": (str,), "error": (str, type(None)),
    "metrics": (dict,), "scoring": (dict, type(None)), "latencies_ms": (list,),
    "seconds": (int, float, type(None)), "cpu_seconds": (int, float, type(None)),
    "options": (dict,), "bag_identity": (dict,), "resumed": (bool,), "record_sha256": (str,),
}
#: Keys the aggregate reads from a record's ``metrics``.
METRIC_KEYS: dict[str, tuple[type, ...]] = {"frames": (int,), "frames_skipped": (int,)}


def _bag_files(bag: Path) -> list[Path]:
    if bag.is_dir():
        return sorted(p for p in bag.iterdir() if p.is_file())
    return [bag]


def bag_identity(bag: Path) -> dict:
    """What tells this bag from another at the same path, without reading it all: per file (the
    bag itself, or every file of a rosbag2 directory) its name, size and mtime, and a SHA-256 over
    those and the first and last :data:`EDGE_BYTES` of each file (``metadata.yaml`` whole).

    Raises:
        OSError: a file cannot be read.
    """
    h = hashlib.sha256()
    size, mtime = 0, 0
    for p in _bag_files(bag):
        st = p.stat()
        size += st.st_size
        mtime = max(mtime, st.st_mtime_ns)
        h.update(f"{p.name}\0{st.st_size}\0{st.st_mtime_ns}\0".encode())
        with open(p, "rb") as f:
            h.update(f.read(EDGE_BYTES))
            if st.st_size > 2 * EDGE_BYTES:
                f.seek(st.st_size - EDGE_BYTES)
                h.update(f.read(EDGE_BYTES))
            elif st.st_size > EDGE_BYTES:
                h.update(f.read())
    return {"bytes": size, "mtime_ns": mtime, "sha256": h.hexdigest()}


def _digest(record: dict) -> str:
    body = {k: v for k, v in record.items() if k != "record_sha256"}
    return hashlib.sha256(json.dumps(body, sort_keys=True, allow_nan=False).encode()).hexdigest()


def seal(record: dict) -> dict:
    """``record`` with its ``record_sha256``."""
    return {**record, "record_sha256": _digest(record)}


def read_record(path: Path, ok: str = "ok") -> dict | str:
    """The record at ``path``, or why it cannot be used (a short phrase). Only a record whose
    status is ``ok`` is checked key by key (the others are replayed again anyway).
    """
    try:
        if not path.exists():
            return "no record"
        if not path.is_file():
            return f"{path} is not a file"
        if path.stat().st_size > MAX_RECORD_BYTES:
            return f"{path} is too large"
        record = json.loads(path.read_bytes().decode("utf-8"))
    except OSError as exc:
        return f"{path} is unreadable ({exc.strerror or exc})"
    except (UnicodeDecodeError, ValueError, RecursionError):
        return f"{path} is damaged (not JSON)"
    if not isinstance(record, dict):
        return f"{path} is damaged (not a JSON object)"
    if record.get("status") != ok:
        return record
    for key, types in RECORD_TYPES.items():
        value = record.get(key, KeyError)
        if value is KeyError:
            return f"{path} is damaged (no {key!r})"
        if not isinstance(value, types) or (isinstance(value, bool) and bool not in types):
            return f"{path} is damaged ({key!r} is {type(value).__name__})"
    for key, types in METRIC_KEYS.items():
        value = record["metrics"].get(key)
        if not isinstance(value, types) or isinstance(value, bool):
            return f"{path} is damaged (metrics {key!r} is {type(value).__name__})"
    if not all(isinstance(v, (int, float)) and not isinstance(v, bool) for v in record["latencies_ms"]):
        return f"{path} is damaged (latencies_ms holds other than numbers)"
    try:
        same = _digest(record) == record["record_sha256"]
    except ValueError:  # NaN / infinity written by hand
        same = False
    if not same:
        return f"{path} was changed after it was written (its record_sha256 does not match)"
    return record


def resumable(bag: Path, record_path: Path, metrics_path: Path, wanted: dict, ok: str) -> tuple[dict | None, str]:
    """``(record, "")`` when the bag's record lets ``--resume`` skip it, else ``(None, why)``
    (``why`` is empty when there is simply nothing finished to resume).

    Raises:
        BagError: the bag was completed with other options (resuming would mix them).
    """
    record = read_record(record_path, ok)
    if isinstance(record, str):
        return None, "" if record == "no record" else record
    if record.get("status") != ok:
        return None, ""
    if record["bag"] != str(bag.resolve()):
        return None, f"{record_path} is of another bag ({record['bag']})"
    if record["options"] != wanted:
        theirs = record["options"]
        diff = sorted(k for k in set(wanted) | set(theirs) if wanted.get(k) != theirs.get(k))
        raise BagError(f"{record_path.parent} was evaluated with other options (they differ in {diff}); "
                       "pass the same options to resume, or --force to start over")
    try:
        identity = bag_identity(bag)
    except OSError as exc:
        return None, f"the bag cannot be read ({exc.strerror or exc})"
    if record["bag_identity"] != identity:
        theirs = record["bag_identity"]
        what = "size" if theirs.get("bytes") != identity["bytes"] else \
            "modification time" if theirs.get("mtime_ns") != identity["mtime_ns"] else "contents"
        return None, f"the bag changed since it was evaluated (its {what})"
    if not os.path.isfile(metrics_path):
        return None, f"{metrics_path} is missing"
    return record, ""


__all__ = ["EDGE_BYTES", "RECORD_TYPES", "bag_identity", "read_record", "resumable", "seal"]
