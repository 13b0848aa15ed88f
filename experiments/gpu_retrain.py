"""Retrain every shipped RGB model in one go on a lent GPU machine (issue #26), within minutes.

One prepared command for a device session (an H100 / H200 with 16 CPU cores, about ten
minutes of work). It renders the drives every run needs in parallel on the machine's cores,
probes each run's rate (all at once, two short epochs) and plans each run's epochs to fill the
time left before ``--deadline-min`` (``--no-plan``: the recipes' epochs as written), trains all
runs at once on the GPU, each also stopped (resumably) by that budget, optionally times every
method on the GPU (``--bench``: ``bench/bench_cuda.py``), and writes the weights, logs and a
summary under ``--out`` (``--pack DIR``: the best weights and a log archive, for the trip home).
Weights trained on a GPU are scored again on CPU before they ship
(``experiments/score_rgb26.sh``, ``experiments/cards_rgb26.py``).

Runs (``--runs``, default the first four; each a ``bev-train`` command of :data:`RUNS`, every
one from the shipped segmenter's trunk, with the photometric augmentation on):

* ``s2g2``: supervised-only S2G2, front1, ``ahead`` grid;
* ``s2g2_semi``: the same with unlabeled frames: synthetic drives in the held-out ``dusk`` style
  and, with ``--camvid DIR``, CamVid's training images (``--unlabeled-real``);
* ``focusbev``: FocusBEV on the trunk (``--backbone efficientnet``), front1, ``ahead`` grid;
* ``bimapper_rgb``: end-to-end RGB Bi-Mapper, surround6, its encoders of the trunk's sizes;
* the second session's ablation rows on fixed recipes (``*_clip``, ``focusbev_mlp``,
  ``focusbev_w1``, ``s2g2_prior``, ``focusbev_prior``, ``bimapper_prior``: see :data:`RUNS`).

The drives are rendered with the cache specs the runs themselves compute (the method's input
size, classes, grid, frames, stride, style), so ``bev-train --cache`` finds every drive and
renders none. Phases resume: rendered drives stay in the cache, runs continue with ``--resume``.

    python experiments/gpu_retrain.py --out /tmp/gr --device cuda --deadline-min 9 --camvid camvid --bench --pack $OUT
    .venv/bin/python experiments/gpu_retrain.py --out /tmp/gr --tiny        # the CPU check

``--tiny`` shrinks every run (one short drive, a few steps, small models) so that the whole
script runs on a CPU in about two minutes: ``tests/experiments/test_gpu_retrain.py``.
"""

from __future__ import annotations

import argparse
import json
import multiprocessing
import os
import shutil
import subprocess
import sys
import tarfile
import time
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
if str(REPO) not in sys.path:  # run as a script from anywhere (the device runs it from its copy)
    sys.path.insert(0, str(REPO))

#: run name -> its bev-train flags (the data and the method; --out, --cache, --device, budget added)
RUNS: dict[str, list[str]] = {
    "s2g2": ["--method", "s2g2", "--rig", "front1", "--input", "rgb", "--grid", "ahead", "--train-drives", "40",
             "--epochs", "30", "--frames-per-epoch", "800", "--batch", "8", "--lr", "1e-3", "--lr-step-epoch", "22",
             "--optimizer", "adam", "--val-frames", "60", "--supervised-only"],
    "s2g2_semi": ["--method", "s2g2", "--rig", "front1", "--input", "rgb", "--grid", "ahead", "--train-drives", "40",
                  "--epochs", "30", "--frames-per-epoch", "800", "--batch", "8", "--lr", "1e-3",
                  "--lr-step-epoch", "22", "--optimizer", "adam", "--val-frames", "60", "--unlabeled-drives", "27",
                  "--unlabeled-style", "dusk"],
    "focusbev": ["--method", "focusbev", "--rig", "front1", "--input", "rgb", "--grid", "ahead",
                 "--backbone", "efficientnet", "--train-drives", "40",
                 "--epochs", "28", "--frames-per-epoch", "800", "--batch", "8", "--lr", "4e-4",
                 "--lr-step-epoch", "22", "--val-frames", "60"],
    "bimapper_rgb": ["--method", "bimapper", "--rig", "surround6", "--input", "rgb", "--train-drives", "40",
                     "--epochs", "20", "--frames-per-epoch", "800", "--batch", "4", "--lr", "1e-3",
                     "--lr-step-epoch", "15", "--val-frames", "40", "--ipm-skip", "--pos-weight", "none"],
}
def _override(flags: list[str], pairs: list[str]) -> list[str]:
    """``flags`` with each ``--name value`` pair of ``pairs`` replacing its own (or added)."""
    out = list(flags)
    for name, value in zip(pairs[::2], pairs[1::2]):
        if name in out:
            out[out.index(name) + 1] = value
        else:
            out += [name, value]
    return out


