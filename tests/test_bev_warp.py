"""BEV layers moved between ego poses (bev_mapper_core/geometry/bev_warp.py): exact cell shifts for known
motions, rotations about the ego origin, validity at the border, and bad transforms refused."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from bev_mapper_core.errors import ConfigError
from bev_mapper_core.geometry.bev_warp import source_points, warp_layers
from bev_mapper_core.geometry.grid import BevGrid, grid_preset
from bev_mapper_core.geometry.transforms import rpy_to_rot

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
    prev = torch.zeros(1, *GRID.shape)
    prev[0, 10, 20] = 1.0  # row 10 (y), col 20 (x)
    # the car drove cells_x cells forward and cells_y cells left: the world moves back and right
    T = prev_from_cur(pose(), pose(cells_x * GRID.resolution, cells_y * GRID.resolution))
    out, valid = warp_layers(prev, GRID, T)
    hits = torch.nonzero(out[0] > 0.5).tolist()
    assert hits == [[10 - cells_y, 20 - cells_x]] and out.sum().item() == pytest.approx(1.0, abs=1e-5)
    # cells whose earlier point fell off the grid are the strips the car drove into
    assert valid.sum().item() == (GRID.width - abs(cells_x)) * (GRID.height - abs(cells_y))
    if cells_x:
        assert not valid[:, GRID.width - cells_x:].any() and valid[:, : GRID.width - cells_x].any()


def test_a_yaw_turns_the_layer_about_the_ego_origin():
    grid = grid_preset("ahead")  # not centred on the ego: x 0..32 m
    marker_xy = (20.125, 4.125)  # a cell centre
    prev = torch.zeros(1, *grid.shape)
    r, c = grid.metric_to_cell(*marker_xy)
    prev[0, int(r), int(c)] = 1.0
    yaw = math.radians(10.0)
    out, _ = warp_layers(prev, grid, prev_from_cur(pose(), pose(yaw=yaw)))
    # the car turned left by 10 degrees: the marker now lies 10 degrees further right
    want = (math.cos(-yaw) * marker_xy[0] - math.sin(-yaw) * marker_xy[1],
            math.sin(-yaw) * marker_xy[0] + math.cos(-yaw) * marker_xy[1])
    rows, cols = torch.nonzero(out[0] > 0.05, as_tuple=True)
    xs, ys = grid.cell_to_metric(rows.numpy(), cols.numpy())
    w = out[0, rows, cols].numpy()
    centroid = (float((xs * w).sum() / w.sum()), float((ys * w).sum() / w.sum()))
    assert centroid == pytest.approx(want, abs=0.5 * grid.resolution)
    assert out.sum().item() == pytest.approx(1.0, abs=0.05)  # bilinear spreads it, keeps its mass


def test_identity_and_batches_and_source_points():
    x = torch.rand(2, 3, *GRID.shape)
    out, valid = warp_layers(x, GRID, np.eye(4))
    torch.testing.assert_close(out, x)
    assert valid.all()
    xs, ys = source_points(GRID, pose(1.0, 0.0))
    np.testing.assert_allclose(xs, GRID.centers[0] + 1.0)
    np.testing.assert_allclose(ys, GRID.centers[1])
    single, _ = warp_layers(x[0], GRID, pose(1.0, 0.0))
    batch, _ = warp_layers(x, GRID, pose(1.0, 0.0))
    torch.testing.assert_close(single, batch[0])


def test_bad_transforms_and_layers_are_refused():
    x = torch.zeros(1, *GRID.shape)
    with pytest.raises(ConfigError, match="4x4"):
        warp_layers(x, GRID, np.eye(3))
    with pytest.raises(ConfigError, match="finite"):
        warp_layers(x, GRID, np.full((4, 4), np.nan))
    scaled = np.eye(4)
    scaled[0, 0] = 2.0
    with pytest.raises(ConfigError, match="rotation"):
        warp_layers(x, GRID, scaled)
    with pytest.raises(ValueError, match="layers must be"):
        warp_layers(torch.zeros(1, 5, 5), GRID, np.eye(4))
