"""Replaying many bags as Ray tasks and adding their scores up exactly (``bev-bag evaluate``).

One bag is one task running :func:`bags.replay.replay` (the same code as ``bev-bag replay``)
into its own output directory; the task returns a small JSON-able *record*: the bag's status,
its ``metrics.json``, the mergeable scoring state (:meth:`bags.replay.ReplayScorer.state`) and
the mapping latency of every frame. :func:`aggregate` merges the states of the complete bags,
so its IoU is the dataset-level IoU of all their frames (summed intersections and unions),
Chamfer distances are weighted by frames and latency percentiles are over all frames: the
same as replaying every frame through one accumulator.

A bag that raises (unreadable, unusable calibration, a crash of its worker) fails alone:
its record says ``failed`` with the error. A bag replayed up to damage is ``damaged``: its
outputs cover the frames before the damage, and it stays out of the aggregate, which is over
complete drives only. Ray itself is imported by :mod:`bags.fleet.ray_tasks` only when tasks run
(the ``fleet`` extra).
"""

from __future__ import annotations

import hashlib
import time
from collections.abc import Callable, Iterable
from dataclasses import asdict, replace
from pathlib import Path

from bev_mapper_core.errors import BevMapperError
from bev_mapper_core.metrics import MetricAccumulator, WholeGridAccumulator

from ..errors import BagError
from ..io.sources import BAG_SUFFIXES
from ..memory import keep_freed_memory
from ..replay import ReplayOptions, ReplayScorer, percentiles, replay
from . import ray_tasks

OK, DAMAGED, FAILED = "ok", "damaged", "failed"
#: seconds between two progress reports of a task
PROGRESS_EVERY_S = 0.2


# ------------------------------------------------------------------ inputs
def find_bags(paths: Iterable[Path]) -> list[Path]:
    """The bags named by ``paths``, in order: a bag itself (rosbag2 directory, ``.mcap`` or
    ``.db3`` file), or a directory searched recursively for bags (sorted by path).

    Raises:
        BagError: a path does not exist, or names no bag.
    """
    found: list[Path] = []
    for p in map(Path, paths):
        if not p.exists():
            raise BagError(f"{p}: no such file or directory")
        if _is_bag(p):
            found.append(p)
            continue
        if not p.is_dir():
            raise BagError(f"{p}: not a bag (a rosbag2 directory, {' or '.join(BAG_SUFFIXES)} file)")
        inner = _bags_under(p)
        if not inner:
            raise BagError(f"{p}: no bags in this directory")
        found.extend(inner)
    seen, unique = set(), []
    for b in found:
        key = b.resolve()
        if key not in seen:
            seen.add(key)
            unique.append(b)
    return unique


def _is_bag(p: Path) -> bool:
    if p.is_dir():
        return (p / "metadata.yaml").exists()
    return p.suffix in BAG_SUFFIXES


def _bags_under(root: Path) -> list[Path]:
    out = []
    for p in sorted(root.iterdir()):
        if _is_bag(p):
            out.append(p)
        elif p.is_dir() and not p.name.startswith("."):
            out.extend(_bags_under(p))
    return out


def bag_names(bags: list[Path]) -> list[str]:
    """A unique output name per bag: its name without the suffix, and where several bags
    share it, that name plus a hash of the bag's absolute path (the same in every run).
    """
    stems = [b.name[: -len(b.suffix)] if b.suffix in BAG_SUFFIXES else b.name for b in bags]
    names = []
    for bag, stem in zip(bags, stems):
        if stems.count(stem) > 1:
            stem += "-" + hashlib.sha1(str(bag.resolve()).encode()).hexdigest()[:8]
        names.append(stem)
    return names


def options_record(options: ReplayOptions) -> dict:
    """What defines a bag's results, as JSON: ``options`` without the bag, the output
    directory and the run details (force, progress bar, scoring process). Two runs with equal
    records give the same metrics.
    """
    d = asdict(replace(options, bag=Path(), out=Path()))
    for key in ("bag", "out", "force", "progress", "score_process"):
        d.pop(key)
    return _jsonable(d)


def _jsonable(v):
    if isinstance(v, dict):
        return {str(k): _jsonable(x) for k, x in v.items()}
    if isinstance(v, (list, tuple)):
        return [_jsonable(x) for x in v]
    if v is None or isinstance(v, (bool, int, float, str)):
        return v
    return str(v)


# ------------------------------------------------------------------ one task
class _ReportedBar:
    """The ``progress`` object :func:`replay` updates, reporting to the progress actor at most
    every :data:`PROGRESS_EVERY_S` (never waiting for it).
    """

    def __init__(self, board, name: str, total: int | None) -> None:
        self._board, self._name, self._total = board, name, total
        self._done, self._sent = 0, 0.0
        board.report.remote(name, 0, total)

    def update(self, n: int = 1) -> None:
        self._done += n
        now = time.monotonic()
        if now - self._sent >= PROGRESS_EVERY_S:
            self._sent = now
            self._board.report.remote(self._name, self._done, self._total)

    def close(self) -> None:
        self._board.report.remote(self._name, self._done, self._total)