# The second GPU session's rows (issue #26's ablations), on fixed recipes (``--no-plan``): the
# S2G2 rows with the same steps as each other and a gradient clip (run 1's semi-supervised run
# diverged at epoch 12), the FocusBEV rows with the steps of run 1's full FocusBEV (18 epochs).
_S2G2_FIXED = ["--epochs", "28", "--lr-step-epoch", "21", "--grad-clip", "5"]
_FB_FIXED = ["--epochs", "18", "--lr-step-epoch", "14"]
RUNS.update({
    "s2g2_clip": _override(RUNS["s2g2"], _S2G2_FIXED),
    "s2g2_semi_clip": _override(RUNS["s2g2_semi"], _S2G2_FIXED),  # + CamVid's frames with --camvid
    "s2g2_semi_synth_clip": _override(RUNS["s2g2_semi"], _S2G2_FIXED),  # unlabeled synthetic frames only
    "s2g2_384_clip": _override(RUNS["s2g2"], _S2G2_FIXED + ["--input-width", "384"]),
    "focusbev_mlp": _override(RUNS["focusbev"], _FB_FIXED + ["--decoder-layers", "0", "--window", "1"]) + ["--no-cycle"],
    "focusbev_w1": _override(RUNS["focusbev"], _FB_FIXED + ["--window", "1"]),
})
# Issue #39's S2G2 recipe (the shipped front1 file, docs/RESULTS.md "Seed methods on the pretrained
# trunk"): segipm's map as a prior the branches correct, the trunk frozen and its features cached
# once per frame, low positive weights but pedestrians at 10; on CPU it ran 1000 steps of batch 4.
RUNS["s2g2_prior"] = _override(RUNS["s2g2"], ["--batch", "4", "--epochs", "30", "--lr-step-epoch", "24",
                                              "--grad-clip", "5", "--pos-weight-max", "3"]) + [
    "--prior-skip", "--frozen-encoder", "--feature-copies", "2", "--pos-weight-classes", "pedestrian=10"]
# Issue #39's FocusBEV recipe (the shipped front1 file, w2 in docs/RESULTS.md "FocusBEV with segipm's
# prior"): the same prior, frozen trunk and weights, window 2 (the memory bank: the trunk runs on
# both frames of a window, so no feature cache); on CPU it ran 2400 steps of batch 4 (12 epochs,
# the lr x0.1 for the last two).
RUNS["focusbev_prior"] = _override(RUNS["focusbev"], ["--batch", "4", "--lr", "1e-3", "--epochs", "30",
                                                      "--lr-step-epoch", "25", "--window", "2", "--grad-clip", "5",
                                                      "--pos-weight-max", "3"]) + [
    "--prior-skip", "--frozen-encoder", "--pos-weight-classes", "pedestrian=10"]
# Issue #39's RGB Bi-Mapper recipe (docs/RESULTS.md "RGB Bi-Mapper with segipm's prior"): the prior
# of the six cameras in place of the IPM skip, no ASL or mutual learning, the same weights; on CPU it
# ran 1200 steps of batch 4. Its ImageNet variant (run i1): at 1200 steps the shipped run from
# scratch (s1) was 0.7 ahead on validation, within the epochs' swings; a longer run may differ.
RUNS["bimapper_prior"] = _override(RUNS["bimapper_rgb"], ["--epochs", "30", "--lr-step-epoch", "24",
                                                          "--val-frames", "60", "--grad-clip", "5",
                                                          "--mutual", "none", "--pos-weight", "auto",
                                                          "--pos-weight-max", "3", "--encoder-init", "imagenet"])
