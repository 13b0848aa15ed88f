"""Building ROS messages for two worlds: rclpy message classes and rosbags dataclasses.

Builders in this package never import a message class themselves; they ask a *factory*:

* :class:`RclpyFactory` imports ``<pkg>.msg`` lazily with :mod:`importlib` (nothing ROS is
  imported when this module is imported) and fills array fields the way the generated
  setters accept fast: ``array.array`` for dynamic arrays (``uint8[]`` -> ``'B'``, ``int8[]``
  -> ``'b'``, ``float64[]`` -> ``'d'``) and float64 ``numpy`` arrays for fixed-size arrays.
* :class:`RosbagsFactory` takes classes from ``typestore.types`` and fills every array field
  with a ``numpy`` array of the field's dtype (what the CDR serializer expects). rosbags
  dataclasses have no defaults, so builders pass *all* fields, nested ones included.

Reading is duck-typed and needs no factory: rclpy and rosbags messages expose the same field
names. Time conversions (``stamp_ns`` <-> ``(sec, nanosec)``) live here and only here.
"""

from __future__ import annotations

import array
import importlib
from typing import Any, Protocol

import numpy as np

from ._fields import as_int, field
from .errors import MessageFactoryError, StampError

_NS_PER_S = 1_000_000_000
#: ``builtin_interfaces/Time`` field ranges: ``sec`` is an int32, ``nanosec`` a uint32.
#: A usable ``builtin_interfaces/Time``: non-negative seconds (int32), normalized nanoseconds
#: (rclpy's ``Time`` refuses negative times; ``nanosec`` >= 1e9 is not a normalized stamp).
_SEC_RANGE = (0, 2**31 - 1)
_NANOSEC_RANGE = (0, 10**9 - 1)


# ------------------------------------------------------------------------ time
def ns_to_sec_nanosec(stamp_ns: int) -> tuple[int, int]:
    """Split integer nanoseconds into ``(sec, nanosec)`` with ``0 <= nanosec < 1e9``."""
    stamp_ns = int(stamp_ns)
    sec, nanosec = divmod(stamp_ns, _NS_PER_S)
    return int(sec), int(nanosec)


def stamp_to_ns(stamp: Any) -> int:
    """Integer nanoseconds of a ``builtin_interfaces/Time`` (anything with ``sec``/``nanosec``).

    Raises:
        StampError: a field is missing, not an integer, or outside its range (``sec`` in
            ``[0, 2**31)``, ``nanosec`` in ``[0, 1e9)``).
    """
    sec = as_int(field(stamp, "sec", StampError, "stamp"), "sec", StampError, "stamp", *_SEC_RANGE)
    nanosec = as_int(field(stamp, "nanosec", StampError, "stamp"), "nanosec", StampError, "stamp",
                     *_NANOSEC_RANGE)
    return sec * _NS_PER_S + nanosec


def header_stamp_ns(msg: Any) -> int:
    """Integer nanoseconds of ``msg.header.stamp``.

    Raises:
        StampError: no ``header.stamp``, or a stamp :func:`stamp_to_ns` refuses.
    """
    return stamp_to_ns(field(msg, "header.stamp", StampError, "message"))


def normalize_typename(typename: str) -> tuple[str, str]:
    """``'sensor_msgs/msg/Image'`` or ``'sensor_msgs/Image'`` -> ``('sensor_msgs', 'Image')``."""
    parts = typename.split("/")
    if len(parts) == 3 and parts[1] == "msg":
        return parts[0], parts[2]
    if len(parts) == 2:
        return parts[0], parts[1]
    raise MessageFactoryError(f"invalid message type name {typename!r}; expected 'pkg/msg/Name'")


# --------------------------------------------------------------------- protocol
class MessageFactory(Protocol):
    """What builders need from a message world."""

    #: Short name of the world, ``'rclpy'`` or ``'rosbags'``.
    name: str

    def msg(self, typename: str, **fields: Any) -> Any:
        """Instantiate message ``typename`` (``'pkg/msg/Name'``) with ``fields``."""

    def uint8_seq(self, data: np.ndarray) -> Any:
        """Value for a ``uint8[]`` field from a flat uint8 array."""

    def int8_seq(self, data: np.ndarray) -> Any:
        """Value for an ``int8[]`` field from a flat int8 array."""

    def float64_seq(self, data: Any) -> Any:
        """Value for a ``float64[]`` (dynamic) field."""

    def float64_fixed(self, data: Any, size: int) -> Any:
        """Value for a ``float64[size]`` (fixed) field."""


def _flat(data: Any, dtype: Any) -> np.ndarray:
    return np.ascontiguousarray(np.asarray(data, dtype=dtype).ravel())


def _fixed(data: Any, size: int) -> np.ndarray:
    arr = _flat(data, np.float64)
    if arr.size != size:
        raise MessageFactoryError(f"fixed float64 array needs {size} values, got {arr.size}")
    return arr


