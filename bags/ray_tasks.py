"""Independent jobs as Ray tasks: a local Ray runtime that lives as long as the command, or an
existing cluster joined with ``ray.init(address=...)``.

:func:`ray_runtime` starts (or joins) Ray so that its workers import the same code as this
process: a local runtime gets this checkout on the workers' ``PYTHONPATH``; a joined cluster
gets the packages uploaded with the job (``runtime_env`` ``py_modules``; the nodes still need
the third-party dependencies: numpy, torch, rosbags). :func:`run_tasks` runs one task per item
and yields the results as they complete; per-item failures are results, not exceptions.

Ray is the optional ``fleet`` extra (``pip install .[fleet]``); it is imported only here.
"""

from __future__ import annotations

import contextlib
import logging
import os
import signal
import threading
from collections.abc import Callable, Iterable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from bev_mapper_core.errors import BevMapperError

from .errors import BagError

log = logging.getLogger(__name__)

#: The directory holding ``bags``, ``bev_mapper_core`` and ``msg_adapters``.
CODE_ROOT = Path(__file__).resolve().parent.parent
#: Packages a joined cluster's workers import from this checkout.
PACKAGES = ("bags", "bev_mapper_core", "msg_adapters")
#: Not uploaded to a joined cluster (the tasks here need no weights).
UPLOAD_EXCLUDES = ("*.safetensors", "__pycache__", "*.pyc")


@dataclass(frozen=True)
class RayOptions:
    """Where the tasks run.

    Args:
        address: ``None``: start a local Ray runtime for the command (stopped at its end);
            ``auto`` (the cluster this machine belongs to), ``host:port`` (a cluster's GCS) or
            ``ray://host:port`` (Ray client): join that cluster (``ray.init(address=...)``).
        workers: local runtime: its CPUs, i.e. tasks at once (``None``: all of the machine's);
            joined cluster: the most tasks in flight at once (``None``: no limit, the cluster's
            CPUs decide).
    """

    address: str | None = None
    workers: int | None = None

    def __post_init__(self) -> None:
        if self.workers is not None and (isinstance(self.workers, bool) or not isinstance(self.workers, int)
                                         or self.workers < 1):
            raise BagError(f"workers must be an integer >= 1, got {self.workers!r}")
        if self.address is not None and not self.address.strip():
            raise BagError("the Ray address must not be empty")


def _runtime_env(local: bool) -> dict:
    """Workers import this checkout: on ``PYTHONPATH`` locally, uploaded to a joined cluster."""
    if local:
        path = [str(CODE_ROOT)] + [p for p in os.environ.get("PYTHONPATH", "").split(os.pathsep) if p]
        return {"env_vars": {"PYTHONPATH": os.pathsep.join(dict.fromkeys(path))}}
    return {"py_modules": [str(CODE_ROOT / p) for p in PACKAGES], "excludes": list(UPLOAD_EXCLUDES)}


def import_ray():
    """The ``ray`` module, or BagError saying how to install it."""
    try:
        import ray
    except ImportError as exc:
        raise BagError(f"this command runs on Ray, which is not installed ({exc}); "
                       "install the 'fleet' extra: pip install '.[fleet]'") from None
    return ray


@contextlib.contextmanager
def ray_runtime(options: RayOptions) -> Iterator[Any]:
    """Start or join Ray for the duration of the ``with`` block; yields the ``ray`` module.

    ``ray.init`` replaces the SIGTERM handler; the previous one is put back, so that the
    command's own handling (see :mod:`bags.cli`) still applies.

    Raises:
        BagError: Ray is not installed, or the cluster cannot be joined / the runtime started.
    """
    ray = import_ray()
    local = options.address is None
    main = threading.current_thread() is threading.main_thread()
    previous = signal.getsignal(signal.SIGTERM) if main else None
    kw: dict[str, Any] = dict(log_to_driver=False, logging_level=logging.WARNING, runtime_env=_runtime_env(local))
    if local:
        kw.update(address="local", num_cpus=options.workers, include_dashboard=False)
    else:
        kw.update(address=options.address)
    try:
        ray.init(**kw)
    except (ConnectionError, RuntimeError, ValueError, TimeoutError) as exc:
        where = "start a local Ray runtime" if local else f"join the Ray cluster at {options.address!r}"
        raise BagError(f"cannot {where}: {exc}") from None
    finally:
        if main and previous is not None:
            signal.signal(signal.SIGTERM, previous)
    try:
        res = ray.cluster_resources()
        log.debug("Ray %s: %s CPUs", "local runtime" if local else options.address, res.get("CPU"))
        yield ray
    finally:
        ray.shutdown()  # a local runtime stops; a joined cluster is only disconnected from


@dataclass(frozen=True)
class TaskFailure:
    """A task that raised (or whose worker died): ``message`` says why."""

    message: str


def failure_message(exc: BaseException) -> str:
    """One line for a task's exception: the message of the project's own errors, else the type too."""
    cause = getattr(exc, "cause", None)  # RayTaskError: the exception raised in the task
    if isinstance(cause, BaseException):
        exc = cause
    if isinstance(exc, (BevMapperError, OSError)):
        return str(exc)
    text = str(exc).strip().splitlines()
    return f"{type(exc).__name__}: {text[-1] if text else ''}".rstrip(": ")


def run_tasks(ray, fn: Callable, items: Iterable, *args, max_in_flight: int | None = None,
              num_cpus: float = 1) -> Iterator[tuple[Any, Any]]:
    """Run ``fn(item, *args)`` as one Ray task per item (``num_cpus`` each); yield
    ``(item, result)`` in completion order, ``result`` a :class:`TaskFailure` when the task
    failed. At most ``max_in_flight`` tasks are submitted at once (``None``: all).

    Leaving early (an exception in the consumer, Ctrl-C) cancels the tasks still running.
    """
    remote = ray.remote(num_cpus=num_cpus)(fn)
    shared = [ray.put(a) for a in args]  # once, not once per task
    todo = list(items)
    todo.reverse()
    pending: dict[Any, Any] = {}
    try:
        while todo or pending:
            while todo and (max_in_flight is None or len(pending) < max_in_flight):
                item = todo.pop()
                pending[remote.remote(item, *shared)] = item
            done, _ = ray.wait(list(pending), num_returns=1)
            ref = done[0]
            item = pending.pop(ref)
            try:
                result = ray.get(ref)
            except ray.exceptions.RayError as exc:
                result = TaskFailure(failure_message(exc))
            yield item, result
    finally:
        for ref in pending:
            with contextlib.suppress(Exception):
                ray.cancel(ref, force=True)
