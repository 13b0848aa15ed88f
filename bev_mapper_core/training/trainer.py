"""The one training loop of every learned method: optimizer, step lr, epochs, time budget,
per-epoch validation, safetensors checkpoints, resume. The method itself (model, loss, what it
saves) is a :class:`~.method.TrainMethod` plug-in; the frames come from a
:class:`~.sources.DataSource` the caller hands in (synthetic drives by default).

Run directory layout (``config.out``)::

    last.safetensors        model weights after the last finished epoch (TrainMethod.save)
    last.json               training state: epoch (last finished, 0-based), step, best val
                            mIoU and its epoch, lr, history, the TrainConfig
    last_optim.safetensors  optimizer state, flattened to tensors (``state.<i>.<name>``) with the
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
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import torch
from safetensors import safe_open
from safetensors.torch import save_file

from ..errors import BevMapperError, ConfigError
from ..geometry.grid import BevGrid
from .config import TrainConfig
from .data import FrameSet
from .distributed import Ranks, batch_frames, launch, no_log, torchrun_ranks
from .evaluate import score_frameset
from .method import TrainMethod, method_class
from .sources import DataSource, InMemorySource, SynthSource, TrainData


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


# ------------------------------------------------------------------- validation
@torch.no_grad()
def validate(method: TrainMethod, frames: FrameSet, grid: BevGrid, batch: int = 4,
             limit: int | None = None) -> dict:
    """Metrics of ``method.predict`` over ``frames`` (in order, first ``limit``), scored by the
    one loop of ``bev-train eval`` (:func:`~.evaluate.score_frameset`, visible cells).
    """
    model = method.model
    was = model.training
    model.eval()
    try:
        with torch.no_grad():
            return score_frameset(method.predict, frames, grid, method.cfg.class_names, batch=batch, limit=limit)
    finally:
        model.train(was)


@dataclass
class TrainState:
    """Optimizer-free training state saved as JSON beside each checkpoint."""

    epoch: int = -1  # last finished epoch (0-based); -1 = none
    step: int = 0
    best_miou: float | None = None
    best_epoch: int | None = None
    train_seconds: float = 0.0
    history: list = field(default_factory=list)

    def to_json(self, cfg: TrainConfig, method: TrainMethod) -> dict:
        """The ``last.json`` / ``best.json`` document of this state."""
        return {"epoch": self.epoch, "step": self.step, "best_val_miou": self.best_miou, "best_epoch": self.best_epoch,
                "train_seconds": self.train_seconds, "history": self.history, "config": cfg.to_dict(),
                **method.checkpoint_info(), "torch": torch.__version__, "threads": torch.get_num_threads()}


def _write_json(path: Path, d: dict) -> None:
    tmp = path.with_name(path.name + ".tmp")
    tmp.write_text(json.dumps(d, indent=1, allow_nan=False))
    os.replace(tmp, path)


def _resume(cfg: TrainConfig, method: TrainMethod, opt: torch.optim.Optimizer, out: Path) -> TrainState:
    """Load ``out``'s last checkpoint into ``method`` and ``opt`` (configuration checked)."""
    last_json = out / "last.json"
    if not last_json.is_file():
        raise TrainingError(f"--resume: no checkpoint in {out} (missing {last_json.name})")
    doc = json.loads(last_json.read_text())
    old = TrainConfig.from_dict(doc["config"])  # also the flat form of runs before the plug-in split
    diff = cfg.resume_compatible(old)
    if diff:
        raise TrainingError(f"--resume: configuration differs from the checkpoint's in {diff}")
    method.load(out / "last.safetensors")
    load_optimizer(opt, out / "last_optim.safetensors")
    return TrainState(doc["epoch"], doc["step"], doc["best_val_miou"], doc["best_epoch"],
                      doc.get("train_seconds", 0.0), doc.get("history", []))


