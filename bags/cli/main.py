"""``bev-bag``: the bag tool's command line.

Each subcommand lives in its own module, listed in :data:`SUBCOMMANDS`. A subcommand module
defines::

    HELP: str                                        # one line for ``bev-bag --help``
    def configure(parser: argparse.ArgumentParser) -> None
    def run(args: argparse.Namespace) -> int         # exit status

Expected failures print ``error: ...``, SIGTERM unwinds like Ctrl-C, and the exit statuses
are those of :mod:`bags.cli.dispatch`, shared with ``bev-train``.
"""

from __future__ import annotations

import argparse
import importlib
import logging
import sys

from ..mcap_checksums import check_in_background
from .dispatch import exit_status, run_guarded

#: Subcommand name -> module implementing it (add new subcommands here).
SUBCOMMANDS: dict[str, str] = {
    "synth": "bags.cli.synth",
    "synth-many": "bags.cli.synth_many",
    "info": "bags.cli.info",
    "replay": "bags.cli.replay",
    "play": "bags.cli.play",
    "evaluate": "bags.cli.evaluate",
    "segment": "bags.cli.segment",
    "import": "bags.cli.import_drives",
    "propose-mask": "bags.cli.propose_mask",
}


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


#: subcommands that read the bags named on their command line: their MCAP checksums start at once
READS_BAGS = frozenset({"replay", "info", "play", "segment", "propose-mask"})


def main(argv: list[str] | None = None) -> int:
    """Entry point of ``bev-bag``; returns the exit status."""
    argv = sys.argv[1:] if argv is None else list(argv)
    if argv and argv[0] in READS_BAGS:  # the checks (GIL-free reading) run beside the imports below
        check_in_background(a for a in argv[1:] if not a.startswith("-"))
    try:
        args = build_parser().parse_args(argv)
    except SystemExit as exc:  # --help or a usage error; argparse printed the message
        return exit_status(exc)
    logging.basicConfig(
        level=logging.DEBUG if args.verbose else logging.INFO,
        format="%(levelname)s: %(message)s",
    )
    return run_guarded(args._run, args)


if __name__ == "__main__":
    sys.exit(main())
