"""Bi-Mapper training loop: Adam, step lr, per-epoch validation, safetensors checkpoints.

Run directory layout (``config.out``)::

    last.safetensors        model weights after the last finished epoch (models.save_weights)
    last.json               training state: epoch (last finished, 0-based), step, best val
                            mIoU and its epoch, lr, history, the TrainConfig
    last_optim.safetensors  Adam state, flattened to tensors (``state.<i>.<name>``) with the
                            param groups as JSON metadata: never pickle / torch.save
    best.safetensors/.json  the checkpoint with the best validation mIoU so far
    metrics.jsonl           one line per epoch (losses, val metrics, time)

Resuming (``resume=True``) loads ``last.*``, checks that the configuration is the same (up to
:attr:`TrainConfig.RESUMABLE_CHANGES`) and continues with the next epoch; the batch order and
torch's RNG are seeded per epoch from ``(seed, epoch)``, so an interrupted + resumed run takes
the same steps as an uninterrupted one.
"""

from __future__ import annotations

import json
import math
import os
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable

import numpy as np
import torch
from safetensors import safe_open
from safetensors.torch import save_file

from ..errors import BevMapperError, ConfigError
from ..grid import BevGrid
from ..metrics import MetricAccumulator
from ..models import BiMapper, BiMapperConfig, BiMapperLossConfig, bimapper_loss, load_state, save_weights
from ..rig import Rig, preset_rig
from .config import TrainConfig
from .data import FrameSet, synth_frameset, train_seeds


class TrainingError(BevMapperError):
    """A run cannot start or continue (bad resume state, missing data, ...)."""


# ------------------------------------------------------------------ optimizer state
def save_optimizer(opt: torch.optim.Optimizer, path: str | os.PathLike) -> None:
    """Adam (any torch optimizer) state as safetensors: tensors flattened, groups as JSON."""
    sd = opt.state_dict()
    tensors, scalars = {}, {}
    for pid, st in sd["state"].items():
        for k, v in st.items():
            if torch.is_tensor(v):
                tensors[f"state.{pid}.{k}"] = v.detach().cpu().contiguous()
            else:
                scalars[f"{pid}.{k}"] = v
    meta = {"param_groups": json.dumps(sd["param_groups"]), "scalars": json.dumps(scalars)}
    path = Path(path)
    tmp = path.with_name(path.name + ".tmp")
    save_file(tensors, str(tmp), metadata=meta)
    os.replace(tmp, path)


def load_optimizer(opt: torch.optim.Optimizer, path: str | os.PathLike) -> None:
    """Inverse of :func:`save_optimizer`."""
    try:
        with safe_open(str(path), framework="pt") as f:
            meta = f.metadata() or {}
            state: dict[int, dict] = {}
            for key in f.keys():
                _, pid, name = key.split(".", 2)
                state.setdefault(int(pid), {})[name] = f.get_tensor(key)
        for key, v in json.loads(meta.get("scalars", "{}")).items():
            pid, name = key.split(".", 1)
            state.setdefault(int(pid), {})[name] = v
        groups = json.loads(meta["param_groups"])
        opt.load_state_dict({"state": state, "param_groups": groups})
    except (KeyError, ValueError, OSError, RuntimeError) as e:
        raise TrainingError(f"cannot load optimizer state {path} ({e})") from None
    except Exception as e:  # safetensors' own error type
        raise TrainingError(f"cannot load optimizer state {path} ({e})") from None


# ------------------------------------------------------------------------ model
def model_config(cfg: TrainConfig) -> BiMapperConfig:
    """The BiMapperConfig a training config asks for."""
    return BiMapperConfig(input_kind=cfg.input, classes=cfg.class_names, input_width=cfg.input_width,
                          gv_hidden=cfg.gv_hidden, streams=cfg.streams, fusion=cfg.fusion,
                          lv_full_res=cfg.lv_full_res, ipm_skip=cfg.ipm_skip)


def loss_config(cfg: TrainConfig, pos_weight: tuple[float, ...] | None = None) -> BiMapperLossConfig:
    return BiMapperLossConfig(asl_weight=1.0 if cfg.asl else 0.0, mutual_start_epoch=cfg.mutual_start,
                              mutual_mode=cfg.mutual, pos_weight=pos_weight)


def class_pos_weight(frames: FrameSet, max_weight: float = 10.0) -> tuple[float, ...]:
    """Per-class BCE positive weights ``clip(sqrt(neg / pos), 1, max_weight)`` over visible cells.

    A deviation from the paper (plain BCE): with a training budget of a few hundred steps the
    thin and rare layers (lane dividers, crossings, boundaries, pedestrians: 0.05-2 % of the
    cells) otherwise stay at zero IoU; the square root keeps the weighting mild.
    """
    m = frames.mask[:, None]  # (M, 1, H, W)
    pos = np.count_nonzero(frames.target & m, axis=(0, 2, 3)).astype(np.float64)
    tot = float(np.count_nonzero(frames.mask))
    w = np.sqrt(np.maximum(tot - pos, 1.0) / np.maximum(pos, 1.0))
    return tuple(float(round(v, 3)) for v in np.clip(w, 1.0, max_weight))


