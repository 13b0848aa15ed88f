"""Issue #41: the compressed camera images of :mod:`compressed_cases` through the adapters the
bag reader and the node use (``compressed_to_rgb`` / ``compressed_to_labels`` with the camera's
calibrated size and ``check_format``): each is decoded as expected or refused with an
``EncodingError`` naming why, never another exception, never a silently different image, and a
header claiming a huge size is refused before anything of that size is allocated.
"""

from __future__ import annotations

import re
import tracemalloc

import compressed_cases as C
import numpy as np
import pytest
from rosbags.typesys import Stores, get_typestore

import msg_adapters as ma

FACTORY = ma.RosbagsFactory(get_typestore(Stores.ROS2_JAZZY))
W, H = 48, 32
_y, _x = np.mgrid[0:H, 0:W]
RGB = C.block_colours(np.dstack([(_x * 5) % 256, (_y * 7) % 256, (_x + _y) * 3 % 256]).astype(np.uint8))
LABELS = ((_x // 8 + _y // 8) % 5).astype(np.uint8)  # Label ids 0..4
GOOD = {"rgb": RGB, "labels": LABELS}
MIB = 2**20


def _msg(data: bytes, fmt: str):
    return FACTORY.msg("sensor_msgs/msg/CompressedImage", header=ma.make_header(FACTORY, 0, "cam"),
                       format=fmt, data=np.frombuffer(data, np.uint8))


def _decode(kind: str, msg):
    if kind == "rgb":
        return ma.compressed_to_rgb(msg, (W, H), check_format=True)
    return ma.compressed_to_labels(msg, (W, H), check_format=True)


@pytest.mark.parametrize("kind, case", [(k, c) for k in ("rgb", "labels") for c in C.cases(k)],
                         ids=lambda v: v if isinstance(v, str) else v.name)
def test_compressed_case(kind, case):
    data, fmt = case.make(GOOD[kind])
    tracemalloc.start()
    try:
        try:
            out = _decode(kind, _msg(data, fmt))
        except ma.EncodingError as exc:
            out = exc
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    assert peak < 4 * MIB + 20 * W * H, f"{case.name}: {peak} bytes allocated"
    if case.refused is not None:
        assert isinstance(out, ma.EncodingError), f"{case.name} was decoded"
        assert re.search(case.refused, str(out)), str(out)
        return
    assert isinstance(out, np.ndarray), f"{case.name}: {out}"
    if kind == "labels":
        np.testing.assert_array_equal(out, LABELS)  # PNG: exact
    else:
        assert out.shape == (H, W, 3) and out.dtype == np.uint8
        err = np.abs(out.astype(int) - RGB)  # the colours, not inverted nor in BGR order
        assert err.mean() <= 3 if "jpeg" in fmt else err.max() == 0, case.name


def test_cmyk_jpeg_is_a_four_component_jpeg_converted_to_the_same_colours():
    """The CMYK decision: converted, within 3 levels (Adobe's inverted inks, as OpenCV reads them)."""
    data = C.cmyk_jpeg(RGB)
    assert data[:2] == b"\xff\xd8" and b"Adobe" in data
    sof = data.index(b"\xff\xc0")
    assert data[sof + 9] == 4  # components
    out = ma.compressed_to_rgb(_msg(data, "jpeg"), (W, H), check_format=True)
    assert np.abs(out.astype(int) - RGB).max() <= 3


def test_the_table_covers_each_kind_of_defect():
    names = {c.name for c in C.CASES}
    for word in ("empty", "truncated", "wrong format", "PNG in a jpeg slot", "40000x40000", "CMYK", "16-bit"):
        assert any(word in n for n in names), word
