r"""Score a segmenter weights file on CamVid (pooled pixel IoU) and time it on the CPU.

    PYTHONPATH=. python experiments/eval_camvid.py bev_mapper_core/weights/segmenter.safetensors \\
        --camvid /work/data/camvid [--split test] [--synth-drives 2] [--threads 1]

The CamVid figures are those of ``bev-train eval --method segmenter --real camvid:DIR --split
test --segmenter FILE`` (the same functions: :mod:`bev_mapper_core.methods.segmenter.real`);
this script adds the held-out synthetic drives' fine pixel IoU (``--synth-drives``) and runs
where only ``bev_mapper_core`` is copied (the device folder of ``pack_for_device.py``).

Prints the IoU of every CamVid class (fine argmax, each fine label mapped to its home CamVid
class: :meth:`~bev_mapper_core.nn.label_space.LabelSpace.coarse_of_fine`; Unlabelled pixels are
left out), the five common classes (road with markings, sidewalk, vehicle, pedestrian, building)
and their mean, and the CPU time per 480x360 frame with ``--threads`` threads (segment():
resize, network, upsampling to 480x360, argmax). ``--synth-drives N`` also scores the fine
pixel IoU on N held-out synthetic drives (seeds 900000000.., 10 frames, surround6), the frames
``segmenter_real.py`` validates on. ``--json FILE`` writes the figures.
"""

from __future__ import annotations

import argparse
import json

import numpy as np
import torch

from bev_mapper_core.datasets import CamVid
from bev_mapper_core.labels.spaces import FINE
from bev_mapper_core.methods.segmenter.real import format_report, ms_per_frame, score_reader
from bev_mapper_core.methods.segmenter.weights import load_segmenter
from bev_mapper_core.nn.label_space import confusion, iou_from_confusion


def main(argv=None) -> int:
    """Command line entry (see the module docstring)."""
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("weights")
    ap.add_argument("--camvid", required=True)
    ap.add_argument("--split", default="test", choices=("train", "val", "test"))
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--limit", type=int, default=0, help="first N frames only")
    ap.add_argument("--timing-frames", type=int, default=10)
    ap.add_argument("--synth-drives", type=int, default=0)
    ap.add_argument("--json", default="")
    a = ap.parse_args(argv)
    torch.set_num_threads(a.threads)
    model = load_segmenter(a.weights)
    ds = CamVid(a.camvid, a.split)
    rep = score_reader(model, ds, a.limit)  # the scoring of `bev-train eval --method segmenter --real`
    ms = ms_per_frame(model, ds.read(0).image, a.timing_frames)
    res = {"weights": a.weights, "config": model.config.to_dict(), "split": a.split, **rep,
           "cpu_ms_per_frame": round(ms, 1), "threads": a.threads,
           "params": sum(p.numel() for p in model.parameters())}
    for line in format_report(f"{a.weights}: CamVid {a.split}", rep):
        print(line)
    print(f"  CPU {ms:.1f} ms/frame (480x360, {a.threads} thread(s)), {res['params'] / 1e6:.2f} M params, "
          f"input {model.config.input_size((480, 360))}")
    if a.synth_drives:
        from bev_mapper_core.geometry.grid import BevGrid
        from bev_mapper_core.geometry.rig import preset_rig
        from bev_mapper_core.labels.classes import BEV_CLASS_NAMES
        from bev_mapper_core.training.data import render_drive, val_seeds

        sconf = torch.zeros(FINE.num_classes, FINE.num_classes + 1, dtype=torch.long)
        for seed in val_seeds(a.synth_drives):
            d = render_drive(preset_rig("surround6"), BevGrid(), BEV_CLASS_NAMES, seed, 10, 3, rgb=(225, 400))
            rgb, lab = d["rgb"].reshape(-1, 225, 400, 3), d["labels"].reshape(-1, 225, 400)
            with torch.inference_mode():
                for i in range(0, len(rgb), 12):
                    pred = model.segment(torch.from_numpy(rgb[i:i + 12]))
                    sconf += confusion(pred, torch.from_numpy(lab[i:i + 12]), FINE.num_classes)
        siou = iou_from_confusion(sconf) * 100
        res["synth_fine_iou"] = {c: round(float(v), 2) for c, v in zip(FINE.classes, siou)}
        res["synth_miou"] = round(float(np.nanmean(siou)), 2)
        print(f"  synthetic held-out ({a.synth_drives} drives x 10 frames x 6 cameras) fine pixel mIoU "
              f"{res['synth_miou']:.1f}: " + "  ".join(f"{c} {v:.1f}" for c, v in res["synth_fine_iou"].items()))
    if a.json:
        with open(a.json, "w") as f:
            json.dump(res, f, indent=1)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