RUNS["bimapper_prior"] = [f for f in RUNS["bimapper_prior"] if f != "--ipm-skip"] + [
    "--prior-skip", "--no-asl", "--pos-weight-classes", "pedestrian=10"]
#: model settings without flags of their own, per run (given with --config): the end-to-end
#: RGB Bi-Mapper's encoders take the shipped segmenter's trunk, so they have its sizes; the prior
#: recipe's are EfficientNet-Lite0's (the ImageNet checkpoint)
RUN_CONFIG: dict[str, dict] = {"bimapper_rgb": {"width_mult": 1.0, "depth_mult": 0.5, "encoder_stages": 5},
                               "bimapper_prior": {"encoder_variant": "lite0", "width_mult": 1.0, "depth_mult": 1.0}}
#: what --tiny changes in every run's flags: one short drive, a few steps
TINY = ["--train-drives", "1", "--val-drives", "1", "--frames-per-drive", "3", "--stride", "2", "--epochs", "1",
        "--frames-per-epoch", "2", "--batch", "1", "--val-frames", "2"]
#: what --tiny sets through a --config file (model sizes without flags of their own; a small grid)
TINY_CONFIG = {
    "s2g2": {"input_width": 32, "width_mult": 0.25, "depth_mult": 0.25, "encoder_stages": 3, "bev_downsample": 4,
             "decoder_channels": 8, "encoder_init": "none", "grid": [0.0, 16.0, -8.0, 8.0, 0.5]},
    "focusbev": {"input_width": 64, "backbone_width": 8, "channels": 16, "decoder_channels": 8,
                 "grid": [0.0, 16.0, -8.0, 8.0, 0.5]},
    "bimapper": {"input_width": 64, "gv_hidden": 16, "decoder_min_channels": 4, "grid": [-8.0, 8.0, -4.0, 4.0, 0.5]},
}


def run_flags(name: str, tiny: bool, camvid: str | None, out: Path) -> list[str]:
    """The bev-train flags of run ``name`` (data and method; :data:`RUN_CONFIG` in
    ``out/config_<name>.yaml`` given with ``--config``); with ``tiny``, shrunk (the data flags
    replaced, the model sizes of :data:`TINY_CONFIG` added to that file).
    """
    flags = list(RUNS[name])
    method = flags[flags.index("--method") + 1]
    config = dict(RUN_CONFIG.get(name, {}))
    if tiny:
        flags = _override(flags, TINY + (["--unlabeled-drives", "1"] if "--unlabeled-drives" in flags else []))
        config.update(TINY_CONFIG[method])
        flags = [f for f in flags if f not in ("--grid", "ahead")]
    if config:
        path = out / f"config_{name}.yaml"
        path.write_text(json.dumps(config) + "\n")  # JSON is YAML
        flags = ["--config", str(path), *flags]
    if name in ("s2g2_semi", "s2g2_semi_clip") and camvid:
        flags += ["--unlabeled-real", f"camvid:{camvid}"]
    return flags


def drive_jobs(flags: list[str], cache: str) -> list[tuple]:
    """``(rig, grid, spec, seed, cache)`` for every drive the run of ``flags`` loads: the specs
    the run computes itself (:class:`~bev_mapper_core.training.sources.SynthSource`).
    """
    from bags.cli.train.train import train_parser
    from bev_mapper_core.geometry.rig import preset_rig
    from bev_mapper_core.training.config import TrainConfig
    from bev_mapper_core.training.data import drive_spec, train_seeds
    from bev_mapper_core.training.method import method_class

    method = flags[flags.index("--method") + 1]
    args = vars(train_parser(method).parse_args(flags))  # as bev-train builds its config
    path = args.pop("config", None)
    cfg = TrainConfig.from_yaml(path, **args) if path else TrainConfig.from_dict(args)
    rig, grid = preset_rig(cfg.rig), cfg.grid
    needs = method_class(cfg.method)(cfg, rig, grid).data_needs()
    rgb = None
    if needs.rgb:
        w, h = rig.cameras[0].model.image_size
        rgb = needs.image_size or (h, w)
    jobs = []
    for seeds, style in ((train_seeds(cfg.seed, cfg.train_drives), cfg.style), (cfg.held_out_seeds, cfg.style),
                         (cfg.unlabeled_seeds, cfg.unlabeled_style or cfg.style)):
        spec = drive_spec(rig, grid, cfg.class_names, cfg.frames_per_drive, cfg.stride, rgb, style)
        jobs += [(rig, grid, spec, s, cache) for s in seeds]
    return jobs


