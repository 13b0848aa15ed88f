"""Hardening of the message adapters (issue #10): the reported defects, then a seeded fuzz.

The first half reproduces each defect of the fuzz campaign with its exact input (these tests
fail on the adapters before the fix). The second half feeds a few thousand randomly mutated
messages to every adapter: the only allowed outcomes are a valid result or the adapter's own
exception type, never another exception, a hang, or an allocation beyond what the limits allow.
Outcome counts per adapter are printed (``pytest -s``).
"""

from __future__ import annotations

import array
import functools
import struct
import time
import tracemalloc
import types
import zlib
from collections import Counter

import cv2
import numpy as np
import pytest

import msg_adapters as ma
from bev_mapper_core.errors import BevMapperError, GridError
from bev_mapper_core.geometry.camera import DISTORTION_MODELS, CameraModel, Roi
from bev_mapper_core.geometry.grid import OCC_MAX, OCC_UNKNOWN, BevGrid
from bev_mapper_core.geometry.rig import surround6
from bev_mapper_core.geometry.transforms import make_transform, rpy_to_rot
from bev_mapper_core.labels.label_maps import label_map
from msg_adapters.image import AMBIGUOUS_ENCODINGS
from msg_adapters.image_header import _JPEG_SOF, PNG_SIGNATURE

LIMITS = ma.DEFAULT_LIMITS
MIB = 2**20


def _factory():
    from rosbags.typesys import Stores, get_typestore

    return ma.RosbagsFactory(get_typestore(Stores.ROS2_JAZZY))


FACTORY = _factory()
# A 1600 x 900 camera delivering full resolution: the size of the issue's examples.
CAM = CameraModel(K=((1266.4, 0, 816.3), (0, 1266.4, 491.5), (0, 0, 1)), width=1600, height=900)


def _info(model: CameraModel = CAM, **changes):
    """A CameraInfo of ``model`` with fields replaced (``roi_<name>`` for the ROI's)."""
    msg = ma.make_camera_info(FACTORY, model, 0, "cam")
    for name, value in changes.items():
        if name.startswith("roi_"):
            setattr(msg.roi, name[4:], value)
        elif name in ("fx", "fy", "cx", "cy"):
            k = np.array(msg.k, dtype=np.float64)
            k[{"fx": 0, "cx": 2, "fy": 4, "cy": 5}[name]] = value
            msg.k = k
        else:
            setattr(msg, name, value)
    return msg


def _peak_bytes(fn, *args, **kwargs):
    """``(result or exception, peak bytes traced while fn ran)``: numpy and OpenCV's output
    arrays are traced by tracemalloc."""
    tracemalloc.start()
    try:
        try:
            out = fn(*args, **kwargs)
        except Exception as exc:  # noqa: BLE001 - returned for the caller to judge
            out = exc
        return out, tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()


# ---------------------------------------------------------------- PNG / JPEG bytes
def _chunk(kind: bytes, payload: bytes) -> bytes:
    return struct.pack(">I", len(payload)) + kind + payload + struct.pack(">I", zlib.crc32(kind + payload))


