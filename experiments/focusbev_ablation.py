"""FocusBEV's ablation: train the paper's rows side by side, score them on held-out drives.

Rows (front1, the ``ahead`` grid, 7 classes; RGB unless the row says labels):

* ``mlp``: the MLP baseline (0 decoder layers, no cycle, no temporal fusion);
* ``mlp_t``: + temporal fusion (window 2);  ``scvt``: + cycle view transformation (2 layers);
* ``full``: both (2 layers, cycle, window 2; the paper's model);
* ``l0`` / ``l1``: the full model with 0 / 1 decoder layers; ``w3``: window 3;
* ``nocycle``: 2 decoder layers without the cycle, single frame;
* ``mlp_labels`` / ``full_labels``: ``mlp`` / ``full`` on label images.

Phases (each skipped when its output exists, so the script resumes): render the drive caches in
parallel (training seeds ``0..train_drives-1``, validation 900000000-05 for model choice, test
950000010-19 never used for training or choice); train every row at once (``bev-train``,
``--resume``); score each row's ``best.safetensors`` through ``create_mapper`` on the test drives
(frames in order with their poses: temporal rows use their memory bank) with
``bev-train eval``; print a markdown table (per-class IoU, mIoU, static / dynamic mIoU, mIoU by
range) and write ``results.json``.

    python experiments/focusbev_ablation.py --out runs/fb --device cuda                 # GPU: every row at once
    python experiments/focusbev_ablation.py --out runs/fb --rows mlp,full --jobs 2       # CPU
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time
from concurrent.futures import ProcessPoolExecutor, ThreadPoolExecutor
from pathlib import Path

ROWS = {
    "mlp": ["--decoder-layers", "0", "--no-cycle", "--window", "1"],
    "mlp_t": ["--decoder-layers", "0", "--no-cycle", "--window", "2"],
    "scvt": ["--decoder-layers", "2", "--window", "1"],
    "full": ["--decoder-layers", "2", "--window", "2"],
    "l0": ["--decoder-layers", "0", "--window", "2"],
    "l1": ["--decoder-layers", "1", "--window", "2"],
    "w3": ["--decoder-layers", "2", "--window", "3"],
    "nocycle": ["--decoder-layers", "2", "--no-cycle", "--window", "1"],
    "mlp_labels": ["--decoder-layers", "0", "--no-cycle", "--window", "1", "--input", "labels"],
    "full_labels": ["--decoder-layers", "2", "--window", "2", "--input", "labels"],
}
TEST_SEEDS = tuple(950_000_010 + i for i in range(10))
COMMON = ["--rig", "front1", "--grid", "ahead", "--style", "mixed"]


def _render(args) -> int:
    seed, rgb, cache = args
    from bev_mapper_core.geometry.grid import grid_preset
    from bev_mapper_core.geometry.rig import preset_rig
    from bev_mapper_core.labels.classes import BEV_CLASS_NAMES
    from bev_mapper_core.training.data import drive_spec, load_or_render

    rig, grid = preset_rig("front1"), grid_preset("ahead")
    spec = drive_spec(rig, grid, BEV_CLASS_NAMES, 20, 3, rgb, "mixed" if rgb else None)
    load_or_render(rig, grid, spec, seed, cache)
    return seed


def render(cache: str, train_drives: int, jobs: int, seed: int = 0) -> None:
    """Every drive the runs and the scoring read, at the sizes they read them (in parallel)."""
    from bev_mapper_core.training.data import train_seeds, val_seeds

    seeds = list(train_seeds(seed, train_drives)) + list(val_seeds(6)) + list(TEST_SEEDS)
    tasks = [(s, rgb, cache) for s in seeds for rgb in ((108, 192), None)]
    tasks += [(s, (225, 400), cache) for s in TEST_SEEDS]  # full-size RGB for the Mapper path
    t0 = time.time()
    with ProcessPoolExecutor(jobs) as ex:
        list(ex.map(_render, tasks))
    print(f"rendered {len(tasks)} drive caches in {time.time() - t0:.0f} s", flush=True)


def train(rows, a) -> None:
    """Every row's ``bev-train`` at once (each resumes its own run directory)."""
    procs = []
    for name in rows:
        out = Path(a.out) / name
        out.mkdir(parents=True, exist_ok=True)
        extra = ROWS[name]
        cmd = [sys.executable, "-m", "bags.cli.train", "--method", "focusbev", *COMMON, "--out", str(out),
               "--epochs", str(a.epochs), "--frames-per-epoch", str(a.frames_per_epoch), "--batch", str(a.batch),
               "--lr", str(a.lr), "--lr-step-epoch", str(a.lr_step_epoch), "--train-drives", str(a.train_drives),
               "--val-frames", "60", "--seed", str(a.seed), "--cache", a.cache, "--device", a.device, "--threads", str(a.threads),
               "--no-progress", *extra] + (["--time-budget", str(a.minutes)] if a.minutes else [])
        if "--input" not in extra:
            cmd += ["--input", "rgb"]
        if (out / "last.safetensors").is_file():
            cmd.append("--resume")
        log = open(out.with_suffix(".log"), "a")
        procs.append(subprocess.Popen(cmd, stdout=log, stderr=subprocess.STDOUT))
    for p in procs:
        p.wait()


