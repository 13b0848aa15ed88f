"""Class balance of a training set, for the methods' BCE terms."""

from __future__ import annotations

import numpy as np

from .data import FrameSet

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
