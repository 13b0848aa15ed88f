"""The ONNX export in a process of its own (issue #41), for callers that must stay responsive
while a model is exported (the node maps with torch meanwhile) and must stop at any moment.

An export takes 7-35 s on a 2-core machine (PyTorch's dynamo exporter, in C++ and Python). Run in
a thread, a signal that ends the program during it ended the interpreter under that thread
(``terminate called without an active exception``, exit -6). Here the parent pickles the module
and its example inputs to a child (``python -m bev_mapper_core.nn.export_process PART THREADS``,
its standard input: one JSON line with the parent's ``sys.path``, then the pickle), which writes
``PART`` (a temporary name in the cache directory that the caller renames when the child
succeeded). The child is in a session of its own and ignores SIGINT, so a Ctrl-C reaches the
parent only, which decides: :func:`cancel_exports` (or the caller's ``cancel`` event) stops the
child (SIGTERM, then SIGKILL) and removes ``PART``. A child whose parent died removes ``PART``
and exits within a second.

This module imports no torch (the child does): a node that maps with IPM stays torch-free.
"""

from __future__ import annotations

import json
import os
import pickle
import signal
import subprocess
import sys
import tempfile
import threading
import time
from collections.abc import Sequence
from pathlib import Path

from ..errors import ConfigError

#: The child's exit status when it cannot rebuild the module (its class is not importable there).
EXIT_UNPICKLE = 3
#: Seconds a stopped child gets between SIGTERM and SIGKILL.
TERM_GRACE_S = 2.0
#: How often the parent looks at the child and at cancellation, and the child at its parent (s).
POLL_S = 0.1
_PACKAGE_ROOT = str(Path(__file__).resolve().parents[2])


class ExportCancelled(ConfigError):
    """The export was stopped before it finished (the program stops): nothing was written."""


class ChildCannotImport(ConfigError):
    """The child could not rebuild the module (e.g. a class defined in ``__main__``)."""


_LIVE: dict[int, tuple[subprocess.Popen, Path]] = {}
_LOCK = threading.Lock()
_CANCELLED = threading.Event()


def cancel_exports() -> int:
    """Stop every export child of this process and remove their partial files; exports asked
    for later raise :class:`ExportCancelled` at once. Returns how many children were running.
    """
    _CANCELLED.set()
    with _LOCK:
        live = list(_LIVE.values())
    for proc, part in live:
        _stop_child(proc, part)
    return len(live)


def exports_cancelled() -> bool:
    """True after :func:`cancel_exports`."""
    return _CANCELLED.is_set()


def _stop_child(proc: subprocess.Popen, part: Path) -> None:
    if proc.poll() is None:
        try:
            proc.terminate()
            proc.wait(TERM_GRACE_S)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait()
        except OSError:
            pass
    _unlink(part)


def _unlink(path: Path) -> None:
    try:
        path.unlink()
    except FileNotFoundError:
        pass
    except OSError:
        pass  # a read-only cache: the stale-part clean-up of a later start retries


