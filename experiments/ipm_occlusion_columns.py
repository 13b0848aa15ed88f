"""Issue #28: IPM's occlusion search per image column against the polar raster's, scored alike.

Every frame of every bag is mapped by two ``IpmMapper`` (occlusion reasoning on) that differ only
in the near-edge search: per image column (``IpmMapper.occlusion_columns``, the default since
#28) and along the polar raster's BEV rays (the search before), and by the classical IPM for
the timing reference. Each search's maps are scored by its own :class:`bags.replay.ReplayScorer`
pooled over the bags of one rig (the replay's scorer, as ``experiments/honest_maps.py``).
Printed per rig: visible mIoU, false vehicle area in hidden cells (m^2/frame), unknown recall,
known precision, the share of cells whose known flag differs, and ms/frame of the three mappers
measured interleaved on the same frames (one frame each in turn).

    for r in surround6 front1 cam2bev4; do for s in 10 11 12; do
      .venv/bin/bev-bag synth /tmp/h28/$r-$s --rig $r --frames 20 --seed 9500000$s \\
        $([ $r = front1 ] && echo --grid ahead); done; done
    .venv/bin/python experiments/ipm_occlusion_columns.py /tmp/h28/surround6-1{0,1,2} \\
        /tmp/h28/front1-1{0,1,2} /tmp/h28/cam2bev4-1{0,1,2} [--json out.json]
"""

from __future__ import annotations

import argparse
import json
import time
from collections import defaultdict
from pathlib import Path

from bags.io.reader import BagReader
from bags.replay import ReplayScorer
from bev_mapper_core.mapper import MapperConfig
from bev_mapper_core.methods.ipm.mapper import IpmMapper


class PolarIpmMapper(IpmMapper):
    """The default IPM with the near-edge search along the polar raster (before #28)."""

    occlusion_columns = False


def summary(result: dict) -> dict:
    """The equivalence figures of a scorer's result."""
    occ = result.get("occlusion") or {}
    vehicle = (occ.get("classes") or {}).get("vehicle", {})
    return {"visible_miou": result.get("miou"), "vehicle_false_m2_per_frame": vehicle.get("false_m2_per_frame"),
            "unknown_recall": occ.get("unknown_recall"), "known_precision": occ.get("known_precision"),
            "iou": {k: v.get("iou") for k, v in (result.get("classes") or {}).items()}}


def main() -> None:
    """Score both searches on the bags given on the command line, pooled per rig."""
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("bags", nargs="+", type=Path)
    p.add_argument("--json", type=Path, help="also write the figures here")
    args = p.parse_args()
    by_rig = defaultdict(list)
    for bag in args.bags:
        with BagReader(bag) as reader:
            by_rig[reader.rig().name].append(bag)
    out = {}
    for rig_name, bags in by_rig.items():
        scorers, ms, n, differ = {}, defaultdict(float), 0, 0.0
        for bag in bags:
            with BagReader(bag) as reader:
                rig, grid = reader.rig(), reader.grid()
                mappers = {"columns": IpmMapper(rig, grid, MapperConfig(method="ipm")),
                           "polar": PolarIpmMapper(rig, grid, MapperConfig(method="ipm")),
                           "classical": IpmMapper(rig, grid, MapperConfig(method="ipm", ipm_occlusion=False))}
                if not scorers:
                    scorers = {k: ReplayScorer(grid, mappers[k].class_names, reader.gt_classes, ground=False)
                               for k in ("columns", "polar")}
                for frame in reader.frames():
                    preds = {}
                    for k, m in mappers.items():  # interleaved: one frame each in turn
                        t0 = time.perf_counter()
                        preds[k] = m.map(frame.labels)
                        ms[k] += (time.perf_counter() - t0) * 1000.0
                    for k, s in scorers.items():
                        s.update(frame, preds[k])
                    differ += float((preds["columns"].known != preds["polar"].known).mean())
                    n += 1
        res = {k: summary(s.result()) for k, s in scorers.items()}
        res["known_differs_share"] = differ / max(n, 1)
        res["ms_per_frame"] = {k: v / max(n, 1) for k, v in ms.items()}
        res["frames"], res["bags"] = n, [str(b) for b in bags]
        out[rig_name] = res
        c, q = res["columns"], res["polar"]
        t = res["ms_per_frame"]
        print(f"{rig_name}: {len(bags)} bags, {n} frames; known flag differs on {100 * res['known_differs_share']:.2f} % of cells")
        print(f"  {'search':8s} {'vis. mIoU':>9s} {'veh. false m2/fr':>16s} {'unknown recall':>14s} {'known prec.':>11s}")
        for k, s in (("polar", q), ("columns", c)):
            print(f"  {k:8s} {100 * s['visible_miou']:9.2f} {s['vehicle_false_m2_per_frame']:16.2f} "
                  f"{100 * s['unknown_recall']:13.2f}% {100 * s['known_precision']:10.2f}%  IoU "
                  + " ".join(f"{name} {100 * v:.1f}" for name, v in s["iou"].items() if v is not None))
        print(f"  ms/frame (interleaved): classical {t['classical']:.2f}, columns {t['columns']:.2f} "
              f"({t['columns'] / t['classical']:.2f}x), polar {t['polar']:.2f} ({t['polar'] / t['classical']:.2f}x)")
    if args.json:
        args.json.write_text(json.dumps(out, indent=2))


if __name__ == "__main__":
    main()
