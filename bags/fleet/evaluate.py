"""``bev-bag evaluate``: many bags replayed as Ray tasks, scored together (see :mod:`bags.fleet.replay_tasks`).

:func:`evaluate` writes into ``options.out``:

* ``bags/<name>/``: what ``bev-bag replay`` writes for that bag (``metrics.json`` last), and
  ``evaluate.json``: the bag's record (status, error, the options that define its results, its
  mergeable scoring state and per-frame latencies, the Ray node it ran on), written when its
  task is done (a bag whose node died is ``failed`` with Ray's ``NodeDiedError``);
* ``summary.json``: the aggregate over the complete bags (dataset-level IoU from the summed
  intersections and unions, Chamfer weighted by frames, latency percentiles over all frames),
  one entry per bag (status ``ok`` / ``damaged`` / ``failed`` with its error, its node), the
  options, the nodes the tasks ran on and timings. Written last.

Every file is written under a temporary name and renamed. With ``resume`` the bags whose
``evaluate.json`` says ``ok`` for the same bag, identity and options are not replayed again
(their records are read back, checked: :mod:`bags.fleet.records`); a bag changed since, or a
damaged or hand-edited record, is replayed again and listed in ``summary.json``'s ``redone``
with the reason; a bag recorded with other options is an error, not a silent mix. What killed
workers left under temporary names is removed at the end of the run.
"""

from __future__ import annotations

import json
import time
from dataclasses import dataclass, field, replace
from pathlib import Path

from ..errors import BagError, BagExistsError
from ..files import remove_partials, remove_path, write_atomic
from ..replay import METRICS_FILE, ReplayOptions
from .ray_tasks import RayOptions, cluster_cpus, ray_runtime
from .records import bag_identity, resumable, seal
from .replay_tasks import OK, aggregate, bag_names, evaluate_bags, find_bags, options_record

SUMMARY_FILE, RECORD_FILE, BAGS_DIR = "summary.json", "evaluate.json", "bags"


@dataclass(frozen=True)
class EvaluateOptions:
    """Everything :func:`evaluate` needs.

    Args:
        bags: bags (rosbag2 directories, ``.mcap`` / ``.db3`` files) or directories holding bags.
        out: output directory.
        replay: the replay of each bag (its ``bag`` / ``out`` / ``force`` / ``progress`` are set
            per bag).
        ray_address: join this Ray cluster (:data:`~bags.fleet.ray_tasks.ADDRESS_HELP`; the code and
            the shipped weights are uploaded with the job); ``None`` = start a local Ray runtime
            of ``workers`` CPUs for the command and stop it at the end.
        workers: bags replayed at once (``None`` = the CPUs of this machine, or of the cluster).
        resume: keep the bags an earlier run of the same options completed.
        force: start over in an ``out`` that holds an earlier evaluation.
        progress: tqdm bars over bags and frames on stderr.
    """

    bags: tuple[Path, ...]
    out: Path
    replay: ReplayOptions
    ray_address: str | None = None
    workers: int | None = None
    resume: bool = False
    force: bool = False
    progress: bool = False

    def __post_init__(self) -> None:
        if not self.bags:
            raise BagError("no bags given")
        if self.resume and self.force:
            raise BagError("--resume keeps earlier results and --force discards them: pass one")
        RayOptions(self.ray_address, self.workers)  # checks workers and the address

    @property
    def ray(self) -> RayOptions:
        """Where the tasks run."""
        return RayOptions(self.ray_address, self.workers)


@dataclass
class EvaluateResult:
    """The summary (as written to ``summary.json``) and every bag's record, in input order."""

    summary: dict
    records: list[dict] = field(default_factory=list)

    @property
    def ok(self) -> bool:
        """Every bag replayed completely and is in the aggregate."""
        return self.summary["complete"]