def png_bytes(width: int, height: int, *, color_type: int = 0, bit_depth: int = 8,
              idat: bytes | None = None) -> bytes:
    """A PNG whose IDAT holds all-zero scanlines (or ``idat``); palette PNGs get a 1-entry PLTE."""
    bits = {0: 1, 2: 3, 3: 1, 4: 2, 6: 4}[color_type] * bit_depth
    if idat is None:
        row = b"\x00" * (1 + (width * bits + 7) // 8)  # filter byte + packed pixels
        comp = zlib.compressobj(9)
        idat = b"".join(comp.compress(row) for _ in range(height)) + comp.flush()
    ihdr = struct.pack(">IIBBBBB", width, height, bit_depth, color_type, 0, 0, 0)
    plte = _chunk(b"PLTE", b"\x10\x20\x30") if color_type == 3 else b""
    return PNG_SIGNATURE + _chunk(b"IHDR", ihdr) + plte + _chunk(b"IDAT", idat) + _chunk(b"IEND", b"")


def with_png_size(data: bytes, width: int, height: int, fix_crc: bool = True) -> bytes:
    """``data`` with the IHDR's width/height replaced (and its CRC recomputed)."""
    out = bytearray(data)
    out[16:24] = struct.pack(">II", width, height)
    if fix_crc:
        out[29:33] = struct.pack(">I", zlib.crc32(bytes(out[12:29])))
    return bytes(out)


def _sof_offset(data: bytes) -> int:
    """Offset of the first SOFn marker's length field in JPEG ``data``."""
    i = 2
    while True:
        marker, length = data[i + 1], struct.unpack(">H", data[i + 2:i + 4])[0]
        if marker in _JPEG_SOF:
            return i + 2
        i += 2 + length


def with_jpeg_size(data: bytes, width: int, height: int) -> bytes:
    """``data`` with the SOF frame header's width/height replaced."""
    out = bytearray(data)
    at = _sof_offset(data)
    out[at + 3:at + 7] = struct.pack(">HH", height, width)
    return bytes(out)


def _compressed(data, fmt="png"):
    return FACTORY.msg("sensor_msgs/msg/CompressedImage", header=ma.make_header(FACTORY, 0, "cam"),
                       format=fmt, data=np.frombuffer(bytes(data), np.uint8))


def _encode(ext: str, arr: np.ndarray, *params) -> bytes:
    ok, enc = cv2.imencode(ext, arr, list(params))
    assert ok
    return enc.tobytes()


# =========================================================== 1. empty delivered image
@pytest.mark.parametrize(
    "changes",
    [dict(binning_y=1000), dict(binning_x=2**32 - 1),
     dict(roi_x_offset=10, roi_y_offset=20, roi_width=300, roi_height=1, binning_y=2)],
    ids=["binning_y=1000-on-900px", "binning_x=2^32-1", "roi-height-1-binning_y-2"],
)
def test_issue10_camera_info_with_empty_delivered_image_is_refused(changes):
    """Before the fix these were accepted and ``model.image_size`` raised later, in the node."""
    with pytest.raises(ma.CalibrationMessageError, match="empty") as info:
        ma.camera_info_to_model(_info(**changes))
    assert "binning" in str(info.value)


def test_camera_info_binning_and_roi_that_leave_pixels_are_kept():
    m = ma.camera_info_to_model(_info(binning_x=1600, binning_y=900))  # 1x1 px: empty it is not
    assert m.image_size == (1, 1)
    m = ma.camera_info_to_model(_info(roi_x_offset=10, roi_y_offset=20, roi_width=300, roi_height=2,
                                      binning_y=2))
    assert m.image_size == (300, 1)


@pytest.mark.parametrize(
    "changes, match",
    [
        (dict(roi_width=0, roi_height=5), "ROI .* is empty"),
        (dict(roi_x_offset=3), "ROI .* is empty"),  # offsets with a zero size: not the full image
        (dict(roi_x_offset=1500, roi_width=200, roi_height=10), "outside the 1600x900 sensor"),
        (dict(binning_x=None), "binning_x must be an integer"),
        (dict(roi_height=-1, roi_width=5), r"roi.height = -1 is outside"),
    ],
)
def test_camera_info_roi_and_binning_rejections(changes, match):
    with pytest.raises(ma.CalibrationMessageError, match=match):
        ma.camera_info_to_model(_info(**changes))


# ====================================================== 2. implausible calibrations
@pytest.mark.parametrize(
    "changes, match",
    [
        (dict(fx=1e-300), "fx = 1e-300 px is implausible"),
        (dict(fx=1e308), "fx = 1e\\+308 px is implausible"),
        (dict(fy=1e-300), "fy = 1e-300 px is implausible"),
        (dict(cx=1e20), "principal point cx = 1e\\+20 px"),
        (dict(cy=-1e20), "principal point cy = -1e\\+20 px"),
        (dict(width=2**32 - 1), "image size 4294967295x900 is outside"),
        (dict(height=2**32 - 1), "image size 1600x4294967295 is outside"),
    ],
    ids=["fx=1e-300", "fx=1e308", "fy=1e-300", "cx=1e20", "cy=-1e20", "width=2^32-1", "height=2^32-1"],
)
def test_issue10_implausible_calibration_is_refused(changes, match):
    with pytest.raises(ma.CalibrationMessageError, match=match):
        ma.camera_info_to_model(_info(**changes))


def test_plausibility_bounds_are_the_limits_fields():
    """The bounds are AdapterLimits' fields, inclusive, and a caller's own limits apply."""
    W, H = CAM.width, CAM.height
    lo, hi, m = LIMITS.min_focal_per_size, LIMITS.max_focal_per_size, LIMITS.principal_point_margin
    for changes in (dict(fx=lo * W), dict(fx=hi * W), dict(fy=lo * H), dict(cx=-m * W),
                    dict(cx=(1 + m) * W), dict(cy=(1 + m) * H)):
        ma.camera_info_to_model(_info(**changes))  # on the bound: accepted
    for changes in (dict(fx=lo * W * 0.999), dict(fx=hi * W * 1.001), dict(cx=-m * W - 1),
                    dict(cy=(1 + m) * H + 1)):
        with pytest.raises(ma.CalibrationMessageError, match="implausible|too far off"):
            ma.camera_info_to_model(_info(**changes))
    side = LIMITS.max_image_side
    big = CameraModel(K=((side, 0, side / 2), (0, 1000, 500), (0, 0, 1)), width=side, height=1000)
    assert ma.camera_info_to_model(_info(big)).image_size == (side, 1000)
    with pytest.raises(ma.CalibrationMessageError, match="outside 1..16384"):
        ma.camera_info_to_model(_info(big, width=side + 1))
    tight = ma.AdapterLimits(max_image_pixels=CAM.width * CAM.height - 1)
    with pytest.raises(ma.CalibrationMessageError, match="exceeds 1439999 pixels"):
        ma.camera_info_to_model(_info(), limits=tight)
    with pytest.raises(BevMapperError, match="min_focal_per_size"):
        ma.AdapterLimits(min_focal_per_size=200.0)


@pytest.mark.parametrize(
    "changes, match",
    [
        (dict(d=np.array([0.1, 1e300, 0, 0, 0])), "exceeds the plausible magnitude"),
        (dict(d=np.array([0.1, float("nan"), 0, 0, 0])), "non-finite"),
        (dict(d=np.array([0.1, 0.0, 0.0, 0.0])), "takes 5 coefficients, got 4"),
        (dict(d=np.array([0.1] * 8), distortion_model="equidistant"), "takes 4 coefficients, got 8"),
        (dict(k=np.array([1266.4, 5000.0, 816.3, 0, 1266.4, 491.5, 0, 0, 1])), "skew"),
        (dict(k=np.array([1266.4, 0, 816.3, 0, 1266.4, 491.5, 0, 0, 2])), "last row"),
        (dict(k=["1266.4"] * 9), "must hold numbers"),
        (dict(d=None), "D must be a sequence of numbers"),
        (dict(distortion_model=None), "distortion_model must be a string"),
        (dict(width=1600.0), "width must be an integer"),
    ],
)
def test_camera_info_value_and_type_rejections(changes, match):
    with pytest.raises(ma.CalibrationMessageError, match=match):
        ma.camera_info_to_model(_info(**changes))


def test_camera_info_missing_field():
    msg = _info()
    del msg.roi
    with pytest.raises(ma.CalibrationMessageError, match="has no field 'roi.x_offset'"):
        ma.camera_info_to_model(msg)


# ============================================================ 3. CompressedImage bombs
def test_issue10_png_header_claiming_40000x40000_is_refused_before_decoding():
    """Before the fix: OpenCV's own 2^30 pixel assertion, a ``cv2.error`` (not an adapter error)."""
    data = with_png_size(png_bytes(64, 48), 40000, 40000)
    assert ma.compressed_image_header(data) == ma.CompressedHeader("png", 40000, 40000)
    out, peak = _peak_bytes(ma.compressed_to_array, _compressed(data))
    assert isinstance(out, ma.EncodingError), repr(out)
    assert "40000x40000 exceeds the maximum of 16384 px per side" in str(out)
    assert peak < MIB


def test_issue10_small_png_decoding_to_16000x16000_is_refused_before_decoding():
    """A 1-bit palette PNG of ~32 KB that OpenCV would decode to 16000x16000 RGB (768 MB)."""
    data = png_bytes(16000, 16000, color_type=3, bit_depth=1)
    assert len(data) < 100_000
    out, peak = _peak_bytes(ma.compressed_to_array, _compressed(data))
    assert isinstance(out, ma.EncodingError), repr(out)
    assert f"exceeds the maximum of {LIMITS.max_image_pixels} pixels" in str(out)
    assert peak < 4 * MIB  # nothing of the 768 MB was allocated
    # With the calibrated size known, even an image within the limits is refused undecoded.
    data = png_bytes(4000, 3000, color_type=3, bit_depth=1)
    out, peak = _peak_bytes(ma.compressed_to_array, _compressed(data), expected_size=(1600, 900))
    assert isinstance(out, ma.EncodingError) and "is 4000x3000, expected 1600x900" in str(out)
    assert peak < 4 * MIB


def test_jpeg_header_size_is_checked_before_decoding():
    rgb = np.random.default_rng(1).integers(0, 256, (48, 64, 3), np.uint8)
    data = _encode(".jpg", rgb, cv2.IMWRITE_JPEG_QUALITY, 90)
    assert ma.compressed_image_header(data) == ma.CompressedHeader("jpeg", 64, 48)
    assert ma.compressed_to_array(_compressed(data, "jpeg"), (64, 48)).shape == (48, 64, 3)
    with pytest.raises(ma.EncodingError, match="is 64x48, expected 640x480"):
        ma.compressed_to_array(_compressed(data, "jpeg"), expected_size=(640, 480))
    out, peak = _peak_bytes(ma.compressed_to_array, _compressed(with_jpeg_size(data, 60000, 60000), "jpeg"))
    assert isinstance(out, ma.EncodingError) and "60000x60000 exceeds" in str(out)
    assert peak < MIB
    with pytest.raises(ma.EncodingError, match="no end-of-image marker"):
        ma.compressed_to_array(_compressed(data[:-2], "jpeg"))


@pytest.mark.parametrize(
    "data, match",
    [
        (b"BM" + bytes(60), "neither PNG nor JPEG"),  # a BMP: OpenCV would decode it
        (png_bytes(8, 8)[:30], "truncated inside its IHDR"),
        (png_bytes(8, 8)[:-20], "cannot decode"),  # truncated IDAT
        (with_png_size(png_bytes(8, 8), 9, 8), "cannot decode"),  # rows too short
        (with_png_size(png_bytes(8, 8), 9, 8, fix_crc=False), "cannot decode"),  # IHDR CRC wrong
        (with_png_size(png_bytes(8, 8), 0, 8), "invalid size 0x8"),
        (b"\xff\xd8\xff\xda" + bytes(20), "before its frame header"),
        (b"\xff\xd8\xff\xe0\x00", "truncated inside a marker segment"),
        (b"", "has no data"),
    ],
    ids=["bmp", "png-header-cut", "png-idat-cut", "png-rows-short", "png-bad-crc", "png-width-0",
         "jpeg-sos-first", "jpeg-cut", "empty"],
)
def test_every_decode_failure_is_an_encoding_error(data, match):
    with pytest.raises(ma.EncodingError, match=match):
        ma.compressed_to_array(_compressed(data))


def test_compressed_old_signature_and_custom_limits():
    """``compressed_to_array(msg)`` still works; ``limits`` lowers the hard cap."""
    rgb = np.random.default_rng(2).integers(0, 256, (30, 40, 3), np.uint8)
    msg = _compressed(_encode(".png", cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR)))
    np.testing.assert_array_equal(ma.compressed_to_array(msg), rgb)
    np.testing.assert_array_equal(ma.compressed_to_array(msg, (40, 30)), rgb)
    with pytest.raises(ma.EncodingError, match="maximum of 1000 pixels"):
        ma.compressed_to_array(msg, limits=ma.AdapterLimits(max_image_pixels=1000))
    with pytest.raises(BevMapperError, match="expected_size"):
        ma.compressed_to_array(msg, expected_size=(40,))


