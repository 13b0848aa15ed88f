"""A per-camera 2-D semantic segmenter: RGB image -> this package's pixel labels.

The first stage of the two-stage RGB pipeline (:mod:`~bev_mapper_core.methods.segipm.mapper`:
segmenter + IPM; and the chained input of label models such as Bi-Mapper). A small
encoder-decoder sized for CPUs:

* **Encoder**: the project's :class:`~.efficientnet.EfficientNet` trunk, its endpoints at output
  strides 2, 4, 8, 16 (``encoder_stages`` 4) or up to 32; ``encoder`` ``lite`` is its Lite form,
  which can start from the ImageNet checkpoint (:meth:`Segmenter.init_imagenet`,
  :mod:`~bev_mapper_core.nn.pretrained`) and then reads its input scaled as that checkpoint was
  trained (:data:`~bev_mapper_core.nn.config.LITE_MEAN`).
* **Decoder**: a feature pyramid (Lin et al. 2017, as in semantic FPN, Kirillov et al. 2019): a
  1x1 lateral per endpoint of stride >= ``decoder_stride``, top-down nearest upsampling and
  addition, one 3x3 conv + BN + ReLU at ``decoder_stride``, and a 1x1 classifier over
  :data:`~bev_mapper_core.labels.classes.NUM_LABELS` labels.
* The logits are upsampled bilinearly to the input size (training) or to the camera's own size
  (:meth:`Segmenter.segment`, up to twice the input width; beyond, the labels decided there are
  nearest-upsampled), so IPM reads a label for every camera pixel.

The input is the camera image resized (bilinear, antialiased) to ``input_width`` wide, the
height following the camera's aspect ratio, normalised like Bi-Mapper's RGB input.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, fields

import torch
from torch import nn
from torch.nn import functional as F

from bev_mapper_core.errors import ConfigError
from bev_mapper_core.labels.classes import NUM_LABELS, Label
from bev_mapper_core.nn.config import MAX_CHANNELS, MAX_WIDTH_PX, rgb_stats
from bev_mapper_core.nn.efficientnet import EfficientNet, EfficientNetConfig
from bev_mapper_core.nn.pretrained import load_lite_imagenet

#: Labels are decided at most this many times the model's input width (its logits are at half
#: of it); wider cameras get them nearest-upsampled (:meth:`Segmenter.segment`).
DECISION_WIDTH_FACTOR = 2

#: Encoder families (:attr:`SegmenterConfig.encoder`).
ENCODERS = ("efficientnet", "lite")

#: Label names in id order: stored with the weights, so a file for another label set is refused.
LABEL_NAMES: tuple[str, ...] = tuple(label.name.lower() for label in Label)


@dataclass(frozen=True)
class SegmenterConfig:
    """Architecture of a :class:`Segmenter` (saved with the weights and checked on load).

    Args:
        input_width: model input width (px); the height follows each camera's aspect ratio.
        width_mult, depth_mult: EfficientNet multipliers (B0 = 1.0, 1.0).
        encoder_stages: EfficientNet stages kept (5: output stride 16, the last at width_mult x 112 channels).
        decoder_channels: width of the feature pyramid.
        labels: the label names the classifier predicts, in id order.
        encoder: ``efficientnet`` (SE, SiLU) or ``lite`` (EfficientNet-Lite: ImageNet weights
            exist for its lite0/1/2 multipliers).
        decoder_stride: output stride of the pyramid's finest level and the classifier (2 or 4).
    """

    input_width: int = 320
    width_mult: float = 1.0
    depth_mult: float = 0.5
    encoder_stages: int = 5
    decoder_channels: int = 64
    labels: tuple[str, ...] = LABEL_NAMES
    encoder: str = "efficientnet"
    decoder_stride: int = 2

    def __post_init__(self) -> None:
        object.__setattr__(self, "labels", tuple(self.labels))
        if self.encoder not in ENCODERS:
            raise ConfigError(f"encoder must be one of {ENCODERS}, got {self.encoder!r}")
        if self.decoder_stride not in (2, 4) or isinstance(self.decoder_stride, bool):
            raise ConfigError(f"decoder_stride must be 2 or 4, got {self.decoder_stride!r}")
        if not isinstance(self.input_width, int) or not 16 <= self.input_width <= MAX_WIDTH_PX:
            raise ConfigError(f"input_width must be an integer in 16..{MAX_WIDTH_PX}, got {self.input_width!r}")
        for name in ("width_mult", "depth_mult"):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, (int, float)) or not 0.05 <= v <= 8.0:
                raise ConfigError(f"{name} must be a number in [0.05, 8], got {v!r}")
        if not isinstance(self.encoder_stages, int) or not 2 <= self.encoder_stages <= 7:
            raise ConfigError(f"encoder_stages must be an integer in 2..7, got {self.encoder_stages!r}")
        if not isinstance(self.decoder_channels, int) or not 1 <= self.decoder_channels <= MAX_CHANNELS:
            raise ConfigError(f"decoder_channels must be in 1..{MAX_CHANNELS}, got {self.decoder_channels!r}")
        if self.labels != LABEL_NAMES:
            raise ConfigError(f"segmenter labels {list(self.labels)} are not this package's {list(LABEL_NAMES)}")

    def to_dict(self) -> dict:
        """JSON-ready dict (tuples as lists)."""
        return {k: list(v) if isinstance(v, tuple) else v for k, v in asdict(self).items()}

    @classmethod
    def from_dict(cls, d: dict) -> "SegmenterConfig":
        """Inverse of :meth:`to_dict`; unknown keys are refused.

        Raises:
            ConfigError: unknown keys or bad values.
        """
        if not isinstance(d, dict):
            raise ConfigError(f"segmenter config must be a mapping, got {type(d).__name__}")
        names = {f.name for f in fields(cls)}
        extra = sorted(set(d) - names)
        if extra:
            raise ConfigError(f"unknown segmenter config keys: {extra}")
        return cls(**d)

    def trunk_config(self, in_channels: int = 3) -> EfficientNetConfig:
        """The encoder's :class:`EfficientNetConfig` (Lite rules and padding for ``lite``)."""
        lite = self.encoder == "lite"
        return EfficientNetConfig(width_mult=self.width_mult, depth_mult=self.depth_mult,
                                  num_stages=self.encoder_stages, in_channels=in_channels, lite=lite, tf_padding=lite)

    def input_size(self, image_size: tuple[int, int]) -> tuple[int, int]:
        """Model input ``(h, w)`` of a camera whose images are ``image_size`` = ``(W, H)``."""
        W, H = image_size
        return max(16, round(self.input_width * H / W)), self.input_width


