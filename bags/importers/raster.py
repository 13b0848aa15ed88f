"""Map geometry of a public dataset onto the package's BEV grid, in the conventions of the
nuScenes devkit's map rasteriser and of HDMapNet's evaluation (numpy and OpenCV only, no shapely).

The grid is placed as a *patch* at an ego pose (:class:`Patch`): its centre at the grid's centre
seen from the ego, rotated by the ego's yaw only (HDMapNet: ``patch_angle = quaternion_yaw(...)``,
the devkit's ``get_map_mask(patch_box, patch_angle, ...)`` with ``patch_box = (x, y, height,
width)``, height along the ego's y). Canvas coordinates are ``((local + extent / 2) * cells /
extent)``: canvas ``(u, v)`` = ``(column, row)`` of the package's grid (column along +x forward,
row along +y left), the corner of cell ``(0, 0)`` at ``(0, 0)``.

* Polygons (:func:`fill_polygons`): clipped to the patch, vertices rounded to integers, filled with
  ``cv2.fillPoly``, holes cleared afterwards (also over polygons filled before, as the devkit's
  ``mask_for_polygons`` does): the devkit's rasteriser. A hole the patch border cuts is a notch of
  the clipped polygon in the devkit; here it is cleared from that polygon alone, which differs
  from the devkit only on the cells of the notch's edges. Cell ``(r, c)``
  is thus set when the point ``(c, r)`` of the canvas (the cell's lower corner, not its centre)
  lies in the polygon, as the devkit does.
* Lines (:func:`draw_lines`): clipped to the patch, vertices truncated to integers
  (``np.int32``), drawn with ``cv2.polylines`` ``thickness`` px wide: HDMapNet's
  ``mask_for_lines`` (thickness 5 in its evaluation).
* Region boundaries (:func:`draw_boundaries`): HDMapNet's ``contours`` class is the outline of the
  union of road segments and lanes, without the parts within 0.2 m of the patch border, drawn like
  the lines. Without shapely the union is made on a canvas 4x finer and its outline traced there
  (``cv2.findContours``), so the outline is within a quarter cell of HDMapNet's.

Clipping is Sutherland-Hodgman's for polygons (exact for any polygon the patch cuts into one
piece; a polygon cut into several pieces keeps zero-width joins along the patch border, which can
set a few cells of the grid's outermost rows or columns) and Liang-Barsky's for lines.
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Sequence
from dataclasses import dataclass

import cv2
import numpy as np

from bev_mapper_core.geometry.grid import BevGrid

#: HDMapNet's line thickness in its evaluation (``--thickness 5``), in canvas pixels (cells).
HDMAPNET_THICKNESS = 5
#: HDMapNet drops the outline of road regions within this many metres of the patch border.
BOUNDARY_MARGIN_M = 0.2
#: How much finer than the grid :func:`draw_boundaries` traces region outlines.
BOUNDARY_SUPERSAMPLE = 4


def yaw_of(rotation: np.ndarray) -> float:
    """Heading of a 3x3 rotation: the angle of its x axis in the xy plane (the devkit's
    ``quaternion_yaw``).
    """
    R = np.asarray(rotation, dtype=np.float64)
    return float(math.atan2(R[1, 0], R[0, 0]))


@dataclass(frozen=True)
class Patch:
    """The package's grid placed at an ego pose in a map's plane.

    Args:
        grid: the BEV grid (cells along x = canvas width, along y = canvas height).
        center_xy: the grid's centre in map coordinates (metres).
        yaw: the ego's heading in the map (radians).
    """

    grid: BevGrid
    center_xy: tuple[float, float]
    yaw: float

    @classmethod
    def at(cls, grid: BevGrid, world_from_ego: np.ndarray) -> "Patch":
        """The patch of ``grid`` around the ego pose ``world_from_ego`` (4x4; yaw only is kept)."""
        T = np.asarray(world_from_ego, dtype=np.float64)
        yaw = yaw_of(T[:3, :3])
        cx, cy = (grid.x_min + grid.x_max) / 2.0, (grid.y_min + grid.y_max) / 2.0
        c, s = math.cos(yaw), math.sin(yaw)
        return cls(grid, (float(T[0, 3] + c * cx - s * cy), float(T[1, 3] + s * cx + c * cy)), yaw)

    @property
    def size(self) -> tuple[float, float]:
        """``(height, width)`` in metres: the devkit's ``patch_box[2:]``."""
        g = self.grid
        return (g.y_max - g.y_min, g.x_max - g.x_min)

    @property
    def canvas(self) -> tuple[int, int]:
        """``(height, width)`` in cells: the devkit's ``canvas_size``."""
        return self.grid.shape

    def bounds(self) -> tuple[float, float, float, float]:
        """``(x_min, y_min, x_max, y_max)`` in map coordinates of the (rotated) patch."""
        h, w = self.size
        c, s = abs(math.cos(self.yaw)), abs(math.sin(self.yaw))
        hx, hy = (w * c + h * s) / 2.0, (w * s + h * c) / 2.0
        x, y = self.center_xy
        return (x - hx, y - hy, x + hx, y + hy)

    def to_canvas(self, xy: np.ndarray, scale: float = 1.0) -> np.ndarray:
        """Map points ``(N, 2)`` -> canvas coordinates ``(N, 2)`` (u along x, v along y), the
        canvas ``scale`` times finer than the grid.
        """
        xy = np.asarray(xy, dtype=np.float64).reshape(-1, 2)  # (N, 2)
        c, s = math.cos(-self.yaw), math.sin(-self.yaw)
        dx, dy = xy[:, 0] - self.center_xy[0], xy[:, 1] - self.center_xy[1]
        h, w = self.size
        H, W = self.canvas
        u = (c * dx - s * dy + w / 2.0) * (W * scale / w)
        v = (s * dx + c * dy + h / 2.0) * (H * scale / h)
        return np.stack([u, v], axis=1)  # (N, 2)


