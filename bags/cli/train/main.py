"""``bev-train``: the training tool's command line, in the idiom of ``bev-bag`` (:mod:`bags.cli.main`).

Each subcommand lives in its own module, listed in :data:`SUBCOMMANDS`; with no subcommand named,
the arguments are those of :data:`DEFAULT` (``bev-train --method bimapper ...`` trains). A
subcommand module defines::

    HELP: str                                                   # the parser's description
    def configure(parser: argparse.ArgumentParser, argv: list[str]) -> None
    def run(args: argparse.Namespace) -> int                    # exit status

``configure`` sees the subcommand's arguments because some flags depend on them: ``train``
offers the flags of the method ``--method`` (or the ``--config`` file) names.

Usage errors print the usage and ``error: ...`` and exit with status 2; errors, Ctrl-C and
SIGTERM end as in ``bev-bag`` (:func:`bags.cli.dispatch.run_guarded`: status 1, 130, 143).
"""

from __future__ import annotations

import argparse
import importlib
import sys

from ..dispatch import EXIT_USAGE, run_guarded

PROG = "bev-train"
#: Subcommand name -> module implementing it (add new subcommands here).
SUBCOMMANDS: dict[str, str] = {
    "train": "bags.cli.train.train",
    "eval": "bags.cli.train.eval",
    "calibrate": "bags.cli.train.calibrate",
}
#: The subcommand of a command line that names none.
DEFAULT = "train"


class _Parser(argparse.ArgumentParser):
    def error(self, message: str):  # noqa: D401 - argparse hook
        self.print_usage(sys.stderr)
        print(f"error: {message}", file=sys.stderr)
        raise SystemExit(EXIT_USAGE)


def subcommand_parser(name: str, argv: list[str] | tuple[str, ...] = ()) -> argparse.ArgumentParser:
    """The parser of subcommand ``name`` for its arguments ``argv`` (which may add flags)."""
    module = importlib.import_module(SUBCOMMANDS[name])
    parser = _Parser(prog=PROG if name == DEFAULT else f"{PROG} {name}", description=module.HELP)
    module.configure(parser, list(argv))
    return parser


def _run(name: str, argv: list[str]) -> int:
    args = subcommand_parser(name, argv).parse_args(argv)
    return importlib.import_module(SUBCOMMANDS[name]).run(args)


def main(argv: list[str] | None = None) -> int:
    """Entry point of ``bev-train``; returns the exit status (0, 1 on errors, 2 on usage errors,
    130 on Ctrl-C, 143 on SIGTERM).
    """
    argv = list(sys.argv[1:] if argv is None else argv)
    name = argv[0] if argv[:1] and argv[0] in SUBCOMMANDS else DEFAULT
    return run_guarded(_run, name, argv[1:] if argv[:1] == [name] else argv)


if __name__ == "__main__":
    sys.exit(main())