class RclpyFactory:
    """Factory for rclpy message classes, imported lazily from ``<pkg>.msg``.

    Args:
        check_fields: passed to every constructor when not ``None`` (Jazzy messages accept
            it; ``True`` makes the generated setters type-check every field, as in tests).
            ``None`` keeps the default (env ``ROS_PYTHON_CHECK_FIELDS``).
    """

    name = "rclpy"

    def __init__(self, check_fields: bool | None = None) -> None:
        self._classes: dict[str, type] = {}
        self._extra = {} if check_fields is None else {"check_fields": bool(check_fields)}

    def cls(self, typename: str) -> type:
        """The rclpy message class of ``typename`` (cached)."""
        if typename not in self._classes:
            pkg, name = normalize_typename(typename)
            try:
                module = importlib.import_module(f"{pkg}.msg")
                self._classes[typename] = getattr(module, name)
            except (ImportError, AttributeError) as exc:
                raise MessageFactoryError(
                    f"cannot import message type {pkg}/msg/{name} for rclpy: {exc}"
                ) from None
        return self._classes[typename]

    def msg(self, typename: str, **fields: Any) -> Any:
        """Instantiate an rclpy message (field types are checked by the generated setters)."""
        return self.cls(typename)(**self._extra, **fields)

    def uint8_seq(self, data: np.ndarray) -> array.array:
        """``uint8[]`` field value (rclpy: ``array.array("B")``)."""
        out = array.array("B")
        out.frombytes(_flat(data, np.uint8).tobytes())
        return out

    def int8_seq(self, data: np.ndarray) -> array.array:
        """``int8[]`` field value (rclpy: ``array.array("b")``)."""
        out = array.array("b")
        out.frombytes(_flat(data, np.int8).tobytes())
        return out

    def float64_seq(self, data: Any) -> array.array:
        """``float64[]`` field value (rclpy: ``array.array("d")``)."""
        out = array.array("d")
        out.frombytes(_flat(data, np.float64).tobytes())
        return out

    def float64_fixed(self, data: Any, size: int) -> np.ndarray:
        """``float64[size]`` field value (checked length, a numpy array)."""
        return _fixed(data, size)


class RosbagsFactory:
    """Factory for the dataclasses of a rosbags typestore (e.g. ``Stores.ROS2_JAZZY``)."""

    name = "rosbags"

    def __init__(self, typestore: Any) -> None:
        self.typestore = typestore

    def cls(self, typename: str) -> type:
        """The rosbags dataclass of ``typename``."""
        pkg, name = normalize_typename(typename)
        try:
            return self.typestore.types[f"{pkg}/msg/{name}"]
        except KeyError:
            raise MessageFactoryError(
                f"message type {pkg}/msg/{name} is not in the rosbags typestore"
            ) from None

    def msg(self, typename: str, **fields: Any) -> Any:
        """Instantiate a rosbags message dataclass (all fields must be given)."""
        try:
            return self.cls(typename)(**fields)
        except TypeError as exc:
            raise MessageFactoryError(f"cannot build {typename}: {exc}") from None

    def uint8_seq(self, data: np.ndarray) -> np.ndarray:
        """``uint8[]`` field value (rosbags: a flat numpy array)."""
        return _flat(data, np.uint8)

    def int8_seq(self, data: np.ndarray) -> np.ndarray:
        """``int8[]`` field value (rosbags: a flat numpy array)."""
        return _flat(data, np.int8)

    def float64_seq(self, data: Any) -> np.ndarray:
        """``float64[]`` field value (rosbags: a flat numpy array)."""
        return _flat(data, np.float64)

    def float64_fixed(self, data: Any, size: int) -> np.ndarray:
        """``float64[size]`` field value (checked length, a numpy array)."""
        return _fixed(data, size)


# ------------------------------------------------------------- common builders
def make_time(factory: MessageFactory, stamp_ns: int) -> Any:
    """``builtin_interfaces/Time`` for integer nanoseconds."""
    sec, nanosec = ns_to_sec_nanosec(stamp_ns)
    return factory.msg("builtin_interfaces/msg/Time", sec=sec, nanosec=nanosec)


def make_header(factory: MessageFactory, stamp_ns: int, frame_id: str) -> Any:
    """``std_msgs/Header`` with ``stamp_ns`` and ``frame_id``."""
    return factory.msg(
        "std_msgs/msg/Header", stamp=make_time(factory, stamp_ns), frame_id=str(frame_id)
    )


def make_vector3(factory: MessageFactory, v: Any) -> Any:
    """``geometry_msgs/Vector3`` from a 3-vector."""
    x, y, z = (float(c) for c in np.asarray(v, dtype=np.float64).reshape(3))
    return factory.msg("geometry_msgs/msg/Vector3", x=x, y=y, z=z)


def make_point(factory: MessageFactory, v: Any) -> Any:
    """``geometry_msgs/Point`` from a 3-vector."""
    x, y, z = (float(c) for c in np.asarray(v, dtype=np.float64).reshape(3))
    return factory.msg("geometry_msgs/msg/Point", x=x, y=y, z=z)


def make_quaternion(factory: MessageFactory, q_xyzw: Any) -> Any:
    """``geometry_msgs/Quaternion`` from ``(x, y, z, w)``."""
    x, y, z, w = (float(c) for c in q_xyzw)
    return factory.msg("geometry_msgs/msg/Quaternion", x=x, y=y, z=z, w=w)
