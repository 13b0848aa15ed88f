"""Files that appear complete or not at all: every output of the bag tool is written under a
hidden temporary name beside its target and renamed into place when complete.

:func:`partial_name` is that temporary name (``<dir>/.<name>.partial-<pid>``, one per process),
:func:`write_atomic` writes a file through it, :func:`remove_path` deletes a file or a directory
tree, and :func:`remove_partials` removes what an interrupted run left under such names
(:func:`remove_dead_partials`: only those of processes that no longer run).
"""

from __future__ import annotations

import glob
import os
import shutil
from pathlib import Path

#: Glob of the temporary names :func:`partial_name` gives (any process).
PARTIAL_GLOB = ".*.partial-*"


def partial_name(path: str | Path) -> Path:
    """The hidden temporary name ``<dir>/.<name>.partial-<pid>`` used while writing ``path``."""
    path = Path(path)
    return path.parent / f".{path.name}.partial-{os.getpid()}"


def write_atomic(path: str | Path, data: bytes) -> Path:
    """Write ``data`` to ``path`` via a temporary file and a rename (no half-written file)."""
    path = Path(path)
    tmp = partial_name(path)
    try:
        with open(tmp, "wb") as f:
            f.write(data)
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)
    finally:
        if tmp.exists():
            tmp.unlink()
    return path


def remove_path(path: Path) -> None:
    """Remove a file, a symlink (not its target) or a directory tree; nothing if absent."""
    if path.is_dir() and not path.is_symlink():
        shutil.rmtree(path)
    elif path.exists() or path.is_symlink():
        path.unlink()


def remove_partials(directory: Path) -> None:
    """Remove what an interrupted earlier run left under temporary names in ``directory``
    (a killed process cannot clean up); only call it where nothing else is writing.
    """
    for p in directory.glob(PARTIAL_GLOB):
        if p.is_dir():
            shutil.rmtree(p, ignore_errors=True)
        else:
            p.unlink(missing_ok=True)


def _alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:  # another user's process
        return True
    return True


def remove_dead_partials(path: str | Path) -> list[Path]:
    """Remove the temporary names of ``path`` (``<dir>/.<name>.partial-<pid>``) whose process no
    longer runs (killed before it could clean up, e.g. by SIGKILL); a live writer's are kept, so
    this is safe where another process may write. Returns what was removed.
    """
    path = Path(path)
    removed = []
    for p in path.parent.glob(f".{glob.escape(path.name)}.partial-*"):
        pid = p.name.rpartition("-")[2]
        if pid.isdigit() and not _alive(int(pid)):
            remove_path(p)
            removed.append(p)
    return removed


__all__ = ["PARTIAL_GLOB", "partial_name", "remove_dead_partials", "remove_partials", "remove_path",
           "write_atomic"]