def train(cfg: TrainConfig, log: Callable[[str], None] = print,
          data: DataSource | tuple[FrameSet, ...] | None = None) -> dict:
    """Run (or resume) training as configured; returns the final ``last.json`` document.

    ``data``: where the frames come from: a :class:`~.sources.DataSource` (the ``bev-train``
    command passes the bag source for ``--bag``), ``(train, val[, unlabeled])`` FrameSets already
    at the size the method needs (tests), or None for the synthetic drives of ``cfg``.

    Data-parallel (:mod:`.distributed`): under ``torchrun`` this process is one rank of its
    world; else ``cfg.nproc`` > 1 spawns that many local ranks (``data`` is pickled to them) and
    returns rank 0's result (a script doing so needs the ``if __name__ == "__main__":`` guard:
    the spawned processes import its main module). One process (``nproc`` 1, no torchrun) is
    the plain loop.
    """
    ranks = torchrun_ranks(cfg)
    if ranks is not None:
        ranks.init("env://")
        try:
            return _train(cfg, log, data, ranks)
        finally:
            ranks.close()
    if cfg.nproc > 1:
        return launch(cfg, log, data, _train)
    return _train(cfg, log, data, Ranks())


def _train(cfg: TrainConfig, log: Callable[[str], None], data: DataSource | tuple[FrameSet, ...] | None,
           ranks: Ranks) -> dict:
    """The training loop of one rank (see :func:`train`); rank 0 logs, validates and writes."""
    torch.set_num_threads(ranks.threads(cfg.threads))
    if cfg.device.startswith("cuda") and not torch.cuda.is_available():
        raise ConfigError(f"device {cfg.device!r} requested but CUDA is not available")
    device = ranks.device(cfg.device)
    main = ranks.is_main
    if not main:
        log = no_log  # under torchrun every rank gets the command's log
    source = SynthSource() if data is None else InMemorySource(*data) if isinstance(data, tuple) else data
    out = Path(cfg.out)
    last_json = out / "last.json"
    rig, grid = source.rig_grid(cfg)
    torch.manual_seed(cfg.seed)
    method = method_class(cfg.method)(cfg, rig, grid)
    method.model.to(device)
    opt = method.configure_optimizer(cfg.lr)
    state = TrainState()
    if cfg.resume:
        state = _resume(cfg, method, opt, out)
        log(f"resumed {out} after epoch {state.epoch + 1} (step {state.step})")
    elif last_json.exists():
        raise TrainingError(f"{out} already holds a run; use --resume or another --out")
    frames = ranks.in_turn(lambda: source.load(cfg, rig, grid, method.data_needs(), log))
    method.prepare(frames, log)
    if main:  # after the data is read: a run that cannot start leaves no directory behind
        out.mkdir(parents=True, exist_ok=True)
    n_params = sum(p.numel() for p in method.model.parameters())
    schedule = method.schedule()
    log(f"model: {n_params / 1e6:.2f} M parameters, {method.describe()}; lr {cfg.lr} x{cfg.lr_gamma} from epoch "
        f"{cfg.lr_step + 1}" + (f", {schedule}" if schedule else ""))
    if ranks.world > 1:
        log(f"data-parallel: {ranks.world} processes of {cfg.batch // ranks.world} frames per batch, "
            f"{ranks.threads(cfg.threads)} threads each")
    step_loss = ranks.wrap(method)  # method.loss, or through DistributedDataParallel
    t_start = time.time()
    budget_s = None if cfg.time_budget_min is None else cfg.time_budget_min * 60.0
    stopped = False
    for epoch in range(state.epoch + 1, cfg.epochs):
        for g in opt.param_groups:
            g["lr"] = cfg.lr_at(epoch)
        torch.manual_seed(ranks.epoch_seed(cfg.seed * 100_003 + epoch))
        method.model.train()
        method.start_epoch(epoch)
        t0 = time.time()
        sums: dict[str, float] = {}
        n = 0
        batches = frames.batches(cfg.batch, cfg.seed, epoch, limit=cfg.frames_per_epoch, shard=ranks.shard)
        total = frames.steps(cfg.batch, cfg.frames_per_epoch)
        if cfg.progress and main:
            from tqdm import tqdm

            batches = tqdm(batches, total=total, desc=f"epoch {epoch + 1}/{cfg.epochs}", unit="batch", mininterval=5)
        for b in batches:
            loss, parts = step_loss(b, epoch, state.step)
            if ranks.world > 1:  # the global batch's parts on every rank; the loss scaled for DDP's mean
                parts, scale = ranks.reduce_parts(parts, batch_frames(b))
                if scale != 1.0:
                    loss = loss * scale
                finite = math.isfinite(parts["total"])
            else:
                finite = bool(torch.isfinite(loss))
            if not finite:
                raise TrainingError(f"loss became {parts['total'] if ranks.world > 1 else float(loss)} "
                                    f"at step {state.step}")
            opt.zero_grad(set_to_none=True)
            loss.backward()
            if cfg.grad_clip is not None:
                torch.nn.utils.clip_grad_norm_(method.model.parameters(), cfg.grad_clip)
            opt.step()
            state.step += 1
            method.after_step(state.step)
            n += 1
            for k, v in parts.items():
                sums[k] = sums.get(k, 0.0) + v
            if cfg.progress and hasattr(batches, "set_postfix"):
                batches.set_postfix(loss=f"{parts['total']:.3f}")
            if budget_s is not None and ranks.any(time.time() - t_start > budget_s):
                stopped = True
                break
        train_s = time.time() - t0
        state.train_seconds += train_s
        state.epoch = epoch
        if main:
            _end_epoch(cfg, log, method, opt, frames, grid, state, epoch, n, total, sums, train_s, stopped)
        ranks.barrier()  # the others wait while rank 0 validates and writes
        if stopped:
            log(f"stopped by the time budget ({cfg.time_budget_min} min) after epoch {epoch + 1}; --resume continues")
            break
    doc = json.loads(last_json.read_text()) if last_json.exists() else state.to_json(cfg, method)
    return doc