class Segmenter(nn.Module):
    """RGB camera image -> per-pixel label logits (see the module docstring)."""

    def __init__(self, config: SegmenterConfig) -> None:
        super().__init__()
        self.config = config
        self.encoder = EfficientNet(config.trunk_config())
        C = config.decoder_channels
        strides = self.encoder.endpoint_strides
        if config.decoder_stride not in strides:
            raise ConfigError(f"decoder_stride {config.decoder_stride} is not an endpoint stride {strides}")
        self._first = strides.index(config.decoder_stride)  # endpoints before it are not read
        chans = self.encoder.endpoint_channels[self._first:]
        self.lateral = nn.ModuleList(nn.Conv2d(c, C, 1) for c in chans)
        self.fuse = nn.Sequential(nn.Conv2d(C, C, 3, padding=1, bias=False), nn.BatchNorm2d(C), nn.ReLU(inplace=True))
        self.classifier = nn.Conv2d(C, NUM_LABELS, 1)
        mean, std = rgb_stats(config.encoder == "lite")
        self.register_buffer("rgb_mean", torch.tensor(mean).view(1, 3, 1, 1), persistent=False)
        self.register_buffer("rgb_std", torch.tensor(std).view(1, 3, 1, 1), persistent=False)

    def init_imagenet(self) -> dict:
        """Start the encoder from the ImageNet EfficientNet-Lite checkpoint of its multipliers
        (:func:`~bev_mapper_core.nn.pretrained.load_lite_imagenet`; its summary).

        Raises:
            PretrainedError: not a ``lite`` encoder of a published variant's multipliers, the
                package missing, or another file behind its name.
        """
        return load_lite_imagenet(self.encoder)

    def preprocess(self, images: torch.Tensor) -> torch.Tensor:
        """``(B, H, W, 3)`` uint8 (or float in [0, 255]) -> ``(B, 3, h, w)`` normalised model input."""
        if images.dim() != 4 or images.shape[-1] != 3:
            raise ValueError(f"RGB images must be (B, H, W, 3), got {tuple(images.shape)}")
        B, H, W, _ = images.shape
        h, w = self.config.input_size((W, H))
        x = images.to(self.rgb_mean.device).float().permute(0, 3, 1, 2) / 255.0  # (B, H, W, 3) -> (B, 3, H, W)
        if (H, W) != (h, w):
            x = F.interpolate(x, size=(h, w), mode="bilinear", align_corners=False, antialias=True)
        return (x - self.rgb_mean) / self.rgb_std

    def forward(self, x: torch.Tensor, size: tuple[int, int] | None = None) -> torch.Tensor:
        """Preprocessed input ``(B, 3, h, w)`` -> logits ``(B, NUM_LABELS, *size)`` (default: ``(h, w)``)."""
        feats = self.encoder(x)[self._first:]  # strides decoder_stride, ..., the last
        y = self.lateral[-1](feats[-1])
        for f, lat in zip(reversed(feats[:-1]), reversed(self.lateral[:-1])):
            y = F.interpolate(y, size=f.shape[-2:], mode="nearest") + lat(f)
        logits = self.classifier(self.fuse(y))  # (B, L, h/s, w/s), s = decoder_stride
        return F.interpolate(logits, size=size or tuple(x.shape[-2:]), mode="bilinear", align_corners=False)

    @torch.inference_mode()
    def segment(self, images: torch.Tensor, size: tuple[int, int] | None = None) -> torch.Tensor:
        """``(B, H, W, 3)`` camera images -> ``(B, *size)`` uint8 label ids (default: the images'
        size).

        The labels are decided (scores upsampled bilinearly, argmax) at :meth:`decision_size`:
        the output size itself up to :data:`DECISION_WIDTH_FACTOR` times the model's input
        width, so a 400 x 225 camera gets exactly the labels it always got; a larger one (a
        1600 x 900 camera) gets those labels nearest-upsampled, so that it costs about what a
        small one does: upsampling 11 class scores to 1.4 M pixels was 70-80 % of its time.
        """
        H, W = size or tuple(images.shape[1:3])
        h, w = self.decision_size((H, W))
        labels = self(self.preprocess(images), size=(h, w)).argmax(dim=1).to(torch.uint8)  # (B, h, w)
        if (h, w) != (H, W):
            labels = F.interpolate(labels[:, None], size=(H, W), mode="nearest")[:, 0]  # (B, 1, H, W) -> (B, H, W)
        return labels

    def decision_size(self, size: tuple[int, int]) -> tuple[int, int]:
        """``(h, w)`` at which labels for an output of ``size`` = ``(H, W)`` are decided."""
        H, W = size
        most = DECISION_WIDTH_FACTOR * self.config.input_width
        if W <= most:
            return H, W
        return max(1, round(H * most / W)), most


