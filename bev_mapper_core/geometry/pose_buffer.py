"""Ego poses looked up at an image's stamp (issue #14, part 2).

Odometry arrives at its own rate, never exactly at the camera stamps. :class:`PoseBuffer` keeps
the last poses (``odom_from_base``, 4x4, with their stamps) in a bounded buffer and answers
:meth:`PoseBuffer.at`: the pose at a stamp, interpolated between the two poses around it
(translation linearly, rotation by quaternion slerp). A stamp outside the buffered span by more
than ``max_extrapolation_s``, or inside a gap between poses longer than ``max_gap_s``, has no
pose (``None``): the caller maps that frame without temporal context rather than with a guess.
A pose older than the newest one (a bag loop, a clock jump back) empties the buffer first.
"""

from __future__ import annotations

import math
from bisect import bisect_left
from collections import deque
from dataclasses import dataclass

import numpy as np

from ..errors import CalibrationError, ConfigError
from .transforms import quat_to_rot, rot_to_quat, validate_transform


@dataclass(frozen=True)
class PoseBufferConfig:
    """Args: ``size``: poses kept; ``max_gap_s``: longest gap interpolated across;
    ``max_extrapolation_s``: how far past either end a stamp may lie and take that end's pose.
    """

    size: int = 200
    max_gap_s: float = 0.5
    max_extrapolation_s: float = 0.05

    def __post_init__(self) -> None:
        if isinstance(self.size, bool) or not isinstance(self.size, int) or not 2 <= self.size <= 100_000:
            raise ConfigError(f"pose buffer size must be an integer in 2..100000, got {self.size!r}")
        for name in ("max_gap_s", "max_extrapolation_s"):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v) or v < 0:
                raise ConfigError(f"{name} must be a finite number >= 0, got {v!r}")


def _slerp(q0: np.ndarray, q1: np.ndarray, t: float) -> np.ndarray:
    """Unit quaternion ``(x, y, z, w)`` a fraction ``t`` of the way from ``q0`` to ``q1``."""
    d = float(np.dot(q0, q1))
    if d < 0.0:  # the shorter way round
        q1, d = -q1, -d
    if d > 0.9995:  # nearly equal: linear, renormalized
        q = q0 + t * (q1 - q0)
        return q / np.linalg.norm(q)
    theta = math.acos(d)
    return (math.sin((1 - t) * theta) * q0 + math.sin(t * theta) * q1) / math.sin(theta)


class PoseBuffer:
    """The last poses of the ego in a fixed frame, and the pose at any stamp between them."""

    def __init__(self, config: PoseBufferConfig = PoseBufferConfig()) -> None:
        self.config = config
        self._stamps: deque[int] = deque(maxlen=config.size)
        self._poses: deque[np.ndarray] = deque(maxlen=config.size)

    def __len__(self) -> int:
        return len(self._stamps)

    @property
    def latest_stamp_ns(self) -> int | None:
        """Stamp of the newest pose (``None`` when empty)."""
        return self._stamps[-1] if self._stamps else None

    def clear(self) -> None:
        """Forget every pose."""
        self._stamps.clear()
        self._poses.clear()

    def add(self, stamp_ns: int, odom_from_base: np.ndarray) -> None:
        """Keep a pose; one older than the newest empties the buffer first (time went back), one
        at the newest stamp replaces it.

        Raises:
            ConfigError: not a finite rigid 4x4 transform (nothing is kept).
        """
        try:
            T = validate_transform(odom_from_base, "ego pose")
        except CalibrationError as exc:
            raise ConfigError(f"an ego pose must be a finite rigid 4x4 transform: {exc}") from None
        stamp_ns = int(stamp_ns)
        if self._stamps and stamp_ns < self._stamps[-1]:
            self.clear()
        if self._stamps and stamp_ns == self._stamps[-1]:
            self._poses[-1] = T.copy()
            return
        self._stamps.append(stamp_ns)
        self._poses.append(T.copy())

    def at(self, stamp_ns: int) -> np.ndarray | None:
        """``odom_from_base`` at ``stamp_ns`` (4x4), or ``None`` (see the module docstring)."""
        if not self._stamps:
            return None
        stamps, cfg = self._stamps, self.config
        ext = int(cfg.max_extrapolation_s * 1e9)
        if stamp_ns <= stamps[0]:
            return self._poses[0].copy() if stamps[0] - stamp_ns <= ext else None
        if stamp_ns >= stamps[-1]:
            return self._poses[-1].copy() if stamp_ns - stamps[-1] <= ext else None
        i = bisect_left(stamps, stamp_ns)  # stamps[i - 1] < stamp_ns <= stamps[i]
        t0, t1 = stamps[i - 1], stamps[i]
        if (t1 - t0) / 1e9 > cfg.max_gap_s:
            return None
        a, b = self._poses[i - 1], self._poses[i]
        t = (stamp_ns - t0) / (t1 - t0)
        q = _slerp(np.array(rot_to_quat(a[:3, :3])), np.array(rot_to_quat(b[:3, :3])), t)
        out = np.eye(4)
        out[:3, :3] = quat_to_rot(*q)
        out[:3, 3] = (1 - t) * a[:3, 3] + t * b[:3, 3]
        return out


__all__ = ["PoseBuffer", "PoseBufferConfig"]