def test_raw_image_size_is_checked_against_expected_size_and_limits():
    labels = np.zeros((6, 5), np.uint8)
    msg = ma.make_image(FACTORY, labels, "mono8", 0, "cam")
    assert ma.image_to_labels(msg, (5, 6)).shape == (6, 5)
    assert ma.image_to_rgb(msg, expected_size=(5, 6)).shape == (6, 5, 3)
    with pytest.raises(ma.EncodingError, match="is 5x6, expected 6x5"):
        ma.image_to_labels(msg, (6, 5))
    with pytest.raises(ma.EncodingError, match="maximum of 29 pixels"):
        ma.image_to_array(msg, limits=ma.AdapterLimits(max_image_pixels=29))
    msg.width, msg.step, msg.height = 2**32 - 1, 2**32 - 1, 1  # a claim the data cannot back
    with pytest.raises(ma.EncodingError, match="exceeds the maximum of 16384 px per side"):
        ma.image_to_array(msg)


# =========================================================== 4. OccupancyGrid values
SMALL_GRID = BevGrid(0.0, 2.0, -1.0, 1.0, 0.5)  # 4 x 4 cells


def _occupancy(values, grid=SMALL_GRID):
    msg = ma.make_occupancy_grid(FACTORY, grid, np.zeros(grid.shape), None, 0, "base_link")
    msg.data = np.asarray(values, dtype=np.int8)
    return msg


