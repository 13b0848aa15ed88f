r"""Train the package's 2-D segmenter on synthetic + real (CamVid) frames; compare several sizes.

Read top to bottom. One run:

1. renders the synthetic training drives (fine labels) with a process pool, once (about 480
   frames x 6 cameras of 400x225: ~40 s on 15 processes), into a
   temporary folder (``--synth-drives`` x ``--synth-frames`` x 6 surround cameras, style
   ``mixed``, the seeds of ``bev-train --seed 0``; plus a few held-out validation drives);
2. trains every config of ``--configs`` (each in its own process, ``--parallel`` at a time, all
   on the one GPU), each for ``--budget-s`` seconds of wall clock:
   * every step a batch of CamVid train crops (coarse labels, the partial-label loss of
     :mod:`bev_mapper_core.nn.label_space`) and a batch of synthetic crops (fine labels,
     ordinary cross-entropy through the same function), both augmented on the device
     (:mod:`bev_mapper_core.nn.augment`), softened median-frequency class weights;
   * AdamW, linear warm-up then cosine decay over the time budget, bf16 autocast on CUDA, an
     exponential moving average (EMA) of the weights, which is what is evaluated and saved;
   * the loading, class weights, batch sampling, mixed-batch loss and scoring are the package's
     (:mod:`bev_mapper_core.methods.segmenter.real`, which ``bev-train --method segmenter --real``
     trains with too);
   * evaluation every ``--eval-every-s`` on CamVid val (pooled pixel IoU per CamVid class, fine
     argmax mapped to CamVid's classes) and on held-out synthetic frames (fine pixel IoU); the
     best by CamVid val (mean of road, sidewalk, car, pedestrian, building) is kept;
3. writes, per config, ``OUT/<name>.safetensors`` (the package's ``save_segmenter`` format, read
   by ``load_segmenter``) and ``OUT/<name>.json`` (config, loss curve, every evaluation, steps,
   wall time; rewritten at every evaluation, so a killed run still leaves its best so far), and
   scores CamVid test if ``DIR/test`` exists.

CPU smoke run::

    PYTHONPATH=. python experiments/segmenter_real.py --camvid /work/data/camvid --out /tmp/o \\
        --configs tiny --budget-s 30 --synth-drives 1 --synth-frames 2 --limit-real 32 --device cpu

Nothing here imports ROS or downloads anything.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import torch

from bev_mapper_core.datasets import CamVid
from bev_mapper_core.labels.classes import BEV_CLASS_NAMES, NUM_LABELS
from bev_mapper_core.labels.spaces import CAMVID, FINE
from bev_mapper_core.methods.segmenter.model import Segmenter, SegmenterConfig
from bev_mapper_core.methods.segmenter.real import (
    RealSet,
    base_copy,
    base_size,
    iou_report,
    joint_class_weights,
    mixed_loss,
    pooled_iou,
    read_split,
    sample_batch,
)
from bev_mapper_core.methods.segmenter.weights import load_segmenter, save_segmenter
from bev_mapper_core.nn.augment import Augment, AugmentConfig
from bev_mapper_core.nn.label_space import joint_cover

# ----------------------------------------------------------------------------------------------
# the configs this script knows (SegmenterConfig fields); "tiny" is for smoke runs only
CONFIGS: dict[str, dict] = {
    "w200": dict(input_width=200, width_mult=0.75, depth_mult=0.5, encoder_stages=5, decoder_channels=48),  # shipped size
    "w320": dict(input_width=320, width_mult=1.0, depth_mult=0.5, encoder_stages=5, decoder_channels=64),
    "w320s6": dict(input_width=320, width_mult=1.0, depth_mult=1.0, encoder_stages=6, decoder_channels=64),
    "w480s6": dict(input_width=480, width_mult=1.0, depth_mult=1.0, encoder_stages=6, decoder_channels=96),
    "tiny": dict(input_width=96, width_mult=0.25, depth_mult=0.25, encoder_stages=4, decoder_channels=16),
    # issue #37: EfficientNet-Lite trunks (whole, 7 stages) at CamVid's own 480 px, pyramid at stride 4
    "lite0": dict(input_width=480, encoder="lite", width_mult=1.0, depth_mult=1.0, encoder_stages=7,
                  decoder_channels=64, decoder_stride=4),
    "lite2": dict(input_width=480, encoder="lite", width_mult=1.1, depth_mult=1.2, encoder_stages=7,
                  decoder_channels=64, decoder_stride=4),
    "tinylite": dict(input_width=96, encoder="lite", width_mult=1.0, depth_mult=1.0, encoder_stages=4,
                     decoder_channels=16, decoder_stride=4),
}
#: Runs of issue #37: a config of CONFIGS and the recipe's settings that differ from the command
#: line's (``init``: imagenet / none; ``real``: train on CamVid too; ``choose``: the checkpoint
#: kept is the best by CamVid val (``camvid``) or by held-out synthetic pixel mIoU (``synth``: no
#: CamVid frame decides anything); ``twin``: also train a from-scratch copy on the very same
#: batches (the ablation at equal steps); ``weights``: median | enet; ``hard``: OHEM fraction;
#: ``scale``: the augmentation's zoom range).
RECIPES: dict[str, dict] = {
    "lite0_camvid": dict(config="lite0", init="imagenet", real=True, choose="camvid", twin=True, weights="enet",
                         scale=(0.5, 2.0)),
    "lite0_camvid_ohem": dict(config="lite0", init="imagenet", real=True, choose="camvid", weights="median",
                              hard=0.3, scale=(0.5, 2.0)),
    "lite2_camvid": dict(config="lite2", init="imagenet", real=True, choose="camvid", weights="enet",
                         scale=(0.5, 2.0)),
    "lite0_open": dict(config="lite0", init="imagenet", real=False, choose="synth", weights="enet",
                       scale=(0.5, 2.0)),
    "tinylite_camvid": dict(config="tinylite", init="imagenet", real=True, choose="camvid", twin=True, weights="enet",
                            scale=(0.5, 2.0), hard=0.5),
    "tinylite_open": dict(config="tinylite", init="imagenet", real=False, choose="synth", weights="enet"),
}
RECIPE_DEFAULTS = dict(init="none", real=True, choose="camvid", twin=False, weights="median", hard=1.0,
                       scale=(0.8, 1.8))
SYNTH_RIG = "surround6"
SYNTH_SIZE = (225, 400)  # (h, w) of the surround6 cameras
SYNTH_VAL_FRAMES = 10


def parse_config(spec: str) -> tuple[str, SegmenterConfig, dict]:
    """``name`` (one of RECIPES or CONFIGS) or ``name=key:value/key:value`` (a new config,
    SegmenterConfig fields): ``(name, config, recipe)``.
    """
    name, _, rest = spec.partition("=")
    if not rest:
        recipe = dict(RECIPE_DEFAULTS, **RECIPES.get(name, {}))
        config = recipe.pop("config", name)
        if config not in CONFIGS:
            raise SystemExit(f"error: unknown config {name!r}; known: {sorted(RECIPES) + sorted(CONFIGS)} or "
                             "name=key:value/key:value")
        return name, SegmenterConfig(**CONFIGS[config]), recipe
    d = {}
    for kv in rest.split("/"):
        k, _, v = kv.partition(":")
        d[k] = v if k == "encoder" else float(v) if k.endswith("_mult") else int(v)
    return name, SegmenterConfig(**d), dict(RECIPE_DEFAULTS)


def get_args(argv=None) -> argparse.Namespace:
    """The command line."""
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--camvid", required=True, help="CamVid folder (train/ trainannot/ val/ valannot/ [test/ testannot/])")
    ap.add_argument("--out", required=True, help="output folder (weights + JSON log per config)")
    ap.add_argument("--configs", default="lite0_camvid,lite0_camvid_ohem,lite2_camvid,lite0_open",
                    help="comma list of recipe or config names (see RECIPES, CONFIGS) or "
                         "name=input_width:320/width_mult:1.0/...")
    ap.add_argument("--budget-s", type=float, default=420.0, help="training wall-clock seconds per config")
    ap.add_argument("--deadline-s", type=float, default=0.0,
                    help="whole command's wall-clock limit: a config's budget shrinks so that it ends 20 s before "
                         "(0: none)")
    ap.add_argument("--parallel", type=int, default=0, help="configs trained at once (0: all)")
    ap.add_argument("--device", default="auto", help="auto | cpu | cuda")
    ap.add_argument("--threads", type=int, default=1, help="torch CPU threads per process")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--synth-drives", type=int, default=40, help="synthetic training drives (0: real frames only)")
    ap.add_argument("--synth-frames", type=int, default=12)
    ap.add_argument("--synth-stride", type=int, default=3)
    ap.add_argument("--synth-val-drives", type=int, default=2)
    ap.add_argument("--synth-procs", type=int, default=0, help="render processes (0: CPU count - 1)")
    ap.add_argument("--batch-real", type=int, default=16)
    ap.add_argument("--batch-synth", type=int, default=8)
    ap.add_argument("--synth-weight", type=float, default=1.0, help="weight of the synthetic loss")
    ap.add_argument("--lr", type=float, default=2.5e-3)
    ap.add_argument("--wd", type=float, default=0.01)
    ap.add_argument("--warmup", type=float, default=0.03, help="warm-up fraction of the budget")
    ap.add_argument("--ema", type=float, default=0.999)
    ap.add_argument("--eval-every-s", type=float, default=0.0, help="0: budget / 8")
    ap.add_argument("--max-steps", type=int, default=0, help="stop after this many steps (0: budget only)")
    ap.add_argument("--limit-real", type=int, default=0, help="use only the first N CamVid train / val frames (smoke)")
    ap.add_argument("--no-flip", action="store_true")
    ap.add_argument("--worker", default="", help=argparse.SUPPRESS)  # internal: train this one config
    ap.add_argument("--synth-dir", default="", help=argparse.SUPPRESS)  # internal: rendered drives
    ap.add_argument("--end-at", type=float, default=0.0, help=argparse.SUPPRESS)  # internal: epoch seconds
    return ap.parse_args(argv)


# ----------------------------------------------------------------------------------------------
# 1. synthetic drives (fine labels), rendered in parallel processes


def _render_one(job: tuple[int, int, int]) -> tuple[np.ndarray, np.ndarray]:
    """One drive -> (rgb (F*6, h, w, 3) uint8, labels (F*6, h, w) uint8)."""
    seed, frames, stride = job
    torch.set_num_threads(1)
    from bev_mapper_core.geometry.grid import BevGrid
    from bev_mapper_core.geometry.rig import preset_rig
    from bev_mapper_core.training.data import render_drive

    d = render_drive(preset_rig(SYNTH_RIG), BevGrid(), BEV_CLASS_NAMES, seed, frames, stride, rgb=SYNTH_SIZE)
    return d["rgb"].reshape(-1, *SYNTH_SIZE, 3), d["labels"].reshape(-1, *SYNTH_SIZE)


def render_synth(args, folder: Path) -> None:
    """Render training and held-out drives into ``folder`` (``{train,val}_{rgb,labels}.npy``)."""
    import multiprocessing as mp

    from bev_mapper_core.training.data import train_seeds, val_seeds

    t0 = time.time()
    jobs = {"train": [(s, args.synth_frames, args.synth_stride) for s in train_seeds(args.seed, args.synth_drives)],
            "val": [(s, SYNTH_VAL_FRAMES, args.synth_stride) for s in val_seeds(max(1, args.synth_val_drives))]}
    procs = args.synth_procs or max(1, (os.cpu_count() or 2) - 1)
    with mp.get_context("spawn").Pool(procs) as pool:  # one map: the validation drives fill idle workers
        parts = pool.map(_render_one, jobs["train"] + jobs["val"], chunksize=1)
    split_parts = {"train": parts[:len(jobs["train"])], "val": parts[len(jobs["train"]):]}
    for split, ps in split_parts.items():
        np.save(folder / f"{split}_rgb.npy", np.concatenate([p[0] for p in ps]))
        np.save(folder / f"{split}_labels.npy", np.concatenate([p[1] for p in ps]))
    n = len(np.load(folder / "train_labels.npy", mmap_mode="r"))
    print(f"synthetic: {n} training images rendered by {procs} processes in {time.time() - t0:.0f} s", flush=True)


# ----------------------------------------------------------------------------------------------
# 2. one config's training (the worker process)


def load_camvid(root: str, split: str, limit: int, device) -> tuple[torch.Tensor, torch.Tensor]:
    """A CamVid split as ``(images (N, H, W, 3) uint8, labels (N, H, W) uint8)`` on ``device``."""
    return read_split(CamVid(root, split), limit, device)


def evaluate(model: Segmenter, images: torch.Tensor, labels: torch.Tensor, space, amp: bool) -> np.ndarray:
    """Pooled pixel IoU per class of ``space`` at the images' own size (fine argmax -> home class)."""
    return pooled_iou(model, images, labels, space, amp)


