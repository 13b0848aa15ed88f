"""Decoding the two big messages of a bag, ``sensor_msgs/Image`` and ``nav_msgs/OccupancyGrid``,
straight from their CDR bytes, the pixels and cells as numpy views of the bytes (no copy).

``rosbags`` builds a message through generated code that copies the array. These decoders read
the same fields (little-endian CDR, offsets aligned as rosbags aligns them, after the 4-byte
encapsulation header) into small objects with the attributes the adapters read
(:mod:`msg_adapters` is duck-typed). Anything unexpected (big-endian CDR, lengths that run past
the bytes, bytes left over where rosbags would refuse the message, text that is no UTF-8) makes
them return ``None``, and the caller deserializes with ``rosbags`` as before, so a damaged
message fails the way it always did. :func:`fast_deserializer` wraps a typestore's
deserializer with them.
"""

from __future__ import annotations

import struct
from collections.abc import Callable
from typing import Any

import numpy as np

_U32 = struct.Struct("<I")
_STAMP = struct.Struct("<iI")
_INFO = struct.Struct("<iIfII")  # map_load_time sec, nanosec, resolution, width, height
_POSE = struct.Struct("<7d")
_CDR_LE = (b"\x00\x01",)

IMAGE_TYPE = "sensor_msgs/msg/Image"
COMPRESSED_IMAGE_TYPE = "sensor_msgs/msg/CompressedImage"
GRID_TYPE = "nav_msgs/msg/OccupancyGrid"
#: Types of which one message that does not deserialize is one lost camera image, not damage to
#: the bag: :func:`fast_deserializer` hands it out as :class:`Undecodable`.
SKIPPABLE_TYPES = frozenset({IMAGE_TYPE, COMPRESSED_IMAGE_TYPE})


class _Fields:
    """A message's fields as attributes (what the adapters read)."""

    def __init__(self, **fields: Any) -> None:
        self.__dict__.update(fields)

    def __repr__(self) -> str:
        return f"{type(self).__name__}({', '.join(f'{k}={v!r}' for k, v in self.__dict__.items())})"


class Time(_Fields):
    """``builtin_interfaces/Time``: ``sec``, ``nanosec``."""


class Header(_Fields):
    """``std_msgs/Header``: ``stamp``, ``frame_id``."""


class Image(_Fields):
    """``sensor_msgs/Image`` with ``data`` a read-only uint8 view of the message bytes."""


class Point(_Fields):
    """``geometry_msgs/Point``."""


class Quaternion(_Fields):
    """``geometry_msgs/Quaternion``."""


class Pose(_Fields):
    """``geometry_msgs/Pose``."""


class MapMetaData(_Fields):
    """``nav_msgs/MapMetaData``."""


class OccupancyGrid(_Fields):
    """``nav_msgs/OccupancyGrid`` with ``data`` a read-only int8 view of the message bytes."""


class Undecodable:
    """A message of :data:`SKIPPABLE_TYPES` that does not deserialize (e.g. truncated): ``reason``
    says why. It has no header: the reader counts it as a decode error and skips it.
    """

    def __init__(self, msgtype: str, reason: str) -> None:
        self.msgtype, self.reason = msgtype, reason

    def __repr__(self) -> str:
        return f"Undecodable({self.msgtype!r}, {self.reason!r})"


def _align(pos: int, n: int) -> int:
    return pos + (-pos % n)


def _string(raw: bytes, pos: int) -> tuple[str, int]:
    """A CDR string at ``pos`` (aligned to 4): its text and the position after it."""
    pos = _align(pos, 4)
    (n,) = _U32.unpack_from(raw, pos)
    end = pos + 4 + n
    if n < 1 or end > len(raw) or raw[end - 1] != 0:
        raise ValueError("bad string")
    return bytes(raw[pos + 4:end - 1]).decode(), end


def _header(raw: bytes, pos: int) -> tuple[Header, int]:
    sec, nanosec = _STAMP.unpack_from(raw, pos)
    frame_id, pos = _string(raw, pos + 8)
    return Header(stamp=Time(sec=sec, nanosec=nanosec), frame_id=frame_id), pos


