"""Typed, frozen training configuration (``bev-train`` flags and ``--config`` YAML map onto it)."""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass, fields
from pathlib import Path

from ..classes import BEV_CLASS_NAMES, CAM2BEV_CLASSES, resolve_classes
from ..errors import ConfigError
from ..grid import BevGrid
from ..models.config import FUSIONS, STREAMS
from ..models.losses import MUTUAL_MODES
from ..rig import PRESETS

METHODS = ("bimapper",)
#: Paper schedule (Bi-Mapper, 30 epochs): lr x0.1 at epoch 10, mutual learning from the 5th.
PAPER_EPOCHS, PAPER_LR_STEP, PAPER_MUTUAL_START = 30, 10, 4
CAM2BEV_CLASS_NAMES = tuple(c.name for c in CAM2BEV_CLASSES)


def class_set(name_or_list, rig: str) -> tuple[str, ...]:
    """``auto`` (Cam2BEV's road / vehicle / static for ``cam2bev4``, else the standard set),
    ``standard``, ``cam2bev``, or a comma-separated list / sequence of class names."""
    if isinstance(name_or_list, str):
        if name_or_list == "auto":
            return CAM2BEV_CLASS_NAMES if rig == "cam2bev4" else BEV_CLASS_NAMES
        if name_or_list == "standard":
            return BEV_CLASS_NAMES
        if name_or_list == "cam2bev":
            return CAM2BEV_CLASS_NAMES
        names = tuple(n.strip() for n in name_or_list.split(",") if n.strip())
    else:
        names = tuple(name_or_list)
    resolve_classes(names)
    return names


