"""EfficientNet (Tan & Le, ICML 2019) and EfficientNet-Lite, written in the project.

MBConv blocks (1x1 expansion, depthwise kxk, squeeze-and-excitation, 1x1 projection, stochastic
depth on the residual) with the B0 stage table; the variants B0..B7 scale that table by their
width (channels) and depth (block repeats) multipliers with the reference rounding rules.

**Lite** (``EfficientNetConfig.variant("lite0")`` .. ``lite2``; the reference's
``efficientnet_lite_builder``): no squeeze-excitation, ReLU6 instead of SiLU, the stem fixed at
32 channels and the first and last stages' repeats not scaled, and TensorFlow's "same" padding
(stride-2 layers pad less on the top / left), so that the published ImageNet checkpoint
(:mod:`~bev_mapper_core.nn.pretrained`) computes here what it computed where it was trained.

Departures from the ImageNet classifier, all deliberate:

* No classifier and no 1x1 "head" convolution: the BEV networks only read the stage outputs
  (as HDMapNet's ``CamEncode``, which Bi-Mapper's GV stream follows).
* ``num_stages`` keeps only the first stages (1..7), so a CPU-trainable network can stop at
  stride 8 or 16; ``width_mult`` / ``depth_mult`` override the variant's multipliers.
* Padding is symmetric ``k // 2`` (PyTorch style) rather than TensorFlow's asymmetric "same"
  (``tf_padding``, the Lite variants' setting); either way every stride-2 layer maps ``n`` pixels
  to ``ceil(n / 2)``.
* BatchNorm momentum defaults to PyTorch's 0.1 (the reference uses 0.01): faster-settling
  running statistics suit short CPU training runs. ``bn_momentum`` restores the reference.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

import torch
from torch import nn

from ..errors import ConfigError

#: B0 stage table: (expand ratio, kernel, stride, in channels, out channels, repeats).
B0_STAGES: tuple[tuple[int, int, int, int, int, int], ...] = (
    (1, 3, 1, 32, 16, 1),
    (6, 3, 2, 16, 24, 2),
    (6, 5, 2, 24, 40, 2),
    (6, 3, 2, 40, 80, 3),
    (6, 5, 1, 80, 112, 3),
    (6, 5, 2, 112, 192, 4),
    (6, 3, 1, 192, 320, 1),
)

#: Variant -> (width multiplier, depth multiplier, reference resolution, dropout).
VARIANTS: dict[str, tuple[float, float, int, float]] = {
    "b0": (1.0, 1.0, 224, 0.2),
    "b1": (1.0, 1.1, 240, 0.2),
    "b2": (1.1, 1.2, 260, 0.3),
    "b3": (1.2, 1.4, 300, 0.3),
    "b4": (1.4, 1.8, 380, 0.4),
    "b5": (1.6, 2.2, 456, 0.4),
    "b6": (1.8, 2.6, 528, 0.5),
    "b7": (2.0, 3.1, 600, 0.5),
}

#: Lite variant -> (width multiplier, depth multiplier, reference resolution, dropout).
LITE_VARIANTS: dict[str, tuple[float, float, int, float]] = {
    "lite0": (1.0, 1.0, 224, 0.2),
    "lite1": (1.0, 1.1, 240, 0.2),
    "lite2": (1.1, 1.2, 260, 0.3),
    "lite3": (1.2, 1.4, 280, 0.3),
    "lite4": (1.4, 1.8, 300, 0.3),
}

#: The activations a trunk may use.
ACTIVATIONS = ("silu", "relu6")


def round_filters(channels: int, width_mult: float, divisor: int = 8) -> int:
    """Scale a channel count by ``width_mult``, rounded to a multiple of ``divisor`` (reference rule)."""
    scaled = channels * width_mult
    new = max(divisor, int(scaled + divisor / 2) // divisor * divisor)
    if new < 0.9 * scaled:  # never round down by more than 10 %
        new += divisor
    return int(new)


def round_repeats(repeats: int, depth_mult: float) -> int:
    """Scale a stage's block count by ``depth_mult`` (ceil, as the reference)."""
    return int(math.ceil(depth_mult * repeats))


#: Upper bound of ``width_mult`` / ``depth_mult`` (a sanity bound, see ``EfficientNetConfig``).
MAX_MULT = 8.0