def test_issue10_occupancy_value_127_is_refused_with_its_count():
    """Before the fix 127 was read as probability 1.27."""
    values = np.zeros(16, np.int8)
    values[[3, 7, 8]] = (127, 101, -2)
    with pytest.raises(ma.GridMessageError, match=r"3 OccupancyGrid cells hold values outside -1..100 "
                                                  r"\(first: 127 at cell 3\)"):
        ma.occupancy_grid_to_layer(_occupancy(values), SMALL_GRID)
    with pytest.raises(GridError, match="1 OccupancyGrid cells"):
        SMALL_GRID.from_occupancy(np.r_[np.zeros(15, np.int8), 127], 4, 4)


def test_occupancy_range_ends_are_kept():
    values = np.array([OCC_UNKNOWN, 0, OCC_MAX, 50] * 4, np.int8)
    probs, known = ma.occupancy_grid_to_layer(_occupancy(values), SMALL_GRID)
    assert probs.max() == 1.0 and probs.min() == 0.0
    np.testing.assert_array_equal(known.ravel(), values >= 0)


@pytest.mark.parametrize(
    "data, match",
    [
        (np.full(16, 200, np.int16), "16 OccupancyGrid cells hold values outside"),  # no wrap to -56
        ([300] * 16, "16 OccupancyGrid cells hold values outside"),
        (np.zeros(16, np.float32), "must hold integers"),
        (array.array("i", [0] * 16), "must be int8"),
        (None, "must be bytes"),
        (np.zeros(15, np.int8), "has 15 cells"),
    ],
)
def test_occupancy_data_types(data, match):
    msg = _occupancy(np.zeros(16))
    msg.data = data
    with pytest.raises(ma.GridMessageError, match=match):
        ma.occupancy_grid_to_layer(msg, SMALL_GRID)


# ====================================================================== 5. the fuzz
SEED = 10  # issue #10
#: Cases per adapter: a few thousand, seconds in all.
CASES = {"CameraInfo": 3000, "Image": 3000, "CompressedImage": 2000, "CompressedLabels": 400, "OccupancyGrid": 2000,
         "TransformStamped": 2000, "TFMessage": 1000, "Odometry": 2000}
#: Limits of the compressed cases without an expected size: a low cap keeps the fuzz fast.
FUZZ_LIMITS = ma.AdapterLimits(max_image_side=2048, max_image_pixels=2**18)
#: No case may take longer than this (a decoder that loops would).
CASE_TIME_S = 2.0
#: Bytes a decoded pixel may cost at most: 4 channels of 16 bits, and one working copy.
BYTES_PER_PIXEL = 4 * 2 * 2

WRONG_TYPES = [None, "12", b"12", 3.5, [1, 2], {}, object(), True, complex(1, 2), np.array([1, 2])]
SPECIAL_FLOATS = [float("nan"), float("inf"), -float("inf"), 0.0, -0.0, 1e-300, 1e308, -1e308, 1e20,
                  -1e20, 2.0**64]
SPECIAL_INTS = [0, 1, 2, 3, -1, 2**31 - 1, 2**31, 2**32 - 1, 2**32, 2**63, -(2**63), 10**30]


def to_ns(msg):
    """A rosbags message as nested ``SimpleNamespace`` (a duck-typed message of another kind)."""
    if hasattr(msg, "__dataclass_fields__"):
        return types.SimpleNamespace(**{k: to_ns(getattr(msg, k)) for k in msg.__dataclass_fields__
                                     if hasattr(msg, k)})  # (a mutation may have deleted one)
    if isinstance(msg, list):
        return [to_ns(m) for m in msg]
    return msg.copy() if isinstance(msg, np.ndarray) else msg


def _get(msg, path):
    for name in path.split("."):
        msg = getattr(msg, name)
    return msg


def _set(msg, path, value):
    *parents, last = path.split(".")
    for name in parents:
        msg = getattr(msg, name)
    setattr(msg, last, value)


def _int_value(rng, base):
    r = rng.random()
    if r < 0.35 and isinstance(base, int):
        return max(0, base + int(rng.integers(-2, 3)))
    if r < 0.75:
        return SPECIAL_INTS[rng.integers(len(SPECIAL_INTS))]
    return int(rng.integers(0, 5000))


def _float_value(rng, base):
    r = rng.random()
    if r < 0.35 and isinstance(base, float):
        return base * float(rng.choice([1.0, 1.0001, 0.5, 2.0, -1.0, 10.0, 0.1]))
    if r < 0.8:
        return SPECIAL_FLOATS[rng.integers(len(SPECIAL_FLOATS))]
    return float(rng.normal() * 10.0 ** rng.integers(-3, 6))


def _floats_value(rng, base):
    try:
        arr = np.array(base, dtype=np.float64).reshape(-1)
    except (TypeError, ValueError):  # an earlier mutation left no numbers
        arr = rng.normal(size=5)
    r = rng.random()
    if r < 0.45 and arr.size:
        arr[rng.integers(arr.size)] = _float_value(rng, float(arr[rng.integers(arr.size)]))
        return arr
    if r < 0.6:
        return arr[: rng.integers(0, arr.size + 1)]
    if r < 0.7:
        return np.concatenate([arr, rng.normal(size=rng.integers(1, 5))])
    if r < 0.8:
        return [str(v) for v in arr]
    if r < 0.85:
        return arr.reshape(1, -1)
    if r < 0.9:
        return np.array([None] * arr.size, dtype=object)
    return arr.tolist()


def _str_value(rng, base, choices):
    r = rng.random()
    if r < 0.6:
        return choices[rng.integers(len(choices))]
    if r < 0.75:
        return ""
    if r < 0.85:
        return "x" * int(rng.integers(1, 300))
    return base.upper() if isinstance(base, str) else "?"


