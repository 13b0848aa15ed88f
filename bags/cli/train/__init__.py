"""``bev-train``'s command line: :mod:`~bags.cli.train.main` dispatches to one module per
subcommand (:mod:`~bags.cli.train.train`, the default; :mod:`~bags.cli.train.eval`;
:mod:`~bags.cli.train.calibrate`), with the flag types of :mod:`~bags.cli.train.flags`.
``python -m bags.cli.train`` (and ``torchrun ... -m bags.cli.train``) runs it.

Public names (in :mod:`~bags.cli.train.main`, not imported here, so that importing this package
imports nothing): ``main`` (the entry point, also :func:`bags.cli.bev_train`), ``SUBCOMMANDS``,
``DEFAULT`` and ``subcommand_parser``; the parsers of the tests and tools are
:func:`bags.cli.train.train.train_parser` and :func:`bags.cli.train.eval.eval_parser`.
"""