def overlapping(boxes: np.ndarray, bounds: tuple[float, float, float, float]) -> np.ndarray:
    """Indices of the ``(M, 4)`` boxes ``(x_min, y_min, x_max, y_max)`` that overlap ``bounds``."""
    if len(boxes) == 0:
        return np.zeros(0, dtype=np.int64)
    x0, y0, x1, y1 = bounds
    hit = (boxes[:, 0] <= x1) & (boxes[:, 2] >= x0) & (boxes[:, 1] <= y1) & (boxes[:, 3] >= y0)
    return np.flatnonzero(hit)


# ------------------------------------------------------------------ clipping
def _clip_half(pts: np.ndarray, axis: int, bound: float, keep_above: bool) -> np.ndarray:
    """One Sutherland-Hodgman step: the polygon ``(N, 2)`` cut to ``pts[:, axis] >= bound``
    (``keep_above``) or ``<= bound``.
    """
    if len(pts) == 0:
        return pts
    d = pts[:, axis] - bound if keep_above else bound - pts[:, axis]
    inside = d >= 0
    if inside.all():
        return pts
    nxt = np.roll(pts, -1, axis=0)
    dn = np.roll(d, -1)
    crossing = inside != (dn >= 0)
    with np.errstate(divide="ignore", invalid="ignore"):
        t = np.where(crossing, d / (d - dn), 0.0)
    cut = pts + (nxt - pts) * t[:, None]
    cut[crossing, axis] = bound  # exactly on the border
    out = np.stack([pts, cut], axis=1).reshape(-1, 2)  # (N, 2, 2) -> (2N, 2): vertex, then crossing
    keep = np.stack([inside, crossing], axis=1).reshape(-1)  # (N, 2) -> (2N,)
    return out[keep]


def clip_polygon(pts: np.ndarray, width: float, height: float) -> np.ndarray:
    """The polygon ``(N, 2)`` clipped to ``[0, width] x [0, height]`` (possibly empty)."""
    p = np.asarray(pts, dtype=np.float64).reshape(-1, 2)  # (N, 2)
    if len(p) and np.array_equal(p[0], p[-1]):
        p = p[:-1]  # closed ring: drop the repeated vertex
    if len(p) and p[:, 0].min() >= 0 and p[:, 1].min() >= 0 and p[:, 0].max() <= width and p[:, 1].max() <= height:
        return p
    for axis, bound, above in ((0, 0.0, True), (0, float(width), False), (1, 0.0, True), (1, float(height), False)):
        p = _clip_half(p, axis, bound, above)
    return p