def _array(raw: bytes, pos: int, dtype) -> tuple[np.ndarray, int]:
    pos = _align(pos, 4)
    (n,) = _U32.unpack_from(raw, pos)
    end = pos + 4 + n
    if end > len(raw):
        raise ValueError("sequence runs past the message")
    return np.frombuffer(raw, dtype, n, pos + 4), end


def _body(raw: bytes) -> memoryview | None:
    """The CDR body after the 4-byte encapsulation header, when little-endian (else ``None``)."""
    if len(raw) < 4 or bytes(raw[:2]) not in _CDR_LE:
        return None
    return memoryview(raw)[4:]


def decode_image(raw: bytes) -> Image | None:
    """A ``sensor_msgs/Image`` from its CDR bytes, or ``None`` (see module docstring)."""
    body = _body(raw)
    if body is None:
        return None
    try:
        header, pos = _header(body, 0)
        pos = _align(pos, 4)
        height, width = struct.unpack_from("<II", body, pos)
        encoding, pos = _string(body, pos + 8)
        is_bigendian = body[pos]
        pos = _align(pos + 1, 4)
        (step,) = _U32.unpack_from(body, pos)
        data, pos = _array(body, pos + 4, np.uint8)
    except (struct.error, ValueError, IndexError, UnicodeDecodeError):
        return None
    if pos + 4 + 3 < len(raw):  # rosbags refuses bytes left over
        return None
    return Image(header=header, height=height, width=width, encoding=encoding, is_bigendian=is_bigendian,
                 step=step, data=data)


def decode_occupancy_grid(raw: bytes) -> OccupancyGrid | None:
    """A ``nav_msgs/OccupancyGrid`` from its CDR bytes, or ``None`` (see module docstring)."""
    body = _body(raw)
    if body is None:
        return None
    try:
        header, pos = _header(body, 0)
        pos = _align(pos, 4)
        sec, nanosec, resolution, width, height = _INFO.unpack_from(body, pos)
        pos = _align(pos + _INFO.size, 8)
        px, py, pz, ox, oy, oz, ow = _POSE.unpack_from(body, pos)
        data, pos = _array(body, pos + _POSE.size, np.int8)
    except (struct.error, ValueError, IndexError, UnicodeDecodeError):
        return None
    if pos + 4 + 3 < len(raw):
        return None
    info = MapMetaData(map_load_time=Time(sec=sec, nanosec=nanosec), resolution=resolution, width=width,
                       height=height, origin=Pose(position=Point(x=px, y=py, z=pz),
                                                  orientation=Quaternion(x=ox, y=oy, z=oz, w=ow)))
    return OccupancyGrid(header=header, info=info, data=data)


#: message type -> its decoder
DECODERS: dict[str, Callable[[bytes], Any]] = {IMAGE_TYPE: decode_image, GRID_TYPE: decode_occupancy_grid}


def fast_deserializer(deserialize: Callable[[bytes, str], Any]) -> Callable[[bytes, str], Any]:
    """``deserialize(raw, msgtype)`` with Images and OccupancyGrids decoded by this module
    (``deserialize`` itself for every other type and whatever these decoders refuse). ``raw``
    may be a memoryview (e.g. of a memory-mapped file): the decoders' arrays are views of it,
    ``deserialize`` gets a copy as bytes. An image (:data:`SKIPPABLE_TYPES`) that ``deserialize``
    refuses too comes back as :class:`Undecodable`, so that one bad image costs that image only.
    """
    def decode(raw: bytes | memoryview, msgtype: str) -> Any:
        fast = DECODERS.get(msgtype)
        msg = fast(raw) if fast is not None else None
        if msg is not None:
            return msg
        data = raw if type(raw) is bytes else bytes(raw)
        if msgtype not in SKIPPABLE_TYPES:
            return deserialize(data, msgtype)
        try:
            return deserialize(data, msgtype)
        except Exception as exc:  # noqa: BLE001 - rosbags raises several kinds for bad bytes
            return Undecodable(msgtype, f"message of {len(data)} bytes does not deserialize "
                                        f"({type(exc).__name__}: {exc})")

    return decode