def camvid_report(iou: np.ndarray) -> dict:
    """IoU (%) per CamVid class, the five common classes and their mean."""
    return iou_report(iou, CAMVID)


class Arm:
    """One model trained in a worker: its weights, optimiser, EMA (what is evaluated and saved)
    and log. A worker trains one arm, or two on the very same batches (``twin``: the scratch
    ablation at equal steps).
    """

    def __init__(self, name: str, cfg: SegmenterConfig, init: str, args, dev: torch.device) -> None:
        self.name = name
        self.model = Segmenter(cfg).to(dev)
        self.init = self.model.init_imagenet() if init == "imagenet" else None
        if dev.type == "cuda":
            self.model = self.model.to(memory_format=torch.channels_last)
        decay = [p for p in self.model.parameters() if p.ndim > 1]
        no_decay = [p for p in self.model.parameters() if p.ndim <= 1]
        self.opt = torch.optim.AdamW([{"params": decay, "weight_decay": args.wd},
                                      {"params": no_decay, "weight_decay": 0.0}],
                                     lr=args.lr, betas=(0.9, 0.99), fused=dev.type == "cuda")
        self.ema = Segmenter(cfg).to(dev)
        self.ema.load_state_dict(self.model.state_dict())
        if dev.type == "cuda":
            self.ema = self.ema.to(memory_format=torch.channels_last)
        self.ema.eval().requires_grad_(False)
        ema_t, model_t = list(self.ema.state_dict().values()), list(self.model.state_dict().values())
        self.float_pairs = [(e, m) for e, m in zip(ema_t, model_t) if e.is_floating_point()]
        self.int_pairs = [(e, m) for e, m in zip(ema_t, model_t) if not e.is_floating_point()]
        self.log = {"name": name, "config": cfg.to_dict(), "params": sum(p.numel() for p in self.model.parameters()),
                    "init": init, "init_info": None if self.init is None else
                    {"variant": self.init["variant"], "loaded": self.init["loaded"]},
                    "loss": [], "evals": [], "best": None}

    def step(self, parts, cover, weight, hard: float, amp: bool, dev, lr: float, ema_decay: float):
        """One optimiser step on ``parts``; the parts' losses."""
        for g in self.opt.param_groups:
            g["lr"] = lr
        self.model.train()
        with torch.autocast(dev.type, dtype=torch.bfloat16, enabled=amp):  # the loss itself runs in float32
            loss, losses = mixed_loss(self.model, parts, cover, weight, hard)
        self.opt.zero_grad(set_to_none=True)
        loss.backward()
        torch.nn.utils.clip_grad_norm_(self.model.parameters(), 5.0)
        self.opt.step()
        with torch.no_grad():
            torch._foreach_lerp_([e for e, _ in self.float_pairs], [m for _, m in self.float_pairs], 1 - ema_decay)
            for e, m in self.int_pairs:
                e.copy_(m)
        return losses


