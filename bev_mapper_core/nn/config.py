"""What the learned models' configurations share: the ``to_dict`` / ``from_dict`` mix-in of their
frozen dataclasses, the RGB input statistics and the sanity bounds of their size knobs.
"""

from __future__ import annotations

from dataclasses import asdict, fields

from bev_mapper_core.errors import ConfigError

#: Sanity bounds of the size knobs, far above any model this package trains (the paper's sizes
#: included): a configuration beyond them, e.g. from a damaged or hostile weights file, is
#: refused before anything is allocated.
MAX_WIDTH_PX = 4096  # input_width


MAX_CHANNELS = 4096  # neck, BEV, U-Net, decoder widths; gv_hidden


MAX_DOWNSAMPLE = 64


#: ImageNet statistics used to normalise RGB input (no pretrained weights; just a standard scale).
RGB_MEAN = (0.485, 0.456, 0.406)


RGB_STD = (0.229, 0.224, 0.225)


#: The input scaling the ImageNet EfficientNet-Lite checkpoints were trained with: ``(x - 127) / 128``
#: on 0..255 RGB (:mod:`~bev_mapper_core.nn.pretrained`); every model with a Lite encoder reads it.
LITE_MEAN = (127.0 / 255,) * 3


LITE_STD = (128.0 / 255,) * 3


def rgb_stats(lite: bool) -> tuple[tuple[float, ...], tuple[float, ...]]:
    """``(mean, std)`` of a model's RGB normalisation: Lite's for a Lite encoder, else ImageNet's."""
    return (LITE_MEAN, LITE_STD) if lite else (RGB_MEAN, RGB_STD)


class DictConfig:
    """``to_dict`` / ``from_dict`` of a frozen config dataclass (JSON-ready: tuples as lists;
    unknown keys refused), as the weights files store it.
    """

    def to_dict(self) -> dict:
        """JSON-ready dict (tuples as lists)."""
        return {k: list(v) if isinstance(v, tuple) else v for k, v in asdict(self).items()}

    @classmethod
    def from_dict(cls, d: dict):
        """Inverse of :meth:`to_dict`.

        Raises:
            ConfigError: not a mapping, unknown keys, or bad values.
        """
        if not isinstance(d, dict):
            raise ConfigError(f"{cls.__name__} must be a mapping, got {type(d).__name__}")
        extra = sorted(set(d) - {f.name for f in fields(cls)})
        if extra:
            raise ConfigError(f"unknown {cls.__name__} fields {extra}")
        return cls(**d)
