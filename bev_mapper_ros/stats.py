"""Run-time counters of the mapper node and their ``diagnostic_msgs`` form.

No rclpy import: :func:`diagnostic_values` returns plain key/value pairs and a level, which the
node packs into a ``DiagnosticStatus``.
"""

from __future__ import annotations

import threading
from collections import deque
from dataclasses import dataclass, field

OK, WARN, ERROR = 0, 1, 2


@dataclass
class NodeStats:
    """Counters shared by callbacks and the worker (guarded by :attr:`lock`)."""

    lock: threading.Lock = field(default_factory=threading.Lock, repr=False)
    mapped: int = 0
    bad_input: int = 0
    errors: int = 0
    waiting: int = 0
    missing_camera_sets: int = 0
    last_error: str = ""
    waiting_for: tuple[str, ...] = ()
    cameras_missing: tuple[str, ...] = ()
    # (wall time s, processing ms, latency ms) of recent mapped sets
    recent: deque = field(default_factory=lambda: deque(maxlen=200), repr=False)

    def record_mapped(self, wall_s: float, processing_ms: float, latency_ms: float, missing) -> None:
        """Count one mapped set."""
        with self.lock:
            self.mapped += 1
            self.recent.append((wall_s, processing_ms, latency_ms))
            self.cameras_missing = tuple(missing)
            if missing:
                self.missing_camera_sets += 1

    def record_bad_input(self, message: str) -> None:
        """Count one rejected message or camera image."""
        with self.lock:
            self.bad_input += 1
            self.last_error = message

    def record_error(self, message: str) -> None:
        """Count one failure of the mapping step."""
        with self.lock:
            self.errors += 1
            self.last_error = message


def diagnostic_values(stats: NodeStats, now_s: float, window_s: float, dropped: int) -> tuple[int, str, dict]:
    """Level, summary message and key/values for ``/diagnostics`` over the last ``window_s``."""
    with stats.lock:
        recent = [r for r in stats.recent if now_s - r[0] <= window_s]
        values = {
            "mapped_sets": stats.mapped,
            "dropped_sets": dropped,
            "bad_input": stats.bad_input,
            "errors": stats.errors,
            "sets_with_missing_cameras": stats.missing_camera_sets,
            "cameras_missing": ",".join(stats.cameras_missing),
            "waiting_for": ",".join(stats.waiting_for),
            "last_error": stats.last_error,
        }
        waiting_for = stats.waiting_for
        missing = stats.cameras_missing
    values["rate_hz"] = round(len(recent) / window_s, 3) if window_s > 0 else 0.0
    if recent:
        values["processing_ms"] = round(sum(r[1] for r in recent) / len(recent), 2)
        values["latency_ms"] = round(sum(r[2] for r in recent) / len(recent), 2)
    else:
        values["processing_ms"] = values["latency_ms"] = ""
    if waiting_for:
        return WARN, "waiting for calibration of " + ", ".join(waiting_for), values
    if not recent:
        return WARN, "no synchronized camera set mapped recently", values
    if missing:
        return WARN, "mapping without cameras " + ", ".join(missing), values
    return OK, f"mapping at {values['rate_hz']} Hz", values
