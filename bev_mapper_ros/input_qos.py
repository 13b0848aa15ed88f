"""QoS of the camera subscriptions (images and CameraInfo): ``image_reliability``.

A synchronized set is a burst: every camera publishes an image of the same instant at once (six
400x225 rgb8 images are 1.6 MB). Over a best-effort subscription DDS drops what does not fit its
buffers while the node's CPU is busy mapping, and the set is then mapped without that camera or
lost. Measured with Bi-Mapper, six cameras at 10 Hz on 2 cores (``bench/bench_table.py``, two
runs): best-effort publishers 8.9 / 9.2 sets/s mapped, reliable ones (``auto`` follows them)
10.0 / 10.1 sets/s with no set missing a camera.

But a reliable subscription does not match a best-effort publisher at all (DDS's request/offer
rule): nothing arrives. Camera drivers differ (``sensor_data`` QoS is best effort; most drivers
and ``ros2 bag play`` / ``bev-bag play`` offer reliable). Hence three settings:

* ``auto`` (default): like ``ros2 bag record``, subscribe with what the publishers offer:
  reliable when every publisher of the topic offers reliable, best effort when any offers
  best effort (or none is there yet; best effort matches both). The publishers are looked
  at again every :data:`RECHECK_S` and a subscription is re-created when that changes.
* ``reliable``: always reliable; a best-effort publisher does not match, and the node warns
  (throttled) that its images do not arrive.
* ``best_effort``: always best effort (``sensor_data``), the ROS default for sensor streams.

Reliable delivery costs nothing when the subscriber keeps up; when it does not, the
publisher's history (its own depth) absorbs the backlog and the node's one-slot mailbox still
maps only the newest set: latency does not build up in the node.
"""

from __future__ import annotations

from collections.abc import Callable, Iterable

from rclpy.event_handler import SubscriptionEventCallbacks
from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy

#: Messages kept per camera topic (as ``sensor_data``).
DEPTH = 5
#: Seconds between looks at the publishers of each camera topic (``auto``).
RECHECK_S = 1.0

_POLICY = {"reliable": ReliabilityPolicy.RELIABLE, "best_effort": ReliabilityPolicy.BEST_EFFORT}


def camera_qos(reliability: str) -> QoSProfile:
    """Keep-last :data:`DEPTH`, volatile, ``reliability`` (``'reliable'`` or ``'best_effort'``)."""
    return QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=DEPTH, reliability=_POLICY[reliability],
                      durability=DurabilityPolicy.VOLATILE)


def offered_reliability(publishers: Iterable) -> str | None:
    """What an ``auto`` subscription should use for these publishers (``TopicEndpointInfo``s):
    ``'reliable'`` when all offer reliable, ``'best_effort'`` when any offers best effort,
    ``None`` when there are none (keep what is there).
    """
    kinds = [p.qos_profile.reliability for p in publishers]
    if not kinds:
        return None
    return "reliable" if all(k == ReliabilityPolicy.RELIABLE for k in kinds) else "best_effort"


class CameraSubscription:
    """One camera topic's subscription with the ``image_reliability`` rule.

    ``setting``: one of :data:`~.config.RELIABILITY_CHOICES` (checked by NodeConfig);
    ``node``: the rclpy node; ``on_change(text)`` / ``on_incompatible(text)``: log lines for a
    re-subscription and for a publisher the subscription cannot match.
    """

    def __init__(self, node, msg_type, topic: str, callback: Callable, setting: str,
                 on_change: Callable[[str], None], on_incompatible: Callable[[str], None]) -> None:
        self.node, self.msg_type, self.topic, self.callback = node, msg_type, topic, callback
        self.setting = setting
        self._on_change, self._on_incompatible = on_change, on_incompatible
        self.reliability = setting
        if setting == "auto":  # what the publishers there now offer; none yet: best effort matches all
            self.reliability = offered_reliability(node.get_publishers_info_by_topic(topic)) or "best_effort"
        self.sub = self._create()

    def _create(self):
        events = SubscriptionEventCallbacks(incompatible_qos=self._incompatible)
        return self.node.create_subscription(self.msg_type, self.topic, self.callback, camera_qos(self.reliability),
                                             event_callbacks=events)

    def _incompatible(self, info) -> None:
        self._on_incompatible(
            f"{self.topic}: a publisher's QoS does not match this {self.reliability} subscription "
            f"({info.total_count} so far): its messages do not arrive; image_reliability:=auto "
            f"(or best_effort) subscribes to best-effort publishers")

    def recheck(self) -> bool:
        """``auto``: re-create the subscription if the publishers now offer other reliability;
        True when it did.
        """
        if self.setting != "auto":
            return False
        want = offered_reliability(self.node.get_publishers_info_by_topic(self.topic))
        if want is None or want == self.reliability:
            return False
        self.node.destroy_subscription(self.sub)
        self.reliability = want
        self.sub = self._create()
        self._on_change(f"{self.topic}: publishers offer {want}; subscribed {want}")
        return True


__all__ = ["DEPTH", "RECHECK_S", "CameraSubscription", "camera_qos", "offered_reliability"]
