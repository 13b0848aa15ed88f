"""``bev-bag play BAG``: publish a bag on live ROS 2 topics with rclpy, like ``ros2 bag play``.

Messages keep the bag's types. Each one is re-serialized to CDR with the rosbags typestore
(exact: the bytes rclpy itself would produce, up to padding) and published as a serialized
message, so no per-type conversion code is needed; :func:`to_rclpy` gives the same message as
an rclpy object (``rclpy.serialization.deserialize_message``). Topics whose type has no rclpy
message class here (e.g. ``tf2_msgs/msg/TFMessage`` where tf2_msgs is neither in a ROS
distribution nor built by ``scripts/setup_venv.sh``) are skipped with a warning; ``/tf`` and
``/tf_static`` are played like any topic where it is.

Playback is paced by the log times divided by ``--rate``; ``--start-offset`` skips the start
(latched topics are still published first); ``--loop`` starts over at the end; ``--clock``
publishes ``/clock`` (rosgraph_msgs/Clock) with the bag time; subscribers that should follow it
(the mapper node) run with ``use_sim_time:=true``. Latched topics (``/tf_static``
and topics recorded with transient-local durability) get transient-local publishers, so late
subscribers still receive them. Ctrl-C stops cleanly (exit 0).

ROS settings come from the environment (``ROS_DOMAIN_ID``, ``ROS_AUTOMATIC_DISCOVERY_RANGE``,
``RMW_IMPLEMENTATION``); ``--domain-id`` overrides the domain.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path
from typing import Any

from msg_adapters import RclpyFactory
from msg_adapters.errors import MessageFactoryError

from ..errors import BagContentError, BagCorruptError, BagError
from ..io import topics as T
from ..io.reader import BagReader

HELP = "publish a bag on live ROS 2 topics (paced by its timestamps, like ros2 bag play)"


def jazzy_typestore():
    """The rosbags typestore of ROS 2 Jazzy's standard messages."""
    from rosbags.typesys import Stores, get_typestore  # noqa: PLC0415

    return get_typestore(Stores.ROS2_JAZZY)


def to_cdr(typestore, msg: Any, msgtype: str) -> bytes:
    """CDR bytes (with encapsulation header) of a rosbags message, as rclpy publishes them."""
    return bytes(typestore.serialize_cdr(msg, msgtype))


def to_rclpy(typestore, msg: Any, msgtype: str, factory: RclpyFactory | None = None) -> Any:
    """The rclpy message equal to a rosbags message (via CDR; generic and exact)."""
    from rclpy.serialization import deserialize_message  # noqa: PLC0415

    cls = (factory or RclpyFactory()).cls(msgtype)
    return deserialize_message(to_cdr(typestore, msg, msgtype), cls)


def latched_topics(reader: BagReader) -> set[str]:
    """``/tf_static`` and every topic the bag records with transient-local offered QoS."""
    return {T.TF_STATIC} | reader.latched_topics


