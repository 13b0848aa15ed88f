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
import socket
import threading
import time
from collections.abc import Callable, Iterable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from bev_mapper_core.errors import BevMapperError

from ..errors import BagError

log = logging.getLogger(__name__)

#: The directory holding ``bags``, ``bev_mapper_core`` and ``msg_adapters``.
CODE_ROOT = Path(__file__).resolve().parents[2]
#: Packages a joined cluster's workers import from this checkout.
PACKAGES = ("bags", "bev_mapper_core", "msg_adapters")
#: Not uploaded to a joined cluster.
UPLOAD_EXCLUDES = ("__pycache__", "*.pyc")
#: ... unless the tasks map with the shipped weights: also not those.
WEIGHTS_EXCLUDES = ("*.safetensors",)
#: Ray's authentication setting: a local runtime gets ``token`` when the user has set none (what
#: Ray chooses anyway, said explicitly so that Ray prints no warning about it); so does joining a
#: cluster when this machine holds a token (what ``ray start --head`` chooses: a head started here
#: checks tokens, and a driver without one is refused only after ~20 s of retries).
AUTH_MODE_ENV = "RAY_AUTH_MODE"
#: ``--ray-address`` forms: ``auto`` (the cluster this machine is part of), ``HOST:PORT`` of a
#: head node's GCS, or ``ray://HOST:PORT`` (Ray client, needs ``ray[client]``).
ADDRESS_HELP = "auto | HOST:PORT | ray://HOST:PORT"


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
            raise BagError(f"--workers must be an integer >= 1, got {self.workers!r}")
        a = self.address
        if a is not None and not (a == "auto" or a.startswith("ray://") or _host_port(a)):
            raise BagError(f"--ray-address must be {ADDRESS_HELP}, got {a!r}")


def add_ray_args(p, what: str) -> None:
    """``--workers`` and ``--ray-address`` (defaults: :class:`RayOptions`'s) on parser or group
    ``p``; ``what``: what one task does, for the help ("drives rendered", "bags replayed").
    """
    p.add_argument("--workers", type=int, default=RayOptions.workers, metavar="N",
                   help=f"{what} at once: a local runtime of N CPUs (default: all of this machine's); with "
                        "--ray-address, the most tasks in flight (default: the cluster's CPUs)")
    p.add_argument("--ray-address", default=RayOptions.address, metavar="ADDR",
                   help=f"join an existing Ray cluster instead of starting a local runtime: {ADDRESS_HELP} "
                        "(this checkout's code is uploaded with the job; the nodes need its dependencies)")


def _host_port(a: str) -> bool:
    host, _, port = a.rpartition(":")
    return bool(host) and port.isdigit()


def _check_reachable(address: str, timeout_s: float = 10.0) -> None:
    """Raise :class:`BagError` unless a TCP connection to ``HOST:PORT`` opens (``ray.init``
    itself would retry for minutes).
    """
    host, _, port = address.rpartition(":")
    try:
        socket.create_connection((host.strip("[]"), int(port)), timeout=timeout_s).close()
    except OSError as exc:
        raise BagError(f"cannot join the Ray cluster at {address}: {exc}") from None


def _runtime_env(local: bool, weights: bool) -> dict:
    """Workers import this checkout: on ``PYTHONPATH`` locally, uploaded to a joined cluster
    (with the shipped weights when ``weights``).
    """
    if local:
        path = [str(CODE_ROOT)] + [p for p in os.environ.get("PYTHONPATH", "").split(os.pathsep) if p]
        return {"env_vars": {"PYTHONPATH": os.pathsep.join(dict.fromkeys(path))}}
    excludes = UPLOAD_EXCLUDES + (() if weights else WEIGHTS_EXCLUDES)
    return {"py_modules": [str(CODE_ROOT / p) for p in PACKAGES], "excludes": list(excludes)}


def import_ray():
    """The ``ray`` module, or BagError saying how to install it."""
    try:
        import ray
    except ImportError as exc:
        raise BagError(f"this command runs on Ray, which is not installed ({exc}); "
                       "install the 'fleet' extra: pip install '.[fleet]'") from None
    return ray


