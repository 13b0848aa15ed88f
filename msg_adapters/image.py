"""``sensor_msgs/Image`` and ``sensor_msgs/CompressedImage`` <-> numpy arrays.

Arrays are always in RGB(A) channel order; the encoding only decides the order on the wire.
So ``bgr8`` messages decode to RGB and ``make_image(..., rgb, 'bgr8')`` stores BGR, and every
encoding round-trips ``array -> Image -> array`` unchanged.

==========  ===============  ======================
encoding    array shape      dtype
==========  ===============  ======================
rgb8, bgr8  ``(H, W, 3)``    uint8 (RGB)
rgba8,      ``(H, W, 4)``    uint8 (RGBA)
bgra8
mono8,      ``(H, W)``       uint8
8UC1
mono16,     ``(H, W)``       uint16 (native order)
16UC1
==========  ===============  ======================

``8UC3``/``8UC4`` (no channel order) and anything else are rejected. ``height``, ``width``,
``step`` and the data length are validated *before* any view of the buffer is made.
"""

from __future__ import annotations

import sys
from dataclasses import dataclass
from typing import Any

import cv2
import numpy as np

from .errors import EncodingError
from .factory import MessageFactory, make_header


@dataclass(frozen=True)
class _Enc:
    channels: int
    itemsize: int
    reverse: bool  # wire order is B,G,R(,A)


ENCODINGS: dict[str, _Enc] = {
    "rgb8": _Enc(3, 1, False),
    "bgr8": _Enc(3, 1, True),
    "rgba8": _Enc(4, 1, False),
    "bgra8": _Enc(4, 1, True),
    "mono8": _Enc(1, 1, False),
    "8UC1": _Enc(1, 1, False),
    "mono16": _Enc(1, 2, False),
    "16UC1": _Enc(1, 2, False),
}
#: Encodings whose channel order is undefined; rejected with a hint.
AMBIGUOUS_ENCODINGS = ("8UC2", "8UC3", "8UC4", "16UC3", "16UC4", "8SC3", "8SC4")
_NATIVE_BIG = sys.byteorder == "big"


def _lookup(encoding: str) -> _Enc:
    if encoding in ENCODINGS:
        return ENCODINGS[encoding]
    if encoding in AMBIGUOUS_ENCODINGS:
        raise EncodingError(
            f"image encoding {encoding!r} is ambiguous (no channel order); "
            "publish rgb8/bgr8/rgba8/bgra8 instead"
        )
    raise EncodingError(f"unsupported image encoding {encoding!r}; supported: {sorted(ENCODINGS)}")


def _byte_buffer(data: Any) -> np.ndarray:
    """Flat uint8 view of a message's ``data`` (numpy array, array.array, bytes, list)."""
    if isinstance(data, np.ndarray):
        if data.dtype == np.uint8:
            return data.reshape(-1)
        return np.ascontiguousarray(data).reshape(-1).view(np.uint8)
    if isinstance(data, (bytes, bytearray, memoryview)) or hasattr(data, "buffer_info"):
        return np.frombuffer(data, dtype=np.uint8)
    return np.asarray(data, dtype=np.uint8).reshape(-1)


def image_to_array(msg: Any, *, copy: bool = False) -> np.ndarray:
    """Decode a ``sensor_msgs/Image`` (rclpy or rosbags) into an array (see module table).

    Args:
        msg: the image message.
        copy: return an array that owns its memory. Without it the result may be a (possibly
            read-only) view of the message buffer.

    Raises:
        EncodingError: unsupported/ambiguous encoding, or size fields inconsistent with the data.
    """
    enc = _lookup(str(msg.encoding))
    h, w, step = int(msg.height), int(msg.width), int(msg.step)
    if h <= 0 or w <= 0:
        raise EncodingError(f"image has empty size {w}x{h}")
    row_bytes = w * enc.channels * enc.itemsize
    if step < row_bytes:
        raise EncodingError(
            f"image step {step} is smaller than one row of {w} px {msg.encoding} ({row_bytes} bytes)"
        )
    buf = _byte_buffer(msg.data)
    if buf.size != step * h:
        raise EncodingError(
            f"image data has {buf.size} bytes, expected step*height = {step}*{h} = {step * h}"
        )
    rows = buf.reshape(h, step)[:, :row_bytes]  # (H*step,) -> (H, step) -> (H, row_bytes)
    if enc.itemsize == 2:
        big = bool(msg.is_bigendian)
        rows = rows.view(">u2" if big else "<u2")  # (H, row_bytes) -> (H, W)
        if big != _NATIVE_BIG:
            rows = rows.astype(np.uint16)
            copy = False
    if enc.channels == 1:
        out = rows.reshape(h, w)
    else:
        out = rows.reshape(h, w, enc.channels)  # (H, W*C) -> (H, W, C)
        if enc.reverse:
            order = [2, 1, 0] if enc.channels == 3 else [2, 1, 0, 3]
            out = out[..., order]  # fancy indexing: already a copy
            copy = False
    if copy:
        out = out.copy()  # C-contiguous, owns its memory
    elif not out.flags.c_contiguous:
        out = np.ascontiguousarray(out)  # padded rows: compact them
    return out


def image_to_rgb(msg: Any) -> np.ndarray:
    """Decode any supported colour or 8-bit mono image to ``(H, W, 3)`` uint8 RGB."""
    arr = image_to_array(msg)
    if arr.dtype != np.uint8:
        raise EncodingError(f"cannot show {msg.encoding!r} image as RGB; expected an 8-bit encoding")
    if arr.ndim == 2:
        return np.repeat(arr[:, :, None], 3, axis=2)  # (H, W) -> (H, W, 3)
    return np.ascontiguousarray(arr[..., :3])