class Player:
    """Publishes the messages of a bag with rclpy publishers, paced by their log times."""

    def __init__(self, node, reader: BagReader, topics: list[str], *, rate: float = 1.0,
                 clock_hz: float | None = None, start_offset_s: float = 0.0) -> None:
        from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy  # noqa: PLC0415

        self.node, self.reader, self.rate = node, reader, float(rate)
        self.start_offset_ns = int(round(start_offset_s * 1e9))
        self.typestore = jazzy_typestore()
        factory = RclpyFactory()
        latched = latched_topics(reader)
        self.pubs: dict[str, Any] = {}
        self.skipped: dict[str, str] = {}
        for topic in topics:
            msgtype = reader.topics[topic].msgtype
            try:
                cls = factory.cls(msgtype)
            except MessageFactoryError:
                self.skipped[topic] = msgtype
                continue
            if msgtype not in self.typestore.types:
                self.skipped[topic] = msgtype
                continue
            if topic in latched:
                qos = QoSProfile(history=HistoryPolicy.KEEP_LAST,
                                 depth=max(1, reader.topics[topic].count),
                                 reliability=ReliabilityPolicy.RELIABLE,
                                 durability=DurabilityPolicy.TRANSIENT_LOCAL)
            else:
                qos = QoSProfile(depth=10)
            self.pubs[topic] = node.create_publisher(cls, topic, qos)
        self.latched = latched & set(self.pubs)
        self.clock_pub = None
        self.clock_period = None
        if clock_hz:
            try:
                from rosgraph_msgs.msg import Clock  # noqa: PLC0415
            except ImportError:
                print("warning: rosgraph_msgs is not importable; --clock ignored", file=sys.stderr)
            else:
                self._Clock = Clock
                self.clock_pub = node.create_publisher(Clock, "/clock", QoSProfile(depth=1))
                self.clock_period = 1.0 / clock_hz
        self.published = 0

    def _publish_clock(self, bag_ns: int) -> None:
        msg = self._Clock()
        msg.clock.sec, msg.clock.nanosec = divmod(int(bag_ns), 1_000_000_000)
        self.clock_pub.publish(msg)

    def _wait(self, target: float, wall0: float, start_ns: int) -> None:
        """Sleep until monotonic ``target``, publishing /clock meanwhile when enabled."""
        while True:
            now = time.monotonic()
            if now >= target:
                return
            if self.clock_pub is None:
                time.sleep(target - now)
                return
            self._publish_clock(start_ns + int((now - wall0) * self.rate * 1e9))
            time.sleep(min(target - now, self.clock_period))

    def play_once(self) -> int:
        """One pass over the bag; returns the number of published messages.

        Raises:
            BagCorruptError: after publishing everything before the damage.
        """
        n = 0
        wall0 = start_ns = None
        for m in self.reader.messages(list(self.pubs)):
            if start_ns is None:
                start_ns = m.log_ns + self.start_offset_ns
                wall0 = time.monotonic()
            if m.log_ns < start_ns:
                if m.topic not in self.latched:
                    continue
            else:
                self._wait(wall0 + (m.log_ns - start_ns) / 1e9 / self.rate, wall0, start_ns)
                if self.clock_pub is not None:
                    self._publish_clock(m.log_ns)
            self.pubs[m.topic].publish(to_cdr(self.typestore, m.msg, m.msgtype))
            n += 1
            self.published += 1
        return n

    def wait_for_subscribers(self, topics: list[str], timeout_s: float) -> list[str]:
        """Wait until each of ``topics`` has a subscriber; returns those still without one."""
        end = time.monotonic() + timeout_s
        pubs = dict(self.pubs)
        if self.clock_pub is not None:
            pubs["/clock"] = self.clock_pub
        while True:
            waiting = [t for t in topics if pubs[t].get_subscription_count() == 0]
            if not waiting or time.monotonic() >= end:
                return waiting
            time.sleep(0.05)

    def wait_for_acks(self, timeout_s: float = 2.0) -> None:
        """Give reliable subscribers a moment to receive the last messages."""
        from rclpy.duration import Duration  # noqa: PLC0415

        end = time.monotonic() + timeout_s
        for pub in self.pubs.values():
            left = end - time.monotonic()
            if left <= 0:
                return
            pub.wait_for_all_acked(Duration(nanoseconds=int(left * 1e9)))


def configure(p: argparse.ArgumentParser) -> None:
    """Arguments of ``bev-bag play``."""
    p.add_argument("bag", type=Path, help="rosbag2 directory, .mcap or .db3 file")
    p.add_argument("--rate", type=float, default=1.0, help="playback speed factor (default 1)")
    p.add_argument("--loop", action="store_true", help="start over at the end, until Ctrl-C")
    p.add_argument("--clock", nargs="?", type=float, const=40.0, default=None, metavar="HZ",
                   help="publish /clock with the bag time (at HZ while waiting, default 40); subscribers "
                        "must use it: run them with use_sim_time:=true (e.g. mapper_node --ros-args "
                        "-p use_sim_time:=true), else they compare the bag's stamps with the wall clock")
    p.add_argument("--topics", nargs="+", default=None, metavar="TOPIC",
                   help="only these topics (default: all)")
    p.add_argument("--start-offset", type=float, default=0.0, metavar="S",
                   help="skip the first S seconds of the bag (latched topics still published)")
    p.add_argument("--delay", type=float, default=0.0, metavar="S",
                   help="wait S seconds after creating the publishers (discovery) before playing")
    p.add_argument("--wait-for", nargs="+", default=None, metavar="TOPIC",
                   help="before playing, wait until these topics (or /clock) have a subscriber")
    p.add_argument("--wait-timeout", type=float, default=30.0, metavar="S",
                   help="give up waiting for subscribers after S seconds (then play anyway)")
    p.add_argument("--domain-id", type=int, default=None, help="ROS domain id (default: env)")
    p.add_argument("--quiet", action="store_true", help="no summary lines")