@torch.no_grad()
def validate(model: BiMapper, frames: FrameSet, grid: BevGrid, batch: int = 4,
             limit: int | None = None) -> dict:
    """Metrics (MetricAccumulator.result) of ``model`` over ``frames`` (in order, first ``limit``)."""
    was = model.training
    model.eval()
    acc = MetricAccumulator(grid, model.config.classes)
    dev = next(model.parameters()).device
    for b in frames.batches(batch, 0, 0, limit=limit, shuffle=False):
        out = model(b["images"].to(dev))
        probs = torch.sigmoid(out["logits"]).float().cpu().numpy()
        known = model.known().cpu().numpy()[0]
        gt = b["target"].numpy() > 0.5
        for i in range(len(probs)):
            acc.update(probs[i], gt[i], b["mask"][i].numpy(), known)
    model.train(was)
    return acc.result()


@dataclass
class TrainState:
    """Optimizer-free training state saved as JSON beside each checkpoint."""

    epoch: int = -1  # last finished epoch (0-based); -1 = none
    step: int = 0
    best_miou: float | None = None
    best_epoch: int | None = None
    train_seconds: float = 0.0
    history: list = field(default_factory=list)

    def to_json(self, cfg: TrainConfig, model: BiMapper) -> dict:
        return {"epoch": self.epoch, "step": self.step, "best_val_miou": self.best_miou, "best_epoch": self.best_epoch,
                "train_seconds": self.train_seconds, "history": self.history, "config": cfg.to_dict(),
                "model_config": model.config.to_dict(), "rig": model.rig.name,
                "torch": torch.__version__, "threads": torch.get_num_threads()}


def _write_json(path: Path, d: dict) -> None:
    tmp = path.with_name(path.name + ".tmp")
    tmp.write_text(json.dumps(d, indent=1, allow_nan=False))
    os.replace(tmp, path)


def load_data(cfg: TrainConfig, rig: Rig, grid: BevGrid, input_size, log: Callable[[str], None]):
    """(train FrameSet, val FrameSet) for a config: synthetic drives, or bags when ``cfg.bag``."""
    if cfg.bag:
        from bags.train_data import bag_frameset  # lazy: bev_mapper_core never needs ROS/rosbags

        train = bag_frameset(cfg.bag, cfg.class_names, rig, grid, input_size)
        val = bag_frameset(cfg.val_bag, cfg.class_names, rig, grid, input_size) if cfg.val_bag else None
        if val is None:
            raise ConfigError("training on bags needs held-out bags (--val-bag)")
        return train, val
    t0 = time.time()
    train = synth_frameset(rig, grid, cfg.class_names, train_seeds(cfg.seed, cfg.train_drives), cfg.frames_per_drive,
                           cfg.stride, cfg.cache, input_size, progress=cfg.progress)
    val = synth_frameset(rig, grid, cfg.class_names, cfg.held_out_seeds, cfg.frames_per_drive, cfg.stride,
                         cfg.cache, input_size, progress=cfg.progress)
    log(f"data: {len(train)} training / {len(val)} held-out frames ({time.time() - t0:.1f} s)")
    return train, val


