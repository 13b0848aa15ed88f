"""Format and size of PNG / JPEG data, read from the header bytes without decoding.

A ``sensor_msgs/CompressedImage`` of a few hundred bytes can claim any size: the decoder
allocates the whole output image before it reads a pixel, so a 16000 x 16000 PNG of 875 KB
costs 768 MB. :func:`compressed_image_header` reads the claimed size from the header alone
(PNG: the ``IHDR`` chunk; JPEG: the ``SOFn`` frame header) so that the size can be checked
before anything is decoded.
"""

from __future__ import annotations

import struct
from dataclasses import dataclass

from .errors import EncodingError

PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"
#: PNG: width and height are 31-bit (PNG specification, section 11.2.2).
PNG_MAX_SIDE = 2**31 - 1
JPEG_SOI = b"\xff\xd8"
JPEG_EOI = b"\xff\xd9"
_JPEG_SOS = 0xDA
# Start-of-frame markers SOF0..SOF15, except DHT (C4), JPG (C8) and DAC (CC).
_JPEG_SOF = frozenset(range(0xC0, 0xD0)) - {0xC4, 0xC8, 0xCC}
# Markers without a length field: TEM and RST0..RST7.
_JPEG_STANDALONE = frozenset({0x01, *range(0xD0, 0xD8)})


@dataclass(frozen=True)
class CompressedHeader:
    """What the header of compressed image data claims."""

    format: str  #: ``"png"`` or ``"jpeg"``, from the data's signature
    width: int
    height: int


def compressed_image_header(data: bytes) -> CompressedHeader:
    """Format and size of PNG or JPEG ``data`` (bytes-like), from its header only.

    JPEG data must also contain its end-of-image marker after the frame header: its absence
    means the data was truncated (scan data never contains that byte pair).

    Raises:
        EncodingError: the data is neither PNG nor JPEG, the header is truncated or invalid
            (zero size, a marker or chunk out of place), or a JPEG lacks its end marker.
    """
    data = bytes(data)
    if data.startswith(PNG_SIGNATURE):
        return _png_header(data)
    if data.startswith(JPEG_SOI):
        return _jpeg_header(data)
    raise EncodingError(
        f"compressed image data is neither PNG nor JPEG (starts with {data[:8].hex(' ') or 'nothing'})"
    )


def _png_header(data: bytes) -> CompressedHeader:
    # signature (8) | IHDR length (4) = 13 | "IHDR" | width (4) | height (4) | 5 more bytes | CRC
    ihdr = data[8:33]
    if len(ihdr) < 25:
        raise EncodingError(f"PNG data of {len(data)} bytes is truncated inside its IHDR header")
    length, kind, width, height = struct.unpack(">I4sII", ihdr[:16])
    if kind != b"IHDR" or length != 13:
        raise EncodingError(f"PNG data does not start with an IHDR chunk (got {kind!r} of {length} bytes)")
    if not (1 <= width <= PNG_MAX_SIDE and 1 <= height <= PNG_MAX_SIDE):
        raise EncodingError(f"PNG header claims an invalid size {width}x{height}")
    return CompressedHeader("png", width, height)


def _jpeg_header(data: bytes) -> CompressedHeader:
    n, i = len(data), 2
    while True:
        if i >= n:
            raise EncodingError(f"JPEG data of {n} bytes ends before its frame header (SOF)")
        if data[i] != 0xFF:
            raise EncodingError(f"JPEG data: marker expected at byte {i}, got 0x{data[i]:02x}")
        while i < n and data[i] == 0xFF:  # a marker may be preceded by fill bytes 0xFF
            i += 1
        if i >= n:
            raise EncodingError(f"JPEG data of {n} bytes ends before its frame header (SOF)")
        marker = data[i]
        i += 1
        if marker in _JPEG_STANDALONE:
            continue
        if marker == _JPEG_SOS or marker in (0xD8, 0xD9) or marker == 0x00:
            raise EncodingError(f"JPEG data has marker 0x{marker:02x} before its frame header (SOF)")
        if i + 2 > n:
            raise EncodingError(f"JPEG data of {n} bytes is truncated inside a marker segment")
        length = (data[i] << 8) | data[i + 1]
        if length < 2:
            raise EncodingError(f"JPEG marker 0x{marker:02x} has an invalid length {length}")
        if marker in _JPEG_SOF:
            # length (2) | precision (1) | height (2) | width (2) | components (1)
            if length < 8 or i + 8 > n:
                raise EncodingError(f"JPEG data of {n} bytes is truncated inside its frame header")
            height, width = struct.unpack(">HH", data[i + 3:i + 7])
            if width == 0 or height == 0:  # height 0: "defined later by a DNL marker"
                raise EncodingError(f"JPEG frame header claims an unsupported size {width}x{height}")
            if data.find(JPEG_EOI, i + length) < 0:
                raise EncodingError(f"JPEG data of {n} bytes is truncated (no end-of-image marker)")
            return CompressedHeader("jpeg", width, height)
        i += length