@contextlib.contextmanager
def ray_runtime(options: RayOptions, weights: bool = False) -> Iterator[Any]:
    """Start or join Ray for the duration of the ``with`` block; yields the ``ray`` module.
    ``weights``: a joined cluster also gets the shipped weights (tasks that map).

    ``ray.init`` replaces the SIGTERM handler; the previous one is put back, so that the
    command's own handling (see :mod:`bags.cli.main`) still applies. Without ``RAY_AUTH_MODE``
    set, Ray's token authentication is used (and unset again at the end) for a local runtime, and
    for a joined cluster when a token is found here (see :data:`AUTH_MODE_ENV`).

    Raises:
        BagError: Ray is not installed, or the cluster cannot be joined / the runtime started.
    """
    local = options.address is None
    auth_set = local and AUTH_MODE_ENV not in os.environ
    if auth_set:  # Ray's default for a local runtime (token auth), said before Ray reads its config
        os.environ[AUTH_MODE_ENV] = "token"
        _refresh_ray_config()
    ray = import_ray()
    if not local and AUTH_MODE_ENV not in os.environ and _has_token():
        auth_set = True  # a cluster without token authentication accepts a driver that sends one
        os.environ[AUTH_MODE_ENV] = "token"
        _refresh_ray_config()
    main = threading.current_thread() is threading.main_thread()
    previous = signal.getsignal(signal.SIGTERM) if main else None
    kw: dict[str, Any] = dict(log_to_driver=False, logging_level=logging.WARNING,
                              runtime_env=_runtime_env(local, weights))
    if local:  # "local": never attach to a runtime that happens to run on this machine
        kw.update(address="local", num_cpus=options.workers, include_dashboard=False)
    else:
        if options.address != "auto" and not options.address.startswith("ray://"):
            _check_reachable(options.address)
        kw.update(address=options.address)
    try:
        ray.init(**kw)
    except (ConnectionError, RuntimeError, ValueError, TimeoutError) as exc:
        _unset_auth(auth_set)
        where = "start a local Ray runtime" if local else f"join the Ray cluster at {options.address!r}"
        hint = "" if local or os.environ.get(AUTH_MODE_ENV) == "token" else (
            " (a cluster with token authentication needs its token here: RAY_AUTH_TOKEN, or the file "
            "~/.ray/auth_token)")
        raise BagError(f"cannot {where}: {exc}{hint}") from None
    finally:
        if main and previous is not None:
            signal.signal(signal.SIGTERM, previous)
    try:
        res = ray.cluster_resources()
        log.debug("Ray %s: %s CPUs", "local runtime" if local else options.address, res.get("CPU"))
        yield ray
    finally:
        ray.shutdown()  # a local runtime stops; a joined cluster is only disconnected from
        _unset_auth(auth_set)


def _refresh_ray_config() -> None:
    """Make an already imported Ray see :data:`AUTH_MODE_ENV` (what Ray's own token set-up does)."""
    import sys  # noqa: PLC0415

    if "ray" in sys.modules:
        with contextlib.suppress(Exception):  # a Ray without this config: nothing cached to refresh
            from ray._raylet import Config  # noqa: PLC0415

            Config.initialize("")


def _has_token() -> bool:
    """Whether Ray finds an authentication token here (``RAY_AUTH_TOKEN``, ``RAY_AUTH_TOKEN_PATH``
    or ``~/.ray/auth_token``), whatever ``RAY_AUTH_MODE`` says.
    """
    try:
        from ray._raylet import AuthenticationTokenLoader  # noqa: PLC0415

        return bool(AuthenticationTokenLoader.instance().has_token(ignore_auth_mode=True))
    except Exception:  # noqa: BLE001 - a Ray without token authentication: nothing to send
        return False


def _unset_auth(was_set: bool) -> None:
    if was_set:
        os.environ.pop(AUTH_MODE_ENV, None)
        _refresh_ray_config()


def cluster_cpus(ray) -> int:
    """The CPUs of the runtime this process is connected to (at least 1)."""
    return max(1, int(ray.cluster_resources().get("CPU", 1)))


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
              num_cpus: float = 1, max_retries: int = 3, poll: Callable[[], None] | None = None,
              poll_every_s: float = 0.2, watch_nodes: bool = False) -> Iterator[tuple[Any, Any]]:
    """Run ``fn(item, *args)`` as one Ray task per item (``num_cpus`` each; a task whose worker
    dies is run again up to ``max_retries`` times, Ray's default); yield ``(item, result)`` in
    completion order, ``result`` a :class:`TaskFailure` when the task failed. At most
    ``max_in_flight`` tasks are submitted at once (``None``: all). ``poll()`` is called at least
    every ``poll_every_s`` while tasks run (e.g. to refresh progress bars).

    ``watch_nodes`` (a cluster of several nodes): each task tells a small actor on this node
    where it runs, and a task whose node the cluster has declared dead fails at once
    (``NodeDiedError``) instead of when Ray's connection to its worker times out, which takes
    up to 7 minutes when the node vanished without closing it (a machine gone, a partition).

    Leaving early (an exception in the consumer) cancels the tasks still running. Ctrl-C or
    SIGTERM (a ``KeyboardInterrupt`` while waiting here) cancels nothing: the caller's
    ``ray.shutdown()`` stops them (a local runtime stops; on a cluster Ray kills the tasks of a
    driver that left). Cancelling then raced their replies, and Ray's core aborted the driver
    (``task_manager.cc: Tried to complete task that was not pending``, exit 1 instead of 143;
    ray-project/ray#54260), with plain cancels as with forced ones.
    """
    watch = _NodeWatch(ray) if watch_nodes else None
    remote = ray.remote(num_cpus=num_cpus, max_retries=max_retries)(_reporting if watch else fn)
    shared = [ray.put(a) for a in args]  # once, not once per task
    todo = list(enumerate(items))
    todo.reverse()
    pending: dict[Any, tuple[int, Any]] = {}
    interrupted = False
    timeout = None if poll is None else poll_every_s
    if watch is not None:
        timeout = min(timeout or NODE_CHECK_S, NODE_CHECK_S)
    try:
        while todo or pending:
            while todo and (max_in_flight is None or len(pending) < max_in_flight):
                key, item = todo.pop()
                head = (fn, watch.board, key, item) if watch else (item,)
                pending[remote.remote(*head, *shared)] = (key, item)
            done, _ = ray.wait(list(pending), num_returns=1, timeout=timeout)
            for ref in done:
                _, item = pending.pop(ref)
                try:
                    result = ray.get(ref)
                except ray.exceptions.RayError as exc:
                    result = TaskFailure(failure_message(exc))
                yield item, result
            if watch is not None:
                for ref, message in watch.lost(pending):
                    _, item = pending.pop(ref)
                    with contextlib.suppress(Exception):
                        ray.cancel(ref, force=False)
                    yield item, TaskFailure(message)
            if poll is not None:
                poll()
    except KeyboardInterrupt:  # Ctrl-C, SIGTERM (bags.cli.dispatch.Terminated): the shutdown stops the tasks
        interrupted = True
        raise
    finally:
        if not interrupted:
            _cancel(ray, list(pending))


