"""FocusBEV's training plug-in (``bev-train --method focusbev --rig front1 --input rgb``).

Each sample is a window of ``window`` consecutive frames of one drive with their ego poses
(:meth:`~.data.FrameSet.windows`; before a drive's first frame the missing history is absent
and the reference feature stands in, as after a memory reset, so the model also learns to map
without history). The history frames run forward only (no gradient: the paper's "history BEV
features only participate in the forward propagation"), newest first into the
:class:`~bev_mapper_core.methods.focusbev.blocks.EgoMotionFusion`; the loss (Eq. 10,
:func:`~bev_mapper_core.methods.focusbev.losses.focusbev_loss`) is the last frame's.

The history is as far back as the training frames are apart: ``stride`` synthetic steps,
``stride / rate_hz`` seconds (0.3 s by default). The weights record it
(``memory_interval_s``), and the mapper's memory bank picks history frames that far apart
whatever the camera rate (:mod:`~bev_mapper_core.methods.focusbev.mapper`).

**Augmentation** (``augment``, default on; RGB input only, label input ignores it). The camera
images of every training window are augmented photometrically
(:meth:`~bev_mapper_core.nn.augment.Augment.camera_images`: exposure, contrast, saturation, white
balance, gamma, blur, noise) from a generator seeded by the run seed, the step and the
data-parallel rank, so ``--resume`` is exact. One draw per window: its frames (``stride /
rate_hz`` = 0.3 s apart by default) share the exposure, colour, gamma and blur, as one camera's
auto-exposure and white balance barely change in that time, and the temporal fusion should not
learn to discount its history for an appearance jump a real camera does not make; the sensor
noise is drawn per frame, as it is. No geometric augmentation: scaling, cropping or flipping the
image changes the camera's calibration, which the polar transform is built from, and the BEV
target would no longer match (a flip with the target mirrored is not exact either: ``front1``'s
camera is neither centred, cx 816.3 of 1600 px, nor straight, 0.3 deg yaw). Validation windows
are not augmented.

Optimizer: AdamW (the paper's); the trainer's step schedule replaces the paper's warm-up and
linear decay. Positive weights of the BCE: the project's ``auto`` weights, as Bi-Mapper's
(PON's weighted BCE weighs classes too; its exact weights are dataset statistics), capped at
``pos_weight_max``, some set by ``pos_weight_classes``.

**segipm's prior on a frozen trunk** (issue #39, as S2G2's;
:mod:`~bev_mapper_core.training.frozen_trunk`). With ``FocusBEVConfig.prior_skip`` the prior of
every training frame (:class:`~bev_mapper_core.methods.segipm.prior.SegIpmPrior`, from the
camera-size image as it is) is computed once in :meth:`FocusBEVMethod.prepare` and indexed by the
batches' frame ids (a window's last frame: the prior enters after the fusion); validation computes
it per frame, as the mapper does. ``frozen_encoder`` keeps the backbone (the shipped segmenter's
trunk or Lite0) as it starts, and ``feature_copies`` caches its maps of every training frame once
(window 1 only: the history frames of a window would need their own copies), so a step runs the
FPN, the view transformers and the top-down network only.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
import torch
from typing_extensions import override

from bev_mapper_core.errors import ConfigError
from bev_mapper_core.nn.augment import Augment, step_augment
from bev_mapper_core.synth.config import SynthConfig
from bev_mapper_core.training.class_weights import POS_WEIGHTS
from bev_mapper_core.training.frozen_trunk import (
    FROZEN_TRUNK_FLAGS,
    PRIOR_SKIP_FLAG,
    FrozenTrunkTraining,
    cache_mib,
    encode_cache,
    pick_cached,
)
from bev_mapper_core.training.method import CliFlag, TrainMethod
from bev_mapper_core.training.sources import DataNeeds, TrainData

from ..segipm.prior import training_priors
from ..segmenter.trunk import check_encoder_init, init_encoder
from .losses import FocusBEVLossConfig, focusbev_loss
from .model import BACKBONES, FocusBEV, FocusBEVConfig
from .weights import load_state_focusbev, save_focusbev


@dataclass(frozen=True)
class FocusBEVTraining(FrozenTrunkTraining):
    """FocusBEV's training settings (and :class:`~bev_mapper_core.training.frozen_trunk.FrozenTrunkTraining`'s
    ``frozen_encoder``, ``feature_copies``, ``pos_weight_max``, ``pos_weight_classes``).

    Args:
        uncertainty_weight, iou_weight: the loss weights (:class:`FocusBEVLossConfig`).
        pos_weight: ``auto`` (per-class BCE weights from the training set) or ``none``.
        weight_decay: AdamW's (PyTorch's default 0.01; the paper does not give it).
        augment: photometric augmentation of the training windows' camera images, one draw per
            window (RGB input; see the module docstring).
        encoder_init: the start of an ``efficientnet`` backbone: ``auto`` (the shipped
            segmenter's trunk on RGB input, none on label input), ``none`` (from scratch),
            ``segmenter`` or a segmenter weights path
            (:func:`~bev_mapper_core.methods.segmenter.trunk.encoder_source`); of a ``lite0``
            backbone: ``imagenet`` (``auto`` on RGB input) or ``none``. The ResNet backbone has
            no pretrained weights: with it only ``auto`` and ``none`` apply.
    """

    uncertainty_weight: float = FocusBEVLossConfig.uncertainty_weight
    iou_weight: float = FocusBEVLossConfig.iou_weight
    pos_weight: str = "auto"
    weight_decay: float = 0.01
    augment: bool = True
    encoder_init: str = "auto"

    def __post_init__(self) -> None:
        check_encoder_init(self.encoder_init)
        if not isinstance(self.augment, bool):
            raise ConfigError(f"augment must be true or false, got {self.augment!r}")
        if self.pos_weight not in POS_WEIGHTS:
            raise ConfigError(f"pos_weight must be one of {POS_WEIGHTS}, got {self.pos_weight!r}")
        v = self.weight_decay
        if isinstance(v, bool) or not isinstance(v, (int, float)) or not np.isfinite(v) or v < 0:
            raise ConfigError(f"weight_decay must be a finite number >= 0, got {v!r}")
        self.check_frozen_trunk()
        self.loss_config()

    def loss_config(self) -> FocusBEVLossConfig:
        """The loss weights of a run."""
        return FocusBEVLossConfig(self.uncertainty_weight, self.iou_weight)


def history(model: FocusBEV, x: torch.Tensor, poses: torch.Tensor, present: torch.Tensor) -> list:
    """The fusion's history for the last frame of windows: model inputs ``x`` ``(B, T, C_in, h, w)``,
    ``poses`` ``(B, T, 4, 4)`` (odom_from_base), ``present`` ``(B, T)`` -> newest-first
    ``(feature, prev_from_cur, present)`` of frames ``T-2 .. 0``, computed without gradient.
    """
    T = x.shape[1]
    cur = poses[:, -1].double()
    out = []
    with torch.no_grad():
        for t in range(T - 2, -1, -1):
            feat = model.bev_features(x[:, t])
            prev_from_cur = torch.linalg.inv(poses[:, t].double()) @ cur  # (B, 4, 4)
            out.append((feat, prev_from_cur, present[:, t]))
    return out


class FocusBEVMethod(TrainMethod):
    """FocusBEV trained on windows of consecutive frames (see the module docstring)."""

    name = "focusbev"
    model_config_type = FocusBEVConfig
    loss_config_type = FocusBEVTraining
    cli_flags = (
        CliFlag("--input-width", "input_width", min_value=32),
        CliFlag("--backbone", "backbone", choices=BACKBONES,
                help="resnet (the paper's, from scratch), efficientnet (the shipped segmenter's trunk) or lite0 "
                     "(EfficientNet-Lite0, from ImageNet)"),
        CliFlag("--encoder-init", "encoder_init",
                help="efficientnet backbone's start: auto (the shipped segmenter on RGB), none, segmenter, or a "
                     "segmenter weights path; lite0's: imagenet (auto on RGB) or none"),
        CliFlag("--backbone-depth", "backbone_depth", min_value=18, help="ResNet depth: 18, 34, 50 or 101"),
        CliFlag("--backbone-width", "backbone_width", min_value=4, help="ResNet stem width (paper 64)"),
        CliFlag("--fpn-levels", "fpn_levels", min_value=1),
        CliFlag("--channels", "channels", min_value=4, help="hidden dimension d"),
        CliFlag("--decoder-layers", "decoder_layers", min_value=0, help="0 = the column-wise MLP baseline"),
        CliFlag("--heads", "heads", min_value=1),
        CliFlag("--no-cycle", "cycle", action="store_false", help="ablation: no BEV-PV-BEV cycle"),
        CliFlag("--window", "window", min_value=1, help="frames of the temporal fusion (1 = off; paper 2)"),
        CliFlag("--bev-downsample", "bev_downsample", min_value=1, help="BEV feature map = grid / this"),
        CliFlag("--decoder-channels", "decoder_channels", min_value=1),
        CliFlag("--uncertainty-weight", "uncertainty_weight", number=True, help="lambda_u (paper 0.001)"),
        CliFlag("--iou-weight", "iou_weight", number=True, help="lambda_iou of the OA-IoU loss (paper 0.01)"),
        CliFlag("--pos-weight", "pos_weight", choices=POS_WEIGHTS, help="BCE class weights (none = plain)"),
        CliFlag("--augment", "augment", action="boolean",
                help="photometric augmentation (colour, exposure, blur, noise) of the training windows' images, "
                     "one draw per window (RGB input)"),
        PRIOR_SKIP_FLAG,
        *FROZEN_TRUNK_FLAGS,
    )

    @override
    def build_model(self) -> FocusBEV:
        model = FocusBEV(self.cfg.model, self.rig, self.grid)
        self.encoder_source = None
        init = self.cfg.loss.encoder_init
        if self.cfg.model.backbone == "efficientnet" and init != "imagenet":
            self.encoder_source = init_encoder(model.backbone.trunk, init, self.cfg.model.input_kind, self.rig.name)
        elif self.cfg.model.backbone == "lite0" and init in ("imagenet", "none", "auto"):
            # auto: ImageNet on RGB input (the segmenter's trunk is no Lite0), none on labels
            rgb = self.cfg.model.input_kind == "rgb"
            spec = "imagenet" if init == "imagenet" or (init == "auto" and rgb) else "none"
            self.encoder_source = init_encoder(model.backbone.trunk, spec, self.cfg.model.input_kind, self.rig.name)
        elif init not in ("auto", "none"):
            need = "lite0" if init == "imagenet" else "efficientnet"
            raise ConfigError(f"encoder_init {init!r} initializes {'a' if need == 'lite0' else 'an'} {need} backbone; "
                              f"the {self.cfg.model.backbone} backbone has no pretrained weights for it "
                              f"(use --backbone {need})")
        if self.cfg.loss.frozen_encoder:
            if self.cfg.model.backbone == "resnet":
                raise ConfigError("frozen_encoder keeps a pretrained trunk: use --backbone efficientnet or lite0")
            model.backbone.requires_grad_(False)
        if self.cfg.loss.feature_copies and self.cfg.model.window != 1:
            raise ConfigError("feature_copies caches single frames' features: it needs --window 1")
        self._cache: tuple[torch.Tensor, ...] = ()
        return model

    @override
    def trainable_parameters(self):
        return [p for p in self.model.parameters() if p.requires_grad]

    @override
    def configure_optimizer(self, lr: float) -> torch.optim.Optimizer:
        return torch.optim.AdamW(self.trainable_parameters(), lr=lr, weight_decay=self.cfg.loss.weight_decay)

    @override
    def describe(self) -> str:
        m, c = self.model, self.cfg.model
        if c.backbone == "resnet":
            trunk = f"ResNet-{c.backbone_depth} width {c.backbone_width}"
        else:
            trunk = f"EfficientNet trunk from {self.encoder_source}" if self.encoder_source else "EfficientNet trunk"
        return (f"input {m.input_size}, {trunk}, FPN {m.level_hw}, "
                f"depth ranges {[f'{a:.1f}-{b:.1f}' for a, b in m.ranges]} m in {m.depths} bins, "
                f"{c.decoder_layers} decoder layers x {c.heads} heads, cycle {'on' if c.cycle else 'off'}, "
                f"window {c.window}, BEV features {m.fgrid.shape}, classes {list(self.cfg.class_names)}")

    @override
    def schedule(self) -> str:
        t = self.cfg.loss
        aug = ", images augmented per window" if self._augments() else ""
        return f"AdamW (wd {t.weight_decay}){aug}, loss BCE + {t.uncertainty_weight} uncertainty + {t.iou_weight} OA-IoU"

    @override
    def data_needs(self) -> DataNeeds:
        w = self.cfg.model.window
        size = None if self.cfg.model.prior_skip else self.model.input_size  # the prior reads camera-size images
        return DataNeeds(image_size=size, sequence_length=w, poses=w > 1,
                         rgb=self.cfg.model.input_kind == "rgb", labels=self.cfg.model.input_kind == "labels")

    @override
    def prepare(self, data: TrainData, log: Callable[[str], None]) -> None:
        pw = self.cfg.loss.run_pos_weights(data.train, self.cfg.class_names)
        self.pos_weight = None if pw is None else torch.tensor(pw, dtype=torch.float32)
        self.loss_cfg = self.cfg.loss.loss_config()
        if pw is not None:
            log(f"BCE positive weights {dict(zip(self.cfg.class_names, pw))}")
        if self.cfg.model.prior_skip:
            self._prior_fn, priors = training_priors(self.rig, self.grid, self.cfg.class_names, self.device,
                                                     {"train": data.train}, log)
            self._priors = priors["train"]
        if self.cfg.loss.feature_copies:
            t0 = time.monotonic()
            n = self.cfg.loss.feature_copies
            self.model.backbone.eval()
            # the FPN reads the maps from stride 8 on: the stride-4 map is not kept
            self._cache = encode_cache(lambda x: self.model.backbone(x)[1:], self._inputs, data.train, n,
                                       self.cfg.seed, self.device)
            log(f"feature cache: {n} cop{'y' if n == 1 else 'ies'} of {self._cache[0].shape[1]} frames, "
                f"{cache_mib(self._cache):.0f} MiB, {time.monotonic() - t0:.1f} s")

    def _augments(self) -> bool:
        """Training images are augmented: ``augment`` on RGB input."""
        return self.cfg.loss.augment and self.cfg.model.input_kind == "rgb"

    def _raw(self, batch: dict, aug: Augment | None = None) -> torch.Tensor:
        """A batch's camera images (RGB on RGB input, else labels) on the device, ``aug``: the RGB
        images photometrically augmented, one draw per window.
        """
        raw = batch["rgb"] if self.cfg.model.input_kind == "rgb" else batch["images"]
        if aug is not None and self.cfg.model.input_kind == "rgb":
            # (B, 1, h, w, 3), or windows (B, T, 1, h, w, 3): each sample's T images (one camera) share the draw
            raw = aug.camera_images(raw.to(self.device), share=math.prod(raw.shape[1:-3]))  # float in [0, 255]
        return raw.to(self.device)

    def _inputs(self, batch: dict, aug: Augment | None = None) -> torch.Tensor:
        """Model input ``(B, C_in, h, w)`` of a batch of single frames (see :meth:`_raw`)."""
        return self.model.preprocess(self._raw(batch, aug))  # (B, 1, h, w[, 3]) -> (B, C_in, h, w)

    def _bev(self, x: torch.Tensor) -> torch.Tensor:
        """This frame's BEV feature ``(B, C, hb, wb)`` of model inputs ``x`` (the backbone without
        gradient when frozen).
        """
        if not self.cfg.loss.frozen_encoder:
            return self.model.bev_features(x)
        with torch.no_grad():
            feats = self.model.backbone(x)
        return self.model.bev_from_trunk(feats)

    def _forward(self, batch: dict, aug: Augment | None = None,
                 prior: torch.Tensor | None = None) -> dict[str, torch.Tensor]:
        """The model on a batch: single frames, or windows whose last frame is mapped; ``aug``:
        the RGB images photometrically augmented, one draw per window; ``prior``: the
        ``prior_skip`` input of the (last) frames.
        """
        if self.cfg.model.window == 1:
            return self.model.decode(self._bev(self._inputs(batch, aug)), None, prior)
        raw = self._raw(batch, aug)
        B, T = raw.shape[:2]
        x = self.model.preprocess(raw.flatten(0, 1))  # (B*T, 1, ...) -> (B*T, C_in, h, w)
        x = x.view(B, T, *x.shape[1:])  # (B*T, C_in, h, w) -> (B, T, C_in, h, w)
        hist = history(self.model, x, batch["poses"].to(self.device), batch["present"].to(self.device))
        return self.model.decode(self._bev(x[:, -1]), hist, prior)

    def _train_prior(self, batch: dict) -> torch.Tensor | None:
        """The cached prior ``(B, K + 1, H, W)`` of a training batch (None without ``prior_skip``)."""
        if not self.cfg.model.prior_skip:
            return None
        return self._priors[batch["index"].cpu()].to(self.device)

    @override
    def loss(self, batch: dict, epoch: int, step: int) -> tuple[torch.Tensor, dict[str, float]]:
        if self.cfg.loss.frozen_encoder:
            self.model.backbone.eval()  # the trainer sets train() each epoch: keep its BatchNorm statistics
        prior = self._train_prior(batch)
        if self._cache:
            feats = [f.to(self.device) for f in pick_cached(self._cache, batch["index"], self.cfg.seed, step)]
            out = self.model.decode(self.model.bev_from_trunk([None, *feats]), None, prior)
        else:
            out = self._forward(batch, step_augment(self.cfg.seed, step, self.device) if self._augments() else None,
                                prior)
        cm = batch.get("class_mask")
        return focusbev_loss(out["logits"], batch["target"].to(self.device), batch["mask"].to(self.device),
                             self.loss_cfg, self.pos_weight, None if cm is None else cm.to(self.device))

    @override
    def predict(self, batch: dict) -> tuple[np.ndarray, np.ndarray]:
        prior = None
        if self.cfg.model.prior_skip:
            rgb = batch["rgb"] if self.cfg.model.window == 1 else batch["rgb"][:, -1]  # (B, 1, H, W, 3)
            prior = self._prior_fn.batch(rgb).to(self.device)
        probs = torch.sigmoid(self._forward(batch, None, prior)["logits"]).float().cpu().numpy()  # (B, K, H, W)
        known = self.model.known().cpu().numpy()
        return probs, np.broadcast_to(known, (len(probs), *known.shape))

    def memory_interval_s(self) -> float:
        """Seconds between the frames of a training window (saved with the weights)."""
        return self.cfg.stride / SynthConfig.rate_hz

    @override
    def save(self, path) -> None:
        save_focusbev(self.model, path, self.memory_interval_s())

    @override
    def load(self, path) -> None:
        load_state_focusbev(self.model, path)


__all__ = ["FocusBEVMethod", "FocusBEVTraining", "history"]