def score(name: str, a) -> dict:
    """The row's best weights on the test drives, through the Mapper (``bev-train eval``)."""
    run = Path(a.out) / name
    out = run / "test.json"
    if out.is_file() and out.stat().st_mtime > (run / "best.safetensors").stat().st_mtime:
        return json.loads(out.read_text())
    kind = "labels" if "--input" in ROWS[name] else "rgb"
    cmd = [sys.executable, "-m", "bags.cli.train", "eval", "--method", "focusbev", "--weights",
           str(run / "best.safetensors"), "--rig", "front1", "--grid", "ahead", "--input", kind, "--style", "mixed",
           "--val-seeds", ",".join(map(str, TEST_SEEDS)), "--cache", a.cache, "--device", a.device,
           "--threads", str(a.threads), "--json", str(out), "--name", name]
    subprocess.run(cmd, check=True, stdout=subprocess.DEVNULL)
    return json.loads(out.read_text())


def table(results: dict) -> str:
    """Markdown: per-class IoU, mIoU, static / dynamic mIoU, mIoU by range (percent)."""
    from bev_mapper_core.labels.classes import bev_class

    first = next(iter(results.values()))
    classes = list(first["classes"])
    bands = list(first["iou_by_range"])
    static = [c for c in classes if bev_class(c).flat]
    dynamic = [c for c in classes if not bev_class(c).flat]
    head = ["row"] + classes + ["mIoU", "static", "dynamic"] + [f"{b} m" for b in bands]
    lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]

    def pct(v):
        return "-" if v is None else f"{100 * v:.1f}"

    for name, r in results.items():
        ious = [r["classes"][c]["iou"] for c in classes]
        st, dy = (sum(r["classes"][c]["iou"] for c in cs) / len(cs) for cs in (static, dynamic))
        cells = [pct(v) for v in ious] + [f"**{pct(r['miou'])}**", pct(st), pct(dy)]
        cells += [pct(row["miou"]) for row in r["iou_by_range"].values()]
        lines.append(f"| {name} | " + " | ".join(cells) + " |")
    return "\n".join(lines)


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--out", default="runs/fb")
    p.add_argument("--rows", default=",".join(ROWS), help=f"comma list of {list(ROWS)}")
    p.add_argument("--cache", default="data/cache")
    p.add_argument("--device", default="cpu")
    p.add_argument("--threads", type=int, default=1)
    p.add_argument("--jobs", type=int, default=os.cpu_count() or 1, help="rendering processes")
    p.add_argument("--train-drives", type=int, default=60)
    p.add_argument("--seed", type=int, default=0, help="run seed: training drives and initialisation")
    p.add_argument("--epochs", type=int, default=28)
    p.add_argument("--lr-step-epoch", type=int, default=22)
    p.add_argument("--frames-per-epoch", type=int, default=800)
    p.add_argument("--batch", type=int, default=8)
    p.add_argument("--lr", type=float, default=4e-4, help="the paper's (nuScenes)")
    p.add_argument("--minutes", type=float, default=0.0, help="training time budget of each row (0: none)")
    p.add_argument("--phase", choices=("all", "render", "train", "score"), default="all")
    a = p.parse_args(argv)
    rows = [r for r in a.rows.split(",") if r]
    unknown = [r for r in rows if r not in ROWS]
    if unknown:
        print(f"error: unknown rows {unknown}; rows: {list(ROWS)}", file=sys.stderr)
        return 2
    if a.phase in ("all", "render"):
        render(a.cache, a.train_drives, a.jobs, a.seed)
    if a.phase in ("all", "train"):
        train(rows, a)
    if a.phase in ("all", "score"):
        done = [r for r in rows if (Path(a.out) / r / "best.safetensors").is_file()]
        with ThreadPoolExecutor(max(len(done), 1)) as ex:  # each eval is its own process
            results = dict(zip(done, ex.map(lambda r: score(r, a), done)))
        Path(a.out, "results.json").write_text(json.dumps(results, indent=1))
        print(table(results))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
