"""``bev-bag evaluate BAG_OR_DIR ... --out DIR``: replay many bags as Ray tasks (one per bag)
and score them together (see :mod:`bags.fleet.evaluate`).
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from bev_mapper_core.metrics import format_table, format_whole_grid_table

from ..fleet.evaluate import EvaluateOptions, evaluate
from ..fleet.ray_tasks import add_ray_args
from .replay import add_replay_args
from .replay import options_from_args as replay_options_from_args

HELP = ("replay many bags as Ray tasks (one per bag, the same code as replay) and score them "
        "together: summary.json, per-bag outputs")

_EPILOG = """\
outputs in DIR (each written under a temporary name and renamed when complete):
  bags/<name>/        what 'bev-bag replay' writes for the bag (metrics.json,
                      bev_bag/, frames/, report.html ...) and evaluate.json: its
                      status, options, mergeable scores and per-frame latencies
  summary.json        the aggregate over the complete bags and one entry per bag
                      (status ok / damaged / failed with its error); written last

The aggregate is exact: IoU from the intersections and unions summed over every
frame of every complete bag (not a mean of per-bag means), Chamfer distances
weighted by frames, latency percentiles over all frames: the same numbers as
replaying all frames through one scorer. A damaged bag (replayed up to its
damage) or an unreadable one fails alone and stays out of the aggregate; the
others complete, and the exit status is then 1.

Ray: without --ray-address a local Ray runtime of --workers CPUs (default: this
machine's) starts and stops with the command. --ray-address auto joins the
cluster this machine belongs to (started with 'ray start'), HOST:PORT a head
node's address, ray://HOST:10001 through the Ray client (needs ray[client]).
Every node needs this package installed and the bags and DIR at the same paths
(shared storage).
"""


def configure(p: argparse.ArgumentParser) -> None:
    """Arguments of ``bev-bag evaluate``: the inputs, Ray's and every flag of ``replay``."""
    p.formatter_class = argparse.RawDescriptionHelpFormatter
    p.epilog = _EPILOG
    p.add_argument("bags", nargs="+", type=Path, metavar="BAG_OR_DIR",
                   help="bags (rosbag2 directories, .mcap, .db3) or directories searched for bags")
    p.add_argument("--out", type=Path, required=True, help="output directory")
    add_ray_args(p.add_argument_group("Ray"), "bags replayed")
    p.add_argument("--resume", action="store_true",
                   help="keep the bags an earlier run with the same options completed in DIR")
    add_replay_args(p)


def options_from_args(args: argparse.Namespace) -> EvaluateOptions:
    """Validate parsed arguments into :class:`EvaluateOptions`."""
    per_bag = argparse.Namespace(**{**vars(args), "bag": Path(), "out": Path(), "force": False,
                                    "quiet": True})
    return EvaluateOptions(
        bags=tuple(args.bags), out=args.out, replay=replay_options_from_args(per_bag),
        ray_address=args.ray_address, workers=args.workers, resume=args.resume,
        force=args.force, progress=not args.quiet and sys.stderr.isatty())


def run(args: argparse.Namespace) -> int:
    """Run ``bev-bag evaluate``: print the per-bag and aggregate tables; 1 if a bag failed."""
    result = evaluate(options_from_args(args))
    print(format_summary(result.summary))
    for r in result.summary.get("redone", []):
        print(f"note: {r['name']} replayed again: {r['reason']}", file=sys.stderr)
    for e in result.summary["per_bag"]:
        sync = e.get("sync") or {}
        if sync.get("partial_sets"):
            missing = ", ".join(f"{c}: {n}" for c, n in sync["missing_by_camera"].items() if n)
            print(f"note: {e['name']}: {sync['partial_sets']} of {sync['sets']} set(s) mapped without some camera "
                  f"({missing}; {sync['split_frames']} split by the {sync['window_ms']:g} ms window)", file=sys.stderr)
    for r in result.records:
        if r["status"] != "ok":
            print(f"error: {r['name']} ({r['bag']}): {r['status']}: {r['error']}", file=sys.stderr)
    for e in result.summary["aggregate"]["excluded"]:
        print(f"error: {e['name']} left out of the aggregate: {e['reason']}", file=sys.stderr)
    if any(r["status"] != "ok" for r in result.records):
        print("note: the same command with --resume replays only the bags that are not ok "
              "(a bag lost with its node, a damaged bag repaired since)", file=sys.stderr)
    return 0 if result.ok else 1


def format_summary(summary: dict) -> str:
    """The per-bag table, then the aggregate's metric tables, as printed by the command."""
    rows = summary["per_bag"]
    width = max([len("bag")] + [len(r["name"]) for r in rows])
    head = f"{'bag':<{width}}  {'status':<8}  {'frames':>6}  {'scored':>6}  {'mIoU%':>6}  {'p50 ms':>7}  {'s':>6}"
    lines = [head, "-" * len(head)]
    for r in rows:
        miou = "-" if r["miou"] is None else f"{100 * r['miou']:.1f}"
        p50 = "-" if r["latency_p50_ms"] is None else f"{r['latency_p50_ms']:.1f}"
        sec = "-" if r["seconds"] is None else f"{r['seconds']:.1f}"
        status = r["status"] + ("*" if r["resumed"] else "")
        lines.append(f"{r['name']:<{width}}  {status:<8}  {_n(r['frames']):>6}  "
                     f"{_n(r['frames_scored']):>6}  {miou:>6}  {p50:>7}  {sec:>6}")
    agg = summary["aggregate"]
    b = summary["bags"]
    lines.append("-" * len(head))
    lat = agg["latency_ms"]
    lines.append(f"{b['ok']} of {b['total']} bag(s) ok ({b['resumed']} resumed: *), {b['damaged']} "
                 f"damaged, {b['failed']} failed; aggregate over {agg['bags']} bag(s), "
                 f"{agg['frames']} frame(s), mapping p50 {lat['p50']} ms, p95 {lat['p95']} ms")
    if agg["frames_scored"]:
        lines += ["", format_table({**agg, "frames": agg["frames_scored"]}), "",
                  format_whole_grid_table(agg)]
    return "\n".join(lines)


def _n(v) -> str:
    return "-" if v is None else str(v)