def run_worker(args, name: str, cfg: SegmenterConfig, recipe: dict) -> None:
    """Train one recipe (one arm, or two with ``twin``) for the time budget; write each arm's
    weights and JSON log (module docstring).
    """
    t_start = time.time()
    dev = torch.device("cuda" if args.device == "auto" and torch.cuda.is_available() else
                       "cpu" if args.device == "auto" else args.device)
    amp = dev.type == "cuda"
    torch.set_num_threads(args.threads)
    torch.manual_seed(args.seed)
    torch.backends.cudnn.benchmark = True
    out = Path(args.out)
    say = lambda msg: print(f"[{name}] {msg}", flush=True)  # noqa: E731

    # data: CamVid train (if the recipe trains on it) and val (coarse), synthetic drives (fine), on the device
    use_real = bool(recipe["real"])
    val_x, val_y = load_camvid(args.camvid, "val", args.limit_real, dev)
    real_hw = cfg.input_size((val_x.shape[2], val_x.shape[1]))  # (h, w) of the model input
    if use_real:
        real_x, real_y = load_camvid(args.camvid, "train", args.limit_real, dev)
        real_x, real_y = base_copy(real_x, real_y, base_size(tuple(real_x.shape[1:3]), real_hw))
    use_synth = bool(args.synth_dir) and args.synth_drives > 0
    if not (use_real or use_synth):
        raise SystemExit(f"error: recipe {name} trains on neither CamVid nor synthetic frames")
    if recipe["choose"] == "synth" and not use_synth:
        raise SystemExit(f"error: recipe {name} chooses on synthetic val, but no synthetic drives are rendered")
    if use_synth:
        sd = Path(args.synth_dir)
        syn_x = torch.from_numpy(np.load(sd / "train_rgb.npy")).to(dev)
        syn_y = torch.from_numpy(np.load(sd / "train_labels.npy")).to(dev)
        sval_x = torch.from_numpy(np.load(sd / "val_rgb.npy")).to(dev)
        sval_y = torch.from_numpy(np.load(sd / "val_labels.npy")).to(dev)
        syn_y = torch.where(syn_y < NUM_LABELS, syn_y, torch.zeros_like(syn_y))  # as the segmenter method
        syn_hw = cfg.input_size((SYNTH_SIZE[1], SYNTH_SIZE[0]))
        syn_x, syn_y = base_copy(syn_x, syn_y, base_size(SYNTH_SIZE, syn_hw))

    # one code space for both: codes 0..10 = fine labels, 11.. = CamVid classes
    cover, (fine_off, cam_off) = joint_cover([FINE, CAMVID])
    cover = cover.to(dev)
    real_counts = RealSet("camvid", CAMVID, real_x, real_y, real_hw).counts() if use_real else None
    syn_counts = torch.bincount(syn_y.long().flatten(), minlength=NUM_LABELS)[:NUM_LABELS].cpu() if use_synth else None
    weight = joint_class_weights([syn_counts, real_counts], [NUM_LABELS, CAMVID.num_classes],
                                 mode=recipe["weights"]).to(dev)
    say(f"class weights ({recipe['weights']}) CamVid "
        + " ".join(f"{c}={w:.2f}" for c, w in zip(CAMVID.classes, weight[NUM_LABELS:].tolist())))

    arms = [Arm(name, cfg, recipe["init"], args, dev)]
    if recipe["twin"]:
        arms.append(Arm(f"{name}_scratch", cfg, "none", args, dev))
    gen = torch.Generator(device=dev).manual_seed(args.seed)
    aug = Augment(AugmentConfig(flip=not args.no_flip, scale=tuple(recipe["scale"])), gen)
    mean, std = arms[0].model.rgb_mean, arms[0].model.rgb_std

    def lr_at(p: float) -> float:
        if p < args.warmup:
            return args.lr * (0.1 + 0.9 * p / args.warmup)
        q = min(1.0, (p - args.warmup) / max(1e-9, 1 - args.warmup))
        return args.lr * (0.01 + 0.99 * 0.5 * (1 + math.cos(math.pi * q)))

    def batch(x_all, y_all, n, hw, offset):
        x, y = sample_batch(x_all, y_all, n, hw, offset, gen, aug, mean, std)
        if dev.type == "cuda":
            x = x.contiguous(memory_format=torch.channels_last)
        return x, y

    common = {"device": str(dev), "gpu": torch.cuda.get_device_name(0) if dev.type == "cuda" else None,
              "args": vars(args), "recipe": recipe, "real_input_hw": list(real_hw)}

    def write_log(arm: Arm) -> None:
        tmp = out / f".{arm.name}.json.tmp"
        tmp.write_text(json.dumps({**arm.log, **common}, indent=1))
        os.replace(tmp, out / f"{arm.name}.json")

    def do_eval(arm: Arm, step: int, t: float) -> None:
        rep = camvid_report(evaluate(arm.ema, val_x, val_y, CAMVID, amp))
        if use_synth:
            syn_iou = evaluate(arm.ema, sval_x, sval_y, FINE, amp)
            rep["synth_fine_iou"] = {c: round(100 * float(v), 2) for c, v in zip(FINE.classes, syn_iou)}
            rep["synth_miou"] = round(100 * float(np.nanmean(syn_iou)), 2)
        rep.update(step=step, train_s=round(t, 1))
        arm.log["evals"].append(rep)
        key = "common_mean" if recipe["choose"] == "camvid" else "synth_miou"
        best = arm.log["best"]
        if best is None or rep[key] >= best[key]:
            arm.log["best"] = rep
            save_segmenter(arm.ema, out / f"{arm.name}.safetensors",
                           ("camvid+" if use_real else "") + SYNTH_RIG)
        say(f"{arm.name} eval step {step} t={t:.0f}s CamVid val common {rep['common']} mean {rep['common_mean']}"
            + (f" synth mIoU {rep['synth_miou']}" if use_synth else "") + f" (chosen on {key})")
        write_log(arm)

    setup_s = time.time() - t_start
    if args.end_at:  # the whole command's deadline: leave time for the last evaluations and the files
        args.budget_s = max(10.0, min(args.budget_s, args.end_at - time.time() - 20.0 * len(arms)))
    say(f"{arms[0].log['params'] / 1e6:.2f} M params x {len(arms)} arm(s), real input {real_hw}, "
        f"init {recipe['init']}, setup {setup_s:.0f} s on {dev}")
    eval_every = args.eval_every_s or args.budget_s / 8
    t0 = time.time()
    next_eval, step = eval_every, 0
    while True:
        t = time.time() - t0
        p = t / args.budget_s if not args.max_steps else max(t / args.budget_s, step / args.max_steps)
        if p >= 1.0:
            break
        parts = []
        if use_real:
            parts.append(batch(real_x, real_y, args.batch_real, real_hw, cam_off) + (1.0,))
        if use_synth:
            parts.append(batch(syn_x, syn_y, args.batch_synth, syn_hw, fine_off) + (args.synth_weight,))
        d = min(args.ema, (1 + step) / (10 + step))  # EMA (shorter memory at the start)
        all_losses = [arm.step(parts, cover, weight, recipe["hard"], amp, dev, lr_at(p), d) for arm in arms]
        step += 1
        if step % 25 == 0:
            for arm, losses in zip(arms, all_losses):
                arm.log["loss"].append([step, round(time.time() - t0, 1)] + [round(v.item(), 4) for v in losses]
                                       + [lr_at(p)])
        if step % 200 == 0:
            say(f"step {step} t={time.time() - t0:.0f}s losses "
                + " / ".join(" ".join(f"{v.item():.3f}" for v in losses) for losses in all_losses))
        if time.time() - t0 >= next_eval:
            for arm in arms:
                do_eval(arm, step, time.time() - t0)
            next_eval += eval_every
    train_s = time.time() - t0
    per_step = (args.batch_real if use_real else 0) + (args.batch_synth if use_synth else 0)
    for arm in arms:
        if not arm.log["evals"] or arm.log["evals"][-1]["step"] != step:
            do_eval(arm, step, train_s)
        arm.log.update(steps=step, train_s=round(train_s, 1), setup_s=round(setup_s, 1),
                       steps_per_s=round(step / max(train_s, 1e-9), 2), images_seen=step * per_step,
                       camvid_epochs=round(step * args.batch_real / len(real_x), 1) if use_real else 0)
        # the best as saved: reloaded through the package's loader, CamVid test scored if present
        best = load_segmenter(out / f"{arm.name}.safetensors", device=dev)
        if (Path(args.camvid) / "test").is_dir():
            tx, ty = load_camvid(args.camvid, "test", 0, dev)
            arm.log["test"] = camvid_report(evaluate(best, tx, ty, CAMVID, amp))
            say(f"{arm.name} TEST common {arm.log['test']['common']} mean {arm.log['test']['common_mean']}")
        arm.log["wall_s"] = round(time.time() - t_start, 1)
        write_log(arm)
        key = "common_mean" if recipe["choose"] == "camvid" else "synth_miou"
        say(f"{arm.name} done: {step} steps in {train_s:.0f} s ({arm.log['steps_per_s']} steps/s), best "
            f"{key} {arm.log['best'][key]} at step {arm.log['best']['step']}")


