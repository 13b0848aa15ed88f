"""Bi-Mapper's training plug-in: model build, ``BCE + ASL + 0.1 * AML`` loss, class weights,
the asynchronous mutual-learning schedule (see :mod:`bev_mapper_core.methods.bimapper.losses`).

``cfg.model`` is a :class:`~bev_mapper_core.methods.bimapper.config.BiMapperConfig`, ``cfg.loss`` a
:class:`BiMapperTraining`; the ``bev-train`` flags ``--streams --fusion --lv-full-res --ipm-skip
--input-width --gv-hidden`` set the former, ``--no-asl --mutual --mutual-start-epoch
--pos-weight --augment/--no-augment`` the latter.

**Augmentation** (``augment``, default on; RGB input only: a label-input model, also one trained
``--on-segmenter``, is unaffected). Every training frame's camera images are augmented
photometrically (:meth:`~bev_mapper_core.nn.augment.Augment.camera_images`: exposure, contrast,
saturation, white balance, gamma, blur, noise), an independent draw per camera image (the
cameras of a rig expose and white-balance each on its own), before anything reads them (both
streams, and the ``ipm_skip`` prior), from a generator seeded by the run seed, the step and the
data-parallel rank, so ``--resume`` is exact. No geometric augmentation: scaling, cropping or
flipping a camera image changes its calibration, from which the LV stream's IPM and the
cameras' places in the BEV come, and the BEV target would no longer match. Validation frames
are not augmented.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, replace

import numpy as np
import torch
from typing_extensions import override

from bev_mapper_core.errors import ConfigError
from bev_mapper_core.geometry.random_rig import RANDOM_RIGS
from bev_mapper_core.nn.augment import Augment, step_augment
from bev_mapper_core.nn.efficientnet import EfficientNetConfig
from bev_mapper_core.training.class_weights import POS_WEIGHT_FLAGS, POS_WEIGHTS, PosWeightTraining, class_pos_weight
from bev_mapper_core.training.config import PAPER_EPOCHS
from bev_mapper_core.training.frozen_trunk import PRIOR_SKIP_FLAG
from bev_mapper_core.training.method import CliFlag, TrainMethod
from bev_mapper_core.training.sources import DataNeeds, TrainData

from ..segipm.prior import training_priors
from ..segmenter.trunk import check_encoder_init, init_encoder, trunk_config
from .config import FUSIONS, STREAMS, BiMapperConfig
from .losses import MUTUAL_MODES, BiMapperLossConfig, bimapper_loss
from .model import BiMapper
from .weights import ANY_RIG, load_state, save_weights

#: Paper: mutual learning both ways from the 5th of 30 epochs (0-based 4; the loss config's
#: default), scaled to the run's epochs.
PAPER_MUTUAL_START = BiMapperLossConfig.mutual_start_epoch
#: GV MLP width of the model ``bev-train`` builds by default (BiMapperConfig's None, one hidden
#: unit per BEV feature cell as in HDMapNet, is too large to train on a CPU).
TRAIN_GV_HIDDEN = 128


@dataclass(frozen=True)
class BiMapperTraining(PosWeightTraining):
    """Bi-Mapper's training settings (turned into a :class:`BiMapperLossConfig` per run), with
    :class:`~bev_mapper_core.training.class_weights.PosWeightTraining`'s cap and per-class
    overrides of the ``auto`` positive weights.

    Args:
        asl: Across-Space Loss on (weight 1, paper) or off.
        mutual: mutual-learning mode (:data:`MUTUAL_MODES`; ``async`` = the paper's AML).
        mutual_start_epoch: 0-based epoch from which GV also teaches LV; None = the paper's
            5th of 30 scaled to the run's epochs.
        pos_weight: ``auto``: per-class positive weight of the ego BCE,
            ``clip(sqrt(negatives / positives), 1, 10)`` over the visible cells of the training
            set (thin and rare layers: lane dividers, crossings, pedestrians); ``none``: plain BCE
            as in the paper. See :func:`class_pos_weight` (``pos_weight_max`` and
            ``pos_weight_classes`` adjust the ``auto`` weights).
        visibility_weight: weight of the visibility head's BCE (issue #11; needs the model's
            ``visibility_head``).
        uncertainty_weight: weight of PON's uncertainty loss on hidden cells (FocusBEV: 0.001).
        init_weights: start a new run from this weights file (fine-tuning): every tensor of the
            file is loaded; only the visibility head may be missing from it (an old file), and
            starts fresh. Ignored on ``--resume``.
        visibility_only: train only the visibility head (with ``init_weights``): every other
            tensor, BatchNorm statistics included, stays as loaded, so the class outputs are
            exactly those of the initial file.
        segmenter: a segmenter weights file: a label-input model then trains (and is
            validated) on the label images this segmenter predicts from the frames' RGB images
            instead of the true ones, i.e. for chained RGB input, where it must live with the
            segmenter's errors. Not in the paper.
        augment: photometric augmentation of every training camera image (RGB input; see the
            module docstring).
        encoder_init: the start of both streams' EfficientNet encoders: ``auto`` (the shipped
            segmenter's trunk on RGB input where the encoder has its sizes, i.e. width 1.0,
            depth 0.5, 5 stages; else from scratch), ``none``, ``segmenter`` or a segmenter
            weights path (:func:`~bev_mapper_core.methods.segmenter.trunk.encoder_source`; these
            two need the trunk's sizes).
    """

    asl: bool = True
    mutual: str = BiMapperLossConfig.mutual_mode
    mutual_start_epoch: int | None = None
    pos_weight: str = "auto"
    visibility_weight: float = BiMapperLossConfig.visibility_weight
    uncertainty_weight: float = BiMapperLossConfig.uncertainty_weight
    init_weights: str | None = None
    visibility_only: bool = False
    segmenter: str | None = None
    augment: bool = True
    encoder_init: str = "auto"

    def __post_init__(self) -> None:
        check_encoder_init(self.encoder_init)
        self.check_pos_weights()
        if not isinstance(self.augment, bool):
            raise ConfigError(f"augment must be true or false, got {self.augment!r}")
        if not isinstance(self.asl, bool):
            raise ConfigError(f"asl must be true or false, got {self.asl!r}")
        if self.mutual not in MUTUAL_MODES:
            raise ConfigError(f"mutual must be one of {MUTUAL_MODES}, got {self.mutual!r}")
        v = self.mutual_start_epoch
        if v is not None and (isinstance(v, bool) or not isinstance(v, int) or v < 0):
            raise ConfigError(f"mutual_start_epoch must be an integer >= 0, got {v!r}")
        if self.pos_weight not in POS_WEIGHTS:
            raise ConfigError(f"pos_weight must be one of {POS_WEIGHTS}, got {self.pos_weight!r}")

    def mutual_start(self, epochs: int) -> int:
        """0-based epoch from which both streams teach (paper: the 5th of 30 -> 4, scaled)."""
        if self.mutual_start_epoch is not None:
            return self.mutual_start_epoch
        return round(epochs * PAPER_MUTUAL_START / PAPER_EPOCHS)

    def loss_config(self, epochs: int, pos_weight: tuple[float, ...] | None = None) -> BiMapperLossConfig:
        """The loss configuration of a run of ``epochs`` epochs."""
        return BiMapperLossConfig(asl_weight=BiMapperLossConfig.asl_weight if self.asl else 0.0,
                                  mutual_start_epoch=self.mutual_start(epochs),
                                  mutual_mode=self.mutual, pos_weight=pos_weight,
                                  visibility_weight=float(self.visibility_weight),
                                  uncertainty_weight=float(self.uncertainty_weight))


def init_from(model: BiMapper, path: str) -> list[str]:
    """Load the tensors of the weights file ``path`` into ``model`` for fine-tuning.

    The file's architecture may differ from the model's only by the visibility head and the
    temperature (an old file): its tensors must then all exist in the model with the same shapes,
    and only ``decoder.vis_head.*`` may be missing from the file. Returns the names left fresh.

    Raises:
        WeightsError: the file is not a Bi-Mapper file of this rig / classes or does not fit.
    """
    from safetensors.torch import load_file

    from bev_mapper_core.nn.weights import WeightsError

    from .weights import WeightsFile

    wf = WeightsFile.open(path)
    stored = replace(wf.config, visibility_head=model.config.visibility_head, temperature=model.config.temperature)
    if stored != model.config or list(wf.cameras) != list(model.rig.names):
        raise WeightsError(f"{path}: its architecture / cameras differ from the run's (beyond the visibility head)")
    state = load_file(path)
    own = model.state_dict()
    bad = [k for k, t in state.items() if k not in own or tuple(own[k].shape) != tuple(t.shape)]
    missing = [k for k in own if k not in state]
    if bad or any(not k.startswith("decoder.vis_head.") for k in missing):
        raise WeightsError(f"{path}: tensors do not fit the run's model (extra/mismatched {bad}, missing {missing})")
    model.load_state_dict(state, strict=False)
    return missing


def segment_frames(path: str, rgb: np.ndarray, device, batch: int = 8) -> np.ndarray:
    """Label images ``(M, N, H, W)`` uint8 a segmenter file predicts from RGB ``(M, N, H, W, 3)``."""
    from ..segmenter.weights import load_segmenter

    model = load_segmenter(path, device)
    M, N, H, W, _ = rgb.shape
    flat = rgb.reshape(M * N, H, W, 3)  # (M, N, H, W, 3) -> (M*N, H, W, 3)
    out = np.empty((M * N, H, W), np.uint8)
    for i in range(0, M * N, batch):
        out[i:i + batch] = model.segment(torch.from_numpy(flat[i:i + batch]).to(device)).cpu().numpy()
    return out.reshape(M, N, H, W)


def frame_marks(rgb: np.ndarray) -> torch.Tensor:
    """A mark of each frame's camera images ``(M, N, H, W, 3)`` uint8 -> ``(M,)`` int64 (the sum of
    their bytes): tells a cached frame's prior from another frame's.
    """
    return torch.from_numpy(np.asarray(rgb).reshape(len(rgb), -1).sum(1, dtype=np.int64))  # (M, N, H, W, 3) -> (M,)


def same_trunk(a: EfficientNetConfig, b: EfficientNetConfig) -> bool:
    """Two EfficientNet configurations have the same weights' shapes (regularization aside)."""
    return (a.width_mult, a.depth_mult, a.num_stages, a.in_channels) == (b.width_mult, b.depth_mult, b.num_stages,
                                                                         b.in_channels)