def _bytes_value(rng, base):
    """A mutation of a uint8[] buffer: length, content, container type."""
    try:
        data = np.array(base, dtype=np.uint8).reshape(-1)
    except (TypeError, ValueError, OverflowError):  # an earlier mutation left no bytes
        data = rng.integers(0, 256, 32, dtype=np.uint8)
    r = rng.random()
    if r < 0.2 and data.size:
        return data[: rng.integers(0, data.size)]
    if r < 0.3:
        return np.concatenate([data, rng.integers(0, 256, rng.integers(1, 64), dtype=np.uint8)])
    if r < 0.45 and data.size:
        idx = rng.integers(0, data.size, rng.integers(1, 9))
        data[idx] = rng.integers(0, 256, idx.size)
        return data
    kinds = [bytes(data), bytearray(data), array.array("B", data.tobytes()), memoryview(data.tobytes()),
             data.tolist(), data.astype(np.float64), data.astype(np.int16), data.reshape(1, -1),
             np.array([300] * min(data.size, 4) + data.tolist()[4:]).tolist(), data.astype(object),
             "x" * data.size, None, []]
    return kinds[rng.integers(len(kinds))]


def mutate(rng, msg, spec: dict):
    """Apply 0-3 random mutations to ``msg`` (in place) from ``spec``: path -> (kind, extra)."""
    paths = list(spec)
    for _ in range(int(rng.choice([0, 1, 1, 1, 2, 2, 3]))):
        path = paths[rng.integers(len(paths))]
        kind, extra = spec[path]
        r = rng.random()
        try:
            base = _get(msg, path)
        except AttributeError:
            continue  # a parent was deleted by an earlier mutation
        if r < 0.08:
            *parents, last = path.split(".")
            try:
                delattr(_get(msg, ".".join(parents)) if parents else msg, last)
            except AttributeError:
                pass
            continue
        if r < 0.22:
            value = WRONG_TYPES[rng.integers(len(WRONG_TYPES))]
        elif kind == "int":
            value = _int_value(rng, base)
        elif kind == "float":
            value = _float_value(rng, base)
        elif kind == "floats":
            value = _floats_value(rng, base)
        elif kind == "str":
            value = _str_value(rng, base, extra)
        elif kind == "bytes":
            value = _bytes_value(rng, base)
        elif kind == "choice":
            value = extra[rng.integers(len(extra))]
        else:  # "msg": a sub-message replaced
            value = [None, 0, "msg", types.SimpleNamespace()][rng.integers(4)]
        try:
            _set(msg, path, value)
        except AttributeError:
            pass
    return msg


def run_fuzz(name: str, make_case, call, allowed: type[BevMapperError], check_valid) -> Counter:
    """Run ``CASES[name]`` seeded cases; fail on any outcome but a valid result or ``allowed``.

    ``make_case(rng) -> (msg, kwargs, alloc_cap_bytes)``; ``check_valid(result, msg, kwargs)``
    checks a valid result. Each case's traced peak allocation must stay below its cap and its
    duration below :data:`CASE_TIME_S`.
    """
    rng = np.random.default_rng([SEED, sum(map(ord, name))])
    counts: Counter = Counter()
    failures = []
    t_start = time.perf_counter()
    slowest = 0.0
    tracemalloc.start()
    try:
        for i in range(CASES[name]):
            msg, kwargs, cap = make_case(rng)
            base = tracemalloc.get_traced_memory()[0]
            tracemalloc.reset_peak()
            t0 = time.perf_counter()
            try:
                result = call(msg, **kwargs)
            except allowed as exc:
                counts[type(exc).__name__] += 1
            except Exception as exc:  # noqa: BLE001 - the defect the fuzz looks for
                counts[f"UNEXPECTED {type(exc).__name__}"] += 1
                failures.append(f"case {i}: {type(exc).__name__}: {exc}")
            else:
                counts["valid"] += 1
                try:
                    check_valid(result, msg, kwargs)
                except Exception as exc:  # noqa: BLE001 - an unusable result, e.g. image_size raising
                    counts["valid"] -= 1
                    counts[f"UNUSABLE result ({type(exc).__name__})"] += 1
                    failures.append(f"case {i}: unusable result: {type(exc).__name__}: {exc}")
            dt = time.perf_counter() - t0
            slowest = max(slowest, dt)
            used = tracemalloc.get_traced_memory()[1] - base
            if used > cap:
                failures.append(f"case {i}: allocated {used / MIB:.1f} MiB > cap {cap / MIB:.1f} MiB")
            if dt > CASE_TIME_S:
                failures.append(f"case {i}: took {dt:.2f} s")
    finally:
        tracemalloc.stop()
    total = sum(counts.values())
    summary = ", ".join(f"{v} {k}" for k, v in counts.most_common())
    print(f"\nfuzz {name}: {total} cases, {summary} ({time.perf_counter() - t_start:.1f} s, "
          f"slowest case {slowest * 1000:.0f} ms)")
    assert not failures, f"{len(failures)} bad outcomes of {total}:\n" + "\n".join(failures[:20])
    # The fuzz reaches both sides: enough valid results, and enough refusals.
    assert counts["valid"] >= 0.05 * total and total - counts["valid"] >= 0.2 * total, summary
    return counts


# ------------------------------------------------------------------ CameraInfo
FUZZ_MODELS = [
    surround6()["front"].model,
    CAM,
    CameraModel(K=((300, 0, 160), (0, 310, 120), (0, 0, 1)), D=(0.1, -0.02, 0.001, 0.002, 0.003,
                0.01, 0.002, 0.0005), distortion_model="rational_polynomial", width=320, height=240,
                roi=Roi(10, 20, 200, 100)),
    CameraModel(K=((200, 0, 150), (0, 200, 100), (0, 0, 1)), D=(0.01, 0.02, -0.003, 0.0004),
                distortion_model="equidistant", width=300, height=200, binning_x=2, binning_y=2),
]
CAMERA_INFO_SPEC = {
    "width": ("int", None), "height": ("int", None), "k": ("floats", None), "d": ("floats", None),
    "r": ("floats", None), "p": ("floats", None),
    "distortion_model": ("str", sorted(DISTORTION_MODELS) + ["", "fisheye"]),
    "binning_x": ("choice", [0, 1, 2, 3, 4, 7, 100, 899, 900, 1000, 2**32 - 1, -1, 2.0]),
    "binning_y": ("choice", [0, 1, 2, 3, 4, 7, 100, 899, 900, 1000, 2**32 - 1, -1, 2.0]),
    "roi.x_offset": ("int", None), "roi.y_offset": ("int", None), "roi.width": ("int", None),
    "roi.height": ("int", None), "roi": ("msg", None), "header": ("msg", None),
}


