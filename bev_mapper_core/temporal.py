"""Method-independent temporal fusion of published BEV maps (issue #14, part 2).

:class:`TemporalFusion` keeps the last ``window`` predictions of any mapper with the ego pose of
each, carries them into the current pose (:func:`~bev_mapper_core.geometry.bev_warp.warp_layers`) and
averages, per cell and class, the **log-odds** of every frame that knows the cell there.
Averaging, rather than summing, log-odds keeps the probabilities' scale: consecutive frames are
far from independent observations.

* Only the **flat** layers are fused by default (``layers="flat"``: drivable, dividers,
  crossings, curbs, sidewalks; the classes whose :class:`~bev_mapper_core.labels.classes.BevClass` is
  flat). Undoing the ego motion does not undo an object's own motion: on the demo drive, fusing
  every layer over 3 frames drops Bi-Mapper's pedestrian IoU from 61.9 to 29.2 (docs/RESULTS.md).
  ``layers="all"`` fuses objects too.
* The **known** cells are the current frame's: a cell the method withholds now stays unknown
  (hidden now is not known from a moment ago: what hides it may have moved).

The memory is dropped (and the frame mapped alone) when:

* the frame has no ego pose (``odom_from_base`` None): the result says why in
  :attr:`FusionResult.note`, for a log line and ``/diagnostics``;
* its stamp is not after the previous one (a bag loop, a clock jump back);
* the gap to the previous frame exceeds ``max_gap_s``;
* the pose moved more than ``max_jump_m`` since the previous frame (a relocalization).

``window`` 1 is no fusion at all. Moving objects smear by their own motion over the window
(only the ego motion is undone), which is why the window stays short.
"""

from __future__ import annotations

import math
from collections import deque
from dataclasses import dataclass

import numpy as np

from .errors import CalibrationError, ConfigError
from .geometry.bev_warp import warp_layers
from .geometry.grid import BevGrid
from .geometry.transforms import validate_transform
from .labels.classes import bev_class
from .mapper import BevPrediction

#: ``TemporalConfig.layers`` choices.
TEMPORAL_LAYERS = ("flat", "all")
#: Probabilities are clipped to [EPS, 1 - EPS] before the log-odds (|logit| <= 9.2).
EPS = 1e-4


@dataclass(frozen=True)
class TemporalConfig:
    """Temporal fusion settings.

    Args:
        window: frames fused, the current one included (1 = off).
        max_gap_s: a longer gap between frames drops the memory.
        max_jump_m: a larger ego translation between consecutive frames drops the memory.
        layers: ``flat`` (the flat classes only) or ``all`` (see the module docstring).
    """

    window: int = 1
    max_gap_s: float = 0.5
    max_jump_m: float = 5.0
    layers: str = "flat"

    def __post_init__(self) -> None:
        if isinstance(self.window, bool) or not isinstance(self.window, int) or not 1 <= self.window <= 16:
            raise ConfigError(f"temporal window must be an integer in 1..16, got {self.window!r}")
        for name in ("max_gap_s", "max_jump_m"):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v) or v <= 0:
                raise ConfigError(f"{name} must be a finite number > 0, got {v!r}")
        if self.layers not in TEMPORAL_LAYERS:
            raise ConfigError(f"temporal layers must be one of {TEMPORAL_LAYERS}, got {self.layers!r}")


def pose_problem(odom_from_base) -> str:
    """Why ``odom_from_base`` cannot align a frame with earlier ones ('' = it can)."""
    if odom_from_base is None:
        return "no ego pose for this frame: mapped without temporal fusion"
    try:
        validate_transform(odom_from_base, "ego pose")
    except CalibrationError as exc:
        return f"the ego pose is not a finite rigid 4x4 transform ({exc}): mapped without temporal fusion"
    return ""


def drop_reason(last_stamp_ns: int, last_pose: np.ndarray, stamp_ns: int, odom_from_base, config: TemporalConfig) -> str:
    """Why memory kept up to a frame at ``last_stamp_ns`` / ``last_pose`` cannot be used with a
    frame at ``stamp_ns`` / ``odom_from_base`` (a valid pose): the stamp went back (a bag loop),
    the gap exceeds ``config.max_gap_s``, or the pose jumped more than ``config.max_jump_m``.
    '' = it can.
    """
    if stamp_ns <= last_stamp_ns:
        return f"stamp went back by {(last_stamp_ns - stamp_ns) / 1e9:.3f} s: temporal memory reset"
    gap = (stamp_ns - last_stamp_ns) / 1e9
    if gap > config.max_gap_s:
        return f"{gap:.3f} s since the previous frame (> {config.max_gap_s} s): temporal memory reset"
    jump = float(np.linalg.norm(np.asarray(odom_from_base)[:3, 3] - np.asarray(last_pose)[:3, 3]))
    if jump > config.max_jump_m:
        return f"ego pose jumped {jump:.2f} m (> {config.max_jump_m} m): temporal memory reset"
    return ""


