"""Issue #11 "Honest maps": pooled visible-cell and whole-grid scores of a method over several bags.

Each bag is read and mapped as ``bev-bag replay`` does (its own rig and grid, the method's
``create_mapper``), and every frame of every bag is scored by one
:class:`bags.replay.ReplayScorer` (the replay's scorer: ``MetricAccumulator`` and
``WholeGridAccumulator``), so the figures pool all frames (dataset-level IoU, per-frame areas
over all frames) instead of averaging per-drive results.

    .venv/bin/bev-bag synth /tmp/d950000010 --rig surround6 --frames 20 --seed 950000010  # ...
    .venv/bin/python bench/honest_maps.py /tmp/d9500000{10,11,12} --method ipm [--no-ipm-occlusion]
    .venv/bin/python bench/honest_maps.py /tmp/d9500000{10,11,12} --json out.json  # Bi-Mapper
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

from bags.reader import BagReader
from bags.replay import ReplayScorer
from bev_mapper_core.mapper import MapperConfig, available_methods, create_mapper
from bev_mapper_core.metrics import format_table, format_whole_grid_table


def main() -> None:
    """Score the bags given on the command line and print both tables."""
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("bags", nargs="+", type=Path)
    p.add_argument("--method", default=MapperConfig.method, choices=available_methods())
    p.add_argument("--ipm-occlusion", action=argparse.BooleanOptionalAction,
                   default=MapperConfig.ipm_occlusion)
    p.add_argument("--json", type=Path, help="also write the pooled result here")
    args = p.parse_args()
    config = MapperConfig(method=args.method, ipm_occlusion=args.ipm_occlusion)
    scorer = None
    t_map, n = 0.0, 0
    for bag in args.bags:
        with BagReader(bag) as reader:
            rig, grid = reader.rig(), reader.grid()
            mapper = create_mapper(rig, grid, config)
            if scorer is None:
                scorer = ReplayScorer(grid, mapper.class_names, reader.gt_classes, ground=False)
            for frame in reader.frames(rgb=False):
                t0 = time.perf_counter()
                pred = mapper.map(frame.labels, ego_pose=frame.odom.world_from_ego if frame.odom else None,
                                  stamp_ns=frame.stamp_ns)
                t_map += time.perf_counter() - t0
                n += 1
                scorer.update(frame, pred)
    result = scorer.result()
    what = f"ipm (ipm_occlusion={config.ipm_occlusion})" if config.method == "ipm" else config.method
    print(f"{what} over {len(args.bags)} bag(s), "
          f"{n} frames, {1000 * t_map / max(n, 1):.1f} ms/frame mapping")
    print(format_table(result))
    print()
    print(format_whole_grid_table(result))
    if args.json:
        args.json.write_text(json.dumps({"method": config.method, "ipm_occlusion": config.ipm_occlusion,
                                         "bags": [str(b) for b in args.bags], **result}, indent=2))


if __name__ == "__main__":
    main()
