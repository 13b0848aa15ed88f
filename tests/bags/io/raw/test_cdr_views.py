"""Images and OccupancyGrids decoded from their CDR bytes equal rosbags' messages field for
field; whatever they are unsure of goes to rosbags (which then decodes or refuses it as before)."""

from __future__ import annotations

import numpy as np
import pytest
from rosbags.typesys import Stores, get_typestore

from bags.io.raw.cdr import GRID_TYPE, IMAGE_TYPE, Undecodable, decode_image, decode_occupancy_grid, fast_deserializer
from bev_mapper_core.geometry.grid import BevGrid
from msg_adapters import RosbagsFactory, make_image, make_occupancy_grid

STORE = get_typestore(Stores.ROS2_JAZZY)
FACTORY = RosbagsFactory(STORE)


def _same(fast, ref, path="msg"):
    """Every field of the rosbags message ``ref`` equals ``fast``'s, with the same type."""
    if isinstance(ref, np.ndarray):
        assert isinstance(fast, np.ndarray) and fast.dtype == ref.dtype, path
        np.testing.assert_array_equal(fast, ref, err_msg=path)
        return
    if hasattr(ref, "__dataclass_fields__"):
        for name in ref.__dataclass_fields__:
            if name != "__msgtype__":
                _same(getattr(fast, name), getattr(ref, name), f"{path}.{name}")
        return
    assert type(fast) is type(ref) and fast == ref, (path, fast, ref)


def _raw(msg, msgtype, little_endian=True) -> bytes:
    return bytes(STORE.serialize_cdr(msg, msgtype, little_endian=little_endian))


@pytest.mark.parametrize("frame_id", ["", "c", "cam", "cam0", "front_left_optical_frame"])
@pytest.mark.parametrize("encoding,shape,dtype,step", [
    ("mono8", (5, 7), np.uint8, None), ("rgb8", (3, 4, 3), np.uint8, 16), ("16UC1", (4, 3), np.uint16, None),
    ("bgra8", (2, 5, 4), np.uint8, None)])
def test_images_decode_as_rosbags_does(frame_id, encoding, shape, dtype, step):
    rng = np.random.default_rng(len(frame_id))
    arr = rng.integers(0, 250, shape).astype(dtype)
    for big in (False, True) if dtype == np.uint16 else (False,):
        msg = make_image(FACTORY, arr, encoding, 1_700_000_000_123_456_789, frame_id, step=step, bigendian=big)
        raw = _raw(msg, IMAGE_TYPE)
        fast = decode_image(raw)
        _same(fast, STORE.deserialize_cdr(raw, IMAGE_TYPE))
        assert not fast.data.flags.writeable  # a view of the bytes, not a copy


@pytest.mark.parametrize("frame_id", ["", "m", "map", "base_link"])
def test_occupancy_grids_decode_as_rosbags_does(frame_id):
    grid = BevGrid(x_min=-3.0, x_max=4.5, y_min=-1.2, y_max=2.4, resolution=0.3)
    rng = np.random.default_rng(7)
    probs = rng.random(grid.shape).astype(np.float32)
    msg = make_occupancy_grid(FACTORY, grid, probs, rng.random(grid.shape) < 0.8, 42_000_000_001, frame_id)
    raw = _raw(msg, GRID_TYPE)
    _same(decode_occupancy_grid(raw), STORE.deserialize_cdr(raw, GRID_TYPE))


def test_what_the_decoders_are_unsure_of_goes_to_rosbags():
    msg = make_image(FACTORY, np.zeros((2, 3), np.uint8), "mono8", 5, "cam")
    raw = _raw(msg, IMAGE_TYPE)
    big = _raw(msg, IMAGE_TYPE, little_endian=False)
    assert decode_image(big) is None  # big-endian CDR
    assert decode_image(raw[:-2]) is None  # the data runs past the bytes
    assert decode_image(raw + bytes(8)) is None  # bytes left over, which rosbags refuses
    assert decode_image(raw[:3]) is None
    assert decode_occupancy_grid(raw) is None  # an Image is no OccupancyGrid
    decode = fast_deserializer(STORE.deserialize_cdr)
    _same(decode(big, IMAGE_TYPE), STORE.deserialize_cdr(big, IMAGE_TYPE))  # rosbags decodes it
    # and refuses what it always refused: an image as an Undecodable (one lost image, counted by
    # the reader), any other message by raising (damage)
    bad = decode(raw + bytes(8), IMAGE_TYPE)
    assert isinstance(bad, Undecodable) and "size mismatch" in bad.reason
    grid = _raw(make_occupancy_grid(FACTORY, BevGrid(-1, 1, -1, 1, 0.5), np.zeros((4, 4), np.float32), None, 5, "b"),
                GRID_TYPE)
    with pytest.raises(Exception, match="size mismatch"):
        decode(grid + bytes(8), GRID_TYPE)
    info = FACTORY.msg("sensor_msgs/msg/RegionOfInterest", x_offset=1, y_offset=2, height=3, width=4,
                       do_rectify=True)
    assert decode(_raw(info, "sensor_msgs/msg/RegionOfInterest"), "sensor_msgs/msg/RegionOfInterest") == info