def clip_polyline(pts: np.ndarray, width: float, height: float) -> list[np.ndarray]:
    """The pieces ``(K, 2)`` of the polyline ``(N, 2)`` inside ``[0, width] x [0, height]``
    (Liang-Barsky per segment; consecutive inside segments stay one piece).
    """
    p = np.asarray(pts, dtype=np.float64).reshape(-1, 2)  # (N, 2)
    if len(p) < 2:
        return []
    if p[:, 0].min() >= 0 and p[:, 1].min() >= 0 and p[:, 0].max() <= width and p[:, 1].max() <= height:
        return [p]
    a, b = p[:-1], p[1:]
    d = b - a
    t0, t1 = np.zeros(len(a)), np.ones(len(a))
    for axis, lo, hi in ((0, 0.0, float(width)), (1, 0.0, float(height))):
        da, pa = d[:, axis], a[:, axis]
        flat = da == 0
        outside = flat & ((pa < lo) | (pa > hi))
        t1[outside], t0[outside] = 0.0, 1.0
        with np.errstate(divide="ignore", invalid="ignore"):
            ta, tb = (lo - pa) / da, (hi - pa) / da
        enter, leave = np.minimum(ta, tb), np.maximum(ta, tb)
        moving = ~flat
        t0[moving] = np.maximum(t0[moving], enter[moving])
        t1[moving] = np.minimum(t1[moving], leave[moving])
    pieces: list[list[np.ndarray]] = []
    open_piece = False
    for i in range(len(a)):
        if t0[i] > t1[i] or (t0[i] == t1[i] and 0 < t0[i] < 1):
            open_piece = False
            continue
        start, end = a[i] + d[i] * t0[i], a[i] + d[i] * t1[i]
        if open_piece and t0[i] == 0.0:
            pieces[-1].append(end)
        else:
            pieces.append([start, end])
        open_piece = t1[i] == 1.0
    out = []
    for piece in pieces:
        arr = np.clip(np.asarray(piece), 0.0, [float(width), float(height)])  # (K, 2); float noise at the border
        out.append(arr)
    return out


# ------------------------------------------------------------- rasterising
@dataclass(frozen=True)
class MapPolygon:
    """A polygon in map coordinates: ``exterior`` ``(N, 2)`` and ``holes`` (each ``(K, 2)``)."""

    exterior: np.ndarray
    holes: tuple[np.ndarray, ...] = ()


def fill_polygons(patch: Patch, polygons: Iterable[MapPolygon], out: np.ndarray | None = None,
                  scale: int = 1) -> np.ndarray:
    """``(H, W)`` uint8 mask (1 inside) of ``polygons`` on the patch, the devkit's way (module
    docstring); ``scale``: a canvas that many times finer. Draws into ``out`` when given.
    """
    H, W = patch.canvas
    mask = np.zeros((H * scale, W * scale), np.uint8) if out is None else out
    w, h = W * scale, H * scale
    for poly in polygons:
        ext = clip_polygon(patch.to_canvas(poly.exterior, scale), w, h)
        if len(ext) < 3:
            continue
        inner, cut = [], []  # holes inside the patch; holes the patch border cuts (notches after clipping)
        for hole in poly.holes:
            c = patch.to_canvas(hole, scale)
            clipped = clip_polygon(c, w, h)
            if len(clipped) >= 3:
                (inner if len(clipped) == len(c) and np.array_equal(clipped, c) else cut).append(
                    np.round(clipped).astype(np.int32))
        ext = np.round(ext).astype(np.int32)
        if cut:  # a notch of this polygon: it does not erase what other polygons filled
            own = np.zeros_like(mask)
            cv2.fillPoly(own, [ext], 1)
            cv2.fillPoly(own, cut, 0)
            for ring in cut:  # the notch's edges are the polygon's boundary: filled, as fillPoly fills edges
                nxt = np.roll(ring, -1, axis=0)
                on_border = ((ring[:, 0] == nxt[:, 0]) & np.isin(ring[:, 0], (0, w))) | (
                    (ring[:, 1] == nxt[:, 1]) & np.isin(ring[:, 1], (0, h)))
                for a, b in zip(ring[~on_border], nxt[~on_border]):
                    cv2.line(own, tuple(map(int, a)), tuple(map(int, b)), 1)
            np.bitwise_or(mask, own, out=mask)
        else:
            cv2.fillPoly(mask, [ext], 1)
        if inner:  # the devkit clears a hole after filling its polygon, also over earlier polygons
            cv2.fillPoly(mask, inner, 0)
    return mask


