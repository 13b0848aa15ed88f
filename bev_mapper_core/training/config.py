"""Typed, frozen training configuration (``bev-train`` flags and ``--config`` YAML map onto it).

A :class:`TrainConfig` holds the run settings (rig, data, schedule, output), the BEV grid as a
:class:`~bev_mapper_core.geometry.grid.BevGrid`, and the training method's own config objects: ``model``
(its architecture, e.g. :class:`~bev_mapper_core.methods.bimapper.config.BiMapperConfig`) and ``loss`` (its
training settings, e.g. :class:`~bev_mapper_core.methods.bimapper.train.BiMapperTraining`). Serialised (``to_dict``,
saved in ``last.json``) it is a mapping with ``grid``, ``model`` and ``loss`` sub-mappings.

:meth:`TrainConfig.from_dict` also reads the flat form that ``bev-train`` flags produce and that
runs written before the plug-in split saved: method fields at top level (``streams``,
``ipm_skip``, ``asl``, ...), ``input`` / ``classes`` for the model's ``input_kind`` / classes,
``grid`` as ``[x_min, x_max, y_min, y_max, resolution]`` or ``null``.
"""

from __future__ import annotations

import math
from dataclasses import MISSING, asdict, dataclass, field, fields
from pathlib import Path
from typing import Any

from ..errors import BevMapperError, ConfigError
from ..geometry.grid import BevGrid, grid_preset
from ..geometry.random_rig import RANDOM_RIGS
from ..geometry.rig import PRESETS
from ..labels.classes import BEV_CLASS_NAMES, CAM2BEV_CLASSES, CLASS_SETS, resolve_classes
from ..labels.label_maps import label_map
from ..mapper import MapperConfig
from ..synth.config import SynthConfig
from ..synth.styles import check_style
from .method import method_class

#: Paper schedule (Bi-Mapper, 30 epochs): lr x0.1 at epoch 10.
PAPER_EPOCHS, PAPER_LR_STEP = 30, 10
CAM2BEV_CLASS_NAMES = tuple(c.name for c in CAM2BEV_CLASSES)
#: Class-set name used when a run names none (see :func:`class_set`).
AUTO_CLASSES = "auto"
#: Flat keys of the model config under another name: flat key -> model field.
MODEL_ALIASES = {"input": "input_kind"}


def class_set(name_or_list, rig: str) -> tuple[str, ...]:
    """``auto`` (Cam2BEV's road / vehicle / static for ``cam2bev4``, else the standard set), a
    class set's name (``standard``, ``cam2bev``, ``s2g2``: :data:`~bev_mapper_core.labels.classes.CLASS_SETS`),
    or a comma-separated list / sequence of class names.
    """
    if isinstance(name_or_list, str):
        if name_or_list == AUTO_CLASSES:
            return CAM2BEV_CLASS_NAMES if rig == "cam2bev4" else BEV_CLASS_NAMES
        if name_or_list in CLASS_SETS:
            return tuple(c.name for c in CLASS_SETS[name_or_list])
        names = tuple(n.strip() for n in name_or_list.split(",") if n.strip())
    else:
        names = tuple(name_or_list)
    resolve_classes(names)
    return names


def _jsonable(obj) -> dict:
    """A config dataclass as a JSON-ready dict (tuples as lists)."""
    d = obj.to_dict() if hasattr(obj, "to_dict") else asdict(obj)
    return {k: list(v) if isinstance(v, tuple) else v for k, v in d.items()}


def _build(cls: type, d: dict, what: str):
    """``cls(**d)`` with unknown keys and wrong types as ConfigError."""
    names = {f.name for f in fields(cls)}
    extra = sorted(set(d) - names)
    if extra:
        raise ConfigError(f"unknown {what} keys {extra}; known: {sorted(names)}")
    try:
        return cls(**d)
    except BevMapperError:
        raise
    except (TypeError, ValueError) as e:
        raise ConfigError(f"bad {what} ({e})") from None


def _grid(v) -> BevGrid:
    """A BevGrid from a BevGrid, a grid's name (:data:`~bev_mapper_core.geometry.grid.GRID_PRESETS`), a
    mapping, the old 5-sequence, or None (the default grid).
    """
    if v is None:
        return BevGrid()
    if isinstance(v, str):
        return grid_preset(v)
    if isinstance(v, BevGrid):
        return v
    if isinstance(v, dict):
        return _build(BevGrid, v, "grid")
    if isinstance(v, (list, tuple)) and len(v) == 5:
        return BevGrid(*(float(x) for x in v))
    raise ConfigError(f"grid must be a mapping of x_min, x_max, y_min, y_max, resolution (or those 5 values), got {v!r}")


