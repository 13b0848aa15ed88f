"""The frame's layers through lookup tables are ``occupancy_grid_to_layer``'s, value for value,
and a layer it refuses is refused with the same error."""

from __future__ import annotations

import numpy as np
import pytest
from rosbags.typesys import Stores, get_typestore

from bags.io.raw.cdr import GRID_TYPE, decode_occupancy_grid
from bags.io.reader.layers import LayerDecoder
from bev_mapper_core.geometry.grid import BevGrid
from msg_adapters import GridMessageError, RosbagsFactory, make_occupancy_grid, occupancy_grid_to_layer

STORE = get_typestore(Stores.ROS2_JAZZY)
FACTORY = RosbagsFactory(STORE)
GRID = BevGrid(x_min=-6.0, x_max=6.0, y_min=-3.0, y_max=3.0, resolution=0.15)


def _message(cells: np.ndarray, grid: BevGrid = GRID):
    """An OccupancyGrid of ``grid`` holding ``cells`` (int8, row-major), as the reader decodes it."""
    msg = make_occupancy_grid(FACTORY, grid, np.zeros(grid.shape, np.float32), None, 7, "base_link")
    msg.data = cells.astype(np.int8)
    return decode_occupancy_grid(bytes(STORE.serialize_cdr(msg, GRID_TYPE))), msg


def test_layers_equal_occupancy_grid_to_layer():
    rng = np.random.default_rng(5)
    dec = LayerDecoder(GRID)
    for _ in range(20):
        cells = rng.integers(-1, 101, GRID.width * GRID.height)
        cells[rng.random(cells.size) < 0.3] = rng.choice([-1, 0, 49, 50, 100])
        fast, slow = _message(cells)
        want_p, want_k = occupancy_grid_to_layer(slow, GRID)
        for msg in (fast, slow):  # the views of the bytes, and rosbags' messages (the slow way)
            probs, known = np.empty(GRID.shape, np.float32), np.empty(GRID.shape, bool)
            dec.into(msg, probs, known)
            np.testing.assert_array_equal(probs, want_p)
            np.testing.assert_array_equal(known, want_k)
            half = dec.half(msg)
            assert half.dtype == bool
            np.testing.assert_array_equal(half, want_p >= 0.5)
            as_f32 = dec.half(msg, np.empty(GRID.shape, np.float32))
            np.testing.assert_array_equal(as_f32, (want_p >= 0.5).astype(np.float32))
            into_bool = np.empty(GRID.shape, bool)
            assert dec.half(msg, into_bool) is into_bool
            np.testing.assert_array_equal(into_bool, want_p >= 0.5)
            half, known = np.empty(GRID.shape, bool), np.empty(GRID.shape, bool)  # the replay's decoding
            dec.half_into(msg, half, known)
            np.testing.assert_array_equal(half, want_p >= 0.5)
            np.testing.assert_array_equal(known, want_k)
        assert dec.cells(fast) is not None and dec.cells(slow) is None


@pytest.mark.parametrize("bad", ["value", "grid"])
def test_a_layer_it_refuses_fails_as_occupancy_grid_to_layer_does(bad):
    cells = np.zeros(GRID.width * GRID.height, np.int64)
    if bad == "value":
        cells[[3, 9]] = 101
        fast, slow = _message(cells)
    else:  # another resolution: the info does not describe the grid
        other = BevGrid(x_min=-6.0, x_max=6.0, y_min=-3.0, y_max=3.0, resolution=0.3)
        fast, slow = _message(np.zeros(other.width * other.height), other)
    with pytest.raises(GridMessageError) as want:
        occupancy_grid_to_layer(slow, GRID)
    dec = LayerDecoder(GRID)
    assert dec.cells(fast) is None
    with pytest.raises(GridMessageError) as got:
        dec.into(fast, np.empty(GRID.shape, np.float32), np.empty(GRID.shape, bool))
    assert str(got.value) == str(want.value)
    with pytest.raises(GridMessageError):
        dec.half(fast)
    with pytest.raises(GridMessageError) as got:
        dec.half_into(fast, np.empty(GRID.shape, bool), np.empty(GRID.shape, bool))
    assert str(got.value) == str(want.value)


def test_frames_read_with_gt_half_are_the_float_layers_at_one_half(tmp_path):
    """``BagReader.frames(gt_half=True)`` (the replay's) gives bool GT and truth layers, the float
    ones ``>= 0.5``, and the same known cells, frame for frame."""
    from bag_helpers import synth_small

    from bags.io.reader import BagReader

    bag = synth_small(tmp_path / "drive", frames=3, seed=31)
    with BagReader(bag) as r:
        floats = list(r.frames(rgb=False))
    with BagReader(bag) as r:
        halves = list(r.frames(rgb=False, gt_half=True))
    assert len(floats) == len(halves) == 3
    for f, h in zip(floats, halves):
        assert f.gt.dtype == np.float32 and h.gt.dtype == bool and h.truth.dtype == bool
        np.testing.assert_array_equal(h.gt, f.gt >= 0.5)
        np.testing.assert_array_equal(h.gt_known, f.gt_known)
        np.testing.assert_array_equal(h.truth, f.truth >= 0.5)
        assert h.gt.any() and not h.gt.all()
