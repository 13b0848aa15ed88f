"""What the package's command lines (``bev-bag``, ``bev-train``) share: the exit statuses, expected
errors printed as ``error: ...`` and SIGTERM unwinding like Ctrl-C, all in :func:`run_guarded`.

Expected failures (any :class:`~bev_mapper_core.errors.BevMapperError`, I/O errors) are printed
as ``error: ...`` on stderr with status :data:`EXIT_ERROR`, without a traceback; argparse's usage
errors end with :data:`EXIT_USAGE`.

SIGTERM (``kill``, a job scheduler, ``timeout``) unwinds like Ctrl-C: while a subcommand runs,
it raises :class:`Terminated` (a ``KeyboardInterrupt``) in the main thread, so every ``finally``
and ``with`` block cleans up (temporary ``.partial-<pid>`` outputs are removed) and the status is
:data:`EXIT_TERMINATED` (Ctrl-C: :data:`EXIT_INTERRUPTED`). Further SIGTERMs are ignored while
that cleanup runs.
"""

from __future__ import annotations

import contextlib
import signal
import sys
import threading
from collections.abc import Callable

from bev_mapper_core.errors import BevMapperError

EXIT_ERROR = 1
EXIT_USAGE = 2
EXIT_INTERRUPTED = 130
EXIT_TERMINATED = 128 + signal.SIGTERM


class Terminated(KeyboardInterrupt):
    """Raised in the main thread on SIGTERM, so that it unwinds like Ctrl-C."""


#: Set when SIGTERM arrived: a library may re-raise :class:`Terminated` as a plain
#: ``KeyboardInterrupt`` (Ray does, for a signal handled while it waits in its C++ core).
_sigterm_seen = threading.Event()


def _on_sigterm(signum, frame) -> None:
    signal.signal(signal.SIGTERM, signal.SIG_IGN)  # one unwinding; let the cleanup finish
    _sigterm_seen.set()
    raise Terminated()


@contextlib.contextmanager
def sigterm_unwinds():
    """While inside, SIGTERM raises :class:`Terminated` (main thread only; the previous
    handler is restored on exit).
    """
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    _sigterm_seen.clear()
    previous = signal.signal(signal.SIGTERM, _on_sigterm)
    try:
        yield
    finally:
        signal.signal(signal.SIGTERM, previous)


def exit_status(exc: SystemExit) -> int:
    """The status of a ``SystemExit`` (argparse's: 0 after ``--help``, 2 for a usage error)."""
    return EXIT_USAGE if isinstance(exc.code, str) else int(exc.code or 0)


def run_guarded(run: Callable[..., int | None], *args) -> int:
    """``run(*args)`` as a command line runs a subcommand; returns the exit status: its own
    (``None``: 0), or :data:`EXIT_ERROR`, :data:`EXIT_USAGE`, :data:`EXIT_INTERRUPTED` or
    :data:`EXIT_TERMINATED` with an ``error: ...`` line on stderr (see the module docstring).
    """
    try:
        with sigterm_unwinds():
            status = int(run(*args) or 0)
        if _sigterm_seen.is_set():  # a library swallowed the unwinding (e.g. as its tasks' failure)
            raise Terminated()
        return status
    except SystemExit as exc:  # a usage error (argparse printed it) or an explicit exit
        return exit_status(exc)
    except (BevMapperError, OSError) as exc:
        print(f"error: {exc}", file=sys.stderr)
        return EXIT_ERROR
    except KeyboardInterrupt as exc:
        if isinstance(exc, Terminated) or _sigterm_seen.is_set():
            print("error: terminated (SIGTERM)", file=sys.stderr)
            return EXIT_TERMINATED
        print("error: interrupted", file=sys.stderr)
        return EXIT_INTERRUPTED


__all__ = ["EXIT_ERROR", "EXIT_INTERRUPTED", "EXIT_TERMINATED", "EXIT_USAGE", "Terminated", "exit_status",
           "run_guarded", "sigterm_unwinds"]