@dataclass(frozen=True)
class TrainConfig:
    """Everything a training run depends on (saved beside every checkpoint).

    Args:
        method: learned method (``bimapper``).
        rig: preset rig name (ignored for the cameras when training on bags: the bag's rig).
        input: ``labels`` (the synthetic drives and bags carry label images; ``rgb`` untested).
        classes: ``auto`` / ``standard`` / ``cam2bev`` / comma list (see :func:`class_set`).
        out: run directory.
        epochs, frames_per_epoch (None = every training frame), batch, lr, seed.
        lr_step_epoch: 0-based epoch from which lr is multiplied by ``lr_gamma``; None = the
            paper's epoch 10 of 30 scaled to ``epochs``.
        mutual_start_epoch: 0-based epoch from which GV also teaches LV (AML); None = the
            paper's 5th of 30 scaled to ``epochs``.
        train_drives, val_drives, frames_per_drive, stride: synthetic data (see ``data.py``).
        val_seeds: explicit held-out drive seeds (default: ``val_seeds(val_drives)``).
        val_frames: frames of the held-out set scored after each epoch (None = all).
        cache: drive cache directory (None = render in memory every run).
        device, threads: torch device and CPU threads.
        resume: continue ``out``'s last checkpoint.
        streams, fusion, asl, mutual: ablation switches (model streams, fusion, Across-Space
            Loss on/off, mutual-learning mode).
        lv_full_res: the LV stream samples camera-size images (BiMapperConfig.lv_full_res).
        ipm_skip: full-resolution IPM prior into the decoder head (BiMapperConfig.ipm_skip;
            not in the paper).
        input_width, gv_hidden: model size knobs (BiMapperConfig).
        time_budget_min: stop (checkpointed, resumable) once this much wall time has passed.
        bag, val_bag: rosbag2 paths with GT topics to train / validate on instead of drives.
        progress: tqdm progress bars.
        grid: ``(x_min, x_max, y_min, y_max, resolution)`` of the BEV grid (None = the default
            60 m x 30 m at 0.15 m, which the shipped weights use); synthetic data only.
        pos_weight: ``auto``: per-class positive weight of the ego BCE,
            ``clip(sqrt(negatives / positives), 1, 10)`` over the visible cells of the training
            set (thin and rare layers: lane dividers, crossings, pedestrians); ``none``: plain BCE
            as in the paper. See :func:`~.trainer.class_pos_weight`.
    """

    method: str = "bimapper"
    rig: str = "surround6"
    input: str = "labels"
    classes: str = "auto"
    out: str = "runs/bimapper"
    epochs: int = 30
    frames_per_epoch: int | None = None
    batch: int = 4
    lr: float = 1e-3
    lr_gamma: float = 0.1
    lr_step_epoch: int | None = None
    mutual_start_epoch: int | None = None
    seed: int = 0
    train_drives: int = 40
    val_drives: int = 6
    val_seeds: tuple[int, ...] | None = None
    frames_per_drive: int = 20
    stride: int = 3
    val_frames: int | None = None
    cache: str | None = "data/cache"
    device: str = "cpu"
    threads: int = 2
    resume: bool = False
    streams: str = "both"
    fusion: str = "sum"
    lv_full_res: bool = False
    ipm_skip: bool = False
    asl: bool = True
    mutual: str = "async"
    input_width: int = 112
    gv_hidden: int | None = 128
    time_budget_min: float | None = None
    bag: tuple[str, ...] | None = None
    val_bag: tuple[str, ...] | None = None
    progress: bool = True
    grid: tuple[float, float, float, float, float] | None = None
    pos_weight: str = "auto"

    def __post_init__(self) -> None:
        if self.grid is not None:
            if len(self.grid) != 5:
                raise ConfigError(f"grid must be (x_min, x_max, y_min, y_max, resolution), got {self.grid!r}")
            object.__setattr__(self, "grid", tuple(float(v) for v in self.grid))
            self.bev_grid()  # validates
        for name in ("val_seeds", "bag", "val_bag"):
            v = getattr(self, name)
            if v is not None:
                object.__setattr__(self, name, tuple(v) if not isinstance(v, str) else (v,))
        if self.method not in METHODS:
            raise ConfigError(f"method must be one of {METHODS}, got {self.method!r}")
        if self.rig not in PRESETS:
            raise ConfigError(f"unknown rig {self.rig!r}; presets: {sorted(PRESETS)}")
        if self.input not in ("labels", "rgb"):
            raise ConfigError(f"input must be 'labels' or 'rgb', got {self.input!r}")
        class_set(self.classes, self.rig)
        for name in ("epochs", "batch", "train_drives", "val_drives", "frames_per_drive", "stride", "threads", "input_width"):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, int) or v < 1:
                raise ConfigError(f"{name} must be an integer >= 1, got {v!r}")
        for name in ("frames_per_epoch", "val_frames", "gv_hidden"):
            v = getattr(self, name)
            if v is not None and (isinstance(v, bool) or not isinstance(v, int) or v < 1):
                raise ConfigError(f"{name} must be an integer >= 1, got {v!r}")
        if not (isinstance(self.lr, (int, float)) and math.isfinite(self.lr) and self.lr > 0):
            raise ConfigError(f"lr must be a finite number > 0, got {self.lr!r}")
        if not (0 < self.lr_gamma <= 1):
            raise ConfigError(f"lr_gamma must be in (0, 1], got {self.lr_gamma}")
        for name in ("lr_step_epoch", "mutual_start_epoch"):
            v = getattr(self, name)
            if v is not None and (not isinstance(v, int) or v < 0):
                raise ConfigError(f"{name} must be an integer >= 0, got {v!r}")
        if not isinstance(self.seed, int) or self.seed < 0:
            raise ConfigError(f"seed must be an integer >= 0, got {self.seed!r}")
        if self.streams not in STREAMS:
            raise ConfigError(f"streams must be one of {STREAMS}, got {self.streams!r}")
        if self.fusion not in FUSIONS:
            raise ConfigError(f"fusion must be one of {FUSIONS}, got {self.fusion!r}")
        if self.pos_weight not in ("auto", "none"):
            raise ConfigError(f"pos_weight must be 'auto' or 'none', got {self.pos_weight!r}")
        if self.mutual not in MUTUAL_MODES:
            raise ConfigError(f"mutual must be one of {MUTUAL_MODES}, got {self.mutual!r}")
        if self.device.split(":")[0] not in ("cpu", "cuda"):
            raise ConfigError(f"device must be cpu or cuda[:N], got {self.device!r}")
        if self.time_budget_min is not None and not self.time_budget_min > 0:
            raise ConfigError(f"time_budget_min must be > 0, got {self.time_budget_min}")
        if self.val_seeds is not None and not self.val_seeds:
            raise ConfigError("val_seeds must not be empty")
        if self.val_bag is not None and self.bag is None:
            raise ConfigError("val_bag needs bag")
        # The splits must be disjoint (checked here so that a bad config fails before any work).
        from .data import check_disjoint, train_seeds, val_seeds

        if self.bag is None:
            check_disjoint(train_seeds(self.seed, self.train_drives), self.held_out_seeds)

    # ------------------------------------------------------------------ derived
    def bev_grid(self) -> BevGrid:
        return BevGrid() if self.grid is None else BevGrid(*self.grid)

    @property
    def class_names(self) -> tuple[str, ...]:
        return class_set(self.classes, self.rig)

    @property
    def held_out_seeds(self) -> tuple[int, ...]:
        from .data import val_seeds

        return self.val_seeds if self.val_seeds is not None else val_seeds(self.val_drives)

    @property
    def lr_step(self) -> int:
        """0-based epoch of the lr step (paper 10 of 30, scaled)."""
        if self.lr_step_epoch is not None:
            return self.lr_step_epoch
        return max(1, round(self.epochs * PAPER_LR_STEP / PAPER_EPOCHS))

    @property
    def mutual_start(self) -> int:
        """0-based epoch from which both streams teach (paper: the 5th of 30 -> 4, scaled)."""
        if self.mutual_start_epoch is not None:
            return self.mutual_start_epoch
        return round(self.epochs * PAPER_MUTUAL_START / PAPER_EPOCHS)

    def lr_at(self, epoch: int) -> float:
        return self.lr * (self.lr_gamma if epoch >= self.lr_step else 1.0)

    # --------------------------------------------------------------------- I/O
    def to_dict(self) -> dict:
        return {k: list(v) if isinstance(v, tuple) else v for k, v in asdict(self).items()}

    @classmethod
    def from_dict(cls, d: dict) -> "TrainConfig":
        names = {f.name for f in fields(cls)}
        extra = sorted(set(d) - names)
        if extra:
            raise ConfigError(f"unknown training config keys {extra}; known: {sorted(names)}")
        try:
            return cls(**d)
        except TypeError as e:
            raise ConfigError(f"bad training config ({e})") from None

    @classmethod
    def from_yaml(cls, path: str | Path, **overrides) -> "TrainConfig":
        import yaml

        try:
            d = yaml.safe_load(Path(path).read_text()) or {}
        except OSError as e:
            raise ConfigError(f"cannot read config {path}: {e}") from None
        except yaml.YAMLError as e:
            raise ConfigError(f"config {path} is not valid YAML ({e})") from None
        if not isinstance(d, dict):
            raise ConfigError(f"config {path} must be a mapping of field: value")
        d.update(overrides)
        return cls.from_dict(d)

    # ------------------------------------------------------------ what resumes
    #: fields that may change between a run and its resumption
    RESUMABLE_CHANGES = ("epochs", "resume", "time_budget_min", "progress", "device", "threads", "val_frames", "cache")

    def resume_compatible(self, other: "TrainConfig") -> list[str]:
        """Fields that differ from ``other`` and would make resuming meaningless."""
        a, b = self.to_dict(), other.to_dict()
        return [k for k in a if k not in self.RESUMABLE_CHANGES and a[k] != b[k]]
