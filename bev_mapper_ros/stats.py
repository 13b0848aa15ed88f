"""Run-time counters of the mapper node and their ``diagnostic_msgs`` form.

No rclpy import: :func:`diagnostic_values` returns plain key/value pairs and a level, which the
node packs into a ``DiagnosticStatus``.

Levels (the thresholds are :class:`~bev_mapper_ros.config.NodeConfig` fields):

- ERROR: images arrive but nothing was mapped for ``stale_error_s``, or no image arrived for
  ``stale_error_s`` after some did;
- WARN: waiting for calibration, image stamps far from the node's clock (``clock_mismatch_s``:
  ``use_sim_time``?), more than ``drop_warn_ratio`` of the sets in the window dropped, cameras
  missing from the sets, or no image yet;
- OK: mapping.
"""

from __future__ import annotations

import threading
from collections import deque
from dataclasses import dataclass, field

from bev_mapper_core.mapper import mapper_class

OK, WARN, ERROR = 0, 1, 2
#: what ``latency_ms`` says when the image stamps and the node's clock disagree
CLOCK_MISMATCH = "clock mismatch"


def human_duration(seconds: float) -> str:
    """``3.0 years``, ``12.5 h``, ``42.0 s``: a duration a person reads at a glance."""
    s = abs(seconds)
    for unit, size in (("years", 365.25 * 86400), ("days", 86400), ("h", 3600), ("min", 60)):
        if s >= 2 * size:
            return f"{s / size:.1f} {unit}"
    return f"{s:.1f} s"


def clock_mismatch_text(skew_s: float, use_sim_time: bool, clock_ns: int) -> str:
    """Why image stamps (``skew_s`` = node clock - stamp) are far from the node's clock, and what to do."""
    if use_sim_time and clock_ns == 0:
        return ("use_sim_time is true but no /clock has arrived: publish /clock (e.g. bev-bag play --clock) "
                "or run the node with use_sim_time:=false")
    where = "behind" if skew_s > 0 else "ahead of"
    text = f"image stamps are {human_duration(skew_s)} {where} the node's clock"
    if use_sim_time:
        return text + " (use_sim_time is true): do the images come from the source of /clock?"
    return text + (" (use_sim_time is false): a bag played with --clock needs the node run with "
                   "-p use_sim_time:=true")


@dataclass
class NodeStats:
    """Counters shared by callbacks and the worker (guarded by :attr:`lock`)."""

    lock: threading.Lock = field(default_factory=threading.Lock, repr=False)
    mapped: int = 0
    bad_input: int = 0
    errors: int = 0
    waiting: int = 0
    missing_camera_sets: int = 0
    missing_by_camera: dict = field(default_factory=dict)  # camera -> mapped sets without it
    split_sets: int = 0  # the synchronizer's SyncStats.split, copied before each diagnostics message
    sync_window_ms: float | None = None  # the synchronizer's window now
    last_error: str = ""
    waiting_for: tuple[str, ...] = ()
    cameras_missing: tuple[str, ...] = ()
    images: int = 0
    first_input_s: float | None = None  # monotonic time of the first / last image
    last_input_s: float | None = None
    last_mapped_s: float | None = None
    mapping_since_s: float | None = None  # monotonic time the set being mapped now was started (None: idle)
    clock_skew_s: float | None = None  # node clock - stamp of the last image
    temporal_frames: int = 0  # frames fused into the last published set (temporal fusion on)
    temporal_note: str = ""  # why the last set was mapped without its history ('' = it was not)
    backend: str = ""  # what runs the model now (Mapper.backend_state; '' = no inference backend)
    # (monotonic s, processing ms, latency ms or None) of recent mapped sets
    recent: deque = field(default_factory=lambda: deque(maxlen=2000), repr=False)
    # (monotonic s, dropped sets so far), one per diagnostics message
    drop_samples: deque = field(default_factory=lambda: deque(maxlen=2000), repr=False)

    def record_input(self, mono_s: float, skew_s: float) -> None:
        """Count one image that arrived (its stamp is ``skew_s`` behind the node's clock)."""
        with self.lock:
            self.images += 1
            if self.first_input_s is None:
                self.first_input_s = mono_s
            self.last_input_s = mono_s
            self.clock_skew_s = skew_s

    def record_mapped(self, mono_s: float, processing_ms: float, latency_ms: float | None, missing) -> None:
        """Count one mapped set (``latency_ms`` None: not meaningful, the clocks disagree)."""
        with self.lock:
            self.mapped += 1
            self.last_mapped_s = mono_s
            self.recent.append((mono_s, processing_ms, latency_ms))
            self.cameras_missing = tuple(missing)
            if missing:
                self.missing_camera_sets += 1
            for camera in missing:
                self.missing_by_camera[camera] = self.missing_by_camera.get(camera, 0) + 1

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

    def dropped_in_window(self, now_s: float, window_s: float, dropped: int) -> int:
        """Record the ``dropped`` total now; return how many were dropped in the last ``window_s``
        (since the oldest sample inside the window). Lock held by the caller.
        """
        self.drop_samples.append((now_s, dropped))
        base = next((d for t, d in self.drop_samples if now_s - t <= window_s), dropped)
        return dropped - base