# ----------------------------------------------------------------------------------------------
# 3. the driver: render once, then one process per config


def main(argv=None) -> int:
    """Render the synthetic drives, train every config in its own process, print a summary."""
    args = get_args(argv)
    if args.worker:
        name, cfg, recipe = parse_config(next(c for c in args.configs.split(",") if c.partition("=")[0] == args.worker))
        run_worker(args, name, cfg, recipe)
        return 0
    t0 = time.time()
    configs = [parse_config(c) for c in args.configs.split(",") if c]
    end_at = ["--end-at", str(t0 + args.deadline_s)] if args.deadline_s else []
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    with tempfile.TemporaryDirectory(prefix="segreal_") as tmp:
        if args.synth_drives > 0:
            render_synth(args, Path(tmp))
        cmd = [sys.executable, os.path.abspath(__file__)] + (argv if argv is not None else sys.argv[1:])
        cmd += (["--synth-dir", tmp] if args.synth_drives > 0 else []) + end_at
        width = args.parallel or len(configs)
        running: list[subprocess.Popen] = []
        failed = []
        for name, _, _ in configs:
            while len(running) >= width:
                time.sleep(1)
                failed += [p for p in running if p.poll() not in (None, 0)]
                running = [p for p in running if p.poll() is None]
            running.append(subprocess.Popen(cmd + ["--worker", name]))
        for p in running:
            if p.wait() != 0:
                failed.append(p)
    print(f"\nall configs done in {time.time() - t0:.0f} s" + (f"; {len(failed)} FAILED" if failed else ""))
    print(f"{'config':8} {'params':>7} {'steps':>6} {'best step':>9} {'val mean5':>9}  road sidewalk car ped building"
          "  synth mIoU  [test mean5]")
    names = [n for n, _, r in configs for n in ([n, f"{n}_scratch"] if r["twin"] else [n])]
    for name in names:
        f = out / f"{name}.json"
        if not f.is_file():
            print(f"{name:8} (no log)")
            continue
        lg = json.loads(f.read_text())
        b = lg["best"]
        c = b["common"]
        test = f"  [{lg['test']['common_mean']}]" if "test" in lg else ""
        print(f"{name:8} {lg['params'] / 1e6:6.2f}M {lg.get('steps', 0):6} {b['step']:9} {b['common_mean']:9}  "
              f"{c['road']} {c['sidewalk']} {c['vehicle']} {c['pedestrian']} {c['building']}  "
              f"{b.get('synth_miou', '-')}{test}")
    return 1 if failed else 0


if __name__ == "__main__":
    raise SystemExit(main())
