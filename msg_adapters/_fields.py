"""Type-checked reading of duck-typed message fields.

Messages reach the adapters from rclpy, from rosbags and from anything else that has the right
attribute names, so a field may be missing, ``None``, a string or an out-of-range number. These
helpers turn every such defect into the calling adapter's own exception type (``err``) with a
message naming the field, instead of an ``AttributeError``/``TypeError``/``OverflowError``.
"""

from __future__ import annotations

import array
import math
import numbers
import operator
from typing import Any

import numpy as np

from .errors import AdapterError

#: Range of the ROS ``uint32`` fields (sizes, binning, ROI, ``step``).
UINT32_MAX = 2**32 - 1

# numpy dtype kinds accepted as numbers: bool, signed int, unsigned int, float
_NUMERIC_KINDS = "biuf"


def field(msg: Any, path: str, err: type[AdapterError], where: str) -> Any:
    """``msg.<path>`` (dotted), or ``err`` when a field on the way is missing."""
    obj = msg
    for name in path.split("."):
        try:
            obj = getattr(obj, name)
        except AttributeError:
            raise err(f"{where}: has no field {path!r}") from None
    return obj


def as_int(value: Any, name: str, err: type[AdapterError], where: str, lo: int = 0,
           hi: int = UINT32_MAX) -> int:
    """An integer field (``int`` or numpy integer; not float, bool or str) within ``[lo, hi]``."""
    if isinstance(value, (bool, np.bool_)):
        raise err(f"{where}: {name} must be an integer, got a bool")
    try:
        v = operator.index(value)
    except TypeError:
        raise err(f"{where}: {name} must be an integer, got {type(value).__name__} {short_repr(value)}") from None
    if not lo <= v <= hi:
        raise err(f"{where}: {name} = {v} is outside [{lo}, {hi}]")
    return int(v)


def as_float(value: Any, name: str, err: type[AdapterError], where: str, finite: bool = True) -> float:
    """A real number (int, float or numpy scalar; not bool, str, complex or None), finite unless
    ``finite=False``.
    """
    if isinstance(value, (bool, np.bool_)) or not isinstance(value, numbers.Real):
        raise err(f"{where}: {name} must be a number, got {type(value).__name__} {short_repr(value)}")
    try:
        v = float(value)
    except OverflowError:  # an int beyond float range
        raise err(f"{where}: {name} = {short_repr(value)} is out of range") from None
    if finite and not math.isfinite(v):
        raise err(f"{where}: {name} is not finite ({v})")
    return v


def as_floats(values: Any, name: str, err: type[AdapterError], where: str) -> np.ndarray:
    """A flat float64 array of a numeric sequence field; non-finite values are left to the caller."""
    if values is None or isinstance(values, (str, bytes, bytearray)):
        raise err(f"{where}: {name} must be a sequence of numbers, got {type(values).__name__}")
    try:
        arr = np.asarray(values)
        if arr.dtype.kind == "O":
            arr = arr.astype(np.float64)
    except (TypeError, ValueError, OverflowError) as exc:
        raise err(f"{where}: {name} is not a sequence of numbers: {exc}") from None
    if arr.dtype.kind not in _NUMERIC_KINDS or arr.dtype.kind == "b":
        raise err(f"{where}: {name} must hold numbers, got dtype {arr.dtype}")
    return arr.astype(np.float64, copy=False).reshape(-1)


def as_str(value: Any, name: str, err: type[AdapterError], where: str) -> str:
    """A string field."""
    if not isinstance(value, str):
        raise err(f"{where}: {name} must be a string, got {type(value).__name__} {short_repr(value)}")
    return value


def byte_buffer(data: Any, name: str, err: type[AdapterError], where: str) -> np.ndarray:
    """Flat uint8 view of a ``uint8[]`` field (numpy array, ``array.array``, bytes, list of ints).

    Numeric numpy arrays and ``array.array`` are viewed as their raw bytes (no copy for
    contiguous data); lists must hold integers 0..255.
    """
    if isinstance(data, np.ndarray):
        if data.dtype == np.uint8:
            return data.reshape(-1)
        if data.dtype.kind in _NUMERIC_KINDS:
            return np.ascontiguousarray(data).reshape(-1).view(np.uint8)
    elif isinstance(data, (bytes, bytearray, memoryview, array.array)):
        try:
            return np.frombuffer(data, dtype=np.uint8)
        except (TypeError, ValueError, BufferError) as exc:
            raise err(f"{where}: {name} is not a readable byte buffer: {exc}") from None
    elif data is None or isinstance(data, str):
        raise err(f"{where}: {name} must be bytes, got {type(data).__name__}")
    try:
        arr = np.asarray(data)
    except (TypeError, ValueError) as exc:
        raise err(f"{where}: {name} is not a byte sequence: {exc}") from None
    if arr.dtype.kind not in "iu" and arr.size > 0:
        raise err(f"{where}: {name} must hold bytes (integers 0..255), got dtype {arr.dtype}")
    if arr.size and (arr.min() < 0 or arr.max() > 255):
        raise err(f"{where}: {name} holds values outside 0..255")
    return arr.astype(np.uint8).reshape(-1)


def short_repr(value: Any, n: int = 40) -> str:
    """``repr`` cut to ``n`` characters, for error messages."""
    try:
        text = repr(value)
    except Exception:  # noqa: BLE001 - a broken __repr__ must not hide the real error
        text = f"<{type(value).__name__}>"
    return text if len(text) <= n else text[: n - 3] + "..."
