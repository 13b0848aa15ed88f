"""Issue #28: the column search's two constants swept, each setting scored against the polar search.

``COLUMN_FACE_BREAK_CELLS`` (a face breaks where the near edge steps by more than
``FACE_BREAK_M`` plus this many cells per image row) and ``COLUMN_SLACK_CELLS`` (a cell is hidden
this many cells farther beyond the object's assumed depth) stand in for the polar raster's
discretisation (:mod:`bev_mapper_core.methods.ipm.columns`). For every pair of
``--face-break`` x ``--slack`` values, the frames of the bags of each rig are mapped with the
column search and scored by the replay's scorer, pooled per rig, beside the polar search's maps
of the same frames (``experiments/ipm_occlusion_columns.py`` compares the default pair alone).
Printed per rig and pair: the change of visible mIoU (points), of the false vehicle area in
hidden cells (%), of the unknown recall (points) and the vehicle IoU; then the pairs ordered by
their largest mIoU change over the rigs. Run it on validation drives only.

    for r in surround6 front1 cam2bev4; do for s in 10 11 12; do
      .venv/bin/bev-bag synth /tmp/h28v/$r-$s --rig $r --frames 20 --seed 9000000$s \\
        $([ $r = front1 ] && echo --grid ahead); done; done
    .venv/bin/python experiments/ipm_occlusion_columns_sweep.py /tmp/h28v/* [--json out.json]
"""

from __future__ import annotations

import argparse
import itertools
import json
from collections import defaultdict
from pathlib import Path

from ipm_occlusion_columns import PolarIpmMapper, summary

import bev_mapper_core.methods.ipm.columns as columns
from bags.io.reader import BagReader
from bags.replay import ReplayScorer
from bev_mapper_core.mapper import MapperConfig
from bev_mapper_core.methods.ipm.mapper import IpmMapper


def _score(mapper, frames, grid, gt_classes) -> dict:
    """The equivalence figures of ``mapper``'s maps of ``frames`` (the replay's scorer)."""
    scorer = ReplayScorer(grid, mapper.class_names, gt_classes, ground=False)
    for frame in frames:
        scorer.update(frame, mapper.map(frame.labels))
    return summary(scorer.result())


def main() -> None:
    """Sweep the pairs on the bags given on the command line, pooled per rig."""
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("bags", nargs="+", type=Path)
    p.add_argument("--face-break", type=float, nargs="+", default=[0.0, 1.0, 2.0, 4.0])
    p.add_argument("--slack", type=float, nargs="+", default=[0.0, 1.0, 2.0, 3.0])
    p.add_argument("--json", type=Path, help="also write the figures here")
    args = p.parse_args()
    by_rig = defaultdict(list)
    for bag in args.bags:
        with BagReader(bag) as reader:
            by_rig[reader.rig().name].append(bag)
    out: dict[str, dict] = {}
    saved = columns.COLUMN_FACE_BREAK_CELLS, columns.COLUMN_SLACK_CELLS
    try:
        for rig_name, bags in by_rig.items():
            frames = []
            for bag in bags:
                with BagReader(bag) as reader:
                    rig, grid, gt_classes = reader.rig(), reader.grid(), reader.gt_classes
                    frames.extend(reader.frames())
            config = MapperConfig(method="ipm")
            ref = _score(PolarIpmMapper(rig, grid, config), frames, grid, gt_classes)
            out[rig_name] = {"polar": ref}
            mapper = IpmMapper(rig, grid, config)
            for fb, sl in itertools.product(args.face_break, args.slack):
                columns.COLUMN_FACE_BREAK_CELLS, columns.COLUMN_SLACK_CELLS = fb, sl  # read per frame
                got = out[rig_name][f"{fb},{sl}"] = _score(mapper, frames, grid, gt_classes)
                print(f"{rig_name} face break {fb} slack {sl}: "
                      f"mIoU {100 * (got['visible_miou'] - ref['visible_miou']):+.2f}, "
                      f"vehicle false {100 * (got['vehicle_false_m2_per_frame'] / ref['vehicle_false_m2_per_frame'] - 1):+.1f} %, "
                      f"unknown recall {100 * (got['unknown_recall'] - ref['unknown_recall']):+.2f}, "
                      f"vehicle IoU {100 * got['iou']['vehicle']:.1f} (polar {100 * ref['iou']['vehicle']:.1f})",
                      flush=True)
    finally:
        columns.COLUMN_FACE_BREAK_CELLS, columns.COLUMN_SLACK_CELLS = saved
    pairs = [k for k in next(iter(out.values())) if k != "polar"]

    def worst(key: str, pair: str, relative: bool) -> float:
        def change(r):
            got, ref = out[r][pair][key], out[r]["polar"][key]
            return 100 * (got / ref - 1 if relative else got - ref)
        return max(abs(change(r)) for r in out)

    print("pairs by their largest change over the rigs:")
    for pair in sorted(pairs, key=lambda k: worst("visible_miou", k, False)):
        print(f"  {pair:9s} mIoU {worst('visible_miou', pair, False):.2f}, "
              f"vehicle false {worst('vehicle_false_m2_per_frame', pair, True):.1f} %")
    if args.json:
        args.json.write_text(json.dumps(out, indent=2))


if __name__ == "__main__":
    main()
