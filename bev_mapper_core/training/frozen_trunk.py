"""What S2G2 and FocusBEV share for CPU-feasible training on a pretrained trunk (issue #39).

* :class:`FrozenTrunkTraining`: the training settings both methods' loss configs inherit: a
  frozen encoder, its features cached per frame (``feature_copies``) and the positive weights
  of the BCE (:class:`~.class_weights.PosWeightTraining`: ``pos_weight_max``,
  ``pos_weight_classes``); :data:`FROZEN_TRUNK_FLAGS` their ``bev-train`` flags and
  :data:`PRIOR_SKIP_FLAG` the model's ``--prior-skip`` (Bi-Mapper's too).
* :func:`prior_cache`: segipm's prior (:class:`~bev_mapper_core.methods.segipm.prior.SegIpmPrior`)
  of every frame of a set, computed once.
* :func:`encode_cache` / :func:`pick_cached`: the frozen encoder's features of every frame, copy 0
  of the image as it is and the others photometrically augmented, each draw a function of the
  run seed, copy and frame; each step draws one copy per frame from the run seed and the step,
  so ``--resume`` is exact.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass

import numpy as np
import torch

from bev_mapper_core.errors import ConfigError
from bev_mapper_core.nn.augment import Augment, AugmentConfig

from .class_weights import POS_WEIGHT_FLAGS, PosWeightTraining
from .method import CliFlag

#: ``feature_copies`` at most (memory: copies x frames x the encoder's features).
MAX_FEATURE_COPIES = 16
#: Frames encoded (or mapped by segipm) at once while filling a cache.
CACHE_BATCH = 32


@dataclass(frozen=True)
class FrozenTrunkTraining(PosWeightTraining):
    """Training settings for a pretrained trunk (inherited by the methods' loss configs, which
    define ``pos_weight`` and ``augment``), with :class:`~.class_weights.PosWeightTraining`'s.

    Args:
        frozen_encoder: the encoder (the shipped segmenter's trunk, ``encoder_init``) never
            trains: no gradient, its BatchNorm on its running statistics. Everything after it
            trains as before.
        feature_copies: with ``frozen_encoder``, the encoder's features of every training (and
            unlabeled) frame are computed once, before the first step, and what follows the
            encoder trains on them: ``n`` copies per frame, copy 0 of the image as it is, copies
            1..n-1 of augmented images (each step draws one copy per frame); 0 = no cache (the
            encoder runs every step). With one copy and ``augment`` off, a step's loss equals the
            uncached frozen step's.
    """

    frozen_encoder: bool = False
    feature_copies: int = 0

    def check_frozen_trunk(self) -> None:
        """Validate these fields and the positive weights' (call from ``__post_init__``).

        Raises:
            ConfigError: a bad value or a combination that does nothing.
        """
        if not isinstance(self.frozen_encoder, bool):
            raise ConfigError(f"frozen_encoder must be true or false, got {self.frozen_encoder!r}")
        n = self.feature_copies
        if isinstance(n, bool) or not isinstance(n, int) or not 0 <= n <= MAX_FEATURE_COPIES:
            raise ConfigError(f"feature_copies must be an integer in 0..{MAX_FEATURE_COPIES}, got {n!r}")
        if n and not self.frozen_encoder:
            raise ConfigError("feature_copies caches the encoder's features: it needs frozen_encoder")
        if n > 1 and not getattr(self, "augment", False):
            raise ConfigError("feature_copies > 1 caches augmented copies: it needs augment")
        self.check_pos_weights()


#: ``--prior-skip`` (a model config field of the methods that have it).
PRIOR_SKIP_FLAG = CliFlag("--prior-skip", "prior_skip", action="store_true",
                          help="segipm's map of the same image (segmenter + IPM) enters the BEV head and the logits "
                               "(which start as segipm's); computed once per training frame")

#: The flags of :class:`FrozenTrunkTraining`'s fields (the positive weights' included).
FROZEN_TRUNK_FLAGS = (
    *POS_WEIGHT_FLAGS,
    CliFlag("--frozen-encoder", "frozen_encoder", action="store_true",
            help="the encoder (the shipped segmenter's trunk) never trains"),
    CliFlag("--feature-copies", "feature_copies", min_value=0,
            help="with --frozen-encoder: cache the encoder's features of N copies of every frame (copy 0 as "
                 "it is, the others augmented) and train on them (default 0: no cache)"),
)


def _ranges(n: int) -> list[np.ndarray]:
    """Frame ids ``0 .. n-1`` in chunks of :data:`CACHE_BATCH`."""
    return [np.arange(s, min(s + CACHE_BATCH, n)) for s in range(0, n, CACHE_BATCH)]


@torch.no_grad()
def prior_cache(prior_fn: Callable[[torch.Tensor], torch.Tensor], fs) -> torch.Tensor:
    """``prior_fn`` (e.g. :meth:`SegIpmPrior.batch`) on every frame of ``fs`` (its own camera images
    ``fs.rgb`` ``(b, N, H, W, 3)`` as they are) -> ``(M, K + 1, H, W)``. Whatever the set's
    ``window``, frame ``i``'s prior is its own: the last frame of the window ending at ``i``, the
    one the model maps.
    """
    return torch.cat([prior_fn(torch.from_numpy(fs.rgb[idx])) for idx in _ranges(len(fs))])


@torch.no_grad()
def encode_cache(encode: Callable[[torch.Tensor], Sequence[torch.Tensor]],
                 inputs: Callable[[dict, Augment | None], torch.Tensor], fs, copies: int, seed: int,
                 device: torch.device | str) -> tuple[torch.Tensor, ...]:
    """The frozen encoder's features of every frame of ``fs``: ``encode`` (model input -> a
    sequence of feature maps ``(b, ...)``) on ``inputs(batch, aug)`` (the batch's model input,
    augmented by ``aug`` unless None); copy 0 as it is, copies ``1..copies-1`` augmented, each
    draw a function of ``seed``, the copy and the frame -> one ``(copies, M, ...)`` per map.
    """
    out = []
    for c in range(copies):
        parts = []
        for idx in _ranges(len(fs)):
            aug = None
            if c > 0:
                state = np.random.SeedSequence([seed, c, int(idx[0]), 25]).generate_state(1, np.uint64)[0]
                aug = Augment(AugmentConfig(), torch.Generator(device=device).manual_seed(int(state >> 1)))
            parts.append(tuple(encode(inputs(fs.batch(idx), aug))))
        out.append([torch.cat(maps) for maps in zip(*parts)])  # per map: (M, ...)
    return tuple(torch.stack(maps) for maps in zip(*out))  # per map: copies x (M, ...) -> (copies, M, ...)


def pick_cached(cache: Sequence[torch.Tensor], index: torch.Tensor, seed: int, step: int) -> tuple[torch.Tensor, ...]:
    """Cached maps of frames ``index`` ``(B,)`` from :func:`encode_cache`'s output, one copy per
    frame drawn from ``seed`` and ``step`` -> one ``(B, ...)`` per map.
    """
    pick = torch.from_numpy(np.random.default_rng([seed, step, 26]).integers(0, cache[0].shape[0], len(index)))
    return tuple(c[pick, index.cpu()] for c in cache)


def cache_mib(tensors) -> float:
    """Memory of a collection of tensors, MiB."""
    return sum(t.numel() * t.element_size() for t in tensors) / 2**20


__all__ = ["CACHE_BATCH", "FROZEN_TRUNK_FLAGS", "FrozenTrunkTraining", "MAX_FEATURE_COPIES", "PRIOR_SKIP_FLAG",
           "cache_mib", "encode_cache", "pick_cached", "prior_cache"]