def _camera_info_case(rng):
    msg = ma.make_camera_info(FACTORY, FUZZ_MODELS[rng.integers(len(FUZZ_MODELS))], 0, "cam")
    if rng.random() < 0.5:
        msg = to_ns(msg)
    return mutate(rng, msg, CAMERA_INFO_SPEC), {}, 4 * MIB


def _check_camera_model(model, msg, kwargs):
    w, h = model.image_size  # the defect of the issue: this raised in the node
    assert 1 <= w and 1 <= h and w * h <= LIMITS.max_image_pixels, (w, h)
    assert max(model.width, model.height) <= LIMITS.max_image_side
    K = model.K_array
    assert LIMITS.min_focal_per_size * model.width <= K[0, 0] <= LIMITS.max_focal_per_size * model.width
    assert LIMITS.min_focal_per_size * model.height <= K[1, 1] <= LIMITS.max_focal_per_size * model.height
    uv, _ = model.project(np.array([[0.0, 0.0, 1.0]]))  # the optical axis lands somewhere finite
    assert np.all(np.isfinite(uv)), uv


def test_fuzz_camera_info():
    counts = run_fuzz("CameraInfo", _camera_info_case, ma.camera_info_to_model,
                      ma.CalibrationMessageError, _check_camera_model)
    assert set(counts) == {"valid", "CalibrationMessageError"}


# ------------------------------------------------------------------ Image
IMAGE_ARRAYS = {
    "rgb8": (np.uint8, 3), "bgr8": (np.uint8, 3), "rgba8": (np.uint8, 4), "bgra8": (np.uint8, 4),
    "mono8": (np.uint8, 0), "8UC1": (np.uint8, 0), "mono16": (np.uint16, 0), "16UC1": (np.uint16, 0),
}
IMAGE_SPEC = {
    "height": ("int", None), "width": ("int", None), "step": ("int", None),
    "encoding": ("str", sorted(ma.ENCODINGS) + list(AMBIGUOUS_ENCODINGS) + ["yuv422", "32FC1"]),
    "is_bigendian": ("choice", [0, 1, 2, 255, 256, -1]), "data": ("bytes", None),
}
#: label maps of the label-image cases: mono8 ids and an rgb8 palette (its dense table built
#: here, once, not inside a case's allocation budget)
FUZZ_LABEL_MAPS = [label_map("cityscapes_ids"), label_map("cam2bev")]
FUZZ_LABEL_MAPS[1].apply(np.zeros((1, 1, 3), np.uint8))
IMAGE_CALLS = [ma.image_to_array, ma.image_to_rgb, ma.image_to_labels,
               *(functools.partial(ma.image_to_labels, label_map=lm) for lm in FUZZ_LABEL_MAPS)]


def _image_case(rng):
    encoding = sorted(IMAGE_ARRAYS)[rng.integers(len(IMAGE_ARRAYS))]
    dtype, channels = IMAGE_ARRAYS[encoding]
    h, w = (int(v) for v in rng.integers(1, 12, 2))
    shape = (h, w, channels) if channels else (h, w)
    arr = rng.integers(0, np.iinfo(dtype).max, shape, dtype=dtype, endpoint=True)
    itemsize = np.dtype(dtype).itemsize
    step = w * max(channels, 1) * itemsize + int(rng.choice([0, 0, itemsize, 3 * itemsize]))
    msg = ma.make_image(FACTORY, arr, encoding, 0, "cam", step=step, bigendian=bool(rng.random() < 0.3))
    if rng.random() < 0.5:
        msg = to_ns(msg)
    mutate(rng, msg, IMAGE_SPEC)
    kwargs = {"call": IMAGE_CALLS[rng.integers(len(IMAGE_CALLS))]}
    if rng.random() < 0.5:
        kwargs["expected_size"] = (w, h)
    # a valid result is at most 3 bytes (RGB) per message byte, or 2 copies of the data
    return msg, kwargs, 8 * (step * h) + MIB


def _call_image(msg, call, **kwargs):
    return call(msg, **kwargs)


def _check_image(arr, msg, kwargs):
    assert isinstance(arr, np.ndarray) and arr.dtype in (np.uint8, np.uint16)
    h, w = arr.shape[:2]
    assert (h, w) == (msg.height, msg.width)
    if "expected_size" in kwargs:
        assert (w, h) == kwargs["expected_size"]
    if kwargs["call"] is ma.image_to_rgb:
        assert arr.shape == (h, w, 3) and arr.dtype == np.uint8
    if kwargs["call"] is ma.image_to_labels or getattr(kwargs["call"], "func", None) is ma.image_to_labels:
        assert arr.shape == (h, w) and arr.dtype == np.uint8


def test_fuzz_image():
    counts = run_fuzz("Image", _image_case, _call_image, ma.EncodingError, _check_image)
    assert set(counts) == {"valid", "EncodingError"}


# ------------------------------------------------------------------ CompressedImage
def _compressed_bases():
    rng = np.random.default_rng(SEED)
    rgb = rng.integers(0, 256, (16, 24, 3), np.uint8)
    mono = rng.integers(0, 256, (16, 24), np.uint8)
    return [
        _encode(".png", rgb), _encode(".png", mono), _encode(".png", mono.astype(np.uint16) * 257),
        _encode(".png", np.dstack([rgb, mono])), _encode(".png", rgb, cv2.IMWRITE_PNG_COMPRESSION, 9),
        _encode(".jpg", rgb, cv2.IMWRITE_JPEG_QUALITY, 90), _encode(".jpg", mono),
        _encode(".jpg", rgb, cv2.IMWRITE_JPEG_PROGRESSIVE, 1),
        png_bytes(24, 16, color_type=3, bit_depth=1),
    ]


