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

Sizes are bounded before anything is decoded or copied: by the caller's ``expected_size``
(``(width, height)``, e.g. the calibrated camera's :attr:`~bev_mapper_core.geometry.camera.CameraModel.image_size`)
when given, and always by :class:`~msg_adapters.limits.AdapterLimits` (``max_image_side``,
``max_image_pixels``). A ``CompressedImage``'s size is read from its PNG/JPEG header
(:mod:`msg_adapters.image_header`), so a small message claiming a huge image is refused
without allocating it. Every defect, including a decoder failure, is an :class:`EncodingError`.
"""

from __future__ import annotations

import operator
import sys
from dataclasses import dataclass
from typing import Any

import cv2
import numpy as np

from bev_mapper_core.errors import ConfigError

from ._fields import UINT32_MAX, as_int, as_str, byte_buffer, field, short_repr
from .errors import EncodingError
from .factory import MessageFactory, make_header
from .image_header import compressed_image_header
from .limits import DEFAULT_LIMITS, AdapterLimits


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


def _expected(expected_size: Any) -> tuple[int, int] | None:
    """``expected_size`` as ``(width, height)`` ints, or None; a malformed one is the caller's bug."""
    if expected_size is None:
        return None
    try:
        w, h = (operator.index(v) for v in expected_size)
    except (TypeError, ValueError):
        raise ConfigError(f"expected_size must be (width, height) integers, got {expected_size!r}") from None
    if w <= 0 or h <= 0:
        raise ConfigError(f"expected_size must be positive, got {expected_size!r}")
    return int(w), int(h)


def check_image_size(width: int, height: int, what: str, expected_size: Any = None,
                     limits: AdapterLimits = DEFAULT_LIMITS) -> None:
    """Refuse an image size before decoding: empty, beyond ``limits`` or not ``expected_size``.

    Args:
        width, height: the size the message claims.
        what: the message, for error messages (``"image"``, ``"PNG image"``).
        expected_size: ``(width, height)`` the image must have, or None for any size.
        limits: ``max_image_side`` and ``max_image_pixels`` bound every image.

    Raises:
        EncodingError: the size is refused.
        ConfigError: ``expected_size`` is not a pair of positive integers.
    """
    expected = _expected(expected_size)
    if width <= 0 or height <= 0:
        raise EncodingError(f"{what} has empty size {width}x{height}")
    if width > limits.max_image_side or height > limits.max_image_side:
        raise EncodingError(
            f"{what} size {width}x{height} exceeds the maximum of {limits.max_image_side} px per side"
        )
    if width * height > limits.max_image_pixels:
        raise EncodingError(
            f"{what} size {width}x{height} exceeds the maximum of {limits.max_image_pixels} pixels"
        )
    if expected is not None and (width, height) != expected:
        raise EncodingError(f"{what} is {width}x{height}, expected {expected[0]}x{expected[1]}")


def image_to_array(msg: Any, *, copy: bool = False, expected_size: Any = None,
                   limits: AdapterLimits = DEFAULT_LIMITS) -> np.ndarray:
    """Decode a ``sensor_msgs/Image`` (rclpy or rosbags) into an array (see module table).

    Args:
        msg: the image message.
        copy: return an array that owns its memory. Without it the result may be a (possibly
            read-only) view of the message buffer.
        expected_size: ``(width, height)`` the image must have (e.g. the camera model's
            ``image_size``); None accepts any size within ``limits``.
        limits: size bounds (default :data:`~msg_adapters.limits.DEFAULT_LIMITS`).

    Raises:
        EncodingError: a field is missing or of the wrong type, unsupported/ambiguous encoding,
            a size refused by :func:`check_image_size`, or size fields inconsistent with the data.
    """
    where = "image"
    enc_name = as_str(field(msg, "encoding", EncodingError, where), "encoding", EncodingError, where)
    enc = _lookup(enc_name)
    h, w, step = (as_int(field(msg, k, EncodingError, where), k, EncodingError, where, 0, UINT32_MAX)
                  for k in ("height", "width", "step"))
    check_image_size(w, h, where, expected_size, limits)
    row_bytes = w * enc.channels * enc.itemsize
    if step < row_bytes:
        raise EncodingError(
            f"image step {step} is smaller than one row of {w} px {enc_name} ({row_bytes} bytes)"
        )
    buf = byte_buffer(field(msg, "data", EncodingError, where), "data", EncodingError, where)
    if buf.size != step * h:
        raise EncodingError(
            f"image data has {buf.size} bytes, expected step*height = {step}*{h} = {step * h}"
        )
    rows = buf.reshape(h, step)[:, :row_bytes]  # (H*step,) -> (H, step) -> (H, row_bytes)
    if enc.itemsize == 2:
        big = bool(as_int(field(msg, "is_bigendian", EncodingError, where), "is_bigendian",
                          EncodingError, where, 0, 255))
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


def image_to_rgb(msg: Any, expected_size: Any = None, *,
                 limits: AdapterLimits = DEFAULT_LIMITS) -> np.ndarray:
    """Decode any supported colour or 8-bit mono image to ``(H, W, 3)`` uint8 RGB.

    ``expected_size`` and ``limits`` as in :func:`image_to_array`.

    Raises:
        EncodingError: as :func:`image_to_array`, or a 16-bit encoding.
    """
    arr = image_to_array(msg, expected_size=expected_size, limits=limits)
    if arr.dtype != np.uint8:
        raise EncodingError(f"cannot show {msg.encoding!r} image as RGB; expected an 8-bit encoding")
    if arr.ndim == 2:
        return np.repeat(arr[:, :, None], 3, axis=2)  # (H, W) -> (H, W, 3)
    return np.ascontiguousarray(arr[..., :3])


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
#: Words of a ``CompressedImage.format`` naming each codec the adapters decode (image_transport
#: writes ``"jpeg"``, ``"png"`` or ``"rgb8; jpeg compressed bgr8"``; some recorders ``"jpg"``).
FORMAT_WORDS = {"jpeg": ("jpeg", "jpg"), "png": ("png",)}


def format_problem(fmt: Any, codec: str) -> str | None:
    """Why a ``CompressedImage.format`` string does not describe data of ``codec`` (``'jpeg'`` or
    ``'png'``, from the data's signature), else ``None``: it must be a string naming that codec and
    no other (``compressedDepth``, whose data is not a plain PNG, is refused). An empty string is
    accepted: the codec is the data's.
    """
    if not isinstance(fmt, str):
        return f"format must be a string, got {short_repr(fmt)}"
    text = fmt.strip().lower()
    if not text:
        return None
    if "compresseddepth" in text:
        return f"format {fmt!r} is image_transport's compressedDepth, not a colour or label image"
    named = [c for c, words in FORMAT_WORDS.items() if any(w in text for w in words)]
    if not named:
        return f"format {fmt!r} names no codec the adapters decode ({', '.join(FORMAT_WORDS)})"
    if named != [codec]:
        return f"format {fmt!r} does not match the data, which is {codec.upper()}"
    return None


def compressed_to_array(msg: Any, expected_size: Any = None, *,
                        limits: AdapterLimits = DEFAULT_LIMITS, check_format: bool = False) -> np.ndarray:
    """Decode a ``sensor_msgs/CompressedImage`` (jpeg/png) to RGB ``(H, W, 3)``, RGBA
    ``(H, W, 4)`` (PNG with alpha) or mono ``(H, W)``.

    16-bit PNGs decode to uint16. The codec is identified from the data's signature; the format
    string is used in error messages, and with ``check_format`` it must name that codec
    (:func:`format_problem`, checked before decoding). The size claimed by the PNG/JPEG header is checked
    (:func:`check_image_size`) *before* decoding, so nothing larger than ``expected_size`` (when
    given) or ``limits.max_image_pixels`` is ever allocated.

    Args:
        msg: the CompressedImage.
        expected_size: ``(width, height)`` the image must have (e.g. the camera model's
            ``image_size``); None accepts any size within ``limits``.
        limits: size bounds (default :data:`~msg_adapters.limits.DEFAULT_LIMITS`).
        check_format: refuse a ``format`` string that names another codec than the data's, or none.

    Raises:
        EncodingError: no data, neither PNG nor JPEG, a refused format (``check_format``), a truncated or invalid header, a size
            refused before decoding, or any decoder failure (corrupt or truncated data).
    """
    raw_fmt = getattr(msg, "format", None)
    fmt = short_repr(raw_fmt)
    buf = byte_buffer(field(msg, "data", EncodingError, "compressed image"), "data", EncodingError,
                      f"compressed image ({fmt})")
    if buf.size == 0:
        raise EncodingError(f"compressed image ({fmt}) has no data")
    try:
        header = compressed_image_header(buf)
    except EncodingError as exc:
        raise EncodingError(f"cannot decode compressed image ({fmt}): {exc}") from None
    what = f"compressed {header.format.upper()} image ({fmt})"
    if check_format:
        problem = format_problem(raw_fmt, header.format)
        if problem:
            raise EncodingError(f"{what}: {problem}")
    check_image_size(header.width, header.height, what, expected_size, limits)
    try:
        img = cv2.imdecode(buf, cv2.IMREAD_UNCHANGED)
    except cv2.error as exc:
        raise EncodingError(f"cannot decode {what}: {str(exc).strip().splitlines()[-1]}") from None
    if img is None:
        raise EncodingError(f"cannot decode {what}: corrupt or truncated data")
    if img.shape[:2] != (header.height, header.width):
        raise EncodingError(
            f"{what} decoded to {img.shape[1]}x{img.shape[0]}, its header says {header.width}x{header.height}"
        )
    if img.ndim == 3:
        if img.shape[2] not in (3, 4):
            raise EncodingError(f"{what} decoded to {img.shape[2]} channels; expected 3 or 4")
        code = cv2.COLOR_BGR2RGB if img.shape[2] == 3 else cv2.COLOR_BGRA2RGBA
        img = cv2.cvtColor(img, code, dst=img)  # in place: no second full-size buffer
    return img


def compressed_to_rgb(msg: Any, expected_size: Any = None, *, limits: AdapterLimits = DEFAULT_LIMITS,
                      check_format: bool = False) -> np.ndarray:
    """Decode a ``sensor_msgs/CompressedImage`` to ``(H, W, 3)`` uint8 RGB, as :func:`image_to_rgb`
    does an Image: through :func:`compressed_to_array` (its checks; ``expected_size``, ``limits`` and
    ``check_format`` as there), an 8-bit grey image repeated into R, G and B, RGBA without alpha.

    Raises:
        EncodingError: as :func:`compressed_to_array`, or a 16-bit PNG.
    """
    arr = compressed_to_array(msg, expected_size, limits=limits, check_format=check_format)
    if arr.dtype != np.uint8:
        raise EncodingError(f"cannot show a {arr.dtype} compressed image as RGB; expected 8-bit data")
    if arr.ndim == 2:
        return np.repeat(arr[:, :, None], 3, axis=2)  # (H, W) -> (H, W, 3)
    return np.ascontiguousarray(arr[..., :3])  # (H, W, 4) -> (H, W, 3): alpha dropped


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
