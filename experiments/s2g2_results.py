"""S2G2 results: score trained runs on the front1 test drives, in the source and the target style.

For each run directory (``bev-train --method s2g2 ... --out runs/NAME``) its ``best.safetensors``
(chosen by the run's validation mIoU, on validation drives in the labeled styles) is scored
through ``create_mapper`` (as the node and ``bev-bag replay``) on the held-out test drives
(seeds 950000010-12, never used for training or model choice), rendered in the labeled styles
(``mixed``) and in the held-out ``dusk`` style. Both branches are scored on the validation drives
too, the evidence for the inference branch. IPM on the true labels and ``segipm`` on the RGB
images are scored on the same drives for scale. Prints markdown tables (mIoU and mAP per style,
per-class IoU and IoU by range on the target style) and writes every result as JSON beside the
run (``eval_<split>_<style>_<branch>.json``).

    .venv/bin/python experiments/s2g2_results.py runs/f1/sup runs/f1/semi40 ... [--threads 1]
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

TEST_SEEDS = (950_000_010, 950_000_011, 950_000_012)
VAL_SEEDS = (900_000_000, 900_000_001, 900_000_002)
STYLES = ("mixed", "dusk")


def score(run: Path, split: str, style: str, branch: str, cache: str) -> dict:
    """The run's best weights, mapping with ``branch``, on ``split`` drives in ``style`` (cached)."""
    out = run / f"eval_{split}_{style}_{branch}.json"
    if out.is_file() and out.stat().st_mtime > (run / "best.safetensors").stat().st_mtime:
        return json.loads(out.read_text())
    from bev_mapper_core.geometry.grid import BevGrid
    from bev_mapper_core.geometry.rig import preset_rig
    from bev_mapper_core.methods.s2g2.weights import load_s2g2, read_s2g2_metadata, save_s2g2
    from bev_mapper_core.training.evaluate import evaluate, save_result

    meta = read_s2g2_metadata(run / "best.safetensors")
    rig, grid = preset_rig(meta["rig"]), BevGrid.from_dict(meta["grid"])
    weights = run / f"best_{branch}.safetensors"
    if not weights.is_file() or weights.stat().st_mtime < (run / "best.safetensors").stat().st_mtime:
        model, _ = load_s2g2(run / "best.safetensors", rig, grid)
        save_s2g2(model, weights, inference_branch=branch)
    seeds = VAL_SEEDS if split == "val" else TEST_SEEDS
    res = evaluate(rig, grid, meta["classes"], "s2g2", str(weights), seeds, cache=cache, input_kind="rgb", style=style)
    save_result(res, out)
    return res


def reference(method: str, style: str, grid_name: str, classes, cache: str, out_dir: Path) -> dict:
    """IPM on the true label images, or segipm on the RGB images, on the test drives."""
    from bev_mapper_core.geometry.grid import grid_preset
    from bev_mapper_core.geometry.rig import preset_rig
    from bev_mapper_core.training.evaluate import evaluate, save_result

    out = out_dir / f"ref_{method}_{style}.json"
    if out.is_file():
        return json.loads(out.read_text())
    kind = "labels" if method == "ipm" else "rgb"
    res = evaluate(preset_rig("front1"), grid_preset(grid_name), classes, method, None, TEST_SEEDS, cache=cache,
                   input_kind=kind, style=style if kind == "rgb" else None)
    save_result(res, out)
    return res


def pct(v) -> str:
    return "-" if v is None else f"{100 * v:.1f}"


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("runs", nargs="+", type=Path)
    ap.add_argument("--cache", default="data/cache")
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--branch", choices=("auto", "active", "passive"), default="auto",
                    help="branch of the test rows (auto: the one with the better validation mIoU)")
    a = ap.parse_args(argv)
    import torch

    torch.set_num_threads(a.threads)
    rows, classes = [], None
    for run in a.runs:
        if not (run / "best.safetensors").is_file():
            print(f"error: {run} holds no best.safetensors", file=sys.stderr)
            return 1
        val = {b: score(run, "val", "mixed", b, a.cache) for b in ("active", "passive")}
        branch = max(val, key=lambda b: val[b]["miou"]) if a.branch == "auto" else a.branch
        test = {st: score(run, "test", st, branch, a.cache) for st in STYLES}
        classes = classes or list(test["dusk"]["classes"])
        rows.append((run.name, branch, val, test))
    from bev_mapper_core.geometry.grid import GRID_PRESETS, BevGrid

    grid = BevGrid.from_dict(rows[0][3]["dusk"]["grid"])
    grid_name = next(n for n, g in GRID_PRESETS.items() if g.isclose(grid))
    refs = {(m, st): reference(m, st, grid_name, classes, a.cache, a.runs[0].parent)
            for m in ("ipm", "segipm") for st in STYLES}

    print("| run | branch (val mIoU active / passive) | mIoU source | mIoU target (dusk) | mAP source | mAP target |")
    print("|---|---|---|---|---|---|")
    for name, branch, val, test in rows:
        print(f"| {name} | {branch} ({pct(val['active']['miou'])} / {pct(val['passive']['miou'])}) | "
              f"{pct(test['mixed']['miou'])} | **{pct(test['dusk']['miou'])}** | {pct(test['mixed']['map'])} | "
              f"{pct(test['dusk']['map'])} |")
    for (m, st), r in refs.items():
        if st == "mixed":
            d = refs[(m, "dusk")]
            label = "IPM, true labels" if m == "ipm" else "segipm (segmenter + IPM)"
            print(f"| *{label}* | | *{pct(r['miou'])}* | *{pct(d['miou'])}* | *{pct(r['map'])}* | *{pct(d['map'])}* |")
    bands = list(rows[0][3]["dusk"]["iou_by_range"])
    print()
    print("| run (target style, dusk) | " + " | ".join(classes) + " | mIoU | mAP | "
          + " | ".join(f"{b} m" for b in bands) + " |")
    print("|---|" + "---|" * (len(classes) + 2 + len(bands)))
    for name, _, _, test in rows:
        d = test["dusk"]
        print(f"| {name} | " + " | ".join(pct(d["classes"][c]["iou"]) for c in classes)
              + f" | **{pct(d['miou'])}** | {pct(d['map'])} | "
              + " | ".join(pct(v["miou"]) for v in d["iou_by_range"].values()) + " |")
    return 0


if __name__ == "__main__":
    sys.exit(main())
