"""Camera images -> model input tensors, the one preprocessing of every learned BEV model.

Bi-Mapper (:meth:`~.bimapper.BiMapper.preprocess`) and S2G2 (:meth:`~.s2g2.S2G2.preprocess`)
both call :func:`preprocess_images`, so a model trained on the drive cache (whose images are
stored already resized with the same operations, :func:`~bev_mapper_core.training.data.resize_labels`
/ :func:`~bev_mapper_core.training.data.resize_rgb`) sees exactly what it sees at inference.
"""

from __future__ import annotations

import torch
from torch.nn import functional as F

from ..labels.classes import NUM_LABELS


def preprocess_images(images: torch.Tensor, input_kind: str, size: tuple[int, int], rgb_mean: torch.Tensor,
                      rgb_std: torch.Tensor) -> torch.Tensor:
    """Raw camera images ``(B, N, H, W[, 3])`` -> model input ``(B, N, C_in, h, w)`` float on
    ``rgb_mean``'s device, ``(h, w) = size``.

    Args:
        images: labels: ``(B, N, H, W)`` integer label ids (ids outside ``0..NUM_LABELS-1`` count
            as unlabeled, 0), resized ``nearest-exact``, then one-hot (``C_in = NUM_LABELS``);
            rgb: ``(B, N, H, W, 3)`` uint8 or float in [0, 255], resized bilinearly
            (antialiased, ``align_corners=False``), scaled to [0, 1] and normalised with
            ``rgb_mean`` / ``rgb_std`` (``C_in = 3``). Images already at ``size`` are not resized.
        input_kind: ``labels`` or ``rgb``.
        size: ``(h, w)`` model input size.
        rgb_mean, rgb_std: normalisation, broadcastable to ``(B, N, 3, h, w)``.

    Raises:
        ValueError: images of the wrong rank or channel count for ``input_kind``.
    """
    h, w = size
    dev = rgb_mean.device
    if input_kind == "labels":
        if images.dim() != 4:
            raise ValueError(f"label images must be (B, N, H, W), got {tuple(images.shape)}")
        B, N, H, W = images.shape
        ids = images.to(dev)
        if (H, W) != (h, w):
            ids = F.interpolate(ids.reshape(B * N, 1, H, W).float(), size=(h, w), mode="nearest-exact")  # (B*N, 1, h, w)
            ids = ids.view(B, N, h, w)  # (B*N, 1, h, w) -> (B, N, h, w)
        ids = ids.long()
        ids = torch.where((ids >= 0) & (ids < NUM_LABELS), ids, torch.zeros_like(ids))
        return F.one_hot(ids, NUM_LABELS).permute(0, 1, 4, 2, 3).float()  # (B, N, h, w, L) -> (B, N, L, h, w)
    if images.dim() != 5 or images.shape[-1] != 3:
        raise ValueError(f"RGB images must be (B, N, H, W, 3), got {tuple(images.shape)}")
    B, N, H, W, _ = images.shape
    x = images.to(dev).float().permute(0, 1, 4, 2, 3).reshape(B * N, 3, H, W) / 255.0  # -> (B*N, 3, H, W)
    if (H, W) != (h, w):
        x = F.interpolate(x, size=(h, w), mode="bilinear", align_corners=False, antialias=True)
    x = x.view(B, N, 3, h, w)  # (B*N, 3, h, w) -> (B, N, 3, h, w)
    return (x - rgb_mean.view(1, 1, 3, 1, 1)) / rgb_std.view(1, 1, 3, 1, 1)  # (3,) -> (1, 1, 3, 1, 1)


def preprocess_one_camera(images: torch.Tensor, input_kind: str, size: tuple[int, int], rgb_mean: torch.Tensor,
                          rgb_std: torch.Tensor, title: str) -> torch.Tensor:
    """:func:`preprocess_images` of a one-camera model: ``(B, 1, H, W[, 3])`` -> ``(B, C_in, h, w)``.

    Raises:
        ValueError: not the images of one camera, or see :func:`preprocess_images`.
    """
    if images.dim() < 2 or images.shape[1] != 1:
        raise ValueError(f"{title} takes the images of one camera, (B, 1, H, W[, 3]); got {tuple(images.shape)}")
    return preprocess_images(images, input_kind, size, rgb_mean, rgb_std)[:, 0]  # (B, 1, C_in, h, w) -> (B, C_in, h, w)


__all__ = ["preprocess_images", "preprocess_one_camera"]