def export_in_child(module, inputs: Sequence, part: Path, threads: int = 1,
                    cancel: threading.Event | None = None) -> Path:
    """Export ``module`` on ``inputs`` to ``part`` in a child process (module docstring); waits
    for it, or stops it as soon as ``cancel`` is set or :func:`cancel_exports` is called.

    Raises:
        ExportCancelled: stopped before it finished (``part`` removed).
        ChildCannotImport: the child could not rebuild the module (the caller may export in
            this process instead).
        ConfigError: the export failed in the child (its last error line).
    """
    if _CANCELLED.is_set() or (cancel is not None and cancel.is_set()):
        raise ExportCancelled("the export was cancelled")
    head = (json.dumps(list(sys.path)) + "\n").encode()
    payload = pickle.dumps((module, list(inputs)), protocol=pickle.HIGHEST_PROTOCOL)
    env = dict(os.environ, PYTHONPATH=os.pathsep.join([_PACKAGE_ROOT, os.environ.get("PYTHONPATH", "")]).rstrip(os.pathsep))
    with tempfile.TemporaryFile() as errors:
        proc = subprocess.Popen([sys.executable, "-m", __name__, str(part), str(max(1, int(threads)))],
                                stdin=subprocess.PIPE, stdout=subprocess.DEVNULL, stderr=errors, env=env,
                                start_new_session=True)  # a terminal's Ctrl-C is the parent's to handle
        with _LOCK:
            _LIVE[proc.pid] = (proc, part)
        try:
            if _CANCELLED.is_set():  # cancel_exports ran between the check above and the registration
                raise ExportCancelled("the export was cancelled")
            try:
                proc.stdin.write(head)
                proc.stdin.write(payload)
                proc.stdin.close()
            except (BrokenPipeError, ValueError, OSError):
                pass  # the child is gone (stopped, or failed early): its status says which
            while True:
                try:
                    code = proc.wait(POLL_S)
                    break
                except subprocess.TimeoutExpired:
                    if _CANCELLED.is_set() or (cancel is not None and cancel.is_set()):
                        _stop_child(proc, part)
                        raise ExportCancelled("the export was cancelled") from None
            if _CANCELLED.is_set() or (cancel is not None and cancel.is_set()):
                raise ExportCancelled("the export was cancelled")
            if code != 0:
                errors.seek(0)
                lines = [ln for ln in errors.read().decode(errors="replace").splitlines() if ln.strip()]
                last = lines[-1].strip() if lines else f"exit status {code}"
                if code == EXIT_UNPICKLE:
                    raise ChildCannotImport(last)
                raise ConfigError(last.removeprefix("error: "))
            if not part.is_file():
                raise ConfigError("the export process wrote no file")
            return part
        except BaseException:
            _stop_child(proc, part)
            raise
        finally:
            with _LOCK:
                _LIVE.pop(proc.pid, None)


def _watch_parent(parent: int, part: Path) -> None:
    """In the child: remove ``part`` and exit as soon as the parent is gone."""
    while True:
        time.sleep(POLL_S * 5)
        if os.getppid() != parent:
            _unlink(part)
            os._exit(1)


def main(argv: list[str] | None = None) -> int:
    """The child: read the JSON ``sys.path`` line and the pickled ``(module, inputs)`` from
    standard input, export to ``PART`` with ``THREADS`` torch threads; exit 0, or
    :data:`EXIT_UNPICKLE`, or 1 with an ``error: ...`` line.
    """
    argv = list(sys.argv[1:] if argv is None else argv)
    signal.signal(signal.SIGINT, signal.SIG_IGN)  # the parent decides; SIGTERM ends the child
    part, threads = Path(argv[0]), int(argv[1])
    threading.Thread(target=_watch_parent, args=(os.getppid(), part), daemon=True).start()
    try:
        paths = json.loads(sys.stdin.buffer.readline())
        sys.path[:] = [p for p in paths if isinstance(p, str)] + [p for p in sys.path if p not in paths]
        import torch  # noqa: PLC0415 - the child only

        torch.set_num_threads(threads)
        module, inputs = pickle.loads(sys.stdin.buffer.read())  # noqa: S301 - from our own parent process
    except Exception as exc:  # noqa: BLE001 - whatever unpickling raises
        print(f"error: the export process cannot rebuild the model ({type(exc).__name__}: {exc})", file=sys.stderr)
        return EXIT_UNPICKLE
    from .backends import export_onnx  # noqa: PLC0415

    try:
        export_onnx(module, inputs, part)
    except Exception as exc:  # noqa: BLE001 - the exporter raises many kinds
        _unlink(part)
        print("error: " + (" ".join(str(exc).split()) or type(exc).__name__)[:300], file=sys.stderr)
        return 1
    return 0


__all__ = ["EXIT_UNPICKLE", "ChildCannotImport", "ExportCancelled", "cancel_exports", "export_in_child",
           "exports_cancelled"]

if __name__ == "__main__":
    sys.exit(main())
