"""Issue #11 "Honest maps": pooled visible-cell and whole-grid scores of a method over several bags.

Each bag is read and mapped as ``bev-bag replay`` does (its own rig and grid, the method's
``create_mapper``), and every frame of every bag is scored by one
:class:`bags.replay.ReplayScorer` (the replay's scorer: ``MetricAccumulator`` and
``WholeGridAccumulator``), so the figures pool all frames (dataset-level IoU, per-frame areas
over all frames) instead of averaging per-drive results.

    .venv/bin/bev-bag synth /tmp/d950000010 --rig surround6 --frames 20 --seed 950000010  # ...
    .venv/bin/python experiments/honest_maps.py /tmp/d9500000{10,11,12} --method ipm [--no-ipm-occlusion]
    .venv/bin/python experiments/honest_maps.py /tmp/d9500000{10,11,12} --json out.json  # Bi-Mapper
    .venv/bin/python experiments/honest_maps.py /tmp/d9000000{10,11,12} --weights W --unknown-below 0.3 0.5 0.7
    .venv/bin/python experiments/honest_maps.py BAGS --input rgb --method segipm   # RGB: + segmenter pixel IoU

On RGB input, a method with a segmenter stage (``segipm``, Bi-Mapper chained on label weights)
also gets its segmenter's pixel IoU per label against the bags' label images.
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np

from bags.io.reader import BagReader
from bags.replay import ReplayScorer
from bev_mapper_core.labels.classes import NUM_LABELS, Label
from bev_mapper_core.mapper import BACKENDS, INPUT_KINDS, SEGMENTER_PRECISIONS, MapperConfig, available_methods, create_mapper
from bev_mapper_core.metrics import format_table, format_whole_grid_table


def main() -> None:
    """Score the bags given on the command line and print both tables."""
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("bags", nargs="+", type=Path)
    p.add_argument("--method", default=MapperConfig.method, choices=available_methods())
    p.add_argument("--ipm-occlusion", action=argparse.BooleanOptionalAction,
                   default=MapperConfig.ipm_occlusion)
    p.add_argument("--weights", default=MapperConfig.weights, help="Bi-Mapper weights (default: the shipped file)")
    p.add_argument("--unknown-below", type=float, nargs="+", default=[MapperConfig.unknown_below],
                   help="Bi-Mapper visibility threshold(s); several values: one pass, one table each")
    p.add_argument("--input", dest="input_kind", default=MapperConfig.input_kind, choices=INPUT_KINDS)
    p.add_argument("--segmenter", default=MapperConfig.segmenter, help="RGB input: auto | none | FILE")
    p.add_argument("--backend", default=MapperConfig.backend, choices=BACKENDS, help="inference runtime")
    p.add_argument("--segmenter-precision", default=MapperConfig.segmenter_precision, choices=SEGMENTER_PRECISIONS,
                   help="RGB input: the segmenter stage's precision (issue #41)")
    p.add_argument("--json", type=Path, help="also write the pooled result here (the first threshold's)")
    args = p.parse_args()
    configs = [MapperConfig(method=args.method, ipm_occlusion=args.ipm_occlusion, weights=args.weights,
                            unknown_below=u, input_kind=args.input_kind, segmenter=args.segmenter,
                            backend=args.backend, segmenter_precision=args.segmenter_precision)
               for u in args.unknown_below]
    for i, config in enumerate(configs):
        run(args, config, args.json if i == 0 else None)


def run(args: argparse.Namespace, config: MapperConfig, json_path: Path | None) -> None:
    """Map and score every frame of ``args.bags`` with ``config``; print (and write) the result."""
    scorer = None
    t_map, n = 0.0, 0
    rgb = config.input_kind == "rgb"
    confusion = np.zeros((NUM_LABELS, NUM_LABELS), np.int64)  # (true, predicted) pixels of the segmenter
    for bag in args.bags:
        with BagReader(bag) as reader:
            rig, grid = reader.rig(), reader.grid()
            mapper = create_mapper(rig, grid, config)
            stage = getattr(mapper, "stage", None) if rgb else None
            if scorer is None:
                scorer = ReplayScorer(grid, mapper.class_names, reader.gt_classes, ground=False)
            for frame in reader.frames(rgb=rgb):
                t0 = time.perf_counter()
                pred = mapper.map(frame.rgb if rgb else frame.labels,
                                  ego_pose=frame.odom.world_from_ego if frame.odom else None, stamp_ns=frame.stamp_ns)
                t_map += time.perf_counter() - t0
                n += 1
                scorer.update(frame, pred)
                if stage is not None:  # segmenter pixel IoU (segmented again: not in the timing)
                    for name, seg in stage.segment(frame.rgb).items():
                        true = np.minimum(frame.labels[name], NUM_LABELS - 1).astype(np.int64)
                        confusion += np.bincount(true.ravel() * NUM_LABELS + seg.ravel(),
                                                 minlength=NUM_LABELS ** 2).reshape(NUM_LABELS, NUM_LABELS)
    result = scorer.result()
    if confusion.any():
        inter = np.diag(confusion)
        union = confusion.sum(0) + confusion.sum(1) - inter
        iou = {Label(i).name.lower(): (float(inter[i] / union[i]) if union[i] else None) for i in range(NUM_LABELS)}
        result["segmenter_pixel_iou"] = iou
        seen = [v for v in iou.values() if v is not None]
        result["segmenter_pixel_miou"] = float(np.mean(seen))
        print("segmenter pixel IoU %: " + ", ".join(f"{k} {100 * v:.1f}" for k, v in iou.items() if v is not None)
              + f"; mean {100 * result['segmenter_pixel_miou']:.1f}")
    what = (f"ipm (ipm_occlusion={config.ipm_occlusion})" if config.method == "ipm"
            else f"{config.method} (weights {config.weights or 'shipped'}, unknown_below={config.unknown_below}, "
                 f"input {config.input_kind})")
    print(f"{what} over {len(args.bags)} bag(s), "
          f"{n} frames, {1000 * t_map / max(n, 1):.1f} ms/frame mapping")
    print(format_table(result))
    print()
    print(format_whole_grid_table(result))
    if json_path:
        json_path.write_text(json.dumps({"method": config.method, "ipm_occlusion": config.ipm_occlusion,
                                         "input": config.input_kind, "segmenter": config.segmenter,
                                         "backend": config.backend, "segmenter_precision": config.segmenter_precision,
                                         "ms_per_frame": 1000 * t_map / max(n, 1),
                                         "weights": config.weights, "unknown_below": config.unknown_below,
                                         "bags": [str(b) for b in args.bags], **result}, indent=2))


if __name__ == "__main__":
    main()
