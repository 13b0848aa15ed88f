"""The camera images of issue #41's compressed-image fuzz: one table, shared by the adapter, bag
and node tests (``tests/msg_adapters/test_compressed_cases.py``, ``tests/bags/io/reader/
test_compressed_fuzz.py``, ``tests/bev_mapper_ros/test_node_hardening.py``).

Each :class:`Case` turns a good image (the camera's RGB or label image) into ``(data, format)``
of a ``sensor_msgs/CompressedImage`` and says what must come of it: ``ok`` (decoded; ``converted``
when the adapters convert it, e.g. CMYK to RGB) or the words of the ``EncodingError`` refusing
it. :func:`cmyk_jpeg` writes a 4-component (CMYK) baseline JPEG, which OpenCV cannot encode.
"""

from __future__ import annotations

import struct
import zlib
from collections.abc import Callable
from dataclasses import dataclass

import cv2
import numpy as np

PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"


def encode(ext: str, arr: np.ndarray) -> bytes:
    """``arr`` (RGB or mono, uint8 or uint16) as ``ext`` (``.png`` / ``.jpg``) bytes."""
    if arr.ndim == 3:
        arr = arr[..., ::-1]  # OpenCV writes BGR
    ok, enc = cv2.imencode(ext, np.ascontiguousarray(arr))
    assert ok
    return enc.tobytes()


def _chunk(kind: bytes, payload: bytes) -> bytes:
    return struct.pack(">I", len(payload)) + kind + payload + struct.pack(">I", zlib.crc32(kind + payload))


def png_claiming(width: int, height: int) -> bytes:
    """A ~100-byte grey PNG whose header claims ``width x height`` (one zero scanline of data)."""
    ihdr = struct.pack(">IIBBBBB", width, height, 8, 0, 0, 0, 0)
    idat = zlib.compress(b"\x00" * (1 + min(width, 4096)))
    return PNG_SIGNATURE + _chunk(b"IHDR", ihdr) + _chunk(b"IDAT", idat) + _chunk(b"IEND", b"")


def jpeg_claiming(data: bytes, width: int, height: int) -> bytes:
    """JPEG ``data`` with its SOF frame header's size replaced."""
    out, i = bytearray(data), 2
    while out[i + 1] not in (0xC0, 0xC1, 0xC2):
        i += 2 + struct.unpack(">H", out[i + 2:i + 4])[0]
    out[i + 5:i + 9] = struct.pack(">HH", height, width)
    return bytes(out)


# ------------------------------------------------------------------ a CMYK JPEG
_DC_BITS = [0, 1, 5, 1, 1, 1, 1, 1, 1, 0, 0, 0, 0, 0, 0, 0]  # JPEG's standard DC luminance table


def _segment(marker: int, payload: bytes) -> bytes:
    return bytes([0xFF, marker]) + struct.pack(">H", len(payload) + 2) + payload


def cmyk_jpeg(rgb: np.ndarray) -> bytes:
    """``rgb`` ``(H, W, 3)`` uint8 (each 8x8 block taken as the colour of its first pixel) as a CMYK
    JPEG in Adobe's convention (an APP14 "Adobe" marker, inverted ink values: what Photoshop and
    ImageMagick write): K = 1 - max(R, G, B), C = (1 - R - K) / (1 - K) ..., stored as 255 - ink.
    Baseline, quantisation 1, DC coefficients only (the blocks are flat).
    """
    h, w = rgb.shape[:2]  # any size: the blocks cover it, the decoder crops to (h, w)
    blocks = rgb[::8, ::8].astype(np.float64) / 255  # (H/8, W/8, 3): one colour per block
    k = 1 - blocks.max(axis=2, keepdims=True)
    ink = np.where(k < 1, (1 - blocks - k) / np.maximum(1 - k, 1e-9), 0)
    stored = np.round(255 * (1 - np.concatenate([ink, k], axis=2))).astype(int)  # (H/8, W/8, 4)
    codes, code, n = {}, 0, 0
    for length in range(1, 17):  # canonical Huffman codes of the DC table
        for _ in range(_DC_BITS[length - 1]):
            codes[n] = (code, length)
            code, n = code + 1, n + 1
        code <<= 1
    bits: list[int] = []

    def put(value: int, count: int) -> None:
        bits.extend((value >> (count - 1 - i)) & 1 for i in range(count))

    pred = [0, 0, 0, 0]
    for row in stored:
        for block in row:
            for c in range(4):
                dc = 8 * (int(block[c]) - 128)  # a flat block's DC coefficient
                diff, pred[c] = dc - pred[c], dc
                size = abs(diff).bit_length()
                put(*codes[size])
                if size:
                    put(diff if diff > 0 else (diff - 1) & ((1 << size) - 1), size)
                put(0, 1)  # end of block: the AC table's only code, "0"
    bits.extend([1] * (-len(bits) % 8))
    scan = bytearray()
    for i in range(0, len(bits), 8):
        scan.append(int("".join(map(str, bits[i:i + 8])), 2))
        if scan[-1] == 0xFF:
            scan.append(0)  # byte stuffing
    comps = range(1, 5)
    return (b"\xff\xd8" + _segment(0xEE, b"Adobe" + struct.pack(">HHHB", 100, 0, 0, 0))
            + _segment(0xDB, b"\x00" + bytes([1] * 64))
            + _segment(0xC0, struct.pack(">BHHB", 8, h, w, 4) + b"".join(bytes([c, 0x11, 0]) for c in comps))
            + _segment(0xC4, b"\x00" + bytes(_DC_BITS) + bytes(range(12)))
            + _segment(0xC4, b"\x10" + bytes([1] + [0] * 15) + b"\x00")
            + _segment(0xDA, b"\x04" + b"".join(bytes([c, 0]) for c in comps) + b"\x00\x3f\x00")
            + bytes(scan) + b"\xff\xd9")