#: Seconds a watched task waits for the start board to note its node before it runs anyway.
BOARD_WAIT_S = 10.0
#: Seconds between two looks at the cluster's dead nodes (``watch_nodes``).
NODE_CHECK_S = 1.0


def _reporting(fn: Callable, board, key: int, item, *args):
    """A watched task's body: tell ``board`` this node (and wait until it knows, so that a node
    lost after this is attributed), then ``fn(item, *args)``. A board that cannot be reached
    (its actor did not start: seen on ``ray.cluster_utils`` clusters) leaves the task unwatched,
    as Ray alone would run it, never failed.
    """
    import ray  # noqa: PLC0415 - in a Ray worker

    try:
        ray.get(board.started.remote(key, ray.get_runtime_context().get_node_id()), timeout=BOARD_WAIT_S)
    except Exception:  # noqa: BLE001 - ActorDiedError, GetTimeoutError, ...: watched or not, the bag runs
        pass
    return fn(item, *args)


class _StartBoard:
    """Where each watched task started: task key -> node id (an actor on the driver's node)."""

    def __init__(self) -> None:
        self.nodes: dict[int, str] = {}

    def started(self, key: int, node: str) -> None:
        self.nodes[key] = node

    def where(self) -> dict[int, str]:
        return self.nodes


class _NodeWatch:
    """The tasks of :func:`run_tasks` whose node died (``watch_nodes``)."""

    def __init__(self, ray) -> None:
        from ray.util.scheduling_strategies import NodeAffinitySchedulingStrategy  # noqa: PLC0415

        self._ray = ray
        here = NodeAffinitySchedulingStrategy(ray.get_runtime_context().get_node_id(), soft=False)
        self.board = ray.remote(num_cpus=0)(_StartBoard).options(scheduling_strategy=here).remote()
        self._next = 0.0

    def lost(self, pending: dict[Any, tuple[int, Any]]) -> list[tuple[Any, str]]:
        """``(ref, message)`` of the pending tasks on nodes the cluster calls dead (at most every
        :data:`NODE_CHECK_S`).
        """
        now = time.monotonic()
        if not pending or now < self._next:
            return []
        self._next = now + NODE_CHECK_S
        dead = {n["NodeID"]: n for n in self._ray.nodes() if not n["Alive"]}
        if not dead:
            return []
        where = self._ray.get(self.board.where.remote())
        lost = []
        for ref, (key, _) in pending.items():
            node = dead.get(where.get(key))
            if node is not None:
                lost.append((ref, f"NodeDiedError: the node this task ran on died (node {node['NodeID']}, "
                                  f"{node.get('NodeManagerAddress', '?')})"))
        return lost


#: Seconds :func:`run_tasks` waits, when it leaves early, for its cancelled tasks to end before
#: the caller goes on (typically to ``ray.shutdown()``, which stops whatever still runs).
CANCEL_WAIT_S = 10.0


def _cancel(ray, refs: list) -> None:
    """Cancel the tasks of ``refs`` and wait (at most :data:`CANCEL_WAIT_S`) until each has ended.

    Not ``force=True``: a forced cancel kills the worker while its reply may be on the way, and
    Ray's core then aborts the whole driver (``task_manager.cc: Tried to complete task that was
    not pending``, exit 1; ray-project/ray#54260), which turned a SIGTERM's status 143 into 1.
    A plain cancel drops the tasks not started and raises KeyboardInterrupt in the running ones,
    each task ending once, through its own reply; waiting for those ends means no completion is
    still in flight when Ray shuts down. A task that ignores the interrupt (long native code) is
    stopped by the shutdown after the wait.
    """
    if not refs:
        return
    for ref in refs:
        with contextlib.suppress(Exception):
            ray.cancel(ref, force=False)
    with contextlib.suppress(Exception):
        ray.wait(refs, num_returns=len(refs), timeout=CANCEL_WAIT_S)
