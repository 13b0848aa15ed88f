"""Ship issue #39's FocusBEV with segipm's prior: copy the chosen run's best file to
``bev_mapper_core/weights/focusbev_front1_rgb.safetensors`` with its model card, the scores read from
``experiments/score_s2g2_39.sh ... focusbev``'s JSON files (test sets A and B, never used for
training or choice).

    .venv/bin/python experiments/cards_focusbev_39.py --run RUN_DIR --eval EVAL_DIR --command "bev-train ..."
    .venv/bin/python -m bev_mapper_core.methods.cards write      # then docs/MODELS.md

The run and its epoch were chosen on the validation drives 900000000-05; this script only ships
it, and refuses unless it beats segipm on both test sets.
"""

from __future__ import annotations

import argparse
import shutil
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
if str(REPO) not in sys.path:
    sys.path.insert(0, str(REPO))
sys.path.insert(0, str(REPO / "experiments"))

from cards_s2g2_39 import LICENSE_NC, PRIOR, SYNTH_F1, TRUNK, _scores  # noqa: E402

from bev_mapper_core.methods import WEIGHTS_DIR  # noqa: E402
from bev_mapper_core.methods.cards import set_card  # noqa: E402

NAME = "focusbev_front1_rgb.safetensors"


def main(argv=None) -> int:
    """Command line entry (see the module docstring)."""
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--run", required=True, help="the chosen run directory (its best.safetensors ships)")
    ap.add_argument("--eval", required=True, help="experiments/score_s2g2_39.sh's output directory (focusbev)")
    ap.add_argument("--command", required=True, help="the run's bev-train command line")
    ap.add_argument("--details", required=True, help="steps, schedule and the chosen epoch")
    a = ap.parse_args(argv)
    scores = _scores(Path(a.eval), "focusbev")
    trunk = {**TRUNK, "description": TRUNK["description"].replace("S2G2's encoder", "FocusBEV's backbone")}
    card = {"card_version": 1,
            "summary": "FocusBEV for one front RGB camera (`front1` rig), mapping the `ahead` grid, 32 m x 32 m ahead "
                       "of base_link at 0.25 m (128 x 128 cells); node preset `config/front1_focusbev.yaml`. With "
                       "segipm's map of the same image as a prior (`prior_skip`, issue #39): the default segmenter's "
                       "labels projected by IPM enter the top-down network's head and the logits, and the network "
                       "learns its correction from the image's BEV features. Single frame (window 1: no memory "
                       "bank). Trained supervised on a frozen trunk (cached features).",
            "input": "the RGB image of the front camera, resized to 192x108 (w x h, from 400x225) for the backbone; "
                     "at its own 400x225 for the segmenter of the prior (which resizes it to its own 480 px)",
            "classes": ["drivable", "lane_divider", "ped_crossing", "road_boundary", "sidewalk", "vehicle",
                        "pedestrian"],
            "training_data": [SYNTH_F1, trunk, PRIOR], "license": LICENSE_NC,
            "training": {"command": a.command + f"\ncp {a.run}/best.safetensors bev_mapper_core/weights/{NAME}",
                         "details": a.details},
            "scores": scores}
    dest = WEIGHTS_DIR / NAME
    shutil.copy(Path(a.run) / "best.safetensors", dest)
    dest.chmod(0o644)
    set_card(dest, card)
    print(f"{NAME}: {scores[0]['values']['mIoU']} / {scores[1]['values']['mIoU']} (A / B)")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
