"""The ``prior_skip`` input of S2G2, FocusBEV and RGB Bi-Mapper: segipm's map of the same camera
images (issue #39; :mod:`bev_mapper_core.nn.prior_skip`).

The shipped 2-D segmenter (:class:`~bev_mapper_core.methods.segmenter.stage.SegmenterStage`,
``MapperConfig.segmenter``: ``auto`` = the default shipped one) labels each camera image at its
own size and :class:`~bev_mapper_core.methods.ipm.mapper.IpmMapper` projects the labels onto the
grid (occlusion reasoning included): exactly the ``segipm`` baseline
(:class:`~bev_mapper_core.methods.segipm.mapper.SegIpmMapper`). Its ``K`` class probabilities and
its ``known`` mask (as a 0/1 coverage channel) are the prior, ``(K + 1, H, W)`` float32. It is a
fixed function of the image (no parameter of the model reaches it), so training computes it once
per frame (:func:`~bev_mapper_core.training.frozen_trunk.prior_cache`, in the methods'
``prepare``), from the image before any photometric augmentation.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Mapping, Sequence
from dataclasses import replace

import numpy as np
import torch

from bev_mapper_core.geometry.grid import BevGrid
from bev_mapper_core.geometry.rig import Rig
from bev_mapper_core.mapper import MapperConfig
from bev_mapper_core.training.frozen_trunk import cache_mib, prior_cache


class SegIpmPrior:
    """segipm's map of a rig's camera images as a ``(K + 1, H, W)`` prior (see the module docstring).

    Args:
        rig: the rig (one camera for the monocular methods, any for Bi-Mapper); grid: the model's
            grid; classes: the model's classes, in order.
        config: the mapper's configuration (its ``segmenter``, ``backend``, ``threads``,
            ``device``, ``ipm_occlusion`` are used); None = the defaults.
    """

    def __init__(self, rig: Rig, grid: BevGrid, classes: Sequence[str], config: MapperConfig | None = None) -> None:
        from .mapper import SegIpmMapper

        base = config or MapperConfig()
        cfg = replace(base, method="segipm", input_kind="rgb", classes=tuple(classes), weights=None)
        self.classes = tuple(classes)
        self.mapper = SegIpmMapper(rig, grid, cfg)
        self.cameras = rig.names

    def set_rig(self, rig: Rig) -> None:
        """A new calibration of the cameras (IPM's tables are rebuilt)."""
        self.mapper.set_rig(rig)
        self.cameras = rig.names

    def frame(self, images: Mapping[str, np.ndarray]) -> np.ndarray:
        """One frame's camera images ``{name: (H_img, W_img, 3) uint8}`` (absent cameras unseen)
        -> the prior ``(K + 1, H, W)`` float32.
        """
        pred = self.mapper.map({k: np.ascontiguousarray(v) for k, v in images.items()})
        probs = np.stack([pred.layer(c) for c in self.classes]).astype(np.float32)  # (K, H, W)
        return np.concatenate([probs, pred.known[None].astype(np.float32)])  # (K + 1, H, W)

    def one(self, image: np.ndarray) -> np.ndarray:
        """The one camera's image ``(H_img, W_img, 3)`` uint8 -> the prior ``(K + 1, H, W)`` float32."""
        return self.frame({self.cameras[0]: image})

    def batch(self, images: torch.Tensor | np.ndarray) -> torch.Tensor:
        """Camera images ``(B, N, H_img, W_img, 3)`` uint8 (the rig's N cameras, in rig order) ->
        ``(B, K + 1, H, W)``.
        """
        arr = images.cpu().numpy() if isinstance(images, torch.Tensor) else np.asarray(images)
        n = len(self.cameras)
        if arr.ndim != 5 or arr.shape[1] != n or arr.shape[-1] != 3:
            raise ValueError(f"the prior needs RGB images (B, {n}, H, W, 3), got {arr.shape}")
        return torch.from_numpy(np.stack([self.frame(dict(zip(self.cameras, a.astype(np.uint8)))) for a in arr]))


def training_priors(rig: Rig, grid: BevGrid, classes: Sequence[str], device, sets: Mapping[str, object],
                    log: Callable[[str], None]) -> tuple[SegIpmPrior, dict[str, torch.Tensor]]:
    """A training run's prior: ``(the prior on one thread, {name: (M, K + 1, H, W)})``, the prior of
    every frame of each named frame set (their camera-size images as they are), computed once.
    """
    t0 = time.monotonic()
    fn = SegIpmPrior(rig, grid, classes, MapperConfig(threads=1, device=str(device)))
    priors = {name: prior_cache(fn.batch, fs) for name, fs in sets.items()}
    log(f"segipm prior of {sum(len(p) for p in priors.values())} frames, {cache_mib(priors.values()):.0f} MiB, "
        f"{time.monotonic() - t0:.1f} s")
    return fn, priors


__all__ = ["SegIpmPrior", "training_priors"]