class BiMapperMethod(TrainMethod):
    """Bi-Mapper (Li et al., RA-L 2023) trained as in the paper, plus the documented deviations
    (``pos_weight``, ``ipm_skip``).
    """

    name = "bimapper"
    model_config_type = BiMapperConfig
    loss_config_type = BiMapperTraining
    cli_flags = (
        CliFlag("--streams", "streams", choices=STREAMS, help="none: only with --ipm-skip (ablation control)"),
        CliFlag("--fusion", "fusion", choices=FUSIONS),
        CliFlag("--no-asl", "asl", action="store_false", help="without the Across-Space Loss"),
        CliFlag("--lv-full-res", "lv_full_res", action="store_true",
                help="LV stream's IPM samples the camera-size images (as the paper)"),
        CliFlag("--ipm-skip", "ipm_skip", action="store_true",
                help="full-resolution IPM prior into the decoder head, logits start at IPM's (not in the paper)"),
        CliFlag("--mutual", "mutual", choices=MUTUAL_MODES),
        CliFlag("--mutual-start-epoch", "mutual_start_epoch", min_value=0,
                help=f"0-based; default paper {PAPER_MUTUAL_START}/{PAPER_EPOCHS} scaled"),
        CliFlag("--pos-weight", "pos_weight", choices=POS_WEIGHTS, help="BCE class weights (none = paper)"),
        *POS_WEIGHT_FLAGS,
        PRIOR_SKIP_FLAG,
        CliFlag("--input-width", "input_width", min_value=1),
        CliFlag("--gv-hidden", "gv_hidden", min_value=1),
        CliFlag("--decoder-min-channels", "decoder_min_channels", min_value=1,
                help="decoder width at the full grid resolution (a lighter head: 8)"),
        CliFlag("--visibility-head", "visibility_head", action="store_true",
                help="extra per-cell visibility logit (issue #11; not in the paper)"),
        CliFlag("--visibility-weight", "visibility_weight", number=True, help="BCE weight of the visibility head"),
        CliFlag("--uncertainty-weight", "uncertainty_weight", number=True,
                help="PON uncertainty loss on hidden cells (FocusBEV 0.001)"),
        CliFlag("--encoder-init", "encoder_init",
                help="the encoders' start: auto (the shipped segmenter's trunk on RGB where the sizes fit), none, "
                     "segmenter, a segmenter weights path, or imagenet (EfficientNet-Lite: --config keys encoder_variant lite0, "
                     "width_mult 1.0, depth_mult 1.0)"),
        CliFlag("--init-weights", "init_weights", help="fine-tune: start from this weights file"),
        CliFlag("--visibility-only", "visibility_only", action="store_true",
                help="train only the visibility head; the class outputs stay the initial file's"),
        CliFlag("--on-segmenter", "segmenter",
                help="label model trained on this segmenter's labels of the RGB images (chained RGB input)"),
        CliFlag("--augment", "augment", action="boolean",
                help="photometric augmentation (colour, exposure, blur, noise) of every training camera image "
                     "(RGB input)"),
    )

    @classmethod
    @override
    def default_model_config(cls, classes: tuple[str, ...]) -> BiMapperConfig:
        return BiMapperConfig(classes=tuple(classes), gv_hidden=TRAIN_GV_HIDDEN)

    @property
    def random_rigs(self) -> bool:
        """The run trains a rig-free model on random rigs (``--rig random``)."""
        return self.cfg.rig == RANDOM_RIGS

    @override
    def build_model(self) -> BiMapper:
        model = BiMapper(self.cfg.model, self.rig, self.grid)
        if self.random_rigs and not model.rig_free:
            raise ConfigError("--rig random trains a model for any rig: it needs one without the GV stream "
                              "(--streams lv; the GV MLPs are sized for one rig's cameras)")
        if self.random_rigs and self.cfg.model.prior_skip:
            raise ConfigError("--prior-skip computes segipm's prior once per frame of one rig: not with --rig random")
        self.encoder_source = None
        spec, kind = self.cfg.loss.encoder_init, self.cfg.model.input_kind
        if spec == "auto" and not same_trunk(self.cfg.model.encoder_config(3), trunk_config()):
            return model  # other sizes than the segmenter's trunk: from scratch
        encoders = []  # the streams the configuration has: GV's camera encoder, LV's U-Net encoder
        if getattr(model, "cam_encoder", None) is not None:
            encoders.append(model.cam_encoder.trunk)
        if getattr(model, "lv", None) is not None:
            encoders.append(model.lv.unet.encoder)
        for encoder in encoders:
            self.encoder_source = init_encoder(encoder, spec, kind, self.rig.name)
        return model

    @override
    def describe(self) -> str:
        init = f", encoders from {self.encoder_source}" if self.encoder_source else ""
        return f"input {self.model.input_size}, classes {list(self.cfg.class_names)}{init}"

    @override
    def schedule(self) -> str:
        aug = ", images augmented" if self._augments() else ""
        mode = self.cfg.loss.mutual
        mutual = {"async": f"mutual: LV teaches GV, both ways from epoch {self.cfg.loss.mutual_start(self.cfg.epochs) + 1}",
                  "sync": "mutual both ways from epoch 1", "lv": "mutual: LV teaches GV",
                  "gv": "mutual: GV teaches LV", "none": "no mutual learning"}[mode]
        return mutual + aug

    @override
    def data_needs(self) -> DataNeeds:
        # Full-resolution LV input and the IPM prior need the camera-size images in memory (else:
        # stored resized, exactly as preprocess would).
        m = self.cfg.model
        full = m.lv_full_res or m.ipm_skip or m.prior_skip or self.random_rigs  # random rigs: sizes differ
        rgb = self.cfg.model.input_kind == "rgb" or self.cfg.loss.segmenter is not None
        labels = self.cfg.model.input_kind == "labels" and self.cfg.loss.segmenter is None
        return DataNeeds(image_size=None if full else self.model.input_size, rgb=rgb, labels=labels)

    def _augments(self) -> bool:
        """Training images are augmented: ``augment`` on RGB input."""
        return self.cfg.loss.augment and self.cfg.model.input_kind == "rgb"

    def _inputs(self, batch: dict, aug: Augment | None = None) -> torch.Tensor:
        """The model's input of a batch: the RGB images on RGB input (photometrically augmented
        by ``aug`` when given, each image its own draw), else the label images.
        """
        if self.cfg.model.input_kind != "rgb":
            return batch["images"].to(self.device)
        raw = batch["rgb"].to(self.device)  # (B, N, h, w, 3)
        return raw if aug is None else aug.camera_images(raw)  # float in [0, 255]

    @override
    def prepare(self, data: TrainData, log: Callable[[str], None]) -> None:
        pw = self.cfg.loss.run_pos_weights(data.train, self.cfg.class_names)
        self.loss_cfg = self.cfg.loss.loss_config(self.cfg.epochs, pw)
        if self.loss_cfg.visibility_weight > 0 and not self.cfg.model.visibility_head:
            raise ConfigError("--visibility-weight needs --visibility-head")
        if self.cfg.loss.init_weights and not self.cfg.resume:
            missing = init_from(self.model, self.cfg.loss.init_weights)
            log(f"initialised from {self.cfg.loss.init_weights}" + (f" (fresh: {missing})" if missing else ""))
        if pw is not None:
            log(f"BCE positive weights {dict(zip(self.cfg.class_names, pw))}")
        if self.cfg.loss.segmenter is not None:
            if self.cfg.model.input_kind != "labels":
                raise ConfigError("--on-segmenter trains a label-input model (--input labels)")
            for frames in (data.train, data.val):
                frames.labels = segment_frames(self.cfg.loss.segmenter, frames.rgb, self.device)
            log(f"labels: predicted by the segmenter {self.cfg.loss.segmenter} from the RGB images")
        if self.cfg.model.prior_skip:
            self._prior_fn, self._priors = training_priors(self.rig, self.grid, self.cfg.class_names, self.device,
                                                           {"train": data.train, "val": data.val}, log)
            self._val_marks = frame_marks(data.val.rgb)

    def _prior(self, batch: dict, name: str) -> torch.Tensor | None:
        """The ``prior_skip`` input ``(B, K + 1, H, W)`` of a batch of set ``name`` (None without it):
        the cached prior of its frames; for ``val``, computed anew unless the batch's images are
        the cached frames' (:func:`frame_marks`), so another frame set is never given a wrong prior.
        """
        if not self.cfg.model.prior_skip:
            return None
        index = batch["index"].cpu()
        if name == "val" and not torch.equal(frame_marks(batch["rgb"].numpy()), self._val_marks[index]):
            return self._prior_fn.batch(batch["rgb"]).to(self.device)
        return self._priors[name][index].to(self.device)

    @override
    def trainable_parameters(self):
        if self.cfg.loss.visibility_only:
            if self.model.decoder.vis_head is None:
                raise ConfigError("--visibility-only needs --visibility-head")
            return self.model.decoder.vis_head.parameters()
        return self.model.parameters()

    @override
    def start_epoch(self, epoch: int) -> None:
        if self.cfg.loss.visibility_only:  # frozen BatchNorm statistics outside the head
            self.model.eval()
            self.model.decoder.vis_head.train()

    def _use_rig(self, batch: dict) -> None:
        """Frames of random rigs: switch the model's tables to the batch's rig (cached per rig)."""
        rig = batch.get("rig")
        if rig is not None and rig is not self.model.rig:
            cache = self.__dict__.setdefault("_tables", {})  # id(rig) -> (rig, tables); the frame set keeps the rigs
            if id(rig) not in cache:
                cache[id(rig)] = (rig, self.model.geometry(rig))
            self.model.set_rig(rig, cache[id(rig)][1])

    @override
    def loss(self, batch: dict, epoch: int, step: int) -> tuple[torch.Tensor, dict[str, float]]:
        self._use_rig(batch)
        dev = self.device
        aug = step_augment(self.cfg.seed, step, dev) if self._augments() else None
        outputs = self.model(self._inputs(batch, aug), prior=self._prior(batch, "train"))
        return bimapper_loss(outputs, {"target": batch["target"].to(dev), "mask": batch["mask"].to(dev)}, epoch,
                             self.loss_cfg)

    @override
    def predict(self, batch: dict) -> tuple[np.ndarray, np.ndarray]:
        self._use_rig(batch)
        out = self.model(self._inputs(batch), prior=self._prior(batch, "val"))
        probs = torch.sigmoid(self.model.calibrated(out["logits"])).float().cpu().numpy()
        known = self.model.known().cpu().numpy()[0]  # (1, H, W) -> (H, W), the same for every frame
        return probs, np.broadcast_to(known, (len(probs), *known.shape))

    @override
    def save(self, path) -> None:
        save_weights(self.model, path, any_rig=self.random_rigs)

    @override
    def load(self, path) -> None:
        load_state(self.model, path)

    @override
    def checkpoint_info(self) -> dict:
        return {"model_config": self.model.config.to_dict(), "rig": ANY_RIG if self.random_rigs else self.model.rig.name}


__all__ = ["BiMapperMethod", "BiMapperTraining", "POS_WEIGHTS", "class_pos_weight"]