def _mean(values) -> float | None:
    values = [v for v in values if v is not None]
    return sum(values) / len(values) if values else None


def diagnostic_values(stats: NodeStats, now_s: float, cfg, dropped: int) -> tuple[int, str, dict]:
    """Level, summary message and key/values for ``/diagnostics``.

    ``cfg``: the node's :class:`~bev_mapper_ros.config.NodeConfig` (window and thresholds);
    ``dropped``: sets dropped so far (mailbox + synchronizer). Rates and times have one decimal.
    """
    window = cfg.diagnostics_window_s
    with stats.lock:
        recent = [r for r in stats.recent if now_s - r[0] <= window]
        dropped_window = stats.dropped_in_window(now_s, window, dropped)
        values = {
            "mapped_sets": stats.mapped,
            "dropped_sets": dropped,
            "bad_input": stats.bad_input,
            "errors": stats.errors,
            "sets_with_missing_cameras": stats.missing_camera_sets,
            "missing_by_camera": ",".join(f"{c}:{n}" for c, n in sorted(stats.missing_by_camera.items())),
            "split_sets": stats.split_sets,
            "sync_window_ms": "" if stats.sync_window_ms is None else round(stats.sync_window_ms, 1),
            "cameras_missing": ",".join(stats.cameras_missing),
            "waiting_for": ",".join(stats.waiting_for),
            "last_error": stats.last_error,
            "backend": stats.backend,
        }
        waiting_for, missing = stats.waiting_for, stats.cameras_missing
        first_in, last_in, last_mapped, skew = (stats.first_input_s, stats.last_input_s, stats.last_mapped_s,
                                                stats.clock_skew_s)
        mapping_since = stats.mapping_since_s
        backend = stats.backend
        first_mapped = stats.recent[0][0] if stats.recent else None
    span = min(window, now_s - first_mapped) if first_mapped is not None else window
    values["rate_hz"] = round(len(recent) / span, 1) if span > 0 and recent else 0.0
    processing, latency = _mean(r[1] for r in recent), _mean(r[2] for r in recent)
    values["processing_ms"] = "" if processing is None else round(processing, 1)
    mismatch = skew is not None and abs(skew) > cfg.clock_mismatch_s
    values["clock_offset_s"] = "" if skew is None else round(skew, 1)
    values["latency_ms"] = CLOCK_MISMATCH if mismatch else ("" if latency is None else round(latency, 1))
    considered = dropped_window + len(recent)
    ratio = dropped_window / considered if considered else 0.0
    values["dropped_in_window"] = dropped_window
    values["drop_ratio"] = round(ratio, 3)
    if cfg.temporal.window > 1 or mapper_class(cfg.mapper.method).uses_ego_pose:
        values["temporal_frames"] = stats.temporal_frames
        values["temporal_note"] = stats.temporal_note

    problems: list[tuple[int, str]] = []
    if last_in is not None and now_s - last_in > cfg.stale_error_s:
        problems.append((ERROR, f"no camera image for {now_s - last_in:.1f} s"))
    elif first_in is not None:
        idle = now_s - (last_mapped if last_mapped is not None else first_in)
        if idle > cfg.stale_error_s and last_mapped is None and mapping_since is not None:
            # the first set is being mapped (the model is being built; exports run in the background)
            problems.append((WARN, f"preparing: the first set has been mapping for {now_s - mapping_since:.1f} s "
                                   "(the model is being loaded; see the log)"))
        elif idle > cfg.stale_error_s:
            why = f": waiting for calibration of {', '.join(waiting_for)}" if waiting_for else ""
            problems.append((ERROR, f"nothing mapped for {idle:.1f} s although images arrive{why}"))
    if waiting_for and not any(level == ERROR for level, _ in problems):
        problems.append((WARN, "waiting for calibration of " + ", ".join(waiting_for)))
    if mismatch:
        problems.append((WARN, "clock mismatch: image stamps " + human_duration(skew)
                         + (" behind" if skew > 0 else " ahead of") + " the node's clock (use_sim_time?)"))
    if ratio > cfg.drop_warn_ratio:
        problems.append((WARN, f"{100 * ratio:.1f} % of the synchronized sets dropped in the last "
                               f"{window:.1f} s (mapping slower than the cameras)"))
    if missing and recent:
        problems.append((WARN, "mapping without cameras " + ", ".join(missing)))
    if first_in is None:
        problems.append((WARN, "no camera image received yet"))
    if not problems:
        # e.g. "mapping at 10.0 Hz with torch (until the openvino model is ready)"
        note = f" with {backend}" if backend.startswith("torch (") else ""
        return OK, f"mapping at {values['rate_hz']:.1f} Hz{note}", values
    level = max(lv for lv, _ in problems)
    problems.sort(key=lambda p: -p[0])
    return level, "; ".join(text for _, text in problems), values