def _check(args: argparse.Namespace, reader: BagReader) -> list[str]:
    if not args.rate > 0:
        raise BagError(f"--rate must be > 0, got {args.rate}")
    if args.start_offset < 0 or args.delay < 0:
        raise BagError("--start-offset and --delay must be >= 0")
    if args.clock is not None and not args.clock > 0:
        raise BagError(f"--clock rate must be > 0 Hz, got {args.clock}")
    if args.domain_id is not None and not 0 <= args.domain_id <= 232:
        raise BagError(f"--domain-id must be in [0, 232], got {args.domain_id}")
    topics = list(reader.topics)
    unknown = [t for t in (args.wait_for or []) if not (t == "/clock" and args.clock) and (
        t not in reader.topics or (args.topics and t not in args.topics))]
    if unknown:
        raise BagContentError(f"--wait-for topics are not played: {unknown}")
    if args.topics:
        missing = [t for t in args.topics if t not in reader.topics]
        if missing:
            raise BagContentError(f"topics not in the bag: {missing}; it has {sorted(topics)}")
        topics = [t for t in topics if t in set(args.topics)]
    return topics


def run(args: argparse.Namespace) -> int:
    """Run ``bev-bag play``: 0 at the end (or on Ctrl-C), 1 on a damaged bag."""
    with BagReader(args.bag) as reader:
        topics = _check(args, reader)
        try:
            import rclpy  # noqa: PLC0415
            from rclpy.signals import SignalHandlerOptions  # noqa: PLC0415
        except ImportError as exc:
            raise BagError(f"rclpy is not available: {exc}") from None
        context = rclpy.Context()
        rclpy.init(context=context, domain_id=args.domain_id,
                   signal_handler_options=SignalHandlerOptions.NO)
        node = rclpy.create_node("bev_bag_player", context=context)
        t0 = time.monotonic()
        damage = None
        try:
            player = Player(node, reader, topics, rate=args.rate, clock_hz=args.clock,
                            start_offset_s=args.start_offset)
            if player.skipped:
                names = ", ".join(f"{t} ({m})" for t, m in sorted(player.skipped.items()))
                print(f"warning: skipping topics whose type has no rclpy message class here: "
                      f"{names}", file=sys.stderr)
            if not player.pubs:
                raise BagContentError("no topic of the bag can be published with rclpy here")
            if not args.quiet:
                print(f"playing {len(player.pubs)} topic(s) from {args.bag} at rate {args.rate:g}"
                      f"{' (loop)' if args.loop else ''}", flush=True)
            waiting = [t for t in (args.wait_for or [])
                       if t in player.pubs or (t == "/clock" and player.clock_pub is not None)]
            if len(waiting) < len(args.wait_for or []):
                raise BagContentError("--wait-for names a skipped topic")
            waiting = player.wait_for_subscribers(waiting, args.wait_timeout)
            if waiting:
                print(f"warning: no subscriber after {args.wait_timeout:g} s on {waiting}; "
                      "playing anyway", file=sys.stderr)
            time.sleep(args.delay)
            while True:
                try:
                    player.play_once()
                except BagCorruptError as exc:
                    damage = str(exc)
                    break
                if not args.loop:
                    break
            player.wait_for_acks()
            if not args.quiet:
                print(f"published {player.published} message(s) in {time.monotonic() - t0:.1f} s",
                      flush=True)
        except KeyboardInterrupt:
            if not args.quiet:
                print("stopped (Ctrl-C)", file=sys.stderr, flush=True)
        finally:
            node.destroy_node()
            rclpy.try_shutdown(context=context)
    if damage:
        print(f"error: {damage}", file=sys.stderr)
        return 1
    return 0
