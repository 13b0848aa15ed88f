"""The ego pose at an image stamp, for the temporal fusion and for methods with their own memory
(FocusBEV): from odometry or TF, as the node's ``pose_source`` says.

:class:`EgoPoses` keeps the odometry the node receives (vetted by
:class:`~bev_mapper_ros.odometry.OdometryWatch`, which also counts it for ``/diagnostics``) and
answers :meth:`EgoPoses.at` from the worker thread. Both sources may lag the images by a little
(the transform or odometry of the same instant often arrives just after the images), so a
lookup waits up to :data:`POSE_WAIT_S` for them. It never raises: no pose is ``None``, the
frame is then mapped without its history, and the reason is counted.
"""

from __future__ import annotations

import threading
import time
from collections.abc import Callable

from bev_mapper_core.errors import BevMapperError
from bev_mapper_core.geometry.pose_buffer import PoseBuffer
from msg_adapters import odometry_to_state

from .odometry import OdometryWatch
from .tf_source import TfLookupError

#: How long a frame waits for the odometry (or TF) of its stamp.
POSE_WAIT_S = 0.2


class EgoPoses:
    """Ego poses from odometry (:meth:`on_odometry`) or TF, looked up by stamp (:meth:`at`).

    Args:
        cfg: the node's :class:`~bev_mapper_ros.config.NodeConfig` (``pose_source``,
            ``odom_frame``, ``base_frame``, ``temporal``).
        tf: the node's TF source, or None (no TF).
        stopping: set when the node stops (a lookup stops waiting).
        data_now_ns: the node's clock moved onto the images' clock (its skew taken out).
        on_tf_problem: ``(kind, message)`` of a failed TF lookup.
        on_warning: ``(key, message)`` of a throttled warning.
        on_bad_input: ``(message, key)`` of a bad odometry message.

    Attributes:
        used: where the last pose came from: ``odom``, ``tf`` or ``''`` (none yet).
        watch: the odometry's vetting and counters.
    """

    def __init__(self, cfg, tf, stopping: threading.Event, data_now_ns: Callable[[], int],
                 on_tf_problem: Callable[[str, str], None], on_warning: Callable[[str, str], None],
                 on_bad_input: Callable[[str, str], None]) -> None:
        self.cfg, self.tf, self._stopping = cfg, tf, stopping
        self._data_now_ns = data_now_ns
        self._on_tf_problem, self._on_warning, self._on_bad_input = on_tf_problem, on_warning, on_bad_input
        self.watch = OdometryWatch(cfg.temporal)
        self.used = ""
        self._buffer = PoseBuffer()
        self._lock = threading.Lock()
        self._odom_seen = False
        self._last_odom_mono: float | None = None

    def at(self, stamp_ns: int):
        """The ego pose at ``stamp_ns`` from odometry or TF, as ``pose_source`` says (``auto``:
        odometry once some arrived, else TF, else odometry that arrives within POSE_WAIT_S);
        None when there is none (the fusion then maps the frame without its history and says
        why). A TF failure is counted unless ``auto`` found the pose in odometry.
        """
        src = self.cfg.pose_source
        if src == "odom" or self.tf is None or (src == "auto" and self._odom_seen):
            self.used = "odom"
            return self._odom_at(stamp_ns)
        try:
            pose = self._tf_at(stamp_ns)
        except TfLookupError as exc:
            if src == "auto":
                pose = self._odom_at(stamp_ns)
                if pose is not None:
                    self.used = "odom"
                    return pose
            self.used = "tf"
            self._on_tf_problem(exc.kind, f"ego pose: {exc}")
            return None
        self.used = "tf"
        return pose

    def lookup(self, stamp_ns: int):
        """The ego pose at ``stamp_ns`` as :meth:`at` finds it, for placing a camera at its own
        time (:mod:`bev_mapper_core.placement`, which counts what has none): a TF failure is not
        counted here and :attr:`used` is left alone.
        """
        src = self.cfg.pose_source
        if src == "odom" or self.tf is None or (src == "auto" and self._odom_seen):
            return self._odom_at(stamp_ns)
        try:
            return self._tf_at(stamp_ns)
        except TfLookupError:
            return self._odom_at(stamp_ns) if src == "auto" else None

    def _tf_at(self, stamp_ns: int):
        """``odom_frame <- base_frame`` at ``stamp_ns`` (tf2 interpolates); waits up to
        POSE_WAIT_S for TF to reach the stamp.

        Raises:
            TfLookupError: no transform at the stamp.
        """
        deadline = time.monotonic() + POSE_WAIT_S
        while True:
            try:
                return self.tf.lookup(self.cfg.odom_frame, self.cfg.base_frame, stamp_ns)
            except TfLookupError as exc:
                ahead = exc.kind == "extrapolation" and "past" not in str(exc)
                if not ahead or time.monotonic() > deadline or self._stopping.is_set():
                    raise
                time.sleep(0.005)

    def _odom_at(self, stamp_ns: int):
        """The odometry pose at ``stamp_ns``; waits up to POSE_WAIT_S for odometry at or after the
        stamp, else None.
        """
        deadline = time.monotonic() + POSE_WAIT_S
        flowing = self._last_odom_mono is not None and time.monotonic() - self._last_odom_mono < 1.0
        while True:
            with self._lock:
                pose, latest = self._buffer.at(stamp_ns), self._buffer.latest_stamp_ns
            if not flowing:  # no odometry kept in the last second: no use waiting for it
                return pose
            if pose is not None or (latest is not None and latest >= stamp_ns) or time.monotonic() > deadline \
                    or self._stopping.is_set():
                return pose
            time.sleep(0.005)

    def on_odometry(self, msg) -> None:
        """Keep the ego pose of a ``nav_msgs/Odometry`` message (a bad one is counted and skipped)."""
        try:
            state = odometry_to_state(msg)
            data_now = self._data_now_ns()
            if self.watch.received(state.stamp_ns, getattr(msg.pose, "covariance", None), data_now):
                self._on_warning("odometry", f"odometry stamped {(state.stamp_ns - data_now) / 1e9:.1f} s "
                                             "ahead of the newest image skipped (odometry_far_stamp)")
                return
            with self._lock:
                self._buffer.add(state.stamp_ns, state.world_from_ego)
            self._odom_seen = True
            self._last_odom_mono = time.monotonic()
        except BevMapperError as exc:
            self._on_bad_input(f"odometry: {exc}", "odometry")


__all__ = ["POSE_WAIT_S", "EgoPoses"]
