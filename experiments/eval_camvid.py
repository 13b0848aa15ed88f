r"""Score a segmenter weights file on CamVid (pooled pixel IoU) and time it on the CPU.

    PYTHONPATH=. python experiments/eval_camvid.py bev_mapper_core/weights/segmenter.safetensors \\
        --camvid /work/data/camvid [--split test] [--synth-drives 2] [--threads 1]

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
import time

import numpy as np
import torch

from bev_mapper_core.datasets import CamVid
from bev_mapper_core.methods.segmenter.weights import load_segmenter
from bev_mapper_core.nn.label_space import CAMVID, COMMON_CAMVID, FINE, coarse_predict, confusion, iou_from_confusion


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
    n = min(a.limit, len(ds)) if a.limit else len(ds)
    conf = torch.zeros(CAMVID.num_classes, CAMVID.num_classes + 1, dtype=torch.long)
    times = []
    with torch.inference_mode():
        for i in range(n):
            s = ds.read(i)
            img = torch.from_numpy(s.image)[None]  # (1, H, W, 3)
            t = time.perf_counter()
            logits = model(model.preprocess(img), size=s.image.shape[:2])
            pred = coarse_predict(logits, CAMVID)
            times.append(time.perf_counter() - t)
            conf += confusion(pred, torch.from_numpy(s.labels)[None], CAMVID.num_classes)
        # timing of the shipped call path (segment: argmax to Label ids), after warm-up
        img = torch.from_numpy(ds.read(0).image)[None]
        model.segment(img)
        t = time.perf_counter()
        for _ in range(a.timing_frames):
            model.segment(img)
        ms = (time.perf_counter() - t) / a.timing_frames * 1000
    iou = iou_from_confusion(conf) * 100
    per = {c: round(float(v), 2) for c, v in zip(CAMVID.classes, iou)}
    common = {k: per[c] for k, c in COMMON_CAMVID.items()}
    res = {"weights": a.weights, "config": model.config.to_dict(), "split": a.split, "frames": n, "per_class": per,
           "common": common, "common_mean": round(float(np.mean(list(common.values()))), 2),
           "cpu_ms_per_frame": round(ms, 1), "threads": a.threads,
           "params": sum(p.numel() for p in model.parameters())}
    print(f"{a.weights}: CamVid {a.split}, {n} frames, pooled pixel IoU %")
    print("  " + "  ".join(f"{c} {v:.1f}" for c, v in per.items()))
    print("  common: " + "  ".join(f"{k} {v:.1f}" for k, v in common.items()) + f"  mean {res['common_mean']:.1f}")
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