def _draw_pieces(mask: np.ndarray, pieces: Iterable[np.ndarray], thickness: int) -> None:
    for piece in pieces:
        coords = np.asarray(piece, np.float64).astype(np.int32).reshape(-1, 2)  # truncation, as np.int32 does
        if len(coords) >= 2:
            cv2.polylines(mask, [coords], False, 1, thickness=int(thickness))


def draw_lines(patch: Patch, lines: Iterable[np.ndarray], thickness: int = HDMAPNET_THICKNESS,
               out: np.ndarray | None = None) -> np.ndarray:
    """``(H, W)`` uint8 mask of the map polylines (each ``(N, 2)``), HDMapNet's way (module
    docstring). Draws into ``out`` when given.
    """
    H, W = patch.canvas
    mask = np.zeros((H, W), np.uint8) if out is None else out
    for line in lines:
        _draw_pieces(mask, clip_polyline(patch.to_canvas(line), W, H), thickness)
    return mask


def _runs(points: np.ndarray, keep: np.ndarray, closed: bool) -> list[np.ndarray]:
    """The maximal runs of consecutive ``points`` where ``keep`` holds (a closed ring wraps)."""
    n = len(points)
    if keep.all():
        return [np.concatenate([points, points[:1]]) if closed else points]
    if not keep.any():
        return []
    if closed:  # start the ring just after a dropped point so that no run wraps
        first = int(np.flatnonzero(~keep)[0])
        order = np.r_[first + 1:n, 0:first + 1]
        points, keep = points[order], keep[order]
    edges = np.flatnonzero(np.diff(np.r_[0, keep.astype(np.int8), 0]))  # run starts and ends
    return [points[s:e] for s, e in zip(edges[::2], edges[1::2])]


def draw_boundaries(patch: Patch, regions: Sequence[MapPolygon], thickness: int = HDMAPNET_THICKNESS,
                    margin_m: float = BOUNDARY_MARGIN_M, supersample: int = BOUNDARY_SUPERSAMPLE) -> np.ndarray:
    """``(H, W)`` uint8 mask of the outline of the union of ``regions`` (HDMapNet's ``contours``,
    module docstring): outer outlines and holes, drawn ``thickness`` cells wide, without the
    outline within ``margin_m`` of the patch border.
    """
    H, W = patch.canvas
    k = int(supersample)
    fine = fill_polygons(patch, regions, scale=k)  # (k*H, k*W)
    mask = np.zeros((H, W), np.uint8)
    if not fine.any():
        return mask
    contours, _ = cv2.findContours(fine, cv2.RETR_CCOMP, cv2.CHAIN_APPROX_NONE)
    mu = margin_m / patch.grid.resolution  # margin in cells
    for contour in contours:
        # (N, 1, 2) -> (N, 2): fine pixel i stands for canvas point i / k (the fill's convention), so
        # the outline runs within half a fine pixel of the region's edge
        pts = contour.reshape(-1, 2).astype(np.float64) / k
        keep = (pts[:, 0] > mu) & (pts[:, 0] < W - mu) & (pts[:, 1] > mu) & (pts[:, 1] < H - mu)
        _draw_pieces(mask, _runs(pts, keep, closed=True), thickness)
    return mask