COMPRESSED_BASES = _compressed_bases()
BOMB = png_bytes(16000, 16000, color_type=3, bit_depth=1)  # 32 KB, 768 MB decoded
# Sizes a rewritten header claims: the true one, a little off, within and beyond every limit.
CLAIMED_SIDES = [24, 16, 25, 1, 0, 600, 2048, 2049, 16384, 16385, 40000, 65535, 2**31 - 1, 2**32 - 1]
COMPRESSED_SPEC = {"format": ("str", ["png", "jpeg", "rgb8; jpeg compressed bgr8", "bmp"]),
                   "data": ("bytes", None), "header": ("msg", None)}
MAGICS = [b"BM", b"GIF89a", b"II*\x00", b"RIFF", b"\x89PNG", b"\xff\xd8", b"P6\n"]


def _mutate_image_bytes(rng, data: bytes) -> bytes:
    """Header-aware mutations: claimed size, truncation, flipped bytes, foreign magic."""
    r = rng.random()
    w, h = (int(rng.choice(CLAIMED_SIDES)) for _ in range(2))
    if r < 0.35:
        if data.startswith(PNG_SIGNATURE):
            return with_png_size(data, w, h, fix_crc=rng.random() < 0.8)
        return with_jpeg_size(data, w % 65536, h % 65536)
    if r < 0.5:
        return data[: rng.integers(0, len(data))]
    if r < 0.65:
        out = bytearray(data)
        for i in rng.integers(0, len(out), rng.integers(1, 6)):
            out[i] = int(rng.integers(0, 256))
        return bytes(out)
    if r < 0.72:
        magic = MAGICS[rng.integers(len(MAGICS))]
        return magic + data[len(magic):]
    return data


def _compressed_case(rng):
    data = COMPRESSED_BASES[rng.integers(len(COMPRESSED_BASES))]
    if rng.random() < 0.7:
        data = _mutate_image_bytes(rng, data)
    if rng.random() < 0.02:  # a real bomb: a tiny PNG that decodes to 16000 x 16000
        data = BOMB
    msg = _compressed(data, "png" if data.startswith(b"\x89") else "jpeg")
    if rng.random() < 0.5:
        msg = to_ns(msg)
    mutate(rng, msg, COMPRESSED_SPEC)
    if rng.random() < 0.6:
        kwargs = {"expected_size": (24, 16)}
        pixels = 24 * 16
    else:
        kwargs = {"limits": FUZZ_LIMITS}
        pixels = FUZZ_LIMITS.max_image_pixels
    return msg, kwargs, BYTES_PER_PIXEL * pixels + 4 * len(data) + MIB


def _check_compressed(img, msg, kwargs):
    assert isinstance(img, np.ndarray) and img.dtype in (np.uint8, np.uint16)
    assert img.ndim == 2 or img.shape[2] in (3, 4)
    h, w = img.shape[:2]
    if "expected_size" in kwargs:
        assert (w, h) == kwargs["expected_size"]
    else:
        assert w * h <= kwargs["limits"].max_image_pixels


def test_fuzz_compressed_image():
    counts = run_fuzz("CompressedImage", _compressed_case, ma.compressed_to_array, ma.EncodingError,
                      _check_compressed)
    assert set(counts) == {"valid", "EncodingError"}


def _compressed_labels_case(rng):
    """Every base image (RGB, mono, 16-bit, RGBA, JPEG, palette PNG) through every label map, with
    mutated message fields; the bytes stay intact (the decoder's own fuzz is the case above, and
    some damaged PNGs take OpenCV most of a second to refuse)."""
    data = COMPRESSED_BASES[rng.integers(len(COMPRESSED_BASES))]
    msg = _compressed(data, "png" if data.startswith(b"\x89") else "jpeg")
    if rng.random() < 0.5:
        msg = to_ns(msg)
    if rng.random() < 0.3:
        mutate(rng, msg, COMPRESSED_SPEC)
    kwargs = {"expected_size": (24, 16)} if rng.random() < 0.6 else {"limits": FUZZ_LIMITS}
    kwargs["label_map"] = [None, *FUZZ_LABEL_MAPS][rng.integers(len(FUZZ_LABEL_MAPS) + 1)]
    return msg, kwargs, BYTES_PER_PIXEL * 24 * 16 + 4 * len(data) + MIB


def _check_compressed_labels(labels, msg, kwargs):
    assert isinstance(labels, np.ndarray) and labels.dtype == np.uint8 and labels.ndim == 2
    _check_compressed(labels, msg, kwargs)


def test_fuzz_compressed_label_image():
    """``compressed_to_labels`` through the native, a mono8 and an rgb8 label map."""
    counts = run_fuzz("CompressedLabels", _compressed_labels_case, ma.compressed_to_labels, ma.EncodingError,
                      _check_compressed_labels)
    assert set(counts) == {"valid", "EncodingError"}


# ------------------------------------------------------------------ OccupancyGrid
FUZZ_GRIDS = [SMALL_GRID, BevGrid(-3.0, 3.0, -1.5, 1.5, 0.25), BevGrid(0.0, 3.3, -1.1, 1.1, 0.1)]
GRID_SPEC = {
    "info.resolution": ("float", None), "info.width": ("int", None), "info.height": ("int", None),
    "info.origin.position.x": ("float", None), "info.origin.position.y": ("float", None),
    "info.origin.orientation.z": ("float", None), "info.origin.orientation.w": ("float", None),
    "info": ("msg", None), "info.origin": ("msg", None), "data": ("cells", None),
}


def _cells_value(rng, base):
    data = np.asarray(base, dtype=np.int8).copy()
    r = rng.random()
    if r < 0.4 and data.size:
        data[rng.integers(0, data.size, rng.integers(1, 4))] = rng.choice([127, -128, 101, -2, 100, -1, 0])
        return data
    kinds = [data[:-1], np.r_[data, 0], data.astype(np.int16) + 150, data.astype(np.float64), data.tolist(),
             data.astype(np.uint8), array.array("b", data.tobytes()), array.array("i", data.tolist()),
             bytes(data.view(np.uint8)), [300] + data.tolist()[1:], None, "x", data.astype(object)]
    return kinds[rng.integers(len(kinds))]


