"""S2G2's training plug-in (``bev-train --method s2g2 --rig front1 --unlabeled-drives N``).

Semi-supervised: every step sees ``batch`` labeled and ``batch`` unlabeled frames (the paper:
2 + 2; :meth:`~.sources.TrainData.batches`), both through the shared encoder and the DVT module;
``L_seg`` reads the labeled frames' ground truth, ``L_cycle``, ``L_BEV`` and ``L_con`` all frames
(:func:`~bev_mapper_core.methods.s2g2.losses.s2g2_loss`). After each optimizer step the passive
branch moves towards the active one (:meth:`S2G2Method.after_step`,
:func:`~bev_mapper_core.methods.s2g2.losses.ema_update`).

**The cycle loss and the encoder** (``cycle_into_encoder``). Eq. 1 compares the encoder's
features ``F`` with ``H_F^B(H_B^F(F))``; both sides depend on the encoder, which can then lower
the loss by making its features easier to reconstruct instead of more useful (the likely
reading of the figures below). Here that costs a lot:
supervised-only runs score 22.5 mIoU with the cycle loss, 28.1 without it (docs/RESULTS.md,
"S2G2"). By default the cycle loss therefore trains the two view-transform blocks only (the
reading of the paper's purpose for it: a front->BEV transform that keeps the front view's
information), with ``F`` detached; ``--cycle-into-encoder`` restores the gradient into the
encoder. The model computes the cycle once more for the loss (two small convolutions).

**Unlabeled frames and the encoder** (``unlabeled_into_encoder``). With both fixes above, the
consistency loss on unlabeled ``dusk`` frames alone still collapses the dusk maps (9.4 mIoU
against 31.6 supervised-only): the shared encoder can tell dusk frames apart and give them
features on which both branches trivially agree, and the passive branch, an average of the
active one, follows. S2G2 has no augmentation to break such agreement (its two views are F_C
and F_I of one image; the photometric augmentation below changes that one image for both views,
so it does not either; these runs predate it). By default the unlabeled frames' losses therefore
train everything after the encoder (view transforms, attentions, active branch) and not the
encoder, which the labeled frames train; ``--unlabeled-into-encoder`` lets them reach it (the
paper's setting).

**BatchNorm and unlabeled frames** (``unlabeled_bn``). ``batch`` runs labeled and unlabeled
frames as one batch, so BatchNorm normalizes both with the statistics of the mix (the paper's
setting, where both come from one domain). When the unlabeled frames come from another domain
(another appearance style) that mix is what breaks the target domain here: unlabeled ``dusk``
frames that only pass through the BatchNorm layers, with every unlabeled loss off, drop the dusk
test score from 31.8 (the same run with ``running``) to 12.6 mIoU (docs/RESULTS.md, "S2G2"): the decoder learns on labeled
features normalized against a batch half of which is dusk, and never sees what a dusk frame alone
looks like. ``running`` (default) runs the unlabeled frames in a second pass whose BatchNorm
layers use the running statistics and leave them alone (dropout and stochastic depth stay on), so
the unlabeled losses train on exactly the features the model computes for such a frame at test
time, and the statistics stay those of the labeled frames.

**Augmentation** (``augment``, default on; RGB input only, label input ignores it). Every
training frame's camera image, labeled and unlabeled alike, is augmented photometrically
(:meth:`~bev_mapper_core.nn.augment.Augment.camera_images`: exposure, contrast, saturation, white
balance, gamma, blur, noise; an independent draw per frame) from a generator seeded by the run
seed, the step and the data-parallel rank, so ``--resume`` is exact. No geometric augmentation:
scaling, cropping or flipping the image changes the camera's calibration, which the view
transform has learnt, and the BEV target would no longer match; a flip with the target mirrored
is not exact either, ``front1``'s camera being neither centred (cx 816.3 of 1600 px) nor
straight (0.3 deg yaw). The passive (EMA teacher) and active branches see the same augmented
image, as they see the same image without augmentation (S2G2's consistency is between the two
branches on one input; Mean Teacher's different student and teacher augmentations are not
used). Validation frames are not augmented.

``cfg.model`` is an :class:`~bev_mapper_core.methods.s2g2.model.S2G2Config` (its ``input_kind``: ``rgb``
by default, as the paper), ``cfg.loss`` an :class:`S2G2Training`.

**Optimizer.** ``adam`` (default) is the project's usual optimizer and the one every S2G2 run
in docs/RESULTS.md used (lr 1e-3, 1e-4 for the last epochs). ``sgd`` is the paper's: SGD,
momentum 0.9, weight decay 1e-4 (the paper's lr is 5e-5 with a 0.995 exponential decay per
epoch; the trainer's own schedule, ``lr`` and a step at ``lr_step_epoch``, applies instead). The
two were not compared over a full run.

**Pretrained feature extractor.** The paper starts from an ImageNet-pretrained EfficientNet-B4.
Nothing can be downloaded here, so the project's equivalent is its own pretrained image encoder:
the EfficientNet trunk of the shipped 2-D segmenter (``weights/segmenter.safetensors``, trained
on labeled drives in the training styles and on CamVid's train split, never on the held-out
``dusk`` style or the test seeds; CamVid is CC BY-NC 4.0, see docs/MODELS.md).
``encoder_init`` ``auto`` (default) copies it into S2G2's encoder on RGB input (the
default :class:`~bev_mapper_core.methods.s2g2.model.S2G2Config` has the segmenter's trunk sizes);
``none`` trains from scratch; a path names another segmenter file. Supervised-only and
semi-supervised runs start from the same encoder, so comparisons between them stay fair.
A resumed run then loads its own checkpoint over it.

**segipm's prior** (``S2G2Config.prior_skip``, issue #39). The prior of every training and
unlabeled frame (:class:`~bev_mapper_core.methods.segipm.prior.SegIpmPrior`, from the camera-size
image as it is, never augmented) is computed once in :meth:`S2G2Method.prepare` and indexed by
the batches' frame ids; validation computes it per frame, as the mapper does. The frozen
encoder, the feature cache and the positive weights' settings are shared with FocusBEV
(:mod:`~bev_mapper_core.training.frozen_trunk`).

Validation scores the branch the weights will map with (``inference_branch``, saved in the
weights' metadata).
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass

import numpy as np
import torch
from typing_extensions import override

from bev_mapper_core.errors import ConfigError
from bev_mapper_core.nn.augment import Augment, step_augment
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
from .blocks import VIEW_TRANSFORMS
from .losses import BEV_TIES, S2G2LossConfig, ema_decay_at, ema_update, s2g2_loss
from .model import BRANCHES, S2G2, S2G2Config
from .weights import load_state_s2g2, save_s2g2

#: ``S2G2Training.optimizer`` choices.
OPTIMIZERS = ("sgd", "adam")
#: ``S2G2Training.unlabeled_bn`` choices.
UNLABELED_BN = ("running", "batch")
#: The paper's SGD settings.
SGD_MOMENTUM, SGD_WEIGHT_DECAY = 0.9, 1e-4


@dataclass(frozen=True)
class S2G2Training(FrozenTrunkTraining):
    """S2G2's training settings (and :class:`~bev_mapper_core.training.frozen_trunk.FrozenTrunkTraining`'s
    ``frozen_encoder``, ``feature_copies``, ``pos_weight_max``, ``pos_weight_classes``).

    Args:
        cycle_weight, bev_weight, bev_tie, consistency_weight, consistency_ramp_steps: the
            loss weights and ramp (:class:`~bev_mapper_core.methods.s2g2.losses.S2G2LossConfig`).
        ema_decay: lambda of Eq. 5 (paper 0.999).
        ema_warmup: Mean Teacher's warm-up of the decay, ``min(ema_decay, 1 - 1/(step + 1))``
            (also in the released S2G2 code; Eq. 5 alone would leave the passive branch near its
            initial weights for the first thousands of steps).
        pos_weight: ``auto``: per-class positive weights of L_seg, as Bi-Mapper's
            (:func:`~bev_mapper_core.training.class_weights.class_pos_weight`; not in the paper); ``none``: plain BCE.
        optimizer: ``adam`` (default, every measured run) or ``sgd`` (the paper's; see the
            module docstring).
        inference_branch: the branch that maps (``active``: the one trained by gradient descent;
            ``passive``: its EMA); scored in validation and saved with the weights.
        supervised_only: train without unlabeled frames (ablation: the consistency loss then
            sees the labeled frames only).
        encoder_init: ``auto`` (the shipped segmenter's trunk on RGB input, none on label
            input), ``none`` (from scratch), ``segmenter`` (the shipped one), or a segmenter
            weights path (see the module docstring).
        cycle_into_encoder: False (default): the cycle loss trains the two view-transform blocks
            only, on the encoder's features taken as fixed (detached); True: its gradient also
            reaches the encoder (see the module docstring).
        unlabeled_into_encoder: False (default): the losses on unlabeled frames train everything
            after the encoder, not the encoder (see the module docstring); True: the encoder too.
        unlabeled_bn: ``running`` (unlabeled frames normalized with the running statistics,
            which they leave alone) or ``batch`` (one batch with the labeled frames: the paper);
            see the module docstring.
        augment: photometric augmentation of every training frame's camera image (RGB input;
            see the module docstring).
    """

    cycle_weight: float = S2G2LossConfig.cycle_weight
    bev_weight: float = S2G2LossConfig.bev_weight
    bev_tie: str = S2G2LossConfig.bev_tie
    consistency_weight: float = S2G2LossConfig.consistency_weight
    consistency_ramp_steps: int = S2G2LossConfig.consistency_ramp_steps
    ema_decay: float = 0.999
    ema_warmup: bool = True
    pos_weight: str = "auto"
    optimizer: str = "adam"
    inference_branch: str = "active"
    supervised_only: bool = False
    encoder_init: str = "auto"
    unlabeled_bn: str = "running"
    cycle_into_encoder: bool = False
    unlabeled_into_encoder: bool = False
    augment: bool = True

    def __post_init__(self) -> None:
        check_encoder_init(self.encoder_init)
        v = self.ema_decay
        if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v) or not 0 <= v <= 1:
            raise ConfigError(f"ema_decay must be a number in [0, 1], got {v!r}")
        for name in ("ema_warmup", "supervised_only", "cycle_into_encoder", "unlabeled_into_encoder",
                     "augment"):
            if not isinstance(getattr(self, name), bool):
                raise ConfigError(f"{name} must be true or false, got {getattr(self, name)!r}")
        for name, choices in (("pos_weight", POS_WEIGHTS), ("optimizer", OPTIMIZERS),
                              ("inference_branch", BRANCHES), ("bev_tie", BEV_TIES),
                              ("unlabeled_bn", UNLABELED_BN)):
            if getattr(self, name) not in choices:
                raise ConfigError(f"{name} must be one of {choices}, got {getattr(self, name)!r}")
        if self.unlabeled_bn == "batch" and not self.unlabeled_into_encoder:
            raise ConfigError("unlabeled_bn 'batch' (one batch with the labeled frames) needs unlabeled_into_encoder")
        self.check_frozen_trunk()
        if self.frozen_encoder and (self.cycle_into_encoder or self.unlabeled_into_encoder):
            raise ConfigError("a frozen encoder trains from no loss: drop cycle_into_encoder / unlabeled_into_encoder")
        self.loss_config()  # validates the weights and the ramp

    def loss_config(self, pos_weight: tuple[float, ...] | None = None) -> S2G2LossConfig:
        """The loss configuration of a run."""
        return S2G2LossConfig(cycle_weight=self.cycle_weight, bev_weight=self.bev_weight, bev_tie=self.bev_tie,
                              consistency_weight=self.consistency_weight,
                              consistency_ramp_steps=self.consistency_ramp_steps, pos_weight=pos_weight)


@contextmanager
def running_batchnorm(model: torch.nn.Module) -> Iterator[None]:
    """Within the block every BatchNorm layer of ``model`` normalizes with its running statistics
    and does not update them; every other module keeps its mode (dropout, stochastic depth).
    """
    bns = [m for m in model.modules() if isinstance(m, torch.nn.modules.batchnorm._BatchNorm) and m.training]
    for m in bns:
        m.eval()
    try:
        yield
    finally:
        for m in bns:
            m.train()


class S2G2Method(TrainMethod):
    """S2G2 (Gao et al., RA-L 2022) trained semi-supervised (see the module docstring)."""

    name = "s2g2"
    model_config_type = S2G2Config
    loss_config_type = S2G2Training
    cli_flags = (
        CliFlag("--input-width", "input_width", min_value=16),
        CliFlag("--view-transform", "view_transform", choices=VIEW_TRANSFORMS,
                help="conv: the paper's two convolutions; fc: PYVA's two fully connected layers"),
        CliFlag("--bev-downsample", "bev_downsample", min_value=1, help="BEV feature map = grid / this"),
        CliFlag("--decoder-channels", "decoder_channels", min_value=1),
        CliFlag("--no-cross-view-attention", "cross_view_attention", action="store_false",
                help="ablation OIVA: F_C = F_BEV"),
        CliFlag("--no-inter-view-attention", "inter_view_attention", action="store_false",
                help="ablation OCVA: F_I = F_BEV"),
        CliFlag("--cycle-weight", "cycle_weight", number=True, help="alpha of the cycle loss (0 = off)"),
        CliFlag("--bev-weight", "bev_weight", number=True, help="beta of L_BEV (0 = off)"),
        CliFlag("--bev-tie", "bev_tie", choices=BEV_TIES, help="L_BEV: l1 (released code) or ce (paper)"),
        CliFlag("--consistency-weight", "consistency_weight", number=True, help="final gamma (0 = off)"),
        CliFlag("--consistency-ramp-steps", "consistency_ramp_steps", min_value=0),
        CliFlag("--ema-decay", "ema_decay", number=True, help="passive branch EMA decay (paper 0.999)"),
        CliFlag("--no-ema-warmup", "ema_warmup", action="store_false", help="Eq. 5's decay from the first step"),
        CliFlag("--pos-weight", "pos_weight", choices=POS_WEIGHTS, help="BCE class weights (none = plain)"),
        CliFlag("--optimizer", "optimizer", choices=OPTIMIZERS, help="sgd: the paper's (momentum 0.9, wd 1e-4)"),
        CliFlag("--inference-branch", "inference_branch", choices=BRANCHES, help="the branch that maps"),
        CliFlag("--supervised-only", "supervised_only", action="store_true", help="no unlabeled frames (ablation)"),
        CliFlag("--cycle-into-encoder", "cycle_into_encoder", action="store_true",
                help="the cycle loss's gradient also reaches the encoder (default: the view transforms only)"),
        CliFlag("--unlabeled-into-encoder", "unlabeled_into_encoder", action="store_true",
                help="the losses on unlabeled frames also train the encoder (default: what follows it)"),
        CliFlag("--unlabeled-bn", "unlabeled_bn", choices=UNLABELED_BN,
                help="BatchNorm of unlabeled frames: running statistics (default) or one batch with the labeled "
                     "frames (the paper)"),
        CliFlag("--encoder-init", "encoder_init",
                help="auto | none | segmenter | imagenet | PATH: pretrained feature extractor, a segmenter's "
                     "EfficientNet trunk (auto: the shipped segmenter's on RGB input), or imagenet: EfficientNet-Lite "
                     "(--config keys encoder_variant lite0, width_mult 1.0, depth_mult 1.0)"),
        CliFlag("--augment", "augment", action="boolean",
                help="photometric augmentation (colour, exposure, blur, noise) of every training image (RGB input)"),
        PRIOR_SKIP_FLAG,
        CliFlag("--prior-pool", "prior_pool", action="store_true",
                help="with --prior-skip: the prior, pooled to the BEV feature map, also enters each branch's first layer"),
        *FROZEN_TRUNK_FLAGS,
    )

    @override
    def build_model(self) -> S2G2:
        model = S2G2(self.cfg.model, self.rig, self.grid)
        self.encoder_source = init_encoder(model.encoder, self.cfg.loss.encoder_init, self.cfg.model.input_kind,
                                           self.rig.name)
        if self.cfg.loss.frozen_encoder:
            model.encoder.requires_grad_(False)
        self._cache: dict[str, torch.Tensor] = {}
        return model

    @override
    def trainable_parameters(self):
        return [p for p in self.model.trainable_parameters() if p.requires_grad]

    @override
    def configure_optimizer(self, lr: float) -> torch.optim.Optimizer:
        if self.cfg.loss.optimizer == "adam":
            return torch.optim.Adam(self.trainable_parameters(), lr=lr)
        return torch.optim.SGD(self.trainable_parameters(), lr=lr, momentum=SGD_MOMENTUM,
                               weight_decay=SGD_WEIGHT_DECAY)

    @override
    def describe(self) -> str:
        m, c = self.model, self.cfg.model
        att = [n for n, on in (("cross-view", c.cross_view_attention), ("inter-view", c.inter_view_attention)) if on]
        init = f"encoder from {self.encoder_source}" if self.encoder_source else "encoder from scratch"
        return (f"input {m.input_size}, {init}, front features {m.front_hw} -> BEV features {m.bev_hw} "
                f"({c.view_transform}), attention {' + '.join(att) or 'none'}, classes {list(self.cfg.class_names)}")

    @override
    def schedule(self) -> str:
        t = self.cfg.loss
        bn = "" if t.supervised_only else f", unlabeled frames through BatchNorm: {t.unlabeled_bn} statistics"
        aug = ", images augmented" if self._augments() else ""
        return (f"{t.optimizer}{aug}, consistency to {t.consistency_weight} over {t.consistency_ramp_steps} steps, "
                f"EMA {t.ema_decay}{' (warm-up)' if t.ema_warmup else ''}{bn}, maps with the {t.inference_branch} branch")

    @override
    def data_needs(self) -> DataNeeds:
        size = None if self.cfg.model.prior_skip else self.model.input_size  # the prior reads camera-size images
        return DataNeeds(image_size=size, unlabeled=not self.cfg.loss.supervised_only,
                         rgb=self.cfg.model.input_kind == "rgb", labels=self.cfg.model.input_kind == "labels")

    @override
    def prepare(self, data: TrainData, log: Callable[[str], None]) -> None:
        if data.unlabeled is None and not self.cfg.loss.supervised_only:
            raise ConfigError("S2G2 trains on unlabeled frames too, and the data source gave none")
        pw = self.cfg.loss.run_pos_weights(data.train, self.cfg.class_names)
        self.loss_cfg = self.cfg.loss.loss_config(pw)
        if pw is not None:
            log(f"BCE positive weights {dict(zip(self.cfg.class_names, pw))}")
        sets = [(name, fs) for name, fs in (("train", data.train), ("unlabeled", data.unlabeled)) if fs is not None]
        if self.cfg.model.prior_skip:
            self._prior_fn, self._priors = training_priors(self.rig, self.grid, self.cfg.class_names, self.device,
                                                           dict(sets), log)
        if self.cfg.loss.feature_copies:
            t0 = time.monotonic()
            n = self.cfg.loss.feature_copies
            self.model.encoder.eval()
            self._cache = {name: encode_cache(lambda x: self.model.encoder(x)[-1:], self._inputs, fs, n, self.cfg.seed,
                                              self.device)[0] for name, fs in sets}
            log(f"feature cache: {n} cop{'y' if n == 1 else 'ies'} of {sum(c.shape[1] for c in self._cache.values())} "
                f"frames, {cache_mib(self._cache.values()):.0f} MiB, {time.monotonic() - t0:.1f} s")

    def _prior(self, name: str, batch: dict) -> torch.Tensor | None:
        """The cached prior ``(B, K + 1, H, W)`` of a batch of set ``name`` (None without ``prior_skip``)."""
        if not self.cfg.model.prior_skip:
            return None
        return self._priors[name][batch["index"].cpu()].to(self.device)

    def _cached(self, name: str, index: torch.Tensor, step: int) -> torch.Tensor:
        """Cached features ``(B, C, hf, wf)`` of frames ``index`` of set ``name``, one copy each
        (drawn from the run seed and the step).
        """
        return pick_cached((self._cache[name],), index, self.cfg.seed, step)[0]

    def _augments(self) -> bool:
        """Training images are augmented: ``augment`` on RGB input."""
        return self.cfg.loss.augment and self.cfg.model.input_kind == "rgb"

    def _inputs(self, batch: dict, aug: Augment | None = None) -> torch.Tensor:
        """Model input ``(B, C_in, h, w)`` of a batch (its RGB images on RGB input, else its
        labels), the RGB images photometrically augmented by ``aug`` when given.
        """
        raw = batch["rgb"] if self.cfg.model.input_kind == "rgb" else batch["images"]  # (B, 1, h, w[, 3])
        raw = raw.to(self.device)
        if aug is not None and self.cfg.model.input_kind == "rgb":
            raw = aug.camera_images(raw)  # (B, 1, h, w, 3) float in [0, 255]
        return self.model.preprocess(raw)

    @override
    def loss(self, batch: dict, epoch: int, step: int) -> tuple[torch.Tensor, dict[str, float]]:
        labeled, unlabeled = (batch["labeled"], batch["unlabeled"]) if "labeled" in batch else (batch, None)
        if self.cfg.loss.frozen_encoder:
            self.model.encoder.eval()  # the trainer sets train() each epoch: keep its BatchNorm statistics
        if self._cache:
            return self._cached_loss(labeled, unlabeled, step)
        aug = step_augment(self.cfg.seed, step, self.device) if self._augments() else None
        x = self._inputs(labeled, aug)  # (B_l, C_in, h, w)
        n = x.shape[0]
        prior = self._prior("train", labeled)
        if unlabeled is None:
            out = self._forward(x, prior=prior)
        elif self.cfg.loss.unlabeled_bn == "batch" and self.cfg.loss.unlabeled_into_encoder:
            both = None if prior is None else torch.cat([prior, self._prior("unlabeled", unlabeled)])
            out = self._forward(torch.cat([x, self._inputs(unlabeled, aug)]), prior=both)  # (B_l + B_u, ...): one pass, shared BN
        else:
            frozen = not self.cfg.loss.unlabeled_into_encoder
            out = self._forward(x, prior=prior)
            with running_batchnorm(self.model):
                out_u = self._forward(self._inputs(unlabeled, aug), frozen, self._prior("unlabeled", unlabeled))
            out = {k: torch.cat([out[k], out_u[k]]) for k in out}  # (B_l + B_u, ...) each
        return s2g2_loss(out, n, labeled["target"], labeled["mask"], step, self.loss_cfg, labeled.get("class_mask"))

    def _cached_loss(self, labeled: dict, unlabeled: dict | None, step: int) -> tuple[torch.Tensor, dict[str, float]]:
        """:meth:`loss` on cached features: the same model and losses after the encoder."""
        out = self._heads(self._cached("train", labeled["index"], step), self._prior("train", labeled))
        n = out["active_logits"].shape[0]
        if unlabeled is not None:
            with running_batchnorm(self.model):
                out_u = self._heads(self._cached("unlabeled", unlabeled["index"], step),
                                    self._prior("unlabeled", unlabeled))
            out = {k: torch.cat([out[k], out_u[k]]) for k in out}  # (B_l + B_u, ...) each
        return s2g2_loss(out, n, labeled["target"].to(self.device), labeled["mask"].to(self.device), step,
                         self.loss_cfg, labeled.get("class_mask"))

    def _heads(self, front: torch.Tensor, prior: torch.Tensor | None = None) -> dict[str, torch.Tensor]:
        """The model after its encoder on features ``front``, as :meth:`_forward` computes it."""
        return self._detached_cycle(self.model.heads(self.model.from_front(front.to(self.device)), prior))

    def _forward(self, x: torch.Tensor, frozen_encoder: bool = False,
                 prior: torch.Tensor | None = None) -> dict[str, torch.Tensor]:
        """The model's outputs on inputs ``x`` (and the ``prior_skip`` input ``prior``); unless
        ``cycle_into_encoder``, the cycle's input and target are the encoder's features detached
        (computed once more for the loss).
        """
        return self._detached_cycle(self.model(x, frozen_encoder, prior))

    def _detached_cycle(self, out: dict[str, torch.Tensor]) -> dict[str, torch.Tensor]:
        """Unless ``cycle_into_encoder``: ``out`` with the cycle computed once more from the
        encoder's features detached (its input and target, fixed).
        """
        if not self.cfg.loss.cycle_into_encoder and self.loss_cfg.cycle_weight > 0:
            front = out["front"].detach()  # (B, C, hf, wf)
            out = {**out, "front": front, "front_cycled": self.model.to_front(self.model.to_bev(front))}
        return out

    @override
    def after_step(self, step: int) -> None:
        t = self.cfg.loss
        ema_update(self.model.passive, self.model.active, ema_decay_at(step, t.ema_decay, t.ema_warmup))

    @override
    def predict(self, batch: dict) -> tuple[np.ndarray, np.ndarray]:
        prior = self._prior_fn.batch(batch["rgb"]).to(self.device) if self.cfg.model.prior_skip else None
        logits = self.model.logits(self._inputs(batch), self.cfg.loss.inference_branch, prior)
        probs = torch.sigmoid(logits).float().cpu().numpy()  # (B, K, H, W)
        known = self.model.known().cpu().numpy()  # (H, W), the same for every frame
        return probs, np.broadcast_to(known, (len(probs), *known.shape))

    @override
    def save(self, path) -> None:
        save_s2g2(self.model, path, self.cfg.loss.inference_branch)

    @override
    def load(self, path) -> None:
        load_state_s2g2(self.model, path)


__all__ = ["OPTIMIZERS", "S2G2Method", "S2G2Training", "UNLABELED_BN", "running_batchnorm"]