def _render(job) -> int:
    from bev_mapper_core.training.data import load_or_render

    rig, grid, spec, seed, cache = job
    load_or_render(rig, grid, spec, seed, cache)
    return seed


def render(jobs: list[tuple], workers: int) -> float:
    """Render (or find in the cache) every drive of ``jobs`` in ``workers`` processes; seconds."""
    t0 = time.monotonic()
    unique = {(j[2], j[3]): j for j in jobs}  # one per (spec, seed)
    # spawned, not forked: this process has torch's thread pools (building the runs' models), which
    # a forked child can deadlock on
    with ProcessPoolExecutor(max(1, workers), mp_context=multiprocessing.get_context("spawn")) as ex:
        list(ex.map(_render, unique.values()))
    return time.monotonic() - t0


def launch(names: list[str], flags: dict[str, list[str]], a, phase: str, budget_min: float | None,
           extra: dict[str, list[str]] | None = None) -> dict[str, dict]:
    """Start one ``bev-train`` process per run at once (``OUT/<phase>/<name>``, log
    ``OUT/logs/<phase>_<name>.log``), wait for all; per run its status and ``last.json``.
    """
    procs = {}
    for name in names:
        out = Path(a.out) / phase / name
        out.mkdir(parents=True, exist_ok=True)
        cmd = [sys.executable, "-m", "bags.cli.train.main", *flags[name], *(extra or {}).get(name, []),
               "--out", str(out), "--cache", a.cache, "--device", a.device, "--threads", str(a.threads),
               "--no-progress", *(["--time-budget", f"{budget_min:.2f}"] if budget_min else []),
               *(["--resume"] if (out / "last.json").is_file() else [])]
        log = open(Path(a.out) / "logs" / f"{phase}_{name}.log", "w")  # noqa: SIM115 - closed below
        log.write("$ " + " ".join(cmd) + "\n")
        log.flush()
        procs[name] = (subprocess.Popen(cmd, cwd=REPO, stdout=log, stderr=subprocess.STDOUT), log, time.monotonic())
    status = {}
    for name, (proc, log, t0) in procs.items():
        code = proc.wait()
        log.close()
        out = Path(a.out) / phase / name
        last = out / "last.json"
        doc = json.loads(last.read_text()) if last.is_file() else {}
        status[name] = {"returncode": code, "seconds": round(time.monotonic() - t0, 1),
                        "best_val_miou": doc.get("best_val_miou"), "best_epoch": doc.get("best_epoch"),
                        "epoch": doc.get("epoch"), "step": doc.get("step"), "history": doc.get("history", []),
                        "weights": sorted(p.name for p in out.glob("*.safetensors"))}
    return status


def _flag(flags: list[str], name: str, default: str | None = None) -> str | None:
    return flags[flags.index(name) + 1] if name in flags else default


