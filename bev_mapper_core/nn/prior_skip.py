"""The ``prior_skip`` input shared by the monocular models (issue #39): a strong prior the network
corrects, segipm's map of the same image (:class:`~bev_mapper_core.methods.segipm.prior.SegIpmPrior`),
``K`` class probabilities + a coverage channel ``(B, K + 1, H, W)`` on the full grid.

It enters the model's BEV head as a skip input (:class:`~bev_mapper_core.nn.decoder.BevDecoder`'s,
whose last layer starts at zero) and reaches the logits through :class:`PriorProjection`, a 1x1
convolution that starts at ``8 p - 4`` per class (as Bi-Mapper's ``ipm_skip``): an untrained model
maps as segipm does, and training learns the correction.
"""

from __future__ import annotations

import torch
from torch import nn

#: ``prior_skip`` initialisation: logit ``8 p - 4`` for a prior class probability ``p``.
PRIOR_LOGIT_SCALE = 8.0


class PriorProjection(nn.Conv2d):
    """1x1 convolution ``(B, K + 1, H, W)`` prior -> ``(B, K, H, W)`` logits, starting at
    ``PRIOR_LOGIT_SCALE * p - PRIOR_LOGIT_SCALE / 2`` per class (the coverage channel at 0).
    """

    def __init__(self, num_classes: int) -> None:
        super().__init__(num_classes + 1, num_classes, 1)
        with torch.no_grad():
            self.weight.zero_()
            self.weight[:, :num_classes, 0, 0] = PRIOR_LOGIT_SCALE * torch.eye(num_classes)
            self.bias.fill_(-PRIOR_LOGIT_SCALE / 2)


def check_prior(prior: torch.Tensor | None, channels: int, grid_shape: tuple[int, int]) -> None:
    """Raise ValueError unless ``prior`` is ``(B, channels, *grid_shape)``."""
    if prior is None or tuple(prior.shape[1:]) != (channels, *grid_shape):
        got = None if prior is None else tuple(prior.shape)
        raise ValueError(f"a prior_skip model needs the prior (B, {channels}, {grid_shape[0]}, {grid_shape[1]}), "
                         f"got {got}")


__all__ = ["PRIOR_LOGIT_SCALE", "PriorProjection", "check_prior"]