def evaluate_bag(options: ReplayOptions, name: str, board=None) -> dict:
    """Replay one bag (the body of a Ray task) and return its record (see :func:`evaluate_bags`).

    Never raises for a problem of the bag: any exception becomes a ``failed`` record.
    """
    record = {"name": name, "bag": str(options.bag), "status": FAILED, "error": None,
              "metrics": None, "scoring": None, "latencies_ms": [], "seconds": None,
              "cpu_seconds": None}
    progress = None if board is None else (lambda total: _ReportedBar(board, name, total))
    keep_freed_memory()  # a worker's per-frame arrays reuse the heap (bags/memory.py)
    t0, c0 = time.perf_counter(), time.process_time()
    try:
        result = replay(options, progress=progress)
    except (BevMapperError, OSError) as exc:
        record["error"] = str(exc)
    except Exception as exc:  # noqa: BLE001 - a bug met by one bag must not end the others
        record["error"] = f"{type(exc).__name__}: {exc}"
    else:
        record.update(status=DAMAGED if result.damage else OK, error=result.damage,
                      metrics=result.metrics, scoring=result.scoring,
                      latencies_ms=[float(v) for v in result.latencies_ms])
    record["seconds"] = time.perf_counter() - t0
    record["cpu_seconds"] = time.process_time() - c0
    return record


# ------------------------------------------------------------------ aggregation
def aggregate(records: list[dict]) -> dict:
    """Dataset-level metrics of the ``ok`` records: their scoring states merged (exactly the
    metrics of all their frames through one accumulator) and latency percentiles over all their
    frames. Records whose scoring cannot be merged with the first scored one (another grid or
    other classes) are left out and listed in ``excluded`` with the reason.
    """
    acc = whole = None
    used, excluded, latencies = [], [], []
    frames = skipped = 0
    for r in records:
        if r["status"] != OK:
            continue
        state = r["scoring"]
        if state is not None:
            try:
                if acc is None:
                    acc = MetricAccumulator.from_state(state["metrics"])
                    whole = WholeGridAccumulator.from_state(state["whole"])
                else:
                    acc.check_state(state["metrics"])
                    whole.merge_state(state["whole"])
                    acc.merge_state(state["metrics"])
            except BevMapperError as exc:
                excluded.append({"name": r["name"], "reason": str(exc)})
                continue
        used.append(r["name"])
        latencies.extend(r["latencies_ms"])
        frames += r["metrics"]["frames"]
        skipped += r["metrics"]["frames_skipped"]
    scores = ReplayScorer.result_of(None if acc is None else {"metrics": acc.state(), "whole": whole.state()})
    return {"bags": len(used), "frames": frames, "frames_scored": scores.pop("frames"),
            "frames_skipped": skipped, **scores, "latency_ms": percentiles(latencies),
            "excluded": excluded}


# ------------------------------------------------------------------ Ray
def evaluate_bags(ray, jobs: list[tuple[str, ReplayOptions]], workers: int, *, show_progress: bool,
                  on_record: Callable[[dict], None], watch_nodes: bool = False) -> None:
    """Run :func:`evaluate_bag` for every ``(name, options)`` as Ray tasks of one CPU each, at
    most ``workers`` at a time (:func:`bags.fleet.ray_tasks.run_tasks`), on the runtime ``ray`` is
    connected to. Each record is handed to ``on_record`` as it arrives (in completion order),
    also for a task whose worker died (a ``failed`` record). With ``show_progress``: tqdm bars
    over bags and frames. ``watch_nodes`` (a joined cluster): a bag whose node dies fails as soon
    as the cluster declares the node dead (see :func:`~bags.fleet.ray_tasks.run_tasks`).
    """
    from tqdm import tqdm  # noqa: PLC0415

    board = _progress_board(ray) if show_progress else None
    bags_bar = tqdm(total=len(jobs), unit="bag", disable=not show_progress, position=0,
                    dynamic_ncols=True, desc="bags")
    frames_bar = tqdm(total=0, unit="frame", disable=not show_progress, position=1,
                      dynamic_ncols=True, desc="frames")

    def refresh() -> None:
        if board is not None:
            done, total = ray.get(board.totals.remote())
            frames_bar.total = max(total, done)
            frames_bar.n = done
            frames_bar.refresh()

    try:
        # a bag that kills its worker fails alone at once, not after retries
        for (name, options), record in ray_tasks.run_tasks(ray, _evaluate_job, jobs, board, max_in_flight=workers,
                                                           max_retries=0, poll=refresh, poll_every_s=PROGRESS_EVERY_S,
                                                           watch_nodes=watch_nodes):
            if isinstance(record, ray_tasks.TaskFailure):  # the worker died, the task was cancelled ...
                record = {"name": name, "bag": str(options.bag), "status": FAILED,
                          "error": record.message, "metrics": None, "scoring": None, "latencies_ms": [],
                          "seconds": None, "cpu_seconds": None, "node": None}
            on_record(record)
            bags_bar.update(1)
    finally:
        bags_bar.close()
        frames_bar.close()


def _evaluate_job(job: tuple[str, ReplayOptions], board) -> dict:
    """The task body: :func:`evaluate_bag` of one ``(name, options)`` job, its record with the
    ``node`` (Ray node id) it ran on.
    """
    name, options = job
    import ray  # noqa: PLC0415 - in a Ray worker

    return {**evaluate_bag(options, name, board), "node": ray.get_runtime_context().get_node_id()}


def _progress_board(ray):
    """A small actor (no CPU reserved) the tasks report their frames to."""

    @ray.remote(num_cpus=0)
    class ProgressBoard:
        def __init__(self) -> None:
            self.bags: dict[str, tuple[int, int]] = {}

        def report(self, name: str, done: int, total: int | None) -> None:
            self.bags[name] = (done, total if total is not None else done)

        def totals(self) -> tuple[int, int]:
            return (sum(d for d, _ in self.bags.values()), sum(t for _, t in self.bags.values()))

    return ProgressBoard.remote()