def train(cfg: TrainConfig, log: Callable[[str], None] = print, data=None) -> dict:
    """Run (or resume) training as configured; returns the final ``last.json`` document.

    ``data`` = (train, val) FrameSets to use instead of loading them (tests).
    """
    torch.set_num_threads(cfg.threads)
    if cfg.device.startswith("cuda") and not torch.cuda.is_available():
        raise ConfigError(f"device {cfg.device!r} requested but CUDA is not available")
    device = torch.device(cfg.device)
    out = Path(cfg.out)
    last_json = out / "last.json"
    rig = preset_rig(cfg.rig) if not cfg.bag else _bag_rig(cfg)
    grid = cfg.bev_grid() if not cfg.bag else _bag_grid(cfg)
    torch.manual_seed(cfg.seed)
    model = BiMapper(model_config(cfg), rig, grid).to(device)
    opt = torch.optim.Adam(model.parameters(), lr=cfg.lr)
    state = TrainState()
    if cfg.resume:
        if not last_json.is_file():
            raise TrainingError(f"--resume: no checkpoint in {out} (missing {last_json.name})")
        doc = json.loads(last_json.read_text())
        old = TrainConfig.from_dict(doc["config"])
        diff = cfg.resume_compatible(old)
        if diff:
            raise TrainingError(f"--resume: configuration differs from the checkpoint's in {diff}")
        load_state(model, out / "last.safetensors")
        load_optimizer(opt, out / "last_optim.safetensors")
        state = TrainState(doc["epoch"], doc["step"], doc["best_val_miou"], doc["best_epoch"],
                           doc.get("train_seconds", 0.0), doc.get("history", []))
        log(f"resumed {out} after epoch {state.epoch + 1} (step {state.step})")
    elif last_json.exists():
        raise TrainingError(f"{out} already holds a run; use --resume or another --out")
    out.mkdir(parents=True, exist_ok=True)
    # Full-resolution LV input and the IPM prior need the camera-size images in memory (else:
    # stored resized).
    input_size = None if (model.config.lv_full_res or model.config.ipm_skip) else model.input_size
    train_set, val_set = data if data is not None else load_data(cfg, rig, grid, input_size, log)
    pw = class_pos_weight(train_set) if cfg.pos_weight == "auto" else None
    lcfg = loss_config(cfg, pw)
    if pw is not None:
        log(f"BCE positive weights {dict(zip(cfg.class_names, pw))}")
    n_params = sum(p.numel() for p in model.parameters())
    log(f"model: {n_params / 1e6:.2f} M parameters, input {model.input_size}, classes {list(cfg.class_names)}; "
        f"lr {cfg.lr} x{cfg.lr_gamma} from epoch {cfg.lr_step + 1}, mutual both ways from epoch {cfg.mutual_start + 1}")
    t_start = time.time()
    budget_s = None if cfg.time_budget_min is None else cfg.time_budget_min * 60.0
    stopped = False
    for epoch in range(state.epoch + 1, cfg.epochs):
        for g in opt.param_groups:
            g["lr"] = cfg.lr_at(epoch)
        torch.manual_seed(cfg.seed * 100_003 + epoch)
        model.train()
        t0 = time.time()
        sums: dict[str, float] = {}
        n = 0
        limit = cfg.frames_per_epoch
        batches = train_set.batches(cfg.batch, cfg.seed, epoch, limit=limit)
        total = math.ceil(min(limit or len(train_set), len(train_set)) / cfg.batch)
        if cfg.progress:
            from tqdm import tqdm

            batches = tqdm(batches, total=total, desc=f"epoch {epoch + 1}/{cfg.epochs}", unit="batch", mininterval=5)
        for b in batches:
            outputs = model(b["images"].to(device))
            loss, parts = bimapper_loss(outputs, {"target": b["target"].to(device), "mask": b["mask"].to(device)}, epoch, lcfg)
            if not torch.isfinite(loss):
                raise TrainingError(f"loss became {float(loss)} at step {state.step}")
            opt.zero_grad(set_to_none=True)
            loss.backward()
            opt.step()
            state.step += 1
            n += 1
            for k, v in parts.items():
                sums[k] = sums.get(k, 0.0) + v
            if cfg.progress and hasattr(batches, "set_postfix"):
                batches.set_postfix(loss=f"{parts['total']:.3f}")
            if budget_s is not None and time.time() - t_start > budget_s:
                stopped = True
                break
        train_s = time.time() - t0
        if stopped and n < total:
            # the cut epoch is validated and checkpointed like a finished one (a resume starts
            # with the next epoch); its history record says ``partial``
            log(f"time budget reached inside epoch {epoch + 1} after {n}/{total} batches")
        tv = time.time()
        res = validate(model, val_set, grid, cfg.batch, cfg.val_frames)
        val_s = time.time() - tv
        miou = res["miou"]
        state.train_seconds += train_s
        rec = {"epoch": epoch, "step": state.step, "lr": cfg.lr_at(epoch), "batches": n, "train_s": round(train_s, 1),
               "val_s": round(val_s, 1), **{f"loss_{k}": v / max(n, 1) for k, v in sums.items()},
               "val_miou": miou, "val_iou": {k: v["iou"] for k, v in res["classes"].items()}, "partial": stopped and n < total}
        state.history.append(rec)
        with open(out / "metrics.jsonl", "a") as f:
            f.write(json.dumps(rec) + "\n")
        log(f"epoch {epoch + 1}/{cfg.epochs}: loss {rec.get('loss_total', float('nan')):.4f} "
            f"(bce {rec.get('loss_bce', 0):.4f} asl {rec.get('loss_asl', 0):.4f} mutual {rec.get('loss_mutual', 0):.4f}) "
            f"val mIoU {100 * (miou or 0):.1f} [{train_s:.0f} s train, {val_s:.0f} s val]")
        state.epoch = epoch
        if miou is not None and (state.best_miou is None or miou > state.best_miou):
            state.best_miou, state.best_epoch = miou, epoch
            save_weights(model, out / "best.safetensors")
            _write_json(out / "best.json", {**state.to_json(cfg, model), "val": res})
        save_weights(model, out / "last.safetensors")
        save_optimizer(opt, out / "last_optim.safetensors")
        _write_json(last_json, state.to_json(cfg, model))
        if stopped:
            log(f"stopped by the time budget ({cfg.time_budget_min} min) after epoch {epoch + 1}; --resume continues")
            break
    doc = json.loads(last_json.read_text()) if last_json.exists() else state.to_json(cfg, model)
    return doc


def _bag_rig(cfg: TrainConfig) -> Rig:
    from bags.train_data import bag_rig_grid

    return bag_rig_grid(cfg.bag[0])[0]


def _bag_grid(cfg: TrainConfig) -> BevGrid:
    from bags.train_data import bag_rig_grid

    return bag_rig_grid(cfg.bag[0])[1]


__all__ = ["TrainState", "TrainingError", "load_optimizer", "model_config", "save_optimizer", "train", "validate"]
