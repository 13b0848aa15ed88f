"""Batched photometric and geometric augmentation of RGB training images, in torch.

Runs on whatever device the batch is on (the GPU in training), drawing every random number from
one seeded :class:`torch.Generator`, so a run is reproducible. The geometric part (random scale,
crop / translation, horizontal flip) is ONE affine resampling per sample, applied to the image
(bilinear) and to its labels (nearest; pixels from outside the source become ``ignore``). The
photometric part (exposure, contrast, saturation, white balance, gamma, Gaussian blur, sensor
noise) touches the image only.

Horizontal flips keep every label's meaning (no left/right classes in :class:`Label`); they are
off for data whose geometry is not mirror-symmetric (``AugmentConfig.flip``).

The photometric part runs alone on a batch's raw camera images (:meth:`Augment.camera_images`):
the BEV methods trained on RGB (S2G2, FocusBEV, Bi-Mapper) use it so, without the geometric
part, since scaling, cropping or flipping a camera image changes its calibration and the BEV
target would no longer match (docs/TRAINING.md, "Augmentation"). A training step's generator is
:func:`step_generator`'s, a function of the run seed, the step and the data-parallel rank, so a
resumed run draws what an uninterrupted one would.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import torch
from torch.nn import functional as F

from ..errors import ConfigError
from ..labels.spaces import IGNORE


@dataclass(frozen=True)
class AugmentConfig:
    """Augmentation strengths (ranges are uniform; ``p_*`` probabilities per sample).

    Args:
        scale: zoom range relative to "the whole source fits the output" (1.0); above 1 crops.
        flip: horizontal flip with probability 0.5.
        brightness, contrast, saturation: multiplicative ranges.
        white_balance: per-channel gain range.
        gamma: exponent range (applied to [0, 1] intensities; > 1 darkens).
        p_blur, blur_sigma: Gaussian blur probability and sigma range (output pixels).
        p_noise, noise_std: additive Gaussian noise probability and std range (of [0, 1]).
    """

    scale: tuple[float, float] = (0.8, 1.8)
    flip: bool = True
    brightness: tuple[float, float] = (0.6, 1.4)
    contrast: tuple[float, float] = (0.7, 1.3)
    saturation: tuple[float, float] = (0.6, 1.4)
    white_balance: tuple[float, float] = (0.9, 1.1)
    gamma: tuple[float, float] = (0.75, 1.4)
    p_blur: float = 0.25
    blur_sigma: tuple[float, float] = (0.4, 1.4)
    p_noise: float = 0.3
    noise_std: tuple[float, float] = (0.005, 0.03)

    def __post_init__(self) -> None:
        for name in ("scale", "brightness", "contrast", "saturation", "white_balance", "gamma", "blur_sigma",
                     "noise_std"):
            lo, hi = getattr(self, name)
            if not (math.isfinite(lo) and math.isfinite(hi) and 0 <= lo <= hi):
                raise ConfigError(f"augmentation {name} must be a range 0 <= lo <= hi, got {(lo, hi)}")
        if self.scale[0] <= 0 or self.gamma[0] <= 0:
            raise ConfigError("augmentation scale and gamma must be positive")
        for name in ("p_blur", "p_noise"):
            if not 0 <= getattr(self, name) <= 1:
                raise ConfigError(f"{name} must be a probability, got {getattr(self, name)}")


class Augment:
    """Apply :class:`AugmentConfig` to batches (see the module docstring).

    Args:
        config: the strengths.
        generator: the random source (its device must be the batches' device).
    """

    def __init__(self, config: AugmentConfig, generator: torch.Generator) -> None:
        self.cfg, self.g = config, generator

    def _u(self, n: int, rng: tuple[float, float], device) -> torch.Tensor:
        lo, hi = rng
        return lo + (hi - lo) * torch.rand(n, generator=self.g, device=device)

    def geometric(self, images: torch.Tensor, labels: torch.Tensor, size: tuple[int, int],
                  ignore_index: int = IGNORE) -> tuple[torch.Tensor, torch.Tensor]:
        """Random scale, crop and flip to output ``size`` = ``(h, w)``.

        Args:
            images: ``(B, 3, H, W)`` float.
            labels: ``(B, H, W)`` integer ids.

        Returns ``(images (B, 3, h, w) float, labels (B, h, w) long)``; label pixels sampled from
        outside the source are ``ignore_index`` (their image pixels are 0).
        """
        B, dev = images.shape[0], images.device
        s = torch.exp(self._u(B, (math.log(self.cfg.scale[0]), math.log(self.cfg.scale[1])), dev))  # log-uniform zoom
        inv = 1.0 / s  # fraction of the source the output spans (normalised coordinates)
        room = (1.0 - inv).abs()  # how far the window may move (also when zoomed out: where to place the image)
        tx = room * (2 * torch.rand(B, generator=self.g, device=dev) - 1)
        ty = room * (2 * torch.rand(B, generator=self.g, device=dev) - 1)
        flip = torch.ones(B, device=dev)
        if self.cfg.flip:
            flip = torch.where(torch.rand(B, generator=self.g, device=dev) < 0.5, -1.0, 1.0)
        theta = torch.zeros(B, 2, 3, device=dev)
        theta[:, 0, 0], theta[:, 0, 2] = inv * flip, tx
        theta[:, 1, 1], theta[:, 1, 2] = inv, ty
        grid = F.affine_grid(theta, (B, 1, *size), align_corners=False)
        out = F.grid_sample(images.float(), grid, mode="bilinear", padding_mode="zeros", align_corners=False)
        lab = F.grid_sample((labels.float() + 1).unsqueeze(1), grid, mode="nearest", padding_mode="zeros",
                            align_corners=False).squeeze(1).long() - 1  # 0 = outside -> -1
        lab = torch.where(lab < 0, torch.full_like(lab, ignore_index), lab)
        return out, lab

    def photometric(self, images: torch.Tensor, share: int = 1) -> torch.Tensor:
        """``(B, 3, H, W)`` float in [0, 1] -> augmented, clamped to [0, 1].

        ``share``: runs of this many consecutive images take the same colour, exposure, gamma and
        blur (e.g. the frames of one camera's window of frames); the sensor noise is drawn per
        image. ``B`` must be a multiple of it; 1 (default): every image its own.
        """
        c, B, dev = self.cfg, images.shape[0], images.device
        if share < 1 or B % share:
            raise ValueError(f"{B} images do not split into runs of {share}")
        n = B // share  # independent draws
        x = images.float()

        def per(v: torch.Tensor) -> torch.Tensor:  # (n,) -> (B, 1, 1, 1)
            return v.repeat_interleave(share).view(B, 1, 1, 1)

        x = x * per(self._u(n, c.brightness, dev))
        x = x * self._u(3 * n, c.white_balance, dev).view(n, 3).repeat_interleave(share, 0).view(B, 3, 1, 1)
        mean = x.mean(dim=(1, 2, 3), keepdim=True)
        x = (x - mean) * per(self._u(n, c.contrast, dev)) + mean
        grey = (0.299 * x[:, 0:1] + 0.587 * x[:, 1:2] + 0.114 * x[:, 2:3])
        x = (x - grey) * per(self._u(n, c.saturation, dev)) + grey
        x = x.clamp(0, 1) ** per(self._u(n, c.gamma, dev))
        if c.p_blur > 0:
            x = self._blur(x, torch.rand(n, generator=self.g, device=dev) < c.p_blur, share)
        if c.p_noise > 0:
            on = (torch.rand(n, generator=self.g, device=dev) < c.p_noise).float()
            std = per(self._u(n, c.noise_std, dev) * on)
            x = x + std * torch.randn(x.shape, generator=self.g, device=dev)
        return x.clamp(0, 1)

    def camera_images(self, images: torch.Tensor, share: int = 1) -> torch.Tensor:
        """Photometric augmentation alone of raw camera images in a batch's layout.

        Args:
            images: ``(..., H, W, 3)`` uint8 or float in [0, 255] (a training batch's ``rgb``:
                ``(B, N, H, W, 3)``, or ``(B, T, N, H, W, 3)`` for windows of frames).
            share: runs of this many consecutive images (in the flattened leading dimensions)
                share their draws (see :meth:`photometric`).

        Returns ``images``' shape, float32 in [0, 255] on ``images``' device, which the models'
        ``preprocess`` takes as it takes uint8.
        """
        shape = images.shape
        if images.dim() < 4 or shape[-1] != 3:
            raise ValueError(f"camera images must be (..., H, W, 3), got {tuple(shape)}")
        x = images.reshape(-1, *shape[-3:]).permute(0, 3, 1, 2).float() / 255.0  # (M, H, W, 3) -> (M, 3, H, W)
        y = self.photometric(x, share) * 255.0
        return y.permute(0, 2, 3, 1).reshape(shape)  # (M, 3, H, W) -> (..., H, W, 3)

    def _blur(self, x: torch.Tensor, which: torch.Tensor, share: int = 1) -> torch.Tensor:
        """Separable Gaussian blur of the samples ``which`` (``(B // share,)``: a sigma per run of
        ``share`` samples; the others unchanged).
        """
        B, C, H, W = x.shape
        sigma = self._u(B // share, self.cfg.blur_sigma, x.device).repeat_interleave(share)
        which = which.repeat_interleave(share)
        r = max(1, math.ceil(3 * self.cfg.blur_sigma[1]))
        t = torch.arange(-r, r + 1, device=x.device, dtype=x.dtype)
        k = torch.exp(-0.5 * (t.view(1, -1) / sigma.view(-1, 1)) ** 2)  # (B, 2r + 1)
        k = k / k.sum(1, keepdim=True)
        k = torch.where(which.view(-1, 1), k, (t == 0).to(x.dtype).expand_as(k))  # identity kernel when off
        kc = k.repeat_interleave(C, 0)  # (B*C, K)
        y = x.reshape(1, B * C, H, W)
        y = F.conv2d(F.pad(y, (r, r, 0, 0), mode="replicate"), kc.view(B * C, 1, 1, -1), groups=B * C)
        y = F.conv2d(F.pad(y, (0, 0, r, r), mode="replicate"), kc.view(B * C, 1, -1, 1), groups=B * C)
        return y.view(B, C, H, W)

    def __call__(self, images: torch.Tensor, labels: torch.Tensor,
                 size: tuple[int, int]) -> tuple[torch.Tensor, torch.Tensor]:
        """``(B, H, W, 3)`` uint8 (or ``(B, 3, H, W)`` float in [0, 1]) images and ``(B, H, W)``
        labels -> ``(B, 3, h, w)`` float in [0, 1] and ``(B, h, w)`` long: geometric, then photometric.
        """
        if images.dtype == torch.uint8:
            images = images.permute(0, 3, 1, 2).float() / 255.0  # (B, H, W, 3) -> (B, 3, H, W)
        x, y = self.geometric(images, labels, size)
        return self.photometric(x), y


def step_generator(seed: int, step: int, device: torch.device | str = "cpu", rank: int = 0) -> torch.Generator:
    """The random source of training step ``step`` of run seed ``seed`` (augmentation, and the
    segmenter's real batches; ``rank``: the data-parallel process): a function of these alone, so
    a resumed run draws what an uninterrupted one would.
    """
    s = int(np.random.SeedSequence([seed, step, rank, 24]).generate_state(1, np.uint64)[0] >> 1)
    return torch.Generator(device=torch.device(device)).manual_seed(s)


def rank_world() -> tuple[int, int]:
    """``(rank, world size)`` of a data-parallel run, ``(0, 1)`` otherwise."""
    import torch.distributed as dist  # noqa: PLC0415

    if dist.is_available() and dist.is_initialized():
        return dist.get_rank(), dist.get_world_size()
    return 0, 1


def step_augment(seed: int, step: int, device: torch.device | str, config: AugmentConfig | None = None) -> Augment:
    """The :class:`Augment` of training step ``step`` (:func:`step_generator` of this process's rank)."""
    return Augment(config or AugmentConfig(), step_generator(seed, step, device, rank_world()[0]))


__all__ = ["Augment", "AugmentConfig", "rank_world", "step_augment", "step_generator"]