def evaluate(options: EvaluateOptions) -> EvaluateResult:
    """Replay every bag as a Ray task and write the outputs (see module docstring).

    Raises:
        BagError: no bags, a path that is no bag, ``out`` holding an earlier evaluation
            without ``resume`` / ``force``, a resumed bag recorded with other options, no Ray
            or no cluster at ``ray_address``. A problem of a single bag is not raised: it is
            that bag's ``failed`` / ``damaged`` record.
    """
    t0 = time.perf_counter()
    out = Path(options.out)
    bags = find_bags(options.bags)
    names = bag_names(bags)
    _check_out(out, options)
    wanted = options_record(options.replay)
    records: dict[str, dict] = {}
    identities: dict[str, dict | None] = {}
    redone: list[dict] = []
    jobs = []
    for bag, name in zip(bags, names):
        bag_out = out / BAGS_DIR / name
        done, why = resumable(bag, bag_out / RECORD_FILE, bag_out / METRICS_FILE, wanted, OK) \
            if options.resume else (None, "")
        if done is not None:
            records[name] = {**done, "resumed": True}
            continue
        if why:
            redone.append({"name": name, "reason": why})
        try:
            identities[name] = bag_identity(bag)  # as the bag is when its replay starts
        except OSError:
            identities[name] = None  # its replay says what is wrong
        remove_partials(bag_out)  # a killed worker's; the bag is replayed again now
        if (bag_out / RECORD_FILE).exists() and not (bag_out / RECORD_FILE).is_file():
            remove_path(bag_out / RECORD_FILE)  # a directory in its place: the new record goes there
        # one process per replay: the workers keep the cores busy
        jobs.append((name, replace(options.replay, bag=bag, out=bag_out, force=True, progress=False,
                                   score_process="off")))

    def on_record(record: dict) -> None:
        bag_out = out / BAGS_DIR / record["name"]
        record = seal({**record, "bag": str(Path(record["bag"]).resolve()), "options": wanted,
                       "bag_identity": identities.get(record["name"]) or {}, "resumed": False})
        bag_out.mkdir(parents=True, exist_ok=True)
        write_atomic(bag_out / RECORD_FILE, _json(record))
        records[record["name"]] = record

    timing = {"ray_start_s": 0.0, "tasks_s": 0.0, "ray_stop_s": 0.0}
    workers = options.workers
    if jobs:
        t = time.perf_counter()
        with ray_runtime(options.ray, weights=True) as ray:  # leaving stops a local runtime
            timing["ray_start_s"] = time.perf_counter() - t
            workers = workers or cluster_cpus(ray)
            t = time.perf_counter()
            try:
                evaluate_bags(ray, jobs, workers, show_progress=options.progress, on_record=on_record,
                              watch_nodes=options.ray_address is not None)
            finally:
                t_stop = time.perf_counter()
                timing["tasks_s"] = t_stop - t
                for _, job in jobs:  # what killed workers left: nothing else writes there now
                    remove_partials(job.out)
        timing["ray_stop_s"] = time.perf_counter() - t_stop
    ordered = [records[n] for n in names]
    t = time.perf_counter()
    agg = aggregate(ordered)
    timing["aggregate_s"] = time.perf_counter() - t
    counts = {s: sum(r["status"] == s for r in ordered) for s in ("ok", "damaged", "failed")}
    timing["total_s"] = time.perf_counter() - t0
    summary = {
        "complete": counts["ok"] == len(ordered) and not agg["excluded"],
        "bags": {"total": len(ordered), **counts, "resumed": sum(r["resumed"] for r in ordered)},
        "aggregate": agg,
        "per_bag": [_entry(r) for r in ordered],
        "redone": redone,
        "options": wanted,
        "ray": {"address": options.ray_address or "local", "workers": workers,
                "nodes": sorted({r["node"] for r in ordered if r.get("node") and not r["resumed"]})},
        "timing": {k: round(v, 3) for k, v in timing.items()},
    }
    write_atomic(out / SUMMARY_FILE, _json(summary))
    return EvaluateResult(summary, ordered)


def _json(d: dict) -> bytes:
    return (json.dumps(d, indent=1, allow_nan=False) + "\n").encode()


def _check_out(out: Path, options: EvaluateOptions) -> None:
    if out.exists() and not out.is_dir():
        raise BagExistsError(f"{out} exists and is not a directory")
    summary = out / SUMMARY_FILE
    if (summary.exists() or summary.is_symlink()) and not summary.is_file():
        raise BagExistsError(f"{summary} is not a file (a directory or another kind): remove it, or pass "
                             "another --out")
    if (out / BAGS_DIR).exists() and not (out / BAGS_DIR).is_dir():
        raise BagExistsError(f"{out / BAGS_DIR} is not a directory: remove it, or pass another --out")
    earlier = summary.exists() or any((out / BAGS_DIR).glob("*"))
    if earlier and not (options.resume or options.force):
        raise BagExistsError(f"{out} holds an earlier evaluation: pass --resume to continue it "
                             "or --force to start over")


def _entry(r: dict) -> dict:
    m = r.get("metrics") or {}
    lat = m.get("latency_ms") or {}
    return {"name": r["name"], "bag": r["bag"], "status": r["status"], "error": r["error"],
            "out": f"{BAGS_DIR}/{r['name']}", "frames": m.get("frames"),
            "frames_scored": m.get("frames_scored"), "miou": m.get("miou"),
            "latency_p50_ms": lat.get("p50"), "sync": m.get("sync"), "seconds": _round(r["seconds"]),
            "cpu_seconds": _round(r.get("cpu_seconds")), "resumed": r["resumed"], "node": r.get("node")}


def _round(v: float | None) -> float | None:
    return None if v is None else round(v, 3)