@dataclass(frozen=True)
class EfficientNetConfig:
    """Architecture of an :class:`EfficientNet` trunk.

    Args:
        width_mult, depth_mult: channel and depth multipliers (B0 = 1.0, 1.0).
        num_stages: how many of the seven MBConv stages to keep (7 = the full network).
        in_channels: input channels (3 for RGB, ``NUM_LABELS`` for one-hot label images).
        drop_connect_rate: stochastic-depth rate of the last block (linearly ramped from 0).
        se_ratio: squeeze-excitation bottleneck, relative to the block's input channels.
        bn_eps, bn_momentum: BatchNorm settings.
        lite: the Lite variants' rules: no squeeze-excitation (``se_ratio`` unused), ReLU6, the
            stem fixed at 32 channels, the first and last stages' repeats not scaled.
        tf_padding: TensorFlow's "same" padding (asymmetric on stride-2 layers), as the
            published Lite checkpoints were trained with.
    """

    width_mult: float = 1.0
    depth_mult: float = 1.0
    num_stages: int = 7
    in_channels: int = 3
    drop_connect_rate: float = 0.2
    se_ratio: float = 0.25
    bn_eps: float = 1e-3
    bn_momentum: float = 0.1
    lite: bool = False
    tf_padding: bool = False

    def __post_init__(self) -> None:
        for name in ("lite", "tf_padding"):
            if not isinstance(getattr(self, name), bool):
                raise ConfigError(f"{name} must be true or false, got {getattr(self, name)!r}")
        if not 1 <= self.num_stages <= len(B0_STAGES):
            raise ConfigError(f"num_stages must be in 1..{len(B0_STAGES)}, got {self.num_stages}")
        for v in (self.width_mult, self.depth_mult):
            # 8 = well above B7's 2.0 / 3.1: larger values come only from a damaged config
            if isinstance(v, bool) or not isinstance(v, (int, float)) or not 0 < v <= MAX_MULT:
                raise ConfigError(f"width/depth multipliers must be in (0, {MAX_MULT}], got "
                                  f"{self.width_mult}, {self.depth_mult}")
        if self.in_channels < 1:
            raise ConfigError(f"in_channels must be >= 1, got {self.in_channels}")
        if not 0.0 <= self.drop_connect_rate < 1.0:
            raise ConfigError(f"drop_connect_rate must be in [0, 1), got {self.drop_connect_rate}")

    @classmethod
    def variant(cls, name: str, **overrides) -> "EfficientNetConfig":
        """Config of variant ``name`` (``b0`` .. ``b7``, ``lite0`` .. ``lite4``); keyword
        arguments override fields.
        """
        key = str(name).lower()
        if key in LITE_VARIANTS:
            w, d, _, _ = LITE_VARIANTS[key]
            return replace(cls(width_mult=w, depth_mult=d, lite=True, tf_padding=True), **overrides)
        try:
            w, d, _, _ = VARIANTS[key]
        except KeyError:
            raise ConfigError(f"unknown EfficientNet variant {name!r}; known: "
                              f"{sorted(VARIANTS) + sorted(LITE_VARIANTS)}") from None
        return replace(cls(width_mult=w, depth_mult=d), **overrides)

    def lite_variant(self) -> str | None:
        """The Lite variant whose multipliers this config has (``lite0`` ...), else ``None``."""
        if not self.lite:
            return None
        return next((n for n, (w, d, _, _) in LITE_VARIANTS.items()
                     if (w, d) == (self.width_mult, self.depth_mult)), None)

    def stem_channels(self) -> int:
        """Channels of the stem (Lite: fixed at 32)."""
        return 32 if self.lite else round_filters(32, self.width_mult)

    def stage_repeats(self, stage: int) -> int:
        """Blocks of stage ``stage`` (0-based) after depth scaling (Lite: the first and last
        stages of the full table keep their repeats).
        """
        repeats = B0_STAGES[stage][5]
        if self.lite and stage in (0, len(B0_STAGES) - 1):
            return repeats
        return round_repeats(repeats, self.depth_mult)


def _bn(channels: int, cfg: EfficientNetConfig) -> nn.BatchNorm2d:
    return nn.BatchNorm2d(channels, eps=cfg.bn_eps, momentum=cfg.bn_momentum)


def _act(cfg: EfficientNetConfig) -> nn.Module:
    return nn.ReLU6() if cfg.lite else nn.SiLU()


