"""Class balance of a training set, for the methods' BCE terms: :func:`class_pos_weight`, and
:class:`PosWeightTraining` (the cap and per-class overrides of the ``auto`` weights, inherited by
the methods' training settings) with its flags :data:`POS_WEIGHT_FLAGS`.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from bev_mapper_core.errors import ConfigError

from .data import FrameSet
from .method import CliFlag

#: ``pos_weight`` settings: ``auto`` (see :func:`class_pos_weight`) or ``none`` (plain BCE, paper).
POS_WEIGHTS = ("auto", "none")


def class_pos_weight(frames: FrameSet, max_weight: float = 10.0) -> tuple[float, ...]:
    """Per-class BCE positive weights ``clip(sqrt(neg / pos), 1, max_weight)`` over visible cells.

    A deviation from the paper (plain BCE): with a training budget of a few hundred steps the
    thin and rare layers (lane dividers, crossings, boundaries, pedestrians: 0.05-2 % of the
    cells) otherwise stay at zero IoU; the square root keeps the weighting mild.
    """
    sets = [f for _, f in frames.parts] if hasattr(frames, "parts") else [frames]  # MultiRigFrames: each rig's
    pos, tot = 0.0, 0.0
    for f in sets:
        m = f.mask[:, None]  # (M, 1, H, W)
        if f.class_mask is not None:
            m = m & f.class_mask  # (M, K, H, W): each class's known cells
        pos = pos + np.count_nonzero(f.target & m, axis=(0, 2, 3)).astype(np.float64)
        tot = tot + np.count_nonzero(np.broadcast_to(m, f.target.shape), axis=(0, 2, 3)).astype(np.float64)
    w = np.sqrt(np.maximum(tot - pos, 1.0) / np.maximum(pos, 1.0))
    return tuple(float(round(v, 3)) for v in np.clip(w, 1.0, max_weight))


@dataclass(frozen=True)
class PosWeightTraining:
    """The ``auto`` BCE positive weights' settings (inherited by the methods' training settings,
    which define ``pos_weight``).

    Args:
        pos_weight_max: the cap of the ``auto`` positive weights (10: Bi-Mapper's; the rare
            pedestrian layer reaches it).
        pos_weight_classes: ``name=w,name=w``: these classes' positive weights set to ``w``
            (with ``pos_weight`` ``auto``; e.g. a low cap for the thin layers and
            ``pedestrian=10``, whose layer collapses without a weight).
    """

    pos_weight_max: float = 10.0
    pos_weight_classes: str = ""

    def check_pos_weights(self) -> None:
        """Validate these fields (call from ``__post_init__``).

        Raises:
            ConfigError: a bad value.
        """
        v = self.pos_weight_max
        if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v) or v < 1:
            raise ConfigError(f"pos_weight_max must be a finite number >= 1, got {v!r}")
        self.class_pos_weights()

    def class_pos_weights(self) -> dict[str, float]:
        """``pos_weight_classes`` parsed: class name -> weight (>= 1).

        Raises:
            ConfigError: not ``name=w`` items, a weight that is not a finite number >= 1, or set
                without ``pos_weight`` ``auto``.
        """
        out: dict[str, float] = {}
        for item in filter(None, (t.strip() for t in str(self.pos_weight_classes).split(","))):
            name, _, w = item.partition("=")
            try:
                v = float(w)
            except ValueError:
                v = float("nan")
            if not name.strip() or not math.isfinite(v) or v < 1:
                raise ConfigError(f"pos_weight_classes items are name=weight (weight >= 1), got {item!r}")
            out[name.strip()] = v
        if out and getattr(self, "pos_weight", "auto") != "auto":
            raise ConfigError("pos_weight_classes sets some of the auto weights: it needs pos_weight 'auto'")
        return out

    def run_pos_weights(self, train, class_names: Sequence[str]) -> tuple[float, ...] | None:
        """The BCE positive weights of a run on the training frames ``train`` (None: plain BCE).

        Raises:
            ConfigError: ``pos_weight_classes`` names a class the run does not map.
        """
        if getattr(self, "pos_weight", "auto") != "auto":
            return None
        over = self.class_pos_weights()
        unknown = sorted(set(over) - set(class_names))
        if unknown:
            raise ConfigError(f"pos_weight_classes names {unknown}, not among the classes {list(class_names)}")
        pw = class_pos_weight(train, self.pos_weight_max)
        return tuple(over.get(c, w) for c, w in zip(class_names, pw))


#: The flags of :class:`PosWeightTraining`'s fields.
POS_WEIGHT_FLAGS = (
    CliFlag("--pos-weight-max", "pos_weight_max", number=True, help="cap of the auto BCE positive weights"),
    CliFlag("--pos-weight-classes", "pos_weight_classes",
            help="name=w,...: these classes' auto BCE positive weights set to w (e.g. pedestrian=10)"),
)