def image_to_labels(msg: Any) -> np.ndarray:
    """Decode a label image (``mono8`` / ``8UC1``) to ``(H, W)`` uint8 label ids."""
    if str(msg.encoding) not in ("mono8", "8UC1"):
        raise EncodingError(f"label images must be mono8 or 8UC1, got {msg.encoding!r}")
    return image_to_array(msg)


def array_to_image_fields(
    array: np.ndarray, encoding: str, *, step: int | None = None, bigendian: bool = False
) -> dict[str, Any]:
    """Wire fields of an Image for ``array`` (RGB(A) order): height, width, encoding, ... data.

    Args:
        array: see the module table for the shape and dtype each encoding takes.
        encoding: target encoding.
        step: row stride in bytes (``None`` = packed); rows are zero-padded up to it.
        bigendian: store 16-bit data big-endian (``is_bigendian = 1``).

    Returns:
        dict with ``height, width, encoding, is_bigendian, step`` (ints/str) and ``data``
        (flat uint8 numpy array).
    """
    enc = _lookup(encoding)
    arr = np.asarray(array)
    want_dtype = np.uint16 if enc.itemsize == 2 else np.uint8
    if arr.dtype != want_dtype:
        raise EncodingError(f"{encoding} needs a {np.dtype(want_dtype).name} array, got {arr.dtype}")
    if enc.channels == 1:
        if arr.ndim != 2:
            raise EncodingError(f"{encoding} needs an (H, W) array, got shape {arr.shape}")
    elif arr.ndim != 3 or arr.shape[2] != enc.channels:
        raise EncodingError(f"{encoding} needs an (H, W, {enc.channels}) array, got {arr.shape}")
    h, w = arr.shape[:2]
    if h == 0 or w == 0:
        raise EncodingError(f"cannot encode an empty image of shape {arr.shape}")
    if enc.reverse:
        arr = arr[..., [2, 1, 0] if enc.channels == 3 else [2, 1, 0, 3]]
    if enc.itemsize == 2:
        arr = arr.astype(">u2" if bigendian else "<u2", copy=False)
    row_bytes = w * enc.channels * enc.itemsize
    rows = np.ascontiguousarray(arr).reshape(h, -1).view(np.uint8)  # (H, W[, C]) -> (H, row_bytes)
    step = row_bytes if step is None else int(step)
    if step < row_bytes:
        raise EncodingError(f"step {step} is smaller than a row ({row_bytes} bytes)")
    if step > row_bytes:
        padded = np.zeros((h, step), dtype=np.uint8)
        padded[:, :row_bytes] = rows
        rows = padded
    return {
        "height": int(h),
        "width": int(w),
        "encoding": encoding,
        "is_bigendian": int(bool(bigendian) and enc.itemsize == 2),
        "step": int(step),
        "data": rows.reshape(-1),
    }


def make_image(
    factory: MessageFactory,
    array: np.ndarray,
    encoding: str,
    stamp_ns: int,
    frame_id: str,
    *,
    step: int | None = None,
    bigendian: bool = False,
) -> Any:
    """Build a ``sensor_msgs/Image`` from an array (see :func:`array_to_image_fields`)."""
    f = array_to_image_fields(array, encoding, step=step, bigendian=bigendian)
    f["data"] = factory.uint8_seq(f["data"])
    return factory.msg("sensor_msgs/msg/Image", header=make_header(factory, stamp_ns, frame_id), **f)


# ------------------------------------------------------------- CompressedImage
def compressed_to_array(msg: Any) -> np.ndarray:
    """Decode a ``sensor_msgs/CompressedImage`` (jpeg/png) to RGB ``(H, W, 3)`` or mono ``(H, W)``.

    16-bit PNGs decode to uint16. The format string is only used in error messages: OpenCV
    identifies the codec from the data itself.
    """
    buf = _byte_buffer(msg.data)
    if buf.size == 0:
        raise EncodingError(f"compressed image ({msg.format!r}) has no data")
    img = cv2.imdecode(buf, cv2.IMREAD_UNCHANGED)
    if img is None:
        raise EncodingError(f"cannot decode compressed image with format {msg.format!r}")
    if img.ndim == 3:
        code = cv2.COLOR_BGR2RGB if img.shape[2] == 3 else cv2.COLOR_BGRA2RGBA
        img = cv2.cvtColor(img, code)
    return img


def make_compressed_image(
    factory: MessageFactory, array: np.ndarray, fmt: str, stamp_ns: int, frame_id: str,
    *, quality: int = 90,
) -> Any:
    """Build a ``sensor_msgs/CompressedImage`` (``fmt`` 'jpeg' or 'png') from RGB or mono data."""
    if fmt not in ("jpeg", "png"):
        raise EncodingError(f"compressed format must be 'jpeg' or 'png', got {fmt!r}")
    arr = np.asarray(array)
    if arr.ndim == 3 and arr.shape[2] == 3:
        arr = cv2.cvtColor(arr, cv2.COLOR_RGB2BGR)
    elif arr.ndim != 2:
        raise EncodingError(f"compressed images take (H, W) or (H, W, 3) arrays, got {arr.shape}")
    params = [cv2.IMWRITE_JPEG_QUALITY, int(quality)] if fmt == "jpeg" else []
    ok, enc = cv2.imencode(".jpg" if fmt == "jpeg" else ".png", arr, params)
    if not ok:
        raise EncodingError(f"OpenCV could not encode a {arr.shape} {arr.dtype} image as {fmt}")
    return factory.msg(
        "sensor_msgs/msg/CompressedImage",
        header=make_header(factory, stamp_ns, frame_id),
        format=fmt,
        data=factory.uint8_seq(enc.reshape(-1)),
    )
