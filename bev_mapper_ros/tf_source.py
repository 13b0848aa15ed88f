"""The node's TF: ``/tf`` and ``/tf_static`` checked, kept in a tf2 buffer, looked up with tf2.

The node looks transforms up through one small interface, :class:`TfSource`
(``lookup(target, source, stamp_ns) -> target_from_source``): :class:`Tf2Source` implements it
with tf2_ros's ``Buffer`` (tf2's interpolation between stamps, chains through any number of
frames), fed by this module's own subscriptions. Each incoming transform is checked first
(:func:`~msg_adapters.tf.transform_stamped_to_matrix`: finite translation, unit quaternion,
valid frames and stamp; a stamp far ahead of the node's clock): a bad one is counted and never
reaches the buffer, so it never reaches a map.

Problems are sorted into :data:`TF_ERROR_KINDS` (:class:`TfLookupError.kind`), the keys of the
``tf_errors_<kind>`` counters in ``/diagnostics``.

:func:`make_tf_source` returns None where tf2_ros is not importable (then the node takes the
``extrinsics.<camera>`` parameters and odometry alone, and says so).
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Protocol

import numpy as np

from bev_mapper_core.errors import BevMapperError
from msg_adapters import transform_stamped_to_matrix
from msg_adapters.errors import TransformError

#: What can go wrong with TF, as counted in ``/diagnostics`` (``tf_errors_<kind>``): kind -> meaning.
TF_ERROR_TEXTS: dict[str, str] = {
    "no_path": "a frame unknown to TF or not connected to the other",
    "cycle": "the transform tree has a loop",
    "extrapolation": "the image stamp outside the times TF holds, in the future or the past",
    "invalid": "a transform with a NaN or infinite value, a non-unit rotation or bad frame names, refused on arrival",
    "future_stamp": "a `/tf` transform stamped more than `clock_mismatch_s` ahead of the node's clock, refused on arrival",
    "extrinsic_jump": "a TF extrinsic moving a camera by more than `tf_extrinsic_jump_m`, refused",
}
TF_ERROR_KINDS = tuple(TF_ERROR_TEXTS)


class TfLookupError(BevMapperError):
    """A TF lookup failed or a transform was refused; :attr:`kind` is one of :data:`TF_ERROR_KINDS`."""

    def __init__(self, kind: str, message: str) -> None:
        super().__init__(message)
        self.kind = kind


class TfSource(Protocol):
    """What the node needs of TF."""

    def lookup(self, target: str, source: str, stamp_ns: int | None = None) -> np.ndarray:
        """``target_from_source`` (4x4 float64) at ``stamp_ns`` (None: the latest).

        Raises:
            TfLookupError: no such transform (its ``kind`` says why).
        """


def _kind_of(exc: Exception) -> str:
    """The :data:`TF_ERROR_KINDS` entry of one of tf2's exceptions."""
    name, text = type(exc).__name__, str(exc).lower()
    if "loop" in text or "cycle" in text:
        return "cycle"
    if "Extrapolation" in name or "extrapolation" in text:
        return "extrapolation"
    return "no_path"


class Tf2Source:
    """:class:`TfSource` over tf2_ros's ``Buffer``, fed by checked ``/tf`` and ``/tf_static``.

    Args:
        node: the rclpy node whose subscriptions (QoS as tf2_ros's listener: depth 100,
            reliable; ``/tf_static`` transient local) fill the buffer.
        on_refused: called with ``(kind, message)`` for each transform refused on arrival.
        future_tolerance_s: transforms stamped more than this ahead of the node's clock are
            refused (``future_stamp``): tf2 would keep them and drop everything older.
        wrap: wraps each subscription callback (the node's containment of exceptions).
    """

    def __init__(self, node, on_refused: Callable[[str, str], None], future_tolerance_s: float,
                 wrap: Callable = lambda where, fn: fn) -> None:
        import rclpy.time  # noqa: PLC0415 - a ROS install's module, like tf2_ros
        from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile  # noqa: PLC0415
        from tf2_msgs.msg import TFMessage  # noqa: PLC0415
        from tf2_ros import Buffer  # noqa: PLC0415

        self._time = rclpy.time.Time
        self._node = node
        self._on_refused = on_refused
        self._future_ns = round(future_tolerance_s * 1e9)
        self.buffer = Buffer(node=node)
        self.received = 0
        # tf2_ros TransformListener's QoS: depth 100, reliable; /tf_static transient local
        qos = {static: QoSProfile(depth=100, history=HistoryPolicy.KEEP_LAST,
                                  durability=DurabilityPolicy.TRANSIENT_LOCAL if static else DurabilityPolicy.VOLATILE)
               for static in (False, True)}
        self._subs = [
            node.create_subscription(TFMessage, "/tf", wrap("tf", lambda m: self._on_tf(m, False)), qos[False]),
            node.create_subscription(TFMessage, "/tf_static", wrap("tf_static", lambda m: self._on_tf(m, True)),
                                     qos[True]),
        ]

    def _on_tf(self, msg, static: bool) -> None:
        now = self._node.get_clock().now().nanoseconds
        for ts in msg.transforms:
            try:
                t = transform_stamped_to_matrix(ts)
            except (TransformError, BevMapperError) as exc:
                self._on_refused("invalid", f"{'/tf_static' if static else '/tf'}: {exc}")
                continue
            if not static and now > 0 and t.stamp_ns > now + self._future_ns:
                self._on_refused("future_stamp", f"/tf: transform {t.parent} -> {t.child} stamped "
                                 f"{(t.stamp_ns - now) / 1e9:.1f} s ahead of the node's clock, refused")
                continue
            self.received += 1
            if static:
                self.buffer.set_transform_static(ts, "bev_mapper")
            else:
                self.buffer.set_transform(ts, "bev_mapper")

    def lookup(self, target: str, source: str, stamp_ns: int | None = None) -> np.ndarray:
        """See :meth:`TfSource.lookup`; tf2 interpolates between the stamps it holds."""
        from tf2_ros import TransformException  # noqa: PLC0415

        when = self._time() if stamp_ns is None else self._time(nanoseconds=int(stamp_ns))
        try:
            ts = self.buffer.lookup_transform(target, source, when)
        except TransformException as exc:
            raise TfLookupError(_kind_of(exc), f"{target} <- {source}: {exc}") from None
        try:
            return transform_stamped_to_matrix(ts).matrix
        except (TransformError, BevMapperError) as exc:
            raise TfLookupError("invalid", f"{target} <- {source}: {exc}") from None


def make_tf_source(node, on_refused, future_tolerance_s: float, wrap=lambda where, fn: fn) -> Tf2Source | None:
    """A :class:`Tf2Source` on ``node``, or None where tf2_ros / tf2_msgs are not importable."""
    try:
        import tf2_msgs.msg  # noqa: F401, PLC0415
        import tf2_ros  # noqa: F401, PLC0415
    except ImportError:
        return None
    return Tf2Source(node, on_refused, future_tolerance_s, wrap)