def _grid_case(rng):
    grid = FUZZ_GRIDS[rng.integers(len(FUZZ_GRIDS))]
    probs = rng.random(grid.shape)
    msg = ma.make_occupancy_grid(FACTORY, grid, probs, rng.random(grid.shape) > 0.2, 0, "base_link")
    if rng.random() < 0.5:
        msg = to_ns(msg)
    if rng.random() < 0.5:
        _set(msg, "data", _cells_value(rng, msg.data))
    mutate(rng, msg, {k: v for k, v in GRID_SPEC.items() if v[0] != "cells"})
    kwargs = {"grid": grid} if rng.random() < 0.5 else {}
    return msg, kwargs, 10 * grid.width * grid.height * 8 + MIB


def _check_layer(result, msg, kwargs):
    probs, known = result
    assert probs.dtype == np.float32 and known.dtype == bool and probs.shape == known.shape
    assert np.all((probs >= 0) & (probs <= 1)) and np.all(probs[~known] == 0)
    if "grid" in kwargs:
        assert probs.shape == kwargs["grid"].shape


def test_fuzz_occupancy_grid():
    counts = run_fuzz("OccupancyGrid", _grid_case, ma.occupancy_grid_to_layer, ma.GridMessageError,
                      _check_layer)
    assert set(counts) == {"valid", "GridMessageError"}


# ------------------------------------------------------------------ TF and odometry
TF_SPEC = {
    "header.frame_id": ("str", ["base_link", "/base_link", "cam", "odom"]),
    "child_frame_id": ("str", ["cam", "base_link", "mount"]),
    "header.stamp.sec": ("int", None), "header.stamp.nanosec": ("int", None),
    "transform.translation.x": ("float", None), "transform.translation.z": ("float", None),
    "transform.rotation.x": ("float", None), "transform.rotation.w": ("float", None),
    "transform": ("msg", None), "transform.rotation": ("msg", None), "header": ("msg", None),
}


def _random_transform(rng):
    return make_transform(rpy_to_rot(*rng.uniform(-np.pi, np.pi, 3)), rng.normal(size=3) * 5)


def _tf_case(rng):
    msg = ma.make_transform_stamped(FACTORY, "base_link", "cam", _random_transform(rng),
                                    int(rng.integers(0, 2**60)))
    if rng.random() < 0.5:
        msg = to_ns(msg)
    return mutate(rng, msg, TF_SPEC), {}, MIB


def _check_rigid(T):
    assert T.shape == (4, 4) and np.all(np.isfinite(T))
    np.testing.assert_allclose(T[:3, :3] @ T[:3, :3].T, np.eye(3), atol=1e-9)
    np.testing.assert_array_equal(T[3], [0, 0, 0, 1])


def _check_transform(st, msg, kwargs):
    assert isinstance(st, ma.StampedTransform) and st.parent and st.child and st.parent != st.child
    _check_rigid(st.matrix)


def test_fuzz_transform_stamped():
    counts = run_fuzz("TransformStamped", _tf_case, ma.transform_stamped_to_matrix, ma.TransformError,
                      _check_transform)
    assert set(counts) == {"valid", "TransformError"}


def _tf_message_case(rng):
    n = int(rng.integers(1, 4))
    items = [mutate(rng, ma.make_transform_stamped(FACTORY, "base_link", f"cam{i}", _random_transform(rng), 5),
                    TF_SPEC) if rng.random() < 0.3 else
             ma.make_transform_stamped(FACTORY, "base_link", f"cam{i}", _random_transform(rng), 5)
             for i in range(n)]
    msg = FACTORY.msg("tf2_msgs/msg/TFMessage", transforms=items)
    if rng.random() < 0.5:
        msg = to_ns(msg)
    r = rng.random()
    if r < 0.1:
        msg.transforms = WRONG_TYPES[rng.integers(len(WRONG_TYPES))]
    elif r < 0.2:
        msg.transforms = list(msg.transforms) + [None]
    return msg, {}, MIB


def test_fuzz_tf_message():
    def check(result, msg, kwargs):
        for st in result:
            _check_transform(st, msg, kwargs)

    counts = run_fuzz("TFMessage", _tf_message_case, ma.tf_message_transforms, ma.TransformError, check)
    assert set(counts) == {"valid", "TransformError"}


ODOM_SPEC = {
    "header.frame_id": ("str", ["odom", "map"]), "child_frame_id": ("str", ["base_link"]),
    "header.stamp.sec": ("int", None), "header.stamp.nanosec": ("int", None),
    "pose.pose.position.x": ("float", None), "pose.pose.position.y": ("float", None),
    "pose.pose.orientation.z": ("float", None), "pose.pose.orientation.w": ("float", None),
    "twist.twist.linear.x": ("float", None), "twist.twist.angular.z": ("float", None),
    "pose.covariance": ("floats", None), "pose": ("msg", None), "twist.twist": ("msg", None),
}


def _odom_case(rng):
    msg = ma.make_odometry(FACTORY, _random_transform(rng), rng.normal(size=3), rng.normal(size=3),
                           int(rng.integers(0, 2**60)))
    if rng.random() < 0.5:
        msg = to_ns(msg)
    return mutate(rng, msg, ODOM_SPEC), {}, MIB


def _check_odometry(st, msg, kwargs):
    assert isinstance(st, ma.OdometryState)
    _check_rigid(st.world_from_ego)
    assert np.all(np.isfinite(st.linear_velocity)) and np.all(np.isfinite(st.angular_velocity))


def test_fuzz_odometry():
    counts = run_fuzz("Odometry", _odom_case, ma.odometry_to_state, ma.TransformError, _check_odometry)
    assert set(counts) == {"valid", "TransformError"}


def test_fuzz_is_seeded():
    """The same seed gives the same messages: a failing case can be replayed."""
    def first_cases():
        rng = np.random.default_rng([SEED, 1])
        return [repr(_camera_info_case(rng)[0]) for _ in range(20)]

    assert first_cases() == first_cases()