class SamePad2d(nn.Module):
    """TensorFlow's "same" padding of a ``kernel`` x ``kernel`` convolution of ``stride``: the
    output is ``ceil(n / stride)``; an odd total pad puts the extra pixel on the bottom / right.
    """

    def __init__(self, kernel: int, stride: int) -> None:
        super().__init__()
        self.kernel, self.stride = kernel, stride

    def _pads(self, n: int) -> tuple[int, int]:
        total = max((-(-n // self.stride) - 1) * self.stride + self.kernel - n, 0)
        return total // 2, total - total // 2

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        """``x`` (B, C, H, W) -> zero-padded (B, C, H + pad_h, W + pad_w)."""
        top, bottom = self._pads(x.shape[-2])
        left, right = self._pads(x.shape[-1])
        return nn.functional.pad(x, (left, right, top, bottom))


def _conv(cin: int, cout: int, kernel: int, stride: int, cfg: EfficientNetConfig, groups: int = 1) -> list[nn.Module]:
    """A bias-free convolution of ``ceil(n / stride)`` output, with the config's padding style."""
    if cfg.tf_padding and stride > 1:
        return [SamePad2d(kernel, stride), nn.Conv2d(cin, cout, kernel, stride, 0, groups=groups, bias=False)]
    return [nn.Conv2d(cin, cout, kernel, stride, kernel // 2, groups=groups, bias=False)]


class SqueezeExcite(nn.Module):
    """Channel attention: global average -> reduce (SiLU) -> expand (sigmoid) -> rescale."""

    def __init__(self, channels: int, reduced: int) -> None:
        super().__init__()
        self.reduce = nn.Conv2d(channels, reduced, 1)
        self.expand = nn.Conv2d(reduced, channels, 1)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        """``x`` (B, C, H, W) -> same shape."""
        s = x.mean((2, 3), keepdim=True)  # (B, C, 1, 1)
        s = torch.sigmoid(self.expand(nn.functional.silu(self.reduce(s))))
        return x * s


class MBConv(nn.Module):
    """Mobile inverted bottleneck with squeeze-excitation and stochastic depth."""

    def __init__(self, cin: int, cout: int, expand: int, kernel: int, stride: int,
                 drop_rate: float, cfg: EfficientNetConfig) -> None:
        super().__init__()
        mid = cin * expand
        layers: list[nn.Module] = []
        if expand != 1:
            layers += [nn.Conv2d(cin, mid, 1, bias=False), _bn(mid, cfg), _act(cfg)]
        layers += [*_conv(mid, mid, kernel, stride, cfg, groups=mid), _bn(mid, cfg), _act(cfg)]
        if not cfg.lite:
            layers.append(SqueezeExcite(mid, max(1, int(cin * cfg.se_ratio))))
        layers += [nn.Conv2d(mid, cout, 1, bias=False), _bn(cout, cfg)]
        self.body = nn.Sequential(*layers)
        self.residual = stride == 1 and cin == cout
        self.drop_rate = drop_rate

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        """``x`` (B, cin, H, W) -> (B, cout, H / stride, W / stride)."""
        y = self.body(x)
        if not self.residual:
            return y
        if self.training and self.drop_rate > 0:
            keep = 1.0 - self.drop_rate
            # per-sample Bernoulli mask (B, 1, 1, 1)
            mask = torch.empty((x.shape[0], 1, 1, 1), dtype=x.dtype, device=x.device).bernoulli_(keep)
            y = y * mask / keep
        return x + y


class EfficientNet(nn.Module):
    """EfficientNet trunk returning its multi-scale endpoints.

    ``forward`` returns a list of feature maps, one per output stride (2, 4, 8, ...): each is the
    output of the last block before the next stride-2 block, and the last one is the trunk's
    final output. :attr:`endpoint_channels` and :attr:`endpoint_strides` describe them.
    """

    def __init__(self, cfg: EfficientNetConfig) -> None:
        super().__init__()
        self.cfg = cfg
        w = cfg.width_mult
        stem = cfg.stem_channels()
        self.stem = nn.Sequential(*_conv(cfg.in_channels, stem, 3, 2, cfg), _bn(stem, cfg), _act(cfg))
        stages = B0_STAGES[: cfg.num_stages]
        total = sum(cfg.stage_repeats(i) for i in range(len(stages)))
        blocks: list[MBConv] = []
        cin = stem
        stride_now = 2
        ends_at: list[int] = []  # block indices whose output is an endpoint
        strides: list[int] = []
        channels: list[int] = []
        for stage, (expand, kernel, stride, _, cout, _) in enumerate(stages):
            cout = round_filters(cout, w)
            for r in range(cfg.stage_repeats(stage)):
                s = stride if r == 0 else 1
                if s == 2:  # the previous output is an endpoint (the stem's, if no block yet)
                    ends_at.append(len(blocks) - 1)
                    strides.append(stride_now)
                    channels.append(cin)
                    stride_now *= 2
                rate = cfg.drop_connect_rate * len(blocks) / total
                blocks.append(MBConv(cin, cout, expand, kernel, s, rate, cfg))
                cin = cout
        ends_at.append(len(blocks) - 1)
        strides.append(stride_now)
        channels.append(cin)
        self.blocks = nn.ModuleList(blocks)
        self._ends = set(ends_at)
        self._stem_is_endpoint = -1 in self._ends
        self.endpoint_strides: tuple[int, ...] = tuple(strides)
        self.endpoint_channels: tuple[int, ...] = tuple(channels)

    @property
    def out_channels(self) -> int:
        """Channels of the final endpoint."""
        return self.endpoint_channels[-1]

    def forward(self, x: torch.Tensor) -> list[torch.Tensor]:
        """``x`` (B, in_channels, H, W) -> endpoints [(B, C_i, ceil(H / s_i), ceil(W / s_i))]."""
        x = self.stem(x)
        outs = [x] if self._stem_is_endpoint else []
        for i, block in enumerate(self.blocks):
            x = block(x)
            if i in self._ends:
                outs.append(x)
        return outs


def downsampled_size(n: int, stride: int) -> int:
    """Size after the trunk's ``log2(stride)`` stride-2 layers: ``ceil`` halving each time."""
    while stride > 1:
        n = (n + 1) // 2
        stride //= 2
    return n


def count_parameters(module: nn.Module) -> int:
    """Number of trainable parameters of a module."""
    return sum(p.numel() for p in module.parameters() if p.requires_grad)
