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

Before any memory sees a pose, :class:`OdometryCheck` vets the stream of poses (here and in
FocusBEV's own memory, in replay and in the node): a missing or non-rigid pose, an odometry stamp
that went back, repeats or lies far from the frame's, a switch of the odometry's frame ids, a
motion no vehicle makes (more than ``max_accel_mps2`` of change in velocity, e.g. a 4 m spike
between two frames 0.1 s apart) are counted per kind (:data:`ODOMETRY_PROBLEMS`) and reset the
memory, which is said; a non-finite covariance is counted (the pose itself is used).

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
        max_accel_mps2: a larger change of the ego velocity between frames (m/s per s) is no
            motion but an odometry jump: the memory is dropped (:class:`OdometryCheck`).
        max_pose_offset_s: an odometry stamp further than this from its frame's stamp is not
            that frame's pose.
    """

    window: int = 1
    max_gap_s: float = 0.5
    max_jump_m: float = 5.0
    layers: str = "flat"
    max_accel_mps2: float = 50.0
    max_pose_offset_s: float = 0.5

    def __post_init__(self) -> None:
        if isinstance(self.window, bool) or not isinstance(self.window, int) or not 1 <= self.window <= 16:
            raise ConfigError(f"temporal window must be an integer in 1..16, got {self.window!r}")
        for name in ("max_gap_s", "max_jump_m", "max_accel_mps2", "max_pose_offset_s"):
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
        with np.errstate(all="ignore"):  # huge entries overflow in the check: refused all the same
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


#: What :class:`OdometryCheck` counts (``metrics.json`` ``temporal.odometry_problems``,
#: ``/diagnostics`` ``odometry_<kind>``).
ODOMETRY_PROBLEMS = ("no_pose", "bad_pose", "stamp_back", "duplicate_stamp", "far_stamp", "frame_change", "jump",
                     "bad_covariance")


@dataclass(frozen=True)
class PoseVerdict:
    """What :meth:`OdometryCheck.check` decided for one frame: the ``pose`` to use (None: map
    without memory), whether the memories must be ``reset`` first, the ``problem`` kind ('' =
    none) and a ``note`` for the log.
    """

    pose: np.ndarray | None
    reset: bool = False
    problem: str = ""
    note: str = ""


class OdometryCheck:
    """Vets each frame's ego pose before a temporal memory uses it; counts what it finds.

    Attributes:
        counts: frames per problem kind (:data:`ODOMETRY_PROBLEMS`).
        resets: memory resets it asked for.
    """

    def __init__(self, config: TemporalConfig = TemporalConfig()) -> None:
        self.config = config
        self.counts = dict.fromkeys(ODOMETRY_PROBLEMS, 0)
        self.resets = 0
        self._last: tuple[int, int | None, np.ndarray, tuple | None] | None = None  # stamp, pose stamp, pose, frames
        self._velocity: np.ndarray | None = None  # m/s of the last accepted step

    def forget(self) -> None:
        """Start afresh (the memories were dropped for another reason)."""
        self._last, self._velocity = None, None

    def check(self, stamp_ns: int, pose, pose_stamp_ns: int | None = None, frames: tuple | None = None,
              covariance=None) -> PoseVerdict:
        """The verdict on frame ``stamp_ns``'s ``pose`` (odom <- base, 4x4, or None), taken from
        odometry stamped ``pose_stamp_ns`` in ``frames`` (``(frame_id, child_frame_id)``), with
        its pose ``covariance`` (any numbers; only checked for finiteness).
        """
        if covariance is not None and not np.all(np.isfinite(np.asarray(covariance, dtype=np.float64))):
            self.counts["bad_covariance"] += 1
        if pose is None:
            return self._refuse("no_pose", "no ego pose for this frame: mapped without temporal memory")
        problem = pose_problem(pose)
        if problem:
            return self._refuse("bad_pose", problem)
        T = np.asarray(pose, dtype=np.float64)
        stamp_ns = int(stamp_ns)
        if pose_stamp_ns is not None and abs(int(pose_stamp_ns) - stamp_ns) > self.config.max_pose_offset_s * 1e9:
            return self._refuse("far_stamp", f"odometry stamped {(int(pose_stamp_ns) - stamp_ns) / 1e9:+.3f} s from "
                                             "its frame: mapped without temporal memory")
        last = self._last
        if last is None:
            self._accept(stamp_ns, pose_stamp_ns, T, frames, None)
            return PoseVerdict(T)
        last_stamp, last_pose_stamp, last_T, last_frames = last
        kind = note = ""
        if pose_stamp_ns is not None and last_pose_stamp is not None and int(pose_stamp_ns) <= last_pose_stamp:
            kind = "duplicate_stamp" if int(pose_stamp_ns) == last_pose_stamp else "stamp_back"
            note = f"odometry stamp {'repeated' if kind == 'duplicate_stamp' else 'went back'}: temporal memory reset"
        elif frames is not None and last_frames is not None and tuple(frames) != tuple(last_frames):
            kind, note = "frame_change", (f"odometry frames changed from {last_frames} to {tuple(frames)}: "
                                          "temporal memory reset")
        elif stamp_ns > last_stamp:
            dt = (stamp_ns - last_stamp) / 1e9
            v = (T[:3, 3] - last_T[:3, 3]) / dt
            if self._velocity is not None and dt <= self.config.max_gap_s:
                accel = float(np.linalg.norm(v - self._velocity)) / dt
                if accel > self.config.max_accel_mps2:
                    kind = "jump"
                    note = (f"ego pose jumped {float(np.linalg.norm(T[:3, 3] - last_T[:3, 3])):.2f} m in {dt:.3f} s "
                            f"({accel:.0f} m/s^2 > {self.config.max_accel_mps2}): temporal memory reset")
            if not kind and float(np.linalg.norm(T[:3, 3] - last_T[:3, 3])) > self.config.max_jump_m:
                kind, note = "jump", (f"ego pose jumped {float(np.linalg.norm(T[:3, 3] - last_T[:3, 3])):.2f} m "
                                      f"(> {self.config.max_jump_m} m): temporal memory reset")
            velocity = None if kind or dt > self.config.max_gap_s else v
            self._accept(stamp_ns, pose_stamp_ns, T, frames, velocity)
            if kind:
                self.counts[kind] += 1
                self.resets += 1
                return PoseVerdict(T, True, kind, note)
            return PoseVerdict(T)
        else:  # the frame stamp itself went back or repeated: the memories reset on it
            self._accept(stamp_ns, pose_stamp_ns, T, frames, None)
            return PoseVerdict(T)
        self.counts[kind] += 1
        self.resets += 1
        self._accept(stamp_ns, pose_stamp_ns, T, frames, None)
        return PoseVerdict(None if kind in ("duplicate_stamp", "stamp_back") else T, True, kind, note)

    def _accept(self, stamp_ns, pose_stamp_ns, T, frames, velocity) -> None:
        self._last = (stamp_ns, None if pose_stamp_ns is None else int(pose_stamp_ns), T,
                      None if frames is None else tuple(frames))
        self._velocity = velocity

    def _refuse(self, kind: str, note: str) -> PoseVerdict:
        self.counts[kind] += 1
        self.forget()
        return PoseVerdict(None, True, kind, note)


__all__ = ["EPS", "ODOMETRY_PROBLEMS", "TEMPORAL_LAYERS", "FusionResult", "OdometryCheck", "PoseVerdict",
           "TemporalConfig", "TemporalFusion", "drop_reason", "pose_problem"]
