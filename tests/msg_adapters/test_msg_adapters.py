"""msg_adapters: round trips and rejections, on rosbags AND rclpy message objects."""

from __future__ import annotations

import array
import importlib.util

import cv2
import numpy as np
import pytest
from import_check import ros_modules_loaded_by

import msg_adapters as ma
from bev_mapper_core.errors import BevMapperError
from bev_mapper_core.geometry.camera import CameraModel, Roi
from bev_mapper_core.geometry.grid import BevGrid
from bev_mapper_core.geometry.rig import surround6
from bev_mapper_core.geometry.transforms import ego_from_optical, make_transform, rpy_to_rot

HAVE_RCLPY = importlib.util.find_spec("rclpy") is not None and importlib.util.find_spec(
    "sensor_msgs"
) is not None


def _rosbags_factory():
    from rosbags.typesys import Stores, get_typestore

    return ma.RosbagsFactory(get_typestore(Stores.ROS2_JAZZY))


@pytest.fixture(
    params=[
        "rosbags",
        pytest.param("rclpy", marks=[pytest.mark.ros, pytest.mark.skipif(not HAVE_RCLPY, reason="rclpy absent")]),
    ]
)
def factory(request):
    return _rosbags_factory() if request.param == "rosbags" else ma.RclpyFactory(check_fields=True)


def _roundtrip_cdr(factory, msg, typename):
    """For rosbags messages, also go through CDR (what a bag stores)."""
    if factory.name != "rosbags":
        return msg
    ts = factory.typestore
    return ts.deserialize_cdr(ts.serialize_cdr(msg, typename), typename)


RNG = np.random.default_rng(0)
ARRAYS = {
    "rgb8": RNG.integers(0, 256, (5, 7, 3), dtype=np.uint8),
    "bgr8": RNG.integers(0, 256, (5, 7, 3), dtype=np.uint8),
    "rgba8": RNG.integers(0, 256, (4, 3, 4), dtype=np.uint8),
    "bgra8": RNG.integers(0, 256, (4, 3, 4), dtype=np.uint8),
    "mono8": RNG.integers(0, 256, (6, 5), dtype=np.uint8),
    "8UC1": RNG.integers(0, 256, (6, 5), dtype=np.uint8),
    "mono16": RNG.integers(0, 65536, (6, 5), dtype=np.uint16),
    "16UC1": RNG.integers(0, 65536, (3, 9), dtype=np.uint16),
}


# ------------------------------------------------------------------- images
@pytest.mark.parametrize("encoding", sorted(ARRAYS))
@pytest.mark.parametrize("pad", [0, 5])
def test_image_roundtrip(factory, encoding, pad):
    arr = ARRAYS[encoding]
    packed = arr.shape[1] * (arr.shape[2] if arr.ndim == 3 else 1) * arr.itemsize
    step = packed + pad * arr.itemsize if pad else None
    msg = ma.make_image(factory, arr, encoding, 1_700_000_000_123_456_789, "cam", step=step)
    msg = _roundtrip_cdr(factory, msg, "sensor_msgs/msg/Image")
    assert msg.step == (step or packed)
    assert ma.header_stamp_ns(msg) == 1_700_000_000_123_456_789
    assert msg.header.frame_id == "cam"
    out = ma.image_to_array(msg)
    assert out.dtype == arr.dtype and out.shape == arr.shape
    np.testing.assert_array_equal(out, arr)


@pytest.mark.parametrize("pad", [0, 3])
def test_mono16_bigendian_roundtrip(factory, pad):
    arr = ARRAYS["mono16"]
    step = arr.shape[1] * 2 + pad * 2
    msg = ma.make_image(factory, arr, "mono16", 0, "cam", step=step, bigendian=True)
    msg = _roundtrip_cdr(factory, msg, "sensor_msgs/msg/Image")
    assert msg.is_bigendian == 1
    raw = bytes(np.asarray(msg.data, dtype=np.uint8)[:2])
    assert raw == int(arr[0, 0]).to_bytes(2, "big")
    out = ma.image_to_array(msg)
    assert out.dtype == np.uint16 and out.dtype.isnative
    np.testing.assert_array_equal(out, arr)


