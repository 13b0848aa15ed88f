"""Ship issue #38's Bi-Mapper weights for any rig: the chosen run's file into
``bev_mapper_core/weights/bimapper_any_labels.safetensors`` with its model card, every score read
from the JSON files ``bev-train eval`` wrote (``experiments/anyrig_eval.sh``), and print the
tables of docs/RESULTS.md's section on it.

    .venv/bin/python experiments/cards_anyrig38.py --run runs/anyrig/run120 --eval out/anyrig
    .venv/bin/python -m bev_mapper_core.methods.cards write      # then docs/MODELS.md

The run was chosen before on validation drives only (its ``best`` checkpoint by the trainer's
validation mIoU on the held-out rigs random-900000000.., and the RGB check on rig
random-900000003 with drives 900000000-01); the test rigs and drives below were scored once,
for this card.
"""

from __future__ import annotations

import argparse
import json
import shutil
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
if str(REPO) not in sys.path:
    sys.path.insert(0, str(REPO))

from bev_mapper_core.geometry.random_rig import random_rig  # noqa: E402
from bev_mapper_core.methods import WEIGHTS_DIR  # noqa: E402
from bev_mapper_core.methods.cards import set_card  # noqa: E402

DEST = "bimapper_any_labels.safetensors"
CLASSES = ("drivable", "lane_divider", "ped_crossing", "road_boundary", "sidewalk", "vehicle", "pedestrian")
#: the rigs no training drive used, scored on the test drives 950000010-12 (100 frames each)
TEST_RIGS = ("random-950000044", "random-950000022")
EVAL_CMD = "bash experiments/anyrig_eval.sh {method} {rig} {input}"


def _row(doc: dict) -> dict:
    vals = {c: round(100 * doc["classes"][c]["iou"], 1) for c in CLASSES}
    vals["mIoU"] = round(100 * doc["miou"], 1)
    return vals


def _describe(rig_name: str) -> str:
    rig = random_rig(int(rig_name.split("-")[1]))
    w, h = rig.cameras[0].model.image_size
    height = rig.cameras[0].ego_from_cam_array[2, 3]
    return f"{rig_name}: {len(rig.cameras)} cameras of {w}x{h} ({w / h:.2f}:1), {height:.2f} m high"


def load(eval_dir: Path, rig: str, kind: str, method: str) -> dict | None:
    path = eval_dir / f"{rig}_{kind}_{method}.json"
    return json.loads(path.read_text()) if path.is_file() else None


def tables(eval_dir: Path) -> str:
    """The markdown tables of the test rigs: RGB (default vs segipm), labels (default vs IPM)."""
    out = []
    for kind, ref in (("rgb", "segipm"), ("labels", "ipm")):
        out.append(f"\n**{kind}** ({'the default = segmenter, then these weights' if kind == 'rgb' else 'true label images'}"
                   f" against {ref}), visible-cell IoU %:\n")
        out.append("| rig | method | " + " | ".join(CLASSES) + " | mIoU |")
        out.append("|---|---|" + "---|" * (len(CLASSES) + 1))
        for rig in TEST_RIGS:
            for method in ("bimapper", ref):
                doc = load(eval_dir, rig, kind, method)
                if doc is None:
                    continue
                v = _row(doc)
                name = "default (weights for any rig)" if method == "bimapper" else method
                out.append(f"| {_describe(rig)} | {name} | " + " | ".join(f"{v[c]}" for c in CLASSES)
                           + f" | **{v['mIoU']}** |")
    return "\n".join(out)