def plan_epochs(flags: list[str], probe: dict, budget_s: float) -> list[str]:
    """The ``--epochs``, ``--frames-per-epoch`` and ``--lr-step-epoch`` that fill ``budget_s``
    seconds of one run at the rate its probe measured (every run at once, as in training): the
    recipe's epochs (fewer where validation would take over 15 % of the time), their frames grown
    or shrunk to fit (at most every training frame, at least 20 steps); more epochs where every
    frame fits, fewer (at least 3) where 20 steps do not; the learning-rate step at the recipe's
    fraction of them.
    """
    epoch = probe["history"][-1]  # the last probe epoch: warm (the first one pays for compiling and tuning)
    s_step = epoch["train_s"] / max(1, epoch["batches"])
    val_s = epoch["val_s"]
    startup_s = max(0.0, probe["seconds"] - sum(h["train_s"] + h["val_s"] for h in probe["history"]))
    avail = max(60.0, budget_s - startup_s)
    batch = int(_flag(flags, "--batch", "8"))
    epochs = int(_flag(flags, "--epochs", "10"))
    step_frac = min(1.0, int(_flag(flags, "--lr-step-epoch", str(int(epochs * 0.75)))) / epochs)
    epochs = min(epochs, max(3, int(0.15 * avail / max(val_s, 1e-3))))  # validation under 15 % of the time
    all_steps = max(1, int(_flag(flags, "--train-drives", "40")) * int(_flag(flags, "--frames-per-drive", "20")) // batch)
    steps = int((avail / epochs - val_s) / s_step)
    if steps > all_steps:  # every frame each epoch: more epochs
        steps = all_steps
        epochs = max(epochs, int(avail / (steps * s_step + val_s)))
    elif steps < min(20, all_steps):
        steps = min(20, all_steps)
        epochs = max(3, int(avail / (steps * s_step + val_s)))
    return ["--epochs", str(epochs), "--frames-per-epoch", str(steps * batch),
            "--lr-step-epoch", str(max(1, round(epochs * step_frac)))]


def _cache_files(cache: str) -> set[Path]:
    return set(Path(cache).rglob("drive_*.npz"))


def main(argv: list[str] | None = None) -> int:
    """Command line entry (see the module docstring)."""
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--out", required=True, help="runs, logs and summary.json go here")
    p.add_argument("--runs", default=",".join(list(RUNS)[:4]), help=f"comma list of {list(RUNS)}")
    p.add_argument("--device", default="cpu", help="cpu | cuda")
    p.add_argument("--deadline-min", type=float, default=8.5,
                   help="the whole script's wall time: rendering, probes, training and the benchmark")
    p.add_argument("--reserve-s", type=float, default=75.0, help="kept at the end for the benchmark and packing")
    p.add_argument("--probe-steps", type=int, default=30, help="steps of each run's probe (its rate)")
    p.add_argument("--cache", default=None, help="drive cache (default OUT/cache)")
    p.add_argument("--workers", type=int, default=os.cpu_count() or 1, help="rendering processes")
    p.add_argument("--threads", type=int, default=None, help="CPU threads per run (default: CPUs / runs)")
    p.add_argument("--camvid", default=None, help="CamVid folder: its training images as unlabeled real frames")
    p.add_argument("--bench", action="store_true", help="then time every method on the GPU (bench/bench_cuda.py)")
    p.add_argument("--pack", default=None, help="copy the trained weights, a log archive and summary.json here")
    p.add_argument("--no-plan", action="store_true",
                   help="no probes: train each recipe's epochs as written (ablation rows of equal steps)")
    p.add_argument("--extra", default="", help="bev-train flags added to every run (e.g. '--input-width 384')")
    p.add_argument("--tiny", action="store_true", help="tiny runs: the CPU check of this script")
    a = p.parse_args(argv)
    t0 = time.monotonic()
    names = [n for n in a.runs.split(",") if n]
    unknown = [n for n in names if n not in RUNS]
    if unknown:
        print(f"error: unknown runs {unknown}; choose from {list(RUNS)}", file=sys.stderr)
        return 2
    a.out = str(Path(a.out).resolve())  # the runs start in another folder: relative paths would not reach
    a.cache = a.cache or str(Path(a.out) / "cache")
    a.threads = a.threads or max(1, (os.cpu_count() or 1) // len(names))
    (Path(a.out) / "logs").mkdir(parents=True, exist_ok=True)
    flags = {n: run_flags(n, a.tiny, a.camvid, Path(a.out)) + a.extra.split() for n in names}
    jobs = [j for n in names for j in drive_jobs(flags[n], a.cache)]
    render_s = render(jobs, a.workers)
    print(f"rendered {len({(j[2], j[3]) for j in jobs})} drives in {render_s:.1f} s", flush=True)
    cached = _cache_files(a.cache)
    summary = {"render_s": round(render_s, 1), "device": a.device, "tiny": a.tiny, "flags": flags}
    probe_extra = {n: ["--epochs", "2", "--frames-per-epoch", str(a.probe_steps * int(_flag(flags[n], "--batch", "1")))]
                   for n in names}  # two epochs: the second one's rate is the warm one
    if a.no_plan:  # the recipes as they are; the deadline still stops them
        ok, plans = names, {}
    else:
        probes = launch(names, flags, a, "probe", None, probe_extra)
        summary["probe"] = probes
        print("probes: " + ", ".join(f"{n} {s['returncode']} ({s['seconds']} s)" for n, s in probes.items()),
              flush=True)
        ok = [n for n in names if probes[n]["returncode"] == 0 and probes[n]["history"]]
    budget_s = a.deadline_min * 60.0 - (time.monotonic() - t0) - a.reserve_s
    plans = plans if a.no_plan else {n: plan_epochs(flags[n], probes[n], budget_s) for n in ok}
    summary["plan"] = {"budget_s": round(budget_s, 1), **plans}
    print(f"training budget {budget_s:.0f} s: {plans}", flush=True)
    status = launch(ok, flags, a, "runs", budget_s / 60.0, plans) if ok else {}
    summary["runs"] = status
    summary["rendered_by_runs"] = len(_cache_files(a.cache) - cached)  # 0: the runs rendered nothing
    for phase in ("train", "bench") if a.bench else ("train",):  # the weights packed before the benchmark runs
        if phase == "bench":
            summary["bench"] = bench(a, status)
        summary["total_s"] = round(time.monotonic() - t0, 1)
        (Path(a.out) / "summary.json").write_text(json.dumps(summary, indent=1) + "\n")
        if a.pack:
            pack(a, status)
    print(json.dumps({n: {k: v for k, v in s.items() if k != "history"} for n, s in status.items()}, indent=1))
    failed = [n for n in names if n not in status or status[n]["returncode"] != 0]
    for n in failed:
        print(f"error: run {n} failed: see {Path(a.out) / 'logs'}", file=sys.stderr)
    return 1 if failed else 0


def bench(a, status: dict) -> dict:
    """bench/bench_cuda.py on the shipped weights and this session's (``OUT/bench_cuda.json``)."""
    wdir = Path(a.out) / "bench_weights"
    wdir.mkdir(exist_ok=True)
    for name, s in status.items():
        src = Path(a.out) / "runs" / name / "best.safetensors"
        if s["returncode"] == 0 and src.is_file():
            shutil.copy(src, wdir / SHIP_NAMES[name])
    out = Path(a.out) / "bench_cuda.json"
    cmd = [sys.executable, str(REPO / "bench" / "bench_cuda.py"), "--weights-dir", str(wdir), "--json", str(out),
           "--device", a.device, *(["--frames", "2", "--repeat", "1"] if a.tiny else ["--frames", "10"])]
    with open(Path(a.out) / "logs" / "bench_cuda.log", "w") as log:
        try:
            code = subprocess.run(cmd, cwd=REPO, stdout=log, stderr=subprocess.STDOUT,
                                  timeout=max(30.0, a.reserve_s - 15.0)).returncode
        except subprocess.TimeoutExpired:
            code = "timed out"
    print((Path(a.out) / "logs" / "bench_cuda.log").read_text(), flush=True)
    return {"returncode": code, **(json.loads(out.read_text()) if out.is_file() else {})}


def pack(a, status: dict) -> None:
    """Into ``--pack``: each run's best weights (named as shipped, prefixed ``gpu_``), and
    ``gpu_runs.tar.gz`` with every run's json files, metrics and logs."""
    dest = Path(a.pack)
    dest.mkdir(parents=True, exist_ok=True)
    for name in status:
        src = Path(a.out) / "runs" / name / "best.safetensors"
        if src.is_file():
            shutil.copy(src, dest / f"gpu_{name}.safetensors")
    with tarfile.open(dest / "gpu_runs.tar.gz", "w:gz") as tar:
        root = Path(a.out)
        for path in [root / "summary.json", *root.glob("logs/*"), *root.glob("*.yaml"), *root.glob("bench_cuda.json"),
                     *root.glob("*/*/*.json"), *root.glob("*/*/*.jsonl")]:
            if path.is_file():
                tar.add(path, arcname=str(path.relative_to(root)))


#: run name -> the file name its weights ship under
SHIP_NAMES = {"s2g2": "s2g2_front1_rgb.safetensors", "s2g2_semi": "s2g2_front1_rgb_semi.safetensors",
              "focusbev": "focusbev_front1_rgb.safetensors", "bimapper_rgb": "bimapper_surround6_rgb.safetensors"}
SHIP_NAMES.update({n: f"{RUNS[n][1]}_{RUNS[n][3]}_rgb_{n}.safetensors" for n in RUNS if n not in SHIP_NAMES})


if __name__ == "__main__":
    raise SystemExit(main())