def test_bgr_wire_order_and_rgb_helpers(factory):
    rgb = ARRAYS["rgb8"]
    msg = ma.make_image(factory, rgb, "bgr8", 0, "cam")
    first = np.asarray(msg.data, dtype=np.uint8)[:3]
    np.testing.assert_array_equal(first, rgb[0, 0, ::-1])
    np.testing.assert_array_equal(ma.image_to_rgb(msg), rgb)
    mono = ma.make_image(factory, ARRAYS["mono8"], "mono8", 0, "cam")
    assert ma.image_to_rgb(mono).shape == (6, 5, 3)
    np.testing.assert_array_equal(ma.image_to_labels(mono), ARRAYS["mono8"])
    with pytest.raises(ma.EncodingError, match="label images"):
        ma.image_to_labels(msg)


def _raw_image(factory, *, height=4, width=5, encoding="rgb8", step=15, nbytes=60, big=0):
    header = ma.make_header(factory, 0, "cam")
    return factory.msg(
        "sensor_msgs/msg/Image", header=header, height=height, width=width, encoding=encoding,
        is_bigendian=big, step=step, data=factory.uint8_seq(np.zeros(nbytes, np.uint8)),
    )


@pytest.mark.parametrize(
    "kwargs, match",
    [
        (dict(nbytes=59), "expected step\\*height"),
        (dict(nbytes=61), "expected step\\*height"),
        (dict(step=14, nbytes=56), "step 14 is smaller"),
        (dict(step=20, nbytes=60), "expected step\\*height"),
        (dict(encoding="8UC3"), "ambiguous"),
        (dict(encoding="yuv422_weird"), "unsupported image encoding"),
        (dict(height=0, nbytes=0), "empty size"),
        (dict(encoding="mono16", step=9, nbytes=36), "smaller than one row"),
    ],
    ids=["short", "long", "step-too-small", "step-vs-length", "8UC3", "unknown", "empty",
         "mono16-step"],
)
def test_image_rejections(factory, kwargs, match):
    msg = _raw_image(factory, **kwargs)
    with pytest.raises(ma.EncodingError, match=match) as info:
        ma.image_to_array(msg)
    assert isinstance(info.value, BevMapperError)


@pytest.mark.parametrize(
    "arr, encoding",
    [
        (np.zeros((4, 4), np.uint8), "rgb8"),
        (np.zeros((4, 4, 3), np.uint16), "rgb8"),
        (np.zeros((4, 4), np.uint8), "mono16"),
        (np.zeros((4, 4, 3), np.uint8), "8UC3"),
    ],
)
def test_make_image_rejections(factory, arr, encoding):
    with pytest.raises(ma.EncodingError):
        ma.make_image(factory, arr, encoding, 0, "cam")


@pytest.mark.parametrize("fmt", ["png", "jpeg"])
def test_compressed_roundtrip(factory, fmt):
    yy, xx = np.mgrid[0:32, 0:48]
    rgb = np.stack([xx * 5, yy * 7, np.full_like(xx, 90)], axis=2).astype(np.uint8)
    msg = ma.make_compressed_image(factory, rgb, fmt, 5, "cam", quality=95)
    msg = _roundtrip_cdr(factory, msg, "sensor_msgs/msg/CompressedImage")
    out = ma.compressed_to_array(msg)
    assert out.shape == rgb.shape
    if fmt == "png":
        np.testing.assert_array_equal(out, rgb)
    else:
        assert np.abs(out.astype(int) - rgb).mean() < 3.0
    bad = factory.msg(
        "sensor_msgs/msg/CompressedImage", header=ma.make_header(factory, 0, "c"), format=fmt,
        data=factory.uint8_seq(np.arange(50, dtype=np.uint8)),
    )
    with pytest.raises(ma.EncodingError, match="cannot decode"):
        ma.compressed_to_array(bad)


