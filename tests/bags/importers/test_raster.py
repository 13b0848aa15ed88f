"""The devkit-convention clipping and rasterising of :mod:`bags.importers.raster`, on hand-computed cells."""

from __future__ import annotations

import math

import numpy as np

from bags.importers.raster import MapPolygon, Patch, clip_polygon, clip_polyline, draw_boundaries, draw_lines, fill_polygons
from bev_mapper_core.geometry.grid import BevGrid

GRID = BevGrid(0.0, 10.0, 0.0, 5.0, 1.0)  # 10 x 5 cells of 1 m, ego at the corner


def _patch(x=5.0, y=2.5, yaw=0.0) -> Patch:
    T = np.eye(4)
    T[:2, :2] = [[math.cos(yaw), -math.sin(yaw)], [math.sin(yaw), math.cos(yaw)]]
    T[:2, 3] = (x - 5.0, y - 2.5) if yaw == 0 else (x, y)
    return Patch.at(GRID, T)


def test_the_patch_is_centred_on_the_grid_seen_from_the_ego():
    p = _patch(yaw=math.pi / 2)  # ego at (5, 2.5) heading +y: the grid's centre (5, 2.5) ahead is at (2.5, 7.5)
    assert np.allclose(p.center_xy, (2.5, 7.5))
    # the map point 3 m ahead, 1 m left of the ego is grid cell corner (3, 1)
    assert np.allclose(p.to_canvas(np.array([[5.0 - 1.0, 2.5 + 3.0]])), [[3.0, 1.0]])


def test_polygons_are_clipped_to_the_patch_and_filled_with_rounded_vertices():
    square = np.array([[-3.0, -1.0], [3.0, -1.0], [3.0, 2.0], [-3.0, 2.0]])
    assert {tuple(p) for p in clip_polygon(square, 10, 5)} == {(0, 0), (3, 0), (3, 2), (0, 2)}
    mask = fill_polygons(_patch(), [MapPolygon(np.array([[1.4, 0.6], [3.6, 0.6], [3.6, 2.4], [1.4, 2.4]]))])
    # vertices round to (1, 1) .. (4, 2): cv2.fillPoly sets the cells whose corner points are inside, edges included
    want = np.zeros((5, 10), np.uint8)
    want[1:3, 1:5] = 1
    assert np.array_equal(mask, want)


def test_holes_are_cleared():
    outer = np.array([[0.0, 0.0], [10.0, 0.0], [10.0, 5.0], [0.0, 5.0]])
    hole = np.array([[3.0, 1.0], [6.0, 1.0], [6.0, 3.0], [3.0, 3.0]])
    mask = fill_polygons(_patch(), [MapPolygon(outer, (hole,))])
    assert mask.sum() == 50 - 12 and not mask[1:4, 3:7].any()


def test_lines_are_clipped_into_pieces_truncated_and_drawn_thick():
    pieces = clip_polyline(np.array([[-2.0, 1.0], [4.0, 1.0], [4.0, 9.0], [6.0, 9.0], [6.0, 2.0]]), 10, 5)
    assert len(pieces) == 2
    assert np.allclose(pieces[0], [[0, 1], [4, 1], [4, 5]]) and np.allclose(pieces[1], [[6, 5], [6, 2]])
    mask = draw_lines(_patch(), [np.array([[0.5, 2.9], [9.5, 2.9]])], thickness=1)
    assert np.array_equal(np.flatnonzero(mask.any(axis=1)), [2])  # y 2.9 truncates to row 2
    assert np.array_equal(np.flatnonzero(mask[2]), np.arange(0, 10))


def test_region_outlines_leave_out_the_patch_border():
    grid = BevGrid(-30.0, 30.0, -15.0, 15.0, 0.15)
    patch = Patch.at(grid, np.eye(4))
    road = MapPolygon(np.array([[-100.0, -5.0], [100.0, -5.0], [100.0, 5.0], [-100.0, 5.0]]))
    mask = draw_boundaries(patch, [road], thickness=1)
    rows = np.flatnonzero(mask[:, 200])
    assert set(rows) == {66, 133}  # y = -5 and 5: rows 66.67 and 133.33, within a quarter cell
    assert not mask[67:133].any()  # no outline where the road leaves the patch