@dataclass(frozen=True)
class FusionResult:
    """One fused frame: ``prediction``, the number of ``frames`` fused into it (1 = alone), and
    a ``note`` saying why the memory was dropped ('' when it was not).
    """

    prediction: BevPrediction
    frames: int
    note: str = ""


@dataclass
class _Entry:
    logits: np.ndarray  # (C, H, W) float32 log-odds, 0 where unknown
    known: np.ndarray  # (H, W) bool
    odom_from_base: np.ndarray  # (4, 4)
    stamp_ns: int


class TemporalFusion:
    """Fuse a mapper's predictions over the last frames (see the module docstring)."""

    def __init__(self, grid: BevGrid, config: TemporalConfig = TemporalConfig()) -> None:
        self.grid, self.config = grid, config
        self._memory: deque[_Entry] = deque(maxlen=max(config.window - 1, 0))
        self._classes: tuple[str, ...] | None = None

    def reset(self) -> None:
        """Forget every kept frame."""
        self._memory.clear()

    def _drop_reason(self, odom_from_base, stamp_ns: int) -> str:
        """Why the kept frames cannot be fused with a frame at this (valid) pose and stamp."""
        if not self._memory:
            return ""
        last = self._memory[-1]
        return drop_reason(last.stamp_ns, last.odom_from_base, stamp_ns, odom_from_base, self.config)

    def update(self, pred: BevPrediction, stamp_ns: int, odom_from_base: np.ndarray | None) -> FusionResult:
        """Fuse ``pred`` (this frame, on :attr:`grid`) with the kept frames and keep it.

        Raises:
            ConfigError: a prediction of another shape or other classes than the kept ones (the
                memory is dropped first, so the next frame starts afresh).
        """
        if pred.probs.shape[-2:] != self.grid.shape:
            raise ConfigError(f"prediction of shape {pred.probs.shape} is not on the grid {self.grid.shape}")
        if self._classes is not None and pred.classes != self._classes:
            self.reset()
        self._classes = pred.classes
        bad_pose = pose_problem(odom_from_base)
        note = bad_pose or self._drop_reason(odom_from_base, int(stamp_ns))
        if note:
            self.reset()
        if self.config.window == 1 or bad_pose:
            return FusionResult(pred, 1, note)
        p = np.clip(pred.probs, EPS, 1.0 - EPS).astype(np.float32)  # (C, H, W)
        known = np.asarray(pred.known, dtype=bool)  # (H, W)
        logits = np.log(p) - np.log1p(-p)
        T_cur = np.asarray(odom_from_base, dtype=np.float64)
        fused_layers = [i for i, c in enumerate(pred.classes) if self.config.layers == "all" or bev_class(c).flat]
        zero = np.float32(0.0)
        kept = np.where(known, logits, zero)  # (C, H, W)
        total = kept[fused_layers].copy()  # (F, H, W)
        count = known.astype(np.float32)  # (H, W)
        frames = 1 + len(self._memory)
        for e in self._memory:
            prev_from_cur = np.linalg.inv(e.odom_from_base) @ T_cur
            both = np.concatenate([e.logits[fused_layers], e.known[None].astype(np.float32)])  # (F + 1, H, W)
            moved, valid = warp_layers(both, self.grid, prev_from_cur)
            # a cell counts only where the current frame and every bilinear neighbour then knew it
            k = known & valid & (moved[-1] > np.float32(1.0 - 1e-4))
            total += np.where(k, moved[:-1], zero)
            count += k.astype(np.float32)
        self._memory.append(_Entry(kept, known, T_cur, int(stamp_ns)))
        probs = pred.probs.astype(np.float32, copy=True)  # (C, H, W)
        mean = total / np.maximum(count, np.float32(1.0))  # (F, H, W) mean log-odds
        fused = np.float32(1.0) / (np.float32(1.0) + np.exp(-mean))  # sigmoid
        probs[fused_layers] = np.where(known, fused, probs[fused_layers])
        return FusionResult(BevPrediction(pred.classes, probs, known.copy()), frames,
                            note)


__all__ = ["EPS", "TEMPORAL_LAYERS", "FusionResult", "TemporalConfig", "TemporalFusion", "drop_reason", "pose_problem"]
