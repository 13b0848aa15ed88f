"""Checks of a bag's messages before they are used, and the count of what failed.

A bag is untrusted input. :class:`~bags.io.reader.BagReader` checks

* each topic's *type* against the role its name gives it (:func:`expected_type`): a topic of
  the wrong type cannot be used at all, so it is an error naming the topic
  (:func:`type_problems`);
* each message's header *stamp* (:func:`stamp_problem`, the adapters' rule): negative seconds,
  nanoseconds outside ``[0, 1e9)`` or a stamp that is not a pair of integers; and a stamp that jumps away
  from its topic's log times by more than :data:`MAX_STAMP_DRIFT_NS` (:class:`StampDrift`);
* the *size* of a GT grid before anything is allocated for it (:func:`check_grid_size`):
  at most :data:`MAX_GRID_CELLS` cells;
* each decoded image against its camera's calibration (size).

Messages that fail a per-message check are skipped and counted in :class:`InputIssues`
(per topic, with the first problem as an example); the replay reports the counts in
``metrics.json`` and marks its outputs incomplete.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

from bev_mapper_core.geometry.grid import MAX_GRID_CELLS
from msg_adapters import AdapterError, header_stamp_ns

from ..errors import BagContentError
from . import topics as T

_NS = 1_000_000_000

#: Most a topic's header stamps may drift against its log (receive) times in one bag. The
#: offset stamp - log time is nearly constant in a recording (milliseconds of latency; sim
#: time or a replayed drive shifts it, but by a constant), so a stamp years away from its
#: neighbours' is a corrupted value, not a late message.
MAX_STAMP_DRIFT_NS = 3600 * _NS

#: What converting an untrusted message can raise besides :class:`AdapterError` (fields of
#: unexpected types or shapes in a message whose schema differs from the standard one).
DECODE_ERRORS = (AdapterError, AttributeError, TypeError, ValueError, OverflowError,
                 IndexError, KeyError)


def expected_types(topic: str) -> tuple[str, ...] | None:
    """The message types a topic's name allows, or ``None`` for topics the tool ignores: a
    camera's image topic carries ``sensor_msgs/Image`` or ``sensor_msgs/CompressedImage``, its
    ``.../compressed`` transport ``CompressedImage`` only.
    """
    if topic in (T.TF_STATIC, T.TF):
        return (T.TF_TYPE,)
    if topic == T.ODOM:
        return (T.ODOM_TYPE,)
    if (topic in (T.GROUND_VISIBILITY, T.ANY_VISIBILITY) or T.parse_gt_topic(topic)
            or T.parse_truth_topic(topic)):
        return (T.GRID_TYPE,)
    parsed = T.parse_camera_topic(topic)
    if parsed:
        if parsed[1] == "camera_info":
            return (T.CAMERA_INFO_TYPE,)
        return (T.COMPRESSED_IMAGE_TYPE,) if T.is_compressed_topic(topic) else T.IMAGE_TYPES
    return None


def expected_type(topic: str) -> str | None:
    """The message type a topic's name calls for (the first of :func:`expected_types`), or
    ``None`` for topics the tool ignores.
    """
    want = expected_types(topic)
    return want[0] if want else None


def type_problems(types: dict[str, str]) -> list[str]:
    """``'<topic> carries <type>, expected <type>'`` for every topic of the wrong type."""
    out = []
    for topic, msgtype in sorted(types.items()):
        want = expected_types(topic)
        if want is not None and msgtype not in want:
            out.append(f"topic {topic} carries {msgtype or 'an unknown type'}, expected {' or '.join(want)}")
    return out


def check_types(path: Any, types: dict[str, str], topics: set[str] | None = None) -> None:
    """Raise :class:`BagContentError` if any of ``topics`` (default all) has the wrong type."""
    used = types if topics is None else {t: v for t, v in types.items() if t in topics}
    problems = type_problems(used)
    if problems:
        raise BagContentError(f"{path}: " + "; ".join(problems))


def stamp_problem(msg: Any) -> str | None:
    """Why ``msg.header.stamp`` is not a usable stamp (the adapters' rule,
    :func:`msg_adapters.header_stamp_ns`: non-negative seconds, nanosec in ``[0, 1e9)``), else ``None``.
    """
    try:
        header_stamp_ns(msg)
    except AdapterError as exc:
        return str(exc)
    return None


class StampDrift:
    """Per topic, the offset stamp - log time of its first valid message; a later message
    whose offset differs from it by more than :data:`MAX_STAMP_DRIFT_NS` has an implausible
    stamp (see there).
    """

    def __init__(self) -> None:
        self._ref: dict[str, int] = {}

    def problem(self, topic: str, stamp: int, log_ns: int) -> str | None:
        """Why ``stamp`` is implausible for a message of ``topic`` logged at ``log_ns``."""
        offset = stamp - int(log_ns)
        ref = self._ref.setdefault(topic, offset)
        if abs(offset - ref) <= MAX_STAMP_DRIFT_NS:
            return None
        return (f"header stamp {stamp / _NS:.3f} s is {(offset - ref) / _NS:+.0f} s away from the "
                f"topic's stamp-to-log-time offset (at most {MAX_STAMP_DRIFT_NS // _NS} s)")


def check_grid_size(info: Any) -> None:
    """Raise :class:`AdapterError` unless an OccupancyGrid ``info`` has a size in
    ``[1, MAX_GRID_CELLS]`` cells (checked before anything of that size is allocated).
    """
    try:
        w, h = int(info.width), int(info.height)
    except DECODE_ERRORS as exc:
        raise AdapterError(f"OccupancyGrid info has no usable size: {exc}") from None
    if w <= 0 or h <= 0:
        raise AdapterError(f"OccupancyGrid has empty size {w}x{h}")
    if w * h > MAX_GRID_CELLS:
        raise AdapterError(f"OccupancyGrid claims {w}x{h} = {w * h} cells, more than the "
                           f"{MAX_GRID_CELLS} a BEV grid may have")


@dataclass
class TopicIssues:
    """Problems of one topic: skipped messages by cause, and the first problem met."""

    decode_errors: int = 0
    bad_stamps: int = 0
    example: str = ""


class InputIssues:
    """Messages a reader skipped because they were damaged, per topic, and cameras that have
    images but no calibration (see module docstring).
    """

    def __init__(self) -> None:
        self.topics: dict[str, TopicIssues] = {}
        self.cameras_without_calibration: list[str] = []

    def _topic(self, topic: str, detail: str) -> TopicIssues:
        t = self.topics.setdefault(topic, TopicIssues())
        if not t.example:
            t.example = detail
        return t

    def decode_error(self, topic: str, detail: str) -> None:
        """Count a message of ``topic`` that could not be decoded or used."""
        self._topic(topic, detail).decode_errors += 1

    def bad_stamp(self, topic: str, detail: str) -> None:
        """Count a message of ``topic`` skipped for its header stamp."""
        self._topic(topic, detail).bad_stamps += 1

    @property
    def decode_errors(self) -> int:
        """Messages that could not be decoded, all topics."""
        return sum(t.decode_errors for t in self.topics.values())

    @property
    def bad_stamps(self) -> int:
        """Messages skipped for invalid stamps, all topics."""
        return sum(t.bad_stamps for t in self.topics.values())

    def __bool__(self) -> bool:
        return bool(self.topics or self.cameras_without_calibration)

    def summary(self) -> str | None:
        """One sentence for the damage note, ``None`` when nothing went wrong."""
        parts = []
        for kind, label in (("decode_errors", "could not be decoded"),
                            ("bad_stamps", "had invalid header stamps")):
            hit = {n: t for n, t in self.topics.items() if getattr(t, kind)}
            if hit:
                total = sum(getattr(t, kind) for t in hit.values())
                first = next(iter(hit.items()))
                parts.append(f"{total} message(s) {label} and were skipped "
                             f"({', '.join(f'{n}: {getattr(t, kind)}' for n, t in hit.items())}; "
                             f"first: {first[0]}: {first[1].example})")
        if self.cameras_without_calibration:
            parts.append(f"camera(s) {self.cameras_without_calibration} have images but no "
                         "CameraInfo topic and were not used")
        return "; ".join(parts) or None

    def to_metrics(self) -> dict:
        """The ``metrics.json`` keys of the counts."""
        return {
            "decode_errors": self.decode_errors,
            "bad_stamps": self.bad_stamps,
            "cameras_without_calibration": list(self.cameras_without_calibration),
            "input_problems": {n: {"decode_errors": t.decode_errors, "bad_stamps": t.bad_stamps,
                                   "first": t.example} for n, t in sorted(self.topics.items())},
        }