@pytest.mark.parametrize("fmt, codec, problem", [
    ("jpeg", "jpeg", None), ("JPG", "jpeg", None), ("rgb8; jpeg compressed bgr8", "jpeg", None),
    ("png", "png", None), ("mono8; png compressed ", "png", None), ("", "png", None),
    ("png", "jpeg", "does not match the data, which is JPEG"), ("theora", "jpeg", "names no codec"),
    ("16UC1; compressedDepth png", "png", "compressedDepth"), ("jpeg png", "png", "does not match"),
    (None, "png", "must be a string"),
])
def test_format_problem(fmt, codec, problem):
    got = ma.format_problem(fmt, codec)
    assert got is None if problem is None else problem in got


def test_compressed_to_rgb_gives_rgb_of_grey_and_rgba_and_checks_the_format(factory):
    grey = np.arange(48 * 32, dtype=np.uint8).reshape(32, 48)
    msg = ma.make_compressed_image(factory, grey, "png", 5, "cam")
    rgb = ma.compressed_to_rgb(msg, (48, 32), check_format=True)
    assert rgb.shape == (32, 48, 3) and all((rgb[..., i] == grey).all() for i in range(3))
    rgba = np.dstack([grey, grey // 2, grey // 3, np.full_like(grey, 7)])
    data = cv2.imencode(".png", cv2.cvtColor(rgba, cv2.COLOR_RGBA2BGRA))[1].reshape(-1)
    msg = factory.msg("sensor_msgs/msg/CompressedImage", header=ma.make_header(factory, 0, "c"), format="png",
                      data=factory.uint8_seq(data))
    np.testing.assert_array_equal(ma.compressed_to_rgb(msg), rgba[..., :3])
    msg.format = "jpeg"
    assert ma.compressed_to_rgb(msg).shape == (32, 48, 3)  # the format is not checked unless asked
    with pytest.raises(ma.EncodingError, match="format 'jpeg' does not match the data, which is PNG"):
        ma.compressed_to_rgb(msg, check_format=True)
    sixteen = cv2.imencode(".png", grey.astype(np.uint16) * 200)[1].reshape(-1)
    msg = factory.msg("sensor_msgs/msg/CompressedImage", header=ma.make_header(factory, 0, "c"), format="png",
                      data=factory.uint8_seq(sixteen))
    with pytest.raises(ma.EncodingError, match="uint16 compressed image as RGB"):
        ma.compressed_to_rgb(msg)


# ---------------------------------------------------------------- CameraInfo
MODELS = [
    surround6()["front"].model,
    CameraModel(K=((300, 0, 160), (0, 310, 120), (0, 0, 1)), D=(0.1, -0.02, 0.001, 0.002, 0.003,
                0.01, 0.002, 0.0005), distortion_model="rational_polynomial", width=320,
                height=240, roi=Roi(10, 20, 200, 100)),
    CameraModel(K=((200, 0, 150), (0, 200, 100), (0, 0, 1)), D=(0.01, 0.02, -0.003, 0.0004),
                distortion_model="equidistant", width=300, height=200, binning_x=2, binning_y=2),
]


@pytest.mark.parametrize("model", MODELS, ids=lambda m: m.distortion_model)
def test_camera_info_roundtrip(factory, model):
    msg = ma.make_camera_info(factory, model, 42, "front_optical_frame")
    msg = _roundtrip_cdr(factory, msg, "sensor_msgs/msg/CameraInfo")
    assert list(np.asarray(msg.r)) == list(np.eye(3).ravel())
    np.testing.assert_array_equal(np.asarray(msg.p).reshape(3, 4)[:, :3], model.K_array)
    assert ma.camera_info_to_model(msg) == model


def test_camera_info_key_changes_with_every_field_the_conversion_reads(factory):
    """Equal keys mean equal models (the node then skips the conversion); any change of size,
    K, D, distortion model, binning, ROI or frame gives another key, and the stamp does not."""
    base = ma.make_camera_info(factory, MODELS[1], 42, "front_optical_frame")
    key = ma.camera_info_key(base)
    assert key is not None and key == ma.camera_info_key(ma.make_camera_info(factory, MODELS[1], 99,
                                                                            "front_optical_frame"))
    changed = [ma.make_camera_info(factory, MODELS[1], 42, "other_frame")]
    for m in (MODELS[0], MODELS[2]):
        changed.append(ma.make_camera_info(factory, m, 42, "front_optical_frame"))
    for name, value in (("width", 321), ("height", 241), ("distortion_model", "plumb_bob"), ("binning_x", 2),
                        ("binning_y", 2)):
        msg = ma.make_camera_info(factory, MODELS[1], 42, "front_optical_frame")
        setattr(msg, name, value)
        changed.append(msg)
    for arr in ("k", "d"):
        msg = ma.make_camera_info(factory, MODELS[1], 42, "front_optical_frame")
        v = np.asarray(getattr(msg, arr), dtype=np.float64).copy()
        v[0] += 1e-9
        setattr(msg, arr, [float(x) for x in v])
        changed.append(msg)
    msg = ma.make_camera_info(factory, MODELS[1], 42, "front_optical_frame")
    msg.roi.x_offset = 11
    changed.append(msg)
    keys = [ma.camera_info_key(m) for m in changed]
    assert all(k is not None and k != key for k in keys) and len(set(keys)) == len(keys)
    assert ma.camera_info_key(object()) is None  # unreadable: convert, and get the error


def _info(factory, *, k=None, d=(0.0,) * 5, model="plumb_bob", width=640, height=480):
    k = [500.0, 0, 320, 0, 500, 240, 0, 0, 1] if k is None else k
    roi = factory.msg("sensor_msgs/msg/RegionOfInterest", x_offset=0, y_offset=0, height=0,
                      width=0, do_rectify=False)
    return factory.msg(
        "sensor_msgs/msg/CameraInfo", header=ma.make_header(factory, 0, "cam"), height=height,
        width=width, distortion_model=model, d=factory.float64_seq(np.asarray(d, float)),
        k=factory.float64_fixed(np.asarray(k, float), 9) if len(k) == 9 else k,
        r=factory.float64_fixed(np.eye(3), 9), p=factory.float64_fixed(np.zeros(12), 12),
        binning_x=0, binning_y=0, roi=roi,
    )


@pytest.mark.parametrize(
    "kwargs, match",
    [
        (dict(k=[0.0] * 9), "uncalibrated"),
        (dict(k=[500.0, 0, 320, 0, float("nan"), 240, 0, 0, 1]), "non-finite"),
        (dict(d=(0.1, 0.2, 0.0)), "takes 5 coefficients, got 3"),
        (dict(d=(0.1,) * 5, model="equidistant"), "takes 4 coefficients, got 5"),
        (dict(d=(0.0, float("inf"), 0, 0, 0)), "non-finite"),
        (dict(model="kannala_brandt_weird"), "unsupported distortion model"),
        (dict(width=0), "image size"),
        (dict(k=[500.0, 0, 320, 0, -500, 240, 0, 0, 1]), "focal lengths"),
    ],
    ids=["K-zero", "K-nan", "D-short", "D-long", "D-inf", "model", "size", "negative-f"],
)
def test_camera_info_rejections(factory, kwargs, match):
    with pytest.raises(ma.CalibrationMessageError, match=match):
        ma.camera_info_to_model(_info(factory, **kwargs))


def test_camera_info_wrong_k_length():
    class Fake:  # duck-typed: a malformed message cannot be built through either factory
        k = [1.0] * 8
        d = []
        distortion_model = "plumb_bob"

    with pytest.raises(ma.CalibrationMessageError, match="9 values, got 8"):
        ma.camera_info_to_model(Fake())


def test_camera_info_lenient_cases(factory):
    m = ma.camera_info_to_model(_info(factory, d=(), model=""))
    assert m.distortion_model == "plumb_bob" and m.D == (0.0,) * 5 and m.binning_x == 1


# ------------------------------------------------------------------ transforms
def _tf(factory, parent, child, T, stamp=0, q=None):
    msg = ma.make_transform_stamped(factory, parent, child, T, stamp)
    if q is not None:
        x, y, z, w = (float(v) for v in q)
        msg.transform.rotation = factory.msg("geometry_msgs/msg/Quaternion", x=x, y=y, z=z, w=w)
    return msg


def test_transform_chain(factory):
    rig = surround6()
    base_from_mount = make_transform(rpy_to_rot(0.01, -0.02, 0.3), (1.0, 0.2, 1.5))
    cam = rig["front"]
    mount_from_cam = np.linalg.inv(base_from_mount) @ cam.ego_from_cam_array
    msgs = [
        _tf(factory, "/base_link", "mount", base_from_mount, 5),
        _tf(factory, "mount", cam.frame_id, mount_from_cam, 5),
        _tf(factory, "base_link", "back_optical_frame", rig["back"].ego_from_cam_array, 5),
    ]
    parsed = [ma.transform_stamped_to_matrix(m) for m in msgs]
    assert parsed[0].parent == "base_link" and parsed[0].stamp_ns == 5
    tree = ma.TfTree(parsed)
    np.testing.assert_allclose(ma.ego_from_camera(tree, "base_link", cam.frame_id),
                               cam.ego_from_cam_array, atol=1e-9)
    # sibling lookup goes through the common ancestor
    back_from_front = tree.lookup("back_optical_frame", cam.frame_id)
    expect = np.linalg.inv(rig["back"].ego_from_cam_array) @ cam.ego_from_cam_array
    np.testing.assert_allclose(back_from_front, expect, atol=1e-9)
    np.testing.assert_allclose(tree.lookup("mount", "mount"), np.eye(4))
    with pytest.raises(ma.TransformError, match="unknown frame"):
        tree.lookup("base_link", "nowhere")
    tree.add([ma.StampedTransform("odom", "island", np.eye(4))])
    with pytest.raises(ma.TransformError, match="not connected"):
        tree.lookup("base_link", "island")


@pytest.mark.parametrize(
    "q", [(0, 0, 0, 0), (0, 0, float("nan"), 1), (0, 0, 0, 2.0)], ids=["zero", "nan", "norm2"]
)
def test_bad_quaternion(factory, q):
    msg = _tf(factory, "base_link", "cam", np.eye(4), q=q)
    with pytest.raises(ma.TransformError, match="quaternion"):
        ma.transform_stamped_to_matrix(msg)


def test_tf_message_rosbags():
    factory = _rosbags_factory()
    rig = surround6()
    ts = [ma.StampedTransform("base_link", c.frame_id, c.ego_from_cam_array, 9) for c in rig.cameras]
    msg = _roundtrip_cdr(factory, ma.make_tf_message(factory, ts), "tf2_msgs/msg/TFMessage")
    tree = ma.TfTree()
    tree.add_message(msg)
    for c in rig.cameras:
        np.testing.assert_allclose(tree.lookup("base_link", c.frame_id), c.ego_from_cam_array,
                                   atol=1e-9)


def test_odometry_roundtrip(factory):
    T = make_transform(rpy_to_rot(0.0, 0.05, 1.2), (10.0, -3.0, 0.2))
    msg = ma.make_odometry(factory, T, (2.0, 0.1, 0.0), (0.0, 0.0, 0.3), 77)
    msg = _roundtrip_cdr(factory, msg, "nav_msgs/msg/Odometry")
    st = ma.odometry_to_state(msg)
    assert (st.frame_id, st.child_frame_id, st.stamp_ns) == ("odom", "base_link", 77)
    np.testing.assert_allclose(st.world_from_ego, T, atol=1e-12)
    np.testing.assert_allclose(st.linear_velocity, (2.0, 0.1, 0.0))
    np.testing.assert_allclose(st.angular_velocity, (0.0, 0.0, 0.3))


# ------------------------------------------------------------------ OccupancyGrid
@pytest.mark.parametrize(
    "grid", [BevGrid(), BevGrid(-10.0, 20.0, -6.0, 6.0, 0.25), BevGrid(0.0, 3.3, -1.1, 1.1, 0.1)],
    ids=["default", "quarter", "tenth"],
)
def test_occupancy_roundtrip(factory, grid):
    probs = RNG.random(grid.shape)
    known = RNG.random(grid.shape) > 0.2
    msg = ma.make_occupancy_grid(factory, grid, probs, known, 11, "base_link")
    data_type = np.ndarray if factory.name == "rosbags" else array.array
    assert isinstance(msg.data, data_type)
    msg = _roundtrip_cdr(factory, msg, "nav_msgs/msg/OccupancyGrid")
    assert (msg.info.width, msg.info.height) == (grid.width, grid.height)
    assert (msg.info.origin.position.x, msg.info.origin.position.y) == grid.origin_xy
    assert ma.grid_from_info(msg.info) == grid
    p, k = ma.occupancy_grid_to_layer(msg, grid)
    np.testing.assert_array_equal(k, known)
    np.testing.assert_allclose(p[known], np.rint(probs[known] * 100) / 100, atol=1e-6)
    assert np.all(p[~known] == 0)
    p2, k2 = ma.occupancy_grid_to_layer(msg)  # grid reconstructed from info
    np.testing.assert_array_equal(k2, k)


def test_occupancy_mismatch(factory):
    grid = BevGrid(-10.0, 20.0, -6.0, 6.0, 0.25)
    msg = ma.make_occupancy_grid(factory, grid, np.zeros(grid.shape), None, 0, "base_link")
    for other, match in [
        (BevGrid(-10.0, 20.0, -6.0, 6.0, 0.5), "resolution"),
        (BevGrid(-9.0, 21.0, -6.0, 6.0, 0.25), "origin"),
        (BevGrid(-10.0, 21.0, -6.0, 6.0, 0.25), "cells"),
    ]:
        with pytest.raises(ma.GridMessageError, match=match):
            ma.occupancy_grid_to_layer(msg, other)
    with pytest.raises(ma.GridMessageError, match="shape"):
        ma.make_occupancy_grid(factory, grid, np.zeros((3, 3)), None, 0, "base_link")


# ------------------------------------------------------------------ misc
@pytest.mark.parametrize("ns", [0, 1, 999_999_999, 1_000_000_000, 1_700_000_000_123_456_789])
def test_time_conversion(factory, ns):
    sec, nsec = ma.ns_to_sec_nanosec(ns)
    assert 0 <= nsec < 1_000_000_000 and sec * 1_000_000_000 + nsec == ns
    assert ma.stamp_to_ns(ma.make_time(factory, ns)) == ns


def test_factory_unknown_type(factory):
    with pytest.raises(ma.MessageFactoryError):
        factory.msg("no_such_msgs/msg/Thing")
    with pytest.raises(ma.MessageFactoryError):
        factory.msg("not a type name")


def test_importing_adapters_loads_no_ros():
    assert ros_modules_loaded_by("import msg_adapters") == []


def test_ego_from_optical_through_tf(factory):
    """A camera given by mount pose survives TransformStamped -> 4x4 exactly."""
    T = ego_from_optical((1.0, 0.5, 1.6), yaw=0.4, pitch=0.1)
    msg = _roundtrip_cdr(factory, _tf(factory, "base_link", "c", T), "geometry_msgs/msg/TransformStamped")
    np.testing.assert_allclose(ma.transform_stamped_to_matrix(msg).matrix, T, atol=1e-12)
