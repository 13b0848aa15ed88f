"""The 2-D segmenter's training plug-in (``bev-train --method segmenter``).

Trains :class:`~bev_mapper_core.methods.segmenter.model.Segmenter` on the RGB camera images of
synthetic drives against their label images (every camera image of a frame is one sample),
with a class-weighted cross-entropy (:func:`~bev_mapper_core.methods.segmenter.model.class_weights`,
``--class-weights none`` for plain cross-entropy). Held-out frames are scored the way the
segmenter is used, in BEV: each camera's prediction is upsampled to the camera's size and
projected by IPM (with occlusion reasoning), i.e. the ``segipm`` method, through the one scorer
of every method. ``cfg.model`` is a :class:`SegmenterModel` (the segmenter's architecture plus
the run's BEV classes for that score), ``cfg.loss`` a :class:`SegmenterTraining`.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, fields

import numpy as np
import torch
from torch.nn import functional as F
from typing_extensions import override

from bev_mapper_core.errors import ConfigError
from bev_mapper_core.labels.classes import BEV_CLASS_NAMES, NUM_LABELS, resolve_classes
from bev_mapper_core.mapper import MapperConfig
from bev_mapper_core.training.method import CliFlag, TrainMethod
from bev_mapper_core.training.sources import DataNeeds, TrainData

from ..ipm.mapper import IpmMapper
from .model import Segmenter, SegmenterConfig, class_weights
from .weights import load_segmenter, save_segmenter

#: ``class_weights`` settings of :class:`SegmenterTraining`.
CLASS_WEIGHTINGS = ("auto", "none")


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
    """Segmenter training settings.

    Args:
        class_weights: ``auto``: cross-entropy weights from the training set's label pixel
            counts (:func:`~bev_mapper_core.methods.segmenter.model.class_weights`); ``none``: plain.
    """

    class_weights: str = "auto"

    def __post_init__(self) -> None:
        if self.class_weights not in CLASS_WEIGHTINGS:
            raise ConfigError(f"class_weights must be one of {CLASS_WEIGHTINGS}, got {self.class_weights!r}")


class SegmenterMethod(TrainMethod):
    """Per-camera semantic segmentation of RGB images (see the module docstring)."""

    name = "segmenter"
    model_config_type = SegmenterModel
    loss_config_type = SegmenterTraining
    cli_flags = (
        CliFlag("--seg-width", "input_width", min_value=16, help="segmenter input width (px)"),
        CliFlag("--class-weights", "class_weights", choices=CLASS_WEIGHTINGS,
                help="cross-entropy label weights (auto: softened median frequency)"),
    )

    @classmethod
    @override
    def default_model_config(cls, classes: tuple[str, ...]) -> SegmenterModel:
        return SegmenterModel(classes=tuple(classes))

    @override
    def build_model(self) -> Segmenter:
        sizes = {c.model.image_size for c in self.rig.cameras}
        if len(sizes) != 1:
            raise ConfigError(f"segmenter training needs cameras of one size; rig {self.rig.name!r} has {sorted(sizes)}")
        self.camera_size = sizes.pop()  # (W, H)
        self.weights = None
        self._ipm = None
        return Segmenter(self.cfg.model.segmenter_config())

    @override
    def describe(self) -> str:
        h, w = self.model.config.input_size(self.camera_size)
        return f"segmenter {w}x{h} input, {NUM_LABELS} labels; validation: segipm on {list(self.cfg.class_names)}"

    @override
    def data_needs(self) -> DataNeeds:
        return DataNeeds(image_size=self.model.config.input_size(self.camera_size), rgb=True)

    @override
    def prepare(self, data: TrainData, log: Callable[[str], None]) -> None:
        if data.train.rgb is None:
            raise ConfigError("the segmenter trains on RGB images; the data source gave none")
        if self.cfg.loss.class_weights == "auto":
            # labels are stored at the input size, ids outside Label already 0 (resize_labels)
            counts = torch.from_numpy(np.bincount(data.train.labels.ravel(), minlength=NUM_LABELS)[:NUM_LABELS])
            self.weights = class_weights(counts)
            log("label weights: " + ", ".join(f"{w:.2f}" for w in self.weights.tolist()))

    @override
    def loss(self, batch: dict, epoch: int, step: int) -> tuple[torch.Tensor, dict[str, float]]:
        rgb = batch["rgb"]  # (B, N, h, w, 3) at the model's input size
        B, N, h, w, _ = rgb.shape
        x = self.model.preprocess(rgb.reshape(B * N, h, w, 3).to(self.device))  # (B*N, 3, h, w)
        target = batch["images"].reshape(B * N, h, w).to(self.device).long()  # (B, N, h, w) -> (B*N, h, w)
        target = torch.where(target < NUM_LABELS, target, torch.zeros_like(target))
        logits = self.model(x)  # (B*N, L, h, w)
        weight = None if self.weights is None else self.weights.to(self.device)
        loss = F.cross_entropy(logits, target, weight=weight)
        with torch.no_grad():
            acc = (logits.argmax(1) == target).float().mean()
        ce = loss.item()
        return loss, {"ce": ce, "pixel_acc": acc.item(), "total": ce}

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