def block_colours(rgb: np.ndarray) -> np.ndarray:
    """``rgb`` with each 8x8 block set to the colour of its top-left pixel (what cmyk_jpeg keeps)."""
    h, w = rgb.shape[:2]
    return np.repeat(np.repeat(rgb[::8, ::8], 8, axis=0), 8, axis=1)[:h, :w]


# ------------------------------------------------------------------ the table
@dataclass(frozen=True)
class Case:
    """One compressed camera image: ``make(good image) -> (data, format)``; ``kinds``: the image
    kinds it applies to; ``refused``: words of the refusal (``None``: decoded)."""

    name: str
    make: Callable[[np.ndarray], tuple[bytes, str]]
    kinds: tuple[str, ...]
    refused: str | None


def _rgb16(img: np.ndarray) -> np.ndarray:
    return img.astype(np.uint16) * 257


CASES = [
    Case("empty", lambda img: (b"", "jpeg"), ("rgb", "labels"), "has no data"),
    Case("truncated JPEG", lambda img: (encode(".jpg", img)[:-200], "jpeg"), ("rgb",),
         "truncated|corrupt"),
    Case("truncated PNG", lambda img: (encode(".png", img)[: len(encode(".png", img)) // 2], "png"),
         ("rgb", "labels"), "truncated|corrupt"),
    Case("wrong format string", lambda img: (encode(".png", img), "theora"), ("rgb", "labels"),
         "names no codec"),
    Case("PNG in a jpeg slot", lambda img: (encode(".png", img), "jpeg"), ("rgb", "labels"),
         "does not match the data, which is PNG"),
    Case("JPEG in a png slot", lambda img: (encode(".jpg", img), "png"), ("rgb",),
         "does not match the data, which is JPEG"),
    Case("compressedDepth format", lambda img: (encode(".png", img), "16UC1; compressedDepth png"),
         ("rgb", "labels"), "compressedDepth"),
    Case("PNG header claiming 40000x40000", lambda img: (png_claiming(40000, 40000), "png"),
         ("rgb", "labels"), "exceeds the maximum"),
    Case("PNG header claiming 8000x4000 (within limits, not the camera)",
         lambda img: (png_claiming(8000, 4000), "png"), ("rgb", "labels"), "is 8000x4000, expected"),
    Case("JPEG header claiming 60000x60000", lambda img: (jpeg_claiming(encode(".jpg", img), 60000, 60000),
                                                          "jpeg"), ("rgb",), "exceeds the maximum"),
    Case("BMP bytes", lambda img: (b"BM" + bytes(200), "png"), ("rgb", "labels"), "neither PNG nor JPEG"),
    # decisions: a CMYK JPEG is converted to RGB (OpenCV's libjpeg path, Adobe's convention);
    # a 16-bit PNG is refused (like a raw mono16/rgb16 Image: no 8-bit colour to show); label images
    # must be 8-bit PNG (JPEG changes label ids)
    Case("CMYK JPEG", lambda img: (cmyk_jpeg(img), "jpeg"), ("rgb",), None),
    Case("16-bit RGB PNG", lambda img: (encode(".png", _rgb16(img)), "png"), ("rgb",), "expected 8-bit data"),
    Case("16-bit label PNG", lambda img: (encode(".png", img.astype(np.uint16)), "png"), ("labels",),
         "must be 8-bit"),
    Case("JPEG label image", lambda img: (encode(".jpg", img), "jpeg"), ("labels",), "must be PNG"),
    Case("CMYK JPEG label image", lambda img: (cmyk_jpeg(np.dstack([img] * 3)), "jpeg"), ("labels",),
         "must be PNG"),
    Case("good, format ''", lambda img: (encode(".png", img), ""), ("rgb", "labels"), None),
    Case("good, format 'rgb8; jpeg compressed bgr8'",
         lambda img: (encode(".jpg", img), "rgb8; jpeg compressed bgr8"), ("rgb",), None),
]


def cases(kind: str) -> list[Case]:
    """The cases that apply to ``kind`` (``rgb`` or ``labels``)."""
    return [c for c in CASES if kind in c.kinds]