@dataclass(frozen=True)
class TrainConfig:
    """Everything a training run depends on (saved beside every checkpoint).

    Args:
        method: registered training method (:func:`~.method.train_methods`).
        rig: preset rig name (ignored for the cameras when training on bags: the bag's rig), or
            ``random``: every synthetic drive seen by its own seeded random rig (a rig-free model,
            :mod:`~.multirig`).
        out: run directory.
        epochs, frames_per_epoch (None = every training frame), batch, lr, seed.
        lr_step_epoch: 0-based epoch from which lr is multiplied by ``lr_gamma``; None = the
            paper's epoch 10 of 30 scaled to ``epochs``.
        grad_clip: clip the gradients' global L2 norm to this before each step (None = off):
            guards against a loss spike throwing a run off (one S2G2 run's BEV loss jumped
            2000-fold in one epoch at Adam lr 1e-3 and never recovered).
        train_drives, val_drives, frames_per_drive, stride: synthetic data (see ``data.py``).
        val_seeds: explicit held-out drive seeds (default: ``val_seeds(val_drives)``).
        val_frames: frames of the held-out set scored after each epoch (None = all).
        cache: drive cache directory (None = render in memory every run).
        device, threads: torch device and CPU threads (with ``nproc`` > 1: the threads of all
            processes together, each taking ``max(1, threads // nproc)``).
        nproc: data-parallel processes (:mod:`~.distributed`: DistributedDataParallel, gloo on
            CPU, nccl on CUDA); each takes ``batch / nproc`` frames of every batch (``batch``
            stays the global batch, so it must be a multiple of ``nproc``). 1 = one process.
            Under ``torchrun`` the world size comes from torchrun (``nproc`` 1 or equal to it).
        resume: continue ``out``'s last checkpoint.
        time_budget_min: stop (checkpointed, resumable) once this much wall time has passed.
        bag, val_bag: rosbag2 paths with GT topics to train / validate on instead of drives (a
            folder of bags stands for the bags in it, as ``bev-bag import`` writes them).
        split, val_split: a dataset's own split (``bev_mapper.split`` in a bag's metadata, which
            ``bev-bag import`` records: nuScenes' ``train`` / ``val`` / ``mini_train`` /
            ``mini_val``, Argoverse 2's ``train`` / ``val``): train on the bags of ``bag`` in
            ``split`` and hold out those of ``val_bag`` (else of ``bag``) in ``val_split``.
        style: appearance style of the synthetic drives' RGB images (a
            :mod:`~bev_mapper_core.synth.styles` name; default ``mixed``: one training style per
            drive, never the held-out one); label images do not depend on it.
        unlabeled_drives: synthetic drives rendered as *unlabeled* frames for semi-supervised
            methods (S2G2): their ground truth is never read. Seeds follow the training drives'
            (``train_seeds(seed, train_drives + unlabeled_drives)[train_drives:]``: other worlds,
            never held-out ones). Each training batch then holds ``batch`` labeled and ``batch``
            unlabeled frames (the paper: 2 + 2). 0 = none (methods that need them refuse).
        unlabeled_style: appearance style of the unlabeled drives' RGB images (None = ``style``),
            e.g. ``dusk``, the style held out of ``mixed``: unlabeled frames of a look the labeled
            ones never show.
        unlabeled_bag: rosbag2 paths of unlabeled frames (``bev-train --unlabeled``; no GT
            needed, the cameras of ``rig``): the ``bev-train`` command reads them with
            ``bags.io.train_data.UnlabeledBagSource``; instead of ``unlabeled_drives``.
        unlabeled_real: a real-image dataset (``camvid:DIR`` / ``folder:DIR``, its training
            split; labels never read) whose images are unlabeled frames of a one-camera rig
            (:mod:`~bev_mapper_core.training.real_unlabeled`), beside ``unlabeled_drives``.
        unlabeled_real_frames: use the first this many of its images (0 = all).
        label_map: what the bags' label images hold (``native``, a preset of another segmenter
            or a YAML file, see :mod:`~bev_mapper_core.labels.label_maps`; default: MapperConfig's);
            bags only: synthetic drives are in this package's own ids.
        progress: tqdm progress bars.
        grid: the BEV grid (default: 60 m x 30 m at 0.15 m, which the shipped weights use);
            synthetic data only (bags bring their own).
        model: the method's architecture config (``None`` = the method's default with the
            ``auto`` class set of ``rig``); its ``input_kind`` and ``classes`` are the run's
            input and classes.
        loss: the method's training settings (``None`` = its defaults).
    """

    method: str = "bimapper"
    rig: str = "surround6"
    out: str = "runs/bimapper"
    epochs: int = 30
    frames_per_epoch: int | None = None
    batch: int = 4
    lr: float = 1e-3
    lr_gamma: float = 0.1
    lr_step_epoch: int | None = None
    grad_clip: float | None = None
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
    nproc: int = 1
    resume: bool = False
    time_budget_min: float | None = None
    bag: tuple[str, ...] | None = None
    val_bag: tuple[str, ...] | None = None
    split: str | None = None
    val_split: str | None = None
    label_map: str = MapperConfig.label_map
    style: str = SynthConfig.style
    unlabeled_drives: int = 0
    unlabeled_style: str | None = None
    unlabeled_bag: tuple[str, ...] | None = None
    unlabeled_real: str | None = None
    unlabeled_real_frames: int = 0
    progress: bool = True
    grid: BevGrid = field(default_factory=BevGrid)
    model: Any = None
    loss: Any = None

    def __post_init__(self) -> None:
        for name in ("val_seeds", "bag", "val_bag", "unlabeled_bag"):
            v = getattr(self, name)
            if v is not None:
                object.__setattr__(self, name, tuple(v) if not isinstance(v, str) else (v,))
        if not isinstance(self.grid, BevGrid):
            raise ConfigError(f"grid must be a BevGrid, got {self.grid!r} (TrainConfig.from_dict converts mappings)")
        cls = method_class(self.method)  # ConfigError for an unknown method
        if self.rig not in PRESETS and self.rig != RANDOM_RIGS:
            raise ConfigError(f"unknown rig {self.rig!r}; presets: {sorted(PRESETS)}, or {RANDOM_RIGS!r} "
                              "(every drive its own random rig)")
        if self.model is None:
            object.__setattr__(self, "model", cls.default_model_config(class_set(AUTO_CLASSES, self.rig)))
        if self.loss is None:
            object.__setattr__(self, "loss", cls.loss_config_type())
        for name, typ in (("model", cls.model_config_type), ("loss", cls.loss_config_type)):
            if not isinstance(getattr(self, name), typ):
                raise ConfigError(f"{name} of method {self.method!r} must be a {typ.__name__}, "
                                  f"got {type(getattr(self, name)).__name__}")
        for name in ("epochs", "batch", "train_drives", "val_drives", "frames_per_drive", "stride", "threads", "nproc"):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, int) or v < 1:
                raise ConfigError(f"{name} must be an integer >= 1, got {v!r}")
        for name in ("frames_per_epoch", "val_frames"):
            v = getattr(self, name)
            if v is not None and (isinstance(v, bool) or not isinstance(v, int) or v < 1):
                raise ConfigError(f"{name} must be an integer >= 1, got {v!r}")
        if self.batch % self.nproc:
            raise ConfigError(f"batch {self.batch} is the global batch of the {self.nproc} processes: it must be a "
                              f"multiple of nproc")
        if not (isinstance(self.lr, (int, float)) and math.isfinite(self.lr) and self.lr > 0):
            raise ConfigError(f"lr must be a finite number > 0, got {self.lr!r}")
        if not (0 < self.lr_gamma <= 1):
            raise ConfigError(f"lr_gamma must be in (0, 1], got {self.lr_gamma}")
        if self.lr_step_epoch is not None and (not isinstance(self.lr_step_epoch, int) or self.lr_step_epoch < 0):
            raise ConfigError(f"lr_step_epoch must be an integer >= 0, got {self.lr_step_epoch!r}")
        if not isinstance(self.seed, int) or self.seed < 0:
            raise ConfigError(f"seed must be an integer >= 0, got {self.seed!r}")
        if self.device.split(":")[0] not in ("cpu", "cuda"):
            raise ConfigError(f"device must be cpu or cuda[:N], got {self.device!r}")
        if self.grad_clip is not None and (isinstance(self.grad_clip, bool) or not isinstance(self.grad_clip, (int, float))
                                           or not math.isfinite(self.grad_clip) or self.grad_clip <= 0):
            raise ConfigError(f"grad_clip must be a finite number > 0 (or absent), got {self.grad_clip!r}")
        if self.time_budget_min is not None and not self.time_budget_min > 0:
            raise ConfigError(f"time_budget_min must be > 0, got {self.time_budget_min}")
        if self.val_seeds is not None and not self.val_seeds:
            raise ConfigError("val_seeds must not be empty")
        if self.val_bag is not None and self.bag is None:
            raise ConfigError("val_bag needs bag")
        if (self.split is not None or self.val_split is not None) and self.bag is None:
            raise ConfigError("split and val_split select imported bags: they need bag")
        if self.val_split is not None and self.split is None:
            raise ConfigError("val_split needs split (the training bags' split)")
        if self.split is not None and self.val_split is None and self.val_bag is None:
            raise ConfigError(f"split {self.split!r} needs the held-out split (val_split) or held-out bags (val_bag)")
        if self.split is not None and self.split == self.val_split:
            raise ConfigError(f"split and val_split are both {self.split!r}: the held-out frames would be trained on")
        label_map(self.label_map)  # ConfigError: no preset, or a bad YAML file
        check_style(self.style)
        self._check_unlabeled()
        if self.label_map != MapperConfig.label_map and ((self.bag is None and self.unlabeled_bag is None)
                                                         or self.model.input_kind != "labels"):
            raise ConfigError(f"label_map {self.label_map!r} applies to the label images of bags (bag, input "
                              "labels); synthetic drives are in this package's own ids")
        # The splits must be disjoint (checked here so that a bad config fails before any work).
        from .data import check_disjoint, train_seeds

        if self.bag is None:
            check_disjoint(train_seeds(self.seed, self.train_drives + self.unlabeled_drives), self.held_out_seeds)

    def _check_unlabeled(self) -> None:
        """``unlabeled_drives`` / ``unlabeled_style`` / ``unlabeled_bag`` (ConfigError)."""
        v = self.unlabeled_drives
        if isinstance(v, bool) or not isinstance(v, int) or v < 0:
            raise ConfigError(f"unlabeled_drives must be an integer >= 0, got {v!r}")
        if self.unlabeled_style is not None:
            check_style(self.unlabeled_style)
            if v == 0:
                raise ConfigError("unlabeled_style needs unlabeled_drives > 0")
        if self.unlabeled_bag is not None and (v or self.unlabeled_style is not None):
            raise ConfigError("unlabeled frames come from bags (unlabeled_bag) or from synthetic drives "
                              "(unlabeled_drives, unlabeled_style), not both")
        if v and self.bag is not None:
            raise ConfigError("unlabeled_drives are synthetic drives of the preset rig; they do not mix with "
                              "training bags (bag)")
        n = self.unlabeled_real_frames
        if isinstance(n, bool) or not isinstance(n, int) or n < 0:
            raise ConfigError(f"unlabeled_real_frames must be an integer >= 0, got {n!r}")
        if self.unlabeled_real is not None and (self.unlabeled_bag is not None or self.bag is not None):
            raise ConfigError("unlabeled_real joins synthetic drives' frames; it does not mix with bags "
                              "(bag, unlabeled_bag)")
        if n and self.unlabeled_real is None:
            raise ConfigError("unlabeled_real_frames needs unlabeled_real (a dataset)")

    # ------------------------------------------------------------------ derived
    @property
    def class_names(self) -> tuple[str, ...]:
        """The BEV classes trained (the model config's)."""
        return tuple(self.model.classes)

    @property
    def unlabeled_seeds(self) -> tuple[int, ...]:
        """Seeds of the unlabeled drives (after the training drives' seeds; empty if none)."""
        from .data import train_seeds

        if not self.unlabeled_drives:
            return ()
        return train_seeds(self.seed, self.train_drives + self.unlabeled_drives)[self.train_drives:]

    @property
    def held_out_seeds(self) -> tuple[int, ...]:
        """Seeds of the held-out drives (``val_seeds``, else ``data.val_seeds(val_drives)``)."""
        from .data import val_seeds

        return self.val_seeds if self.val_seeds is not None else val_seeds(self.val_drives)

    @property
    def lr_step(self) -> int:
        """0-based epoch of the lr step (paper 10 of 30, scaled)."""
        if self.lr_step_epoch is not None:
            return self.lr_step_epoch
        return max(1, round(self.epochs * PAPER_LR_STEP / PAPER_EPOCHS))

    def lr_at(self, epoch: int) -> float:
        """Learning rate of ``epoch`` (0-based): ``lr``, times ``lr_gamma`` from :attr:`lr_step` on."""
        return self.lr * (self.lr_gamma if epoch >= self.lr_step else 1.0)

    # --------------------------------------------------------------------- I/O
    def to_dict(self) -> dict:
        """JSON-ready mapping: run fields, ``grid``, ``model`` and ``loss`` as sub-mappings."""
        d = {f.name: getattr(self, f.name) for f in fields(self) if f.name not in ("grid", "model", "loss")}
        d = {k: list(v) if isinstance(v, tuple) else v for k, v in d.items()}
        return {**d, "grid": asdict(self.grid), "model": _jsonable(self.model), "loss": _jsonable(self.loss)}

    @classmethod
    def from_dict(cls, d: dict) -> "TrainConfig":
        """A config from :meth:`to_dict`'s mapping, from flat keys (flags, old run files), or a mix.

        Keys that are not TrainConfig fields go to the method's configs: ``input`` -> the model's
        ``input_kind``, ``classes`` (``auto`` / ``standard`` / ``cam2bev`` / names, resolved for the
        rig) -> its ``classes``, any other model-config field -> ``model``, loss-config field ->
        ``loss``. Flat keys override the ``model`` / ``loss`` sub-mappings. Unknown keys raise.
        """
        d = dict(d)
        run = {f.name for f in fields(cls)}
        method = method_class(d.get("method", _default("method")))
        model_fields = {f.name for f in fields(method.model_config_type)}
        loss_fields = {f.name for f in fields(method.loss_config_type)}
        model_kw = dict(_mapping(d.pop("model", None), "model"))
        loss_kw = dict(_mapping(d.pop("loss", None), "loss"))
        unknown = []
        for k in [k for k in d if k not in run]:
            v = d.pop(k)
            if k in MODEL_ALIASES:
                model_kw[MODEL_ALIASES[k]] = v
            elif k in model_fields:
                model_kw[k] = v
            elif k in loss_fields:
                loss_kw[k] = v
            else:
                unknown.append(k)
        if unknown:
            known = sorted(run | model_fields | loss_fields | set(MODEL_ALIASES))
            raise ConfigError(f"unknown training config keys {sorted(unknown)}; known: {known}")
        rig = d.get("rig", _default("rig"))
        if rig not in PRESETS and rig != RANDOM_RIGS:
            raise ConfigError(f"unknown rig {rig!r}; presets: {sorted(PRESETS)}, or {RANDOM_RIGS!r}")
        base = _jsonable(method.default_model_config(class_set(AUTO_CLASSES, rig)))
        model_kw["classes"] = class_set(model_kw.get("classes", AUTO_CLASSES), rig)
        d["model"] = _build(method.model_config_type, {**base, **model_kw}, f"{method.name} model config")
        d["loss"] = _build(method.loss_config_type, loss_kw, f"{method.name} loss config")
        d["grid"] = _grid(d.get("grid"))
        return _build(cls, d, "training config")

    @classmethod
    def from_yaml(cls, path: str | Path, **overrides) -> "TrainConfig":
        """The YAML mapping at ``path`` (see :meth:`from_dict`) with flat ``overrides`` on top."""
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
    RESUMABLE_CHANGES = ("epochs", "resume", "time_budget_min", "progress", "device", "threads", "nproc", "val_frames",
                         "cache")

    def resume_compatible(self, other: "TrainConfig") -> list[str]:
        """Fields (``model.streams`` for nested ones) that differ from ``other`` and would make
        resuming meaningless.
        """
        a, b = self.to_dict(), other.to_dict()
        diff = []
        for k, v in a.items():
            if k in self.RESUMABLE_CHANGES or v == b.get(k):
                continue
            if isinstance(v, dict) and isinstance(b.get(k), dict):
                diff += [f"{k}.{n}" for n in sorted(set(v) | set(b[k])) if v.get(n) != b[k].get(n)]
            else:
                diff.append(k)
        return diff


def _default(name: str):
    """Default of TrainConfig field ``name`` (the one source of it)."""
    f = TrainConfig.__dataclass_fields__[name]
    return f.default if f.default is not MISSING else f.default_factory()


def _mapping(v, what: str) -> dict:
    if v is None:
        return {}
    if hasattr(v, "__dataclass_fields__"):
        return _jsonable(v)
    if not isinstance(v, dict):
        raise ConfigError(f"{what} must be a mapping of field: value, got {v!r}")
    return v