def _epoch_metrics(method: TrainMethod, log: Callable[[str], None]) -> dict:
    """The method's extra held-out figures (:meth:`~.method.TrainMethod.epoch_metrics`), in eval mode."""
    model = method.model
    was = model.training
    model.eval()
    try:
        with torch.no_grad():
            return method.epoch_metrics(log)
    finally:
        model.train(was)


def _end_epoch(cfg: TrainConfig, log: Callable[[str], None], method: TrainMethod, opt: torch.optim.Optimizer,
               frames: TrainData, grid: BevGrid, state: TrainState, epoch: int, n: int, total: int,
               sums: dict[str, float], train_s: float, stopped: bool) -> None:
    """Validate, log, and write ``metrics.jsonl`` and the checkpoints of a finished epoch."""
    out = Path(cfg.out)
    if stopped and n < total:
        # the cut epoch is validated and checkpointed like a finished one (a resume starts
        # with the next epoch); its history record says ``partial``
        log(f"time budget reached inside epoch {epoch + 1} after {n}/{total} batches")
    tv = time.time()
    res = validate(method, frames.val, grid, cfg.batch, cfg.val_frames)
    val_s = time.time() - tv
    miou = res["miou"]
    rec = {"epoch": epoch, "step": state.step, "lr": cfg.lr_at(epoch), "batches": n, "train_s": round(train_s, 1),
           "val_s": round(val_s, 1), **{f"loss_{k}": v / max(n, 1) for k, v in sums.items()},
           "val_miou": miou, "val_iou": {k: v["iou"] for k, v in res["classes"].items()}, "partial": stopped and n < total}
    terms = " ".join(f"{k} {v / max(n, 1):.4f}" for k, v in sums.items() if k != "total")
    log(f"epoch {epoch + 1}/{cfg.epochs}: loss {rec.get('loss_total', float('nan')):.4f} ({terms}) "
        f"val mIoU {100 * (miou or 0):.1f} [{train_s:.0f} s train, {val_s:.0f} s val]")
    rec.update(_epoch_metrics(method, log))
    state.history.append(rec)
    with open(out / "metrics.jsonl", "a") as f:
        f.write(json.dumps(rec) + "\n")
    if miou is not None and (state.best_miou is None or miou > state.best_miou):
        state.best_miou, state.best_epoch = miou, epoch
        method.save(out / "best.safetensors")
        _write_json(out / "best.json", {**state.to_json(cfg, method), "val": res})
    method.save(out / "last.safetensors")
    save_optimizer(opt, out / "last_optim.safetensors")
    _write_json(out / "last.json", state.to_json(cfg, method))


__all__ = ["TrainState", "TrainingError", "load_optimizer", "save_optimizer", "train", "validate"]