#: Class weightings of :func:`class_weights`: softened median frequency, ENet's ``1 / ln(c + p)``.
WEIGHTINGS = ("median", "enet")

#: ENet's constant (Paszke et al. 2016): weights bounded by ``1 / ln(1.02)`` = 50.5.
ENET_C = 1.02


def class_weights(counts: torch.Tensor, lo: float = 0.25, hi: float = 10.0, mode: str = "median") -> torch.Tensor:
    """Cross-entropy weights from label pixel counts ``(K,)``.

    ``median``: softened median-frequency balancing, ``clip(sqrt(median / freq), lo, hi)`` (labels
    never seen get ``hi``), so the thin labels (lane dividers, curbs: under 1 % of the pixels) are
    not drowned by road and sky. ``enet``: ENet's ``1 / ln(1.02 + freq)`` (the CamVid anchors'
    recipe; ``lo`` / ``hi`` unused), scaled so the labels seen average 1.
    """
    if mode not in WEIGHTINGS:
        raise ValueError(f"class weighting must be one of {WEIGHTINGS}, got {mode!r}")
    freq = counts.double() / counts.sum().clamp(min=1)
    if mode == "enet":
        w = 1.0 / torch.log(ENET_C + freq)
        seen = freq > 0
        return (w / (w[seen].mean() if seen.any() else 1.0)).float()
    med = freq[freq > 0].median() if (freq > 0).any() else torch.tensor(1.0, dtype=torch.float64)
    w = torch.where(freq > 0, (med / freq.clamp(min=1e-12)).sqrt(), torch.full_like(freq, hi))
    return w.clamp(lo, hi).float()


def pixel_iou(pred: torch.Tensor, target: torch.Tensor, num_labels: int = NUM_LABELS) -> torch.Tensor:
    """Confusion-based IoU per label ``(num_labels,)`` (NaN where a label is in neither) of integer
    label maps of the same shape.
    """
    idx = target.long().flatten() * num_labels + pred.long().flatten()
    conf = torch.bincount(idx, minlength=num_labels * num_labels).view(num_labels, num_labels).double()  # (true, pred)
    inter = conf.diag()
    union = conf.sum(0) + conf.sum(1) - inter
    return torch.where(union > 0, inter / union.clamp(min=1), torch.full_like(union, float("nan")))


__all__ = ["ENCODERS", "ENET_C", "LABEL_NAMES", "WEIGHTINGS", "Segmenter", "SegmenterConfig", "class_weights", "pixel_iou"]
