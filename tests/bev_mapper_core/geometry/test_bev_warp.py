"""BEV layers moved between ego poses (bev_mapper_core/geometry/bev_warp.py, numpy): exact cell shifts for
known motions, rotations about the ego origin, validity at the border, bad transforms refused, and
the same values as torch's grid_sample (bev_mapper_core/nn/bev_warp.py) on random layers and motions."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from bev_mapper_core.errors import ConfigError
from bev_mapper_core.geometry.bev_warp import source_points, warp_layers
from bev_mapper_core.geometry.grid import BevGrid, grid_preset
from bev_mapper_core.geometry.transforms import rpy_to_rot
from bev_mapper_core.nn.bev_warp import warp_batch

GRID = BevGrid(-10.0, 10.0, -5.0, 5.0, 0.5)  # 40 x 20 cells


def pose(x=0.0, y=0.0, yaw=0.0) -> np.ndarray:
    """``odom_from_base`` of a planar pose."""
    T = np.eye(4)
    T[:3, :3] = rpy_to_rot(0.0, 0.0, yaw)
    T[:3, 3] = (x, y, 0.0)
    return T


def prev_from_cur(prev: np.ndarray, cur: np.ndarray) -> np.ndarray:
    return np.linalg.inv(prev) @ cur


@pytest.mark.parametrize("cells_x, cells_y", [(3, 0), (0, -2), (5, 4)])
def test_a_translation_moves_a_marker_by_exactly_that_many_cells(cells_x, cells_y):
    prev = np.zeros((1, *GRID.shape), np.float32)
    prev[0, 10, 20] = 1.0  # row 10 (y), col 20 (x)
    # the car drove cells_x cells forward and cells_y cells left: the world moves back and right
    T = prev_from_cur(pose(), pose(cells_x * GRID.resolution, cells_y * GRID.resolution))
    out, valid = warp_layers(prev, GRID, T)
    hits = np.argwhere(out[0] > 0.5).tolist()
    assert hits == [[10 - cells_y, 20 - cells_x]] and out.sum() == pytest.approx(1.0, abs=1e-5)
    # cells whose earlier point fell off the grid are the strips the car drove into
    assert valid.sum() == (GRID.width - abs(cells_x)) * (GRID.height - abs(cells_y))
    if cells_x:
        assert not valid[:, GRID.width - cells_x:].any() and valid[:, : GRID.width - cells_x].any()


def test_a_yaw_turns_the_layer_about_the_ego_origin():
    grid = grid_preset("ahead")  # not centred on the ego: x 0..32 m
    marker_xy = (20.125, 4.125)  # a cell centre
    prev = np.zeros((1, *grid.shape), np.float32)
    r, c = grid.metric_to_cell(*marker_xy)
    prev[0, int(r), int(c)] = 1.0
    yaw = math.radians(10.0)
    out, _ = warp_layers(prev, grid, prev_from_cur(pose(), pose(yaw=yaw)))
    # the car turned left by 10 degrees: the marker now lies 10 degrees further right
    want = (math.cos(-yaw) * marker_xy[0] - math.sin(-yaw) * marker_xy[1],
            math.sin(-yaw) * marker_xy[0] + math.cos(-yaw) * marker_xy[1])
    rows, cols = np.nonzero(out[0] > 0.05)
    xs, ys = grid.cell_to_metric(rows, cols)
    w = out[0, rows, cols]
    centroid = (float((xs * w).sum() / w.sum()), float((ys * w).sum() / w.sum()))
    assert centroid == pytest.approx(want, abs=0.5 * grid.resolution)
    assert out.sum() == pytest.approx(1.0, abs=0.05)  # bilinear spreads it, keeps its mass


def test_identity_and_batches_and_source_points():
    x = np.random.default_rng(0).random((2, 3, *GRID.shape), dtype=np.float32)
    out, valid = warp_layers(x, GRID, np.eye(4))
    np.testing.assert_allclose(out, x, rtol=0, atol=1e-6)
    assert valid.all()
    xs, ys = source_points(GRID, pose(1.0, 0.0))
    np.testing.assert_allclose(xs, GRID.centers[0] + 1.0)
    np.testing.assert_allclose(ys, GRID.centers[1])
    single, _ = warp_layers(x[0], GRID, pose(1.0, 0.0))
    batch, _ = warp_layers(x, GRID, pose(1.0, 0.0))
    np.testing.assert_array_equal(single, batch[0])


def test_bad_transforms_and_layers_are_refused():
    x = np.zeros((1, *GRID.shape), np.float32)
    with pytest.raises(ConfigError, match="4x4"):
        warp_layers(x, GRID, np.eye(3))
    with pytest.raises(ConfigError, match="finite"):
        warp_layers(x, GRID, np.full((4, 4), np.nan))
    scaled = np.eye(4)
    scaled[0, 0] = 2.0
    with pytest.raises(ConfigError, match="rotation"):
        warp_layers(x, GRID, scaled)
    with pytest.raises(ValueError, match="layers must be"):
        warp_layers(np.zeros((1, 5, 5), np.float32), GRID, np.eye(4))


@pytest.mark.parametrize("seed", range(4))
def test_numpy_warp_equals_torch_grid_sample(seed):
    """Reference test: the numpy warp of the published maps' fusion gives torch's bilinear
    grid_sample values (the learned methods' batched warp) for random layers and planar motions."""
    rng = np.random.default_rng(seed)
    x = rng.standard_normal((3, *GRID.shape)).astype(np.float32)
    T = pose(*rng.uniform(-3.0, 3.0, 2), rng.uniform(-math.pi, math.pi))
    out, valid = warp_layers(x, GRID, T)
    ref, ref_valid = warp_batch(torch.from_numpy(x)[None], GRID, torch.from_numpy(T)[None])
    np.testing.assert_allclose(out, ref[0].numpy(), rtol=0, atol=1e-5)  # float32 rounding of the weights
    np.testing.assert_array_equal(valid, ref_valid[0].numpy())