def main(argv=None) -> int:
    """Copy the chosen file, set its card, print the RESULTS tables."""
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--run", required=True, type=Path, help="the training run (its best.safetensors is shipped)")
    ap.add_argument("--eval", required=True, type=Path, help="the folder of experiments/anyrig_eval.sh's JSON files")
    ap.add_argument("--val", required=True, type=Path, help="the validation JSON of the shipped file on RGB (rig 900000003)")
    ap.add_argument("--val-segipm", required=True, type=Path, help="segipm's on the same validation drives")
    a = ap.parse_args(argv)
    best = json.loads((a.run / "best.json").read_text())
    dest = WEIGHTS_DIR / DEST
    shutil.copyfile(a.run / "best.safetensors", dest)
    scores = []
    for rig in TEST_RIGS:
        for kind, ref in (("rgb", "segipm"), ("labels", "ipm")):
            own, other = load(a.eval, rig, kind, "bimapper"), load(a.eval, rig, kind, ref)
            if own is None:
                continue
            scores.append({
                "data": f"test drives 950000010-12 (3 x 100 frames; never used for training or any choice) seen by "
                        f"{_describe(rig)}: a rig no training drive used; "
                        + ("RGB cameras, through segmenter.safetensors first" if kind == "rgb" else "true label images"),
                "metric": "BEV IoU % of the visible cells",
                "values": _row(own),
                "note": f"{ref} on the same drives: mIoU {_row(other)['mIoU']}" if other else "",
                "command": EVAL_CMD.format(method="bimapper", rig=rig, input=kind)})
    val, val_ref = json.loads(a.val.read_text()), json.loads(a.val_segipm.read_text())
    scores.append({
        "data": "validation drives 900000000-01 (2 x 20 frames) seen by rig random-900000003 (4 cameras), RGB "
                "through segmenter.safetensors (used to choose)",
        "metric": "BEV IoU % of the visible cells", "values": _row(val),
        "note": f"segipm on the same drives: mIoU {_row(val_ref)['mIoU']}",
        "command": "bev-train eval --rig random-900000003 --input rgb --method bimapper --val-seeds "
                   "900000000,900000001 --frames-per-drive 20 --threads 1"})
    card = {
        "card_version": 1,
        "summary": ("Bi-Mapper (RA-L 2023) for any rig: the local-self view stream only (IPM of each camera's "
                    "labels onto its own camera plane, one U-Net shared by every camera, merged into the ego grid "
                    "by the extrinsics) with the IPM skip and a visibility head, trained on drives of 120 seeded "
                    "random rigs (issue #38). Without the global-cross view stream no tensor depends on the number "
                    "of cameras or the image size: the geometry comes from each rig's CameraInfo and TF. The default "
                    "of `create_mapper`, `bev-bag replay` and the node for a rig without weights of its own, or "
                    "whose own weights do not fit its cameras or image aspect; on RGB cameras it runs behind "
                    "segmenter.safetensors (chained). Maps the default grid, 60 m x 30 m around the vehicle at "
                    "0.15 m (400 x 200 cells)."),
        "input": ("label images (the 11 pixel label ids, one-hot) of any number of cameras of any calibration, each "
                  "resized to 112 px wide (the first camera's aspect; cameras of other aspects are resized to it, "
                  "their IPM coordinates follow); RGB cameras through segmenter.safetensors first"),
        "classes": list(CLASSES),
        "training_data": [{
            "name": "synthetic drives of random rigs", "kind": "synthetic",
            "description": ("120 drives, seeds 0-119 (`bev-train --seed 0`), 20 frames each (every 3rd step), drive "
                            "s seen by the seeded random rig random-<s> (1-7 cameras around the body, 1.2-2.2 m "
                            "high, pitch -2..14 degrees, 50-120 degrees of field of view, 320-480 px images of "
                            "aspect 4:3, 16:9, 1.59:1, 16:10 or 2:1; bev_mapper_core/geometry/random_rig.py): "
                            "2400 frames of label images with BEV ground truth and visibility. Validation drives "
                            "900000000-05 with their rigs random-900000000-05 chose the checkpoint; test drives "
                            "950000000.. and their rigs are disjoint by construction."),
            "license": "Apache-2.0: generated by this package's own code; no third-party data",
            "source": "bev_mapper_core.synth (procedural town, ray-cast label images, BEV ground truth with visibility)"}],
        "license": {"weights": "Apache-2.0, as the package (no third-party data or weights in its lineage)",
                    "use": ("Trained only on synthetic drives this package generates: Apache-2.0, commercial use "
                            "included. On RGB it runs behind the default segmenter, whose CamVid lineage makes RGB "
                            "maps non-commercial unless `segmenter:=open` (see segmenter.safetensors).")},
        "training": {
            "command": ("bash experiments/anyrig_train.sh --train-drives 120 --epochs 12 --frames-per-epoch 480 "
                        "--lr-step-epoch 9 --time-budget 60 --out runs/anyrig/run120\n"
                        "python experiments/cards_anyrig38.py --run runs/anyrig/run120 --eval out/anyrig --val "
                        "out/anyrig/val_r3_rgb_run120.json --val-segipm out/anyrig/val_r3_rgb_segipm.json"),
            "details": (f"Batch 4, Adam lr 1e-3 (x0.1 from epoch 10, not reached), plain BCE on the decoder's "
                        f"output (no Across-Space Loss, no mutual learning: one stream), the visibility head's BCE "
                        f"(weight 1), 1 CPU thread, seed 0, one rig a batch. Stopped after epoch 10 of 12: the "
                        f"validation mIoU had fallen since epoch {best['best_epoch'] + 1}. The file is the "
                        f"checkpoint of the best validation mIoU: epoch {best['best_epoch'] + 1} (step "
                        f"{best['step']}), {100 * best['best_val_miou']:.1f} on the first 40 validation frames "
                        f"(true labels). The run with 40 drives of 40 rigs peaked at 79.9 (docs/RESULTS.md, "
                        f"'Any rig, any camera').")},
        "scores": scores,
    }
    set_card(dest, card)
    print(f"{dest}: card set")
    print(tables(a.eval))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
