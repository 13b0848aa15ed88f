"""The command lines: ``bev-bag`` (:mod:`bags.cli.main`, one module per subcommand: ``synth``,
``synth-many``, ``info``, ``replay``, ``play``, ``evaluate``) and ``bev-train``
(:mod:`bags.cli.train`: ``train``, ``eval``, ``calibrate``), both run through
:func:`~bags.cli.dispatch.run_guarded` (errors as ``error: ...``, SIGTERM like Ctrl-C, the same
exit statuses).

Public names: :func:`bev_bag` and :func:`bev_train` (the entry points, argv -> exit status;
imported on first use, so that ``python -m bags.cli.main`` finds its module not yet imported),
:func:`~bags.cli.dispatch.run_guarded` and the exit statuses :data:`EXIT_ERROR`,
:data:`EXIT_USAGE`, :data:`EXIT_INTERRUPTED`, :data:`EXIT_TERMINATED`. Importing this package
imports no subcommand (nor torch, nor Ray): each command line imports the subcommands it runs.
"""

from .dispatch import EXIT_ERROR, EXIT_INTERRUPTED, EXIT_TERMINATED, EXIT_USAGE, run_guarded

#: Entry point name -> the module whose ``main`` it is.
_ENTRY_POINTS = {"bev_bag": "bags.cli.main", "bev_train": "bags.cli.train.main"}


def __getattr__(name: str):
    """:func:`bev_bag` and :func:`bev_train`, imported on first use."""
    if name not in _ENTRY_POINTS:
        raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
    import importlib

    return importlib.import_module(_ENTRY_POINTS[name]).main


__all__ = ["EXIT_ERROR", "EXIT_INTERRUPTED", "EXIT_TERMINATED", "EXIT_USAGE", "bev_bag", "bev_train", "run_guarded"]
