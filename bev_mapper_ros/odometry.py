"""The node's watch over the odometry stream and its clock (issue #29). No rclpy import.

:class:`OdometryWatch` sits between ``/odom`` and the temporal memories (the method-independent
fusion and a method's own, FocusBEV's bank):

* as messages arrive (:meth:`OdometryWatch.received`): a non-finite covariance is counted (the
  pose is kept), a stamp that repeats or goes back is counted (the pose buffer replaces or starts
  over), a stamp further in the future than ``max_pose_offset_s`` of the node's clock is counted
  and the message skipped (it would stand for poses not yet driven);
* per mapped set (:meth:`OdometryWatch.vet`): the pose at the images' stamp goes through
  :class:`~bev_mapper_core.temporal.OdometryCheck` (no or a non-rigid pose, jumps no vehicle
  makes); a problem resets the memories, said in the log and counted;
* :meth:`OdometryWatch.values`: ``/diagnostics`` keys ``temporal_resets`` (every reset of either
  memory since the start), ``frames_without_pose`` and ``odometry_<kind>`` per problem kind.

:class:`ClockWatch` keeps the node's clock honest for latency: a clock that jumps back (a looping
bag with ``/clock``) is counted and said, never subtracted; a latency is never negative.
"""

from __future__ import annotations

import threading

import numpy as np

from bev_mapper_core.temporal import ODOMETRY_PROBLEMS, OdometryCheck, PoseVerdict, TemporalConfig

#: Odometry stamped further ahead of the newest image (seconds) is "far in the future" (camera
#: pipelines lag odometry by a few hundred ms at most).
FAR_AHEAD_S = 2.0


class OdometryWatch:
    """Counts and vets the odometry the node's memories see (see the module docstring)."""

    def __init__(self, config: TemporalConfig) -> None:
        self.config = config
        self.check = OdometryCheck(config)
        self._lock = threading.Lock()
        self._received = dict.fromkeys(ODOMETRY_PROBLEMS, 0)
        self._last_stamp_ns: int | None = None
        self.resets = 0
        self.frames_without_pose = 0

    def received(self, stamp_ns: int, covariance, now_ns: int) -> str:
        """A parsed odometry message arrived (``now_ns``: the data's time now, the newest image
        stamp or the node's clock; 0 = unknown): ``''`` to keep it, else the problem kind of a
        message to skip. Repeats and stamps going back are counted but kept (the buffer copes).
        """
        with self._lock:
            if covariance is not None:
                cov = np.asarray(covariance, dtype=np.float64)
                if not np.all(np.isfinite(cov)):
                    self._received["bad_covariance"] += 1
            if now_ns > 0 and stamp_ns - now_ns > FAR_AHEAD_S * 1e9:
                self._received["far_stamp"] += 1
                return "far_stamp"
            last = self._last_stamp_ns
            if last is not None and stamp_ns <= last:
                self._received["duplicate_stamp" if stamp_ns == last else "stamp_back"] += 1
            self._last_stamp_ns = stamp_ns
        return ""

    def vet(self, stamp_ns: int, pose) -> PoseVerdict:
        """The pose a mapped set at ``stamp_ns`` may use (see :class:`OdometryCheck`); a reset of
        the memories it asks for is counted here.
        """
        verdict = self.check.check(stamp_ns, pose)
        if verdict.reset and verdict.pose is not None:
            with self._lock:
                self.resets += 1
        return verdict

    def count_memory(self, note: str, pose) -> None:
        """Count what a memory (the fusion's or the method's) said about a frame: a reset with a
        pose, or a frame mapped without one.
        """
        if not note:
            return
        with self._lock:
            if pose is None:
                self.frames_without_pose += 1
            else:
                self.resets += 1

    def values(self) -> dict:
        """``/diagnostics`` key/values (see the module docstring)."""
        with self._lock:
            out = {"temporal_resets": self.resets, "frames_without_pose": self.frames_without_pose}
            for kind in ODOMETRY_PROBLEMS:
                out[f"odometry_{kind}"] = self._received[kind] + self.check.counts[kind]
        return out


class ClockWatch:
    """Latency against a clock that may jump back (see the module docstring)."""

    def __init__(self) -> None:
        self._last_ns: int | None = None
        self.jumps_back = 0
        self.last_jump_s = 0.0

    def latency_ms(self, now_ns: int, stamp_ns: int, processing_ms: float, mismatch_s: float) -> float | None:
        """The set's latency (ms) at clock time ``now_ns``: ``now - stamp``, at least the
        ``processing_ms`` just measured; None when the clock jumped back since the last set (it
        is counted in :attr:`jumps_back`) or the stamp is further than ``mismatch_s`` from it.
        """
        last, self._last_ns = self._last_ns, now_ns
        if last is not None and now_ns < last:
            self.jumps_back += 1
            self.last_jump_s = (last - now_ns) / 1e9
            return None
        latency_s = (now_ns - stamp_ns) / 1e9
        if abs(latency_s) > mismatch_s:
            return None
        return max(latency_s * 1000.0, processing_ms)


__all__ = ["FAR_AHEAD_S", "ClockWatch", "OdometryWatch"]
