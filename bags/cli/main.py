"""``bev-bag``: the bag tool's command line.

Each subcommand lives in its own module, listed in :data:`SUBCOMMANDS`. A subcommand module
defines::

    HELP: str                                        # one line for ``bev-bag --help``
    def configure(parser: argparse.ArgumentParser) -> None
    def run(args: argparse.Namespace) -> int         # exit status

Expected failures (any :class:`~bev_mapper_core.errors.BevMapperError`, I/O errors) are printed
as ``error: ...`` on stderr with a non-zero status, without a traceback.

SIGTERM (``kill``, a job scheduler, ``timeout``) unwinds like Ctrl-C: while a subcommand runs,
it raises :class:`Terminated` (a ``KeyboardInterrupt``) in the main thread, so every ``finally``
and ``with`` block cleans up (temporary ``.partial-<pid>`` outputs are removed) and the status is
:data:`EXIT_TERMINATED`. Further SIGTERMs are ignored while that cleanup runs.
"""

from __future__ import annotations

import argparse
import contextlib
import importlib
import logging
import signal
import sys
import threading

from bev_mapper_core.errors import BevMapperError

#: Subcommand name -> module implementing it (add new subcommands here).
SUBCOMMANDS: dict[str, str] = {
    "synth": "bags.cli.synth",
    "synth-many": "bags.cli.synth_many",
    "info": "bags.cli.info",
    "replay": "bags.cli.replay",
    "play": "bags.cli.play",
    "evaluate": "bags.cli.evaluate",
}

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


def build_parser() -> argparse.ArgumentParser:
    """The top-level parser with one sub-parser per registered subcommand."""
    parser = argparse.ArgumentParser(
        prog="bev-bag", description="Write, inspect and replay bev_mapper rosbag2 bags."
    )
    parser.add_argument("-v", "--verbose", action="store_true", help="debug logging")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND", required=True)
    for name, module_name in SUBCOMMANDS.items():
        module = importlib.import_module(module_name)
        p = sub.add_parser(name, help=module.HELP, description=module.HELP)
        module.configure(p)
        p.set_defaults(_run=module.run)
    return parser


def main(argv: list[str] | None = None) -> int:
    """Entry point of ``bev-bag``; returns the exit status."""
    try:
        args = build_parser().parse_args(argv)
    except SystemExit as exc:  # --help or a usage error; argparse printed the message
        return int(exc.code or 0) if not isinstance(exc.code, str) else EXIT_USAGE
    logging.basicConfig(
        level=logging.DEBUG if args.verbose else logging.INFO,
        format="%(levelname)s: %(message)s",
    )
    try:
        with sigterm_unwinds():
            status = int(args._run(args) or 0)
        if _sigterm_seen.is_set():  # a library swallowed the unwinding (e.g. as its tasks' failure)
            raise Terminated()
        return status
    except BevMapperError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return EXIT_ERROR
    except OSError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return EXIT_ERROR
    except KeyboardInterrupt as exc:
        if isinstance(exc, Terminated) or _sigterm_seen.is_set():
            print("error: terminated (SIGTERM)", file=sys.stderr)
            return EXIT_TERMINATED
        print("error: interrupted", file=sys.stderr)
        return EXIT_INTERRUPTED


if __name__ == "__main__":
    sys.exit(main())
