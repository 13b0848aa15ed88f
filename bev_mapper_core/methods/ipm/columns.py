"""IPM's occlusion test per image column: the fast form of :mod:`.occlusion`'s ray search.

:mod:`.occlusion` finds each near edge along BEV rays resampled on a polar raster (about 1,500
rays x 800 samples per camera and frame). Here the rays are the camera's **image columns**: the
ground points of a column's pixels lie on one curve from the camera outwards (a straight ray for
a level pinhole camera, nearly so for the shipped pitched ones), so the near edge of the objects
a column sees is its occluding pixel with the smallest ground distance. Built once per
calibration:

* per pixel of the rows that see the camera's ground cells, a sort key packing its ground
  distance and its row (pixels whose ground point is not one of the camera's cells: never an
  occluder, as in the polar raster, which only reads the camera's cells);
* per cell the camera sees (its :class:`~.mapper.GatherTable` order), the image column of the
  pixel it takes and its distance from the camera's ground point.

Per frame: one ``cv2.LUT`` of the label image into those keys (non-occluders: no key), one
minimum per column (its first near edge, its label and row), the face rule and shadow of
:class:`~.occlusion.OcclusionModel` on the columns (a few hundred), and each cell whose own
pixel shows an occluder reads its column's near edge and shadow end. A second near edge is
searched, like the polar raster's, beyond a finite shadow (:data:`~.occlusion.MAX_EDGES`).

The result differs from the polar raster's in the cells where the two discretisations of a ray
disagree (a column is about 4 mrad wide, a polar ray 1 mrad; the near edge is a pixel's ground
point here, a 0.075 m range sample there); ``experiments/ipm_occlusion_columns.py`` scores both
on held-out drives of every rig (docs/RESULTS.md, "Occlusion per image column").
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from bev_mapper_core.geometry.grid import BevGrid
from bev_mapper_core.geometry.rig import RigCamera

from .occlusion import FACE_BREAK_M, MAX_EDGES, OcclusionModel

#: low bits of a key: the label of the occluding pixel
LABEL_BITS = 4
#: The polar raster's near edge is a cell, sampled along rays 1 mrad apart: its steps between
#: rays are smoothed by the cells, so a face it sees breaks where the near edge jumps by more
#: than :data:`~.occlusion.FACE_BREAK_M`. Between two image columns the near edge steps once per
#: image row of their near edges' difference; a face breaks where a step exceeds FACE_BREAK_M plus
#: this many cells (chosen on the validation drives, seeds 900000010-12: docs/RESULTS.md).
COLUMN_FACE_BREAK_CELLS = 1.0
#: Extra slack (cells) beyond an object's assumed depth: a column's near edge is the nearest
#: occluding pixel over the column's whole width, a polar ray's the first cell on a 1 mrad line.
COLUMN_SLACK_CELLS = 1.0
#: keys at or above this are "no occluder here" (pixels outside the camera's cells, non-occluders)
NO_KEY = np.int32(2 ** 29)


@dataclass(frozen=True)
class ColumnRaster:
    """A camera's image columns as rays over its ground cells, built once per calibration.

    Attributes:
        height: camera height above the ground plane (m).
        rows: ``(r0, r1)``, the image rows holding pixels whose ground point is a cell the
            camera sees; only these rows are read per frame.
        key: ``(r1 - r0, w)`` int32 ``(q << (row_bits + LABEL_BITS)) | (row << LABEL_BITS)``
            with ``q`` the pixel's ground distance in units of ``quantum``; :data:`NO_KEY` for
            pixels whose ground point is no cell of the camera.
        dist: ``(r1 - r0, w)`` float32 ground distance of each pixel (``inf`` where no key).
        dazimuth: ``(r1 - r0, w)`` float32 ground-plane angle (rad) between a pixel's ground
            point and its right neighbour's, seen from the camera's ground point: a column's
            lateral width at distance ``d`` is ``d * dazimuth``.
        quantum: metres per unit of ``q``.
        resolution: the grid's cell size (m).
        row_bits: bits of the row field.
        cell_column: ``(n,)`` int64 image column of each seen cell's pixel (gather order).
        cell_dist: ``(n,)`` float32 distance of each seen cell's centre from the camera's
            ground point (gather order).
    """

    height: float
    rows: tuple[int, int]
    key: np.ndarray
    dist: np.ndarray
    dazimuth: np.ndarray
    quantum: float
    resolution: float
    row_bits: int
    cell_column: np.ndarray
    cell_dist: np.ndarray


def column_raster(camera: RigCamera, grid: BevGrid, valid: np.ndarray, cells: np.ndarray,
                  pixels: np.ndarray) -> ColumnRaster:
    """The column raster of ``camera`` over its seen cells.

    Args:
        camera: the rig camera.
        grid: the BEV grid.
        valid: ``(H, W)`` bool, the cells the camera sees (its ground table).
        cells, pixels: ``(n,)`` the seen cells' flat indices and the flat pixel each takes
            (a :class:`~.mapper.GatherTable`).
    """
    T = camera.ego_from_cam_array
    R, (cx, cy, hc) = T[:3, :3], T[:3, 3]
    w, h = camera.model.image_size
    # each pixel's ray through the middle of its lower edge: the nearest ground point a cell
    # taking that pixel can have (cv2.remap's nearest rounds the cell's row to this pixel from
    # there on), as the polar raster's near edge is the first sample in the first occluder cell
    us, vs = np.meshgrid(np.arange(w, dtype=np.float64), np.arange(h, dtype=np.float64) + 0.5)
    rays = camera.model.unproject(np.stack([us.ravel(), vs.ravel()], axis=1)).reshape(h, w, 3)
    d = rays @ R.T  # (h, w, 3) ray directions in the ego frame
    down = d[..., 2] < -1e-9
    t = -hc / np.where(down, d[..., 2], -1.0)
    gx, gy = cx + t * d[..., 0], cy + t * d[..., 1]  # (h, w) ground points
    ok = down & grid.contains(gx, gy)
    row, col = grid.metric_to_cell(np.where(ok, gx, grid.x_min + grid.resolution / 2),
                                   np.where(ok, gy, grid.y_min + grid.resolution / 2))
    H, W = grid.shape
    ok &= valid[np.clip(row, 0, H - 1), np.clip(col, 0, W - 1)]  # (rounding at the far edges)
    dist = np.hypot(gx - cx, gy - cy)
    az = np.arctan2(gy - cy, gx - cx)
    daz = np.abs(np.angle(np.exp(1j * np.diff(az, axis=1))))  # (h, w - 1)
    daz = np.concatenate([daz, daz[:, -1:]], axis=1)  # the last column: its left neighbour's
    used = np.flatnonzero(ok.any(axis=1))
    r0, r1 = (int(used[0]), int(used[-1]) + 1) if len(used) else (0, 1)
    ok, dist, daz = ok[r0:r1], dist[r0:r1], daz[r0:r1]
    row_bits = max(1, (r1 - r0 - 1).bit_length())
    q_bits = 29 - row_bits - LABEL_BITS
    d_max = float(dist[ok].max()) if ok.any() else 1.0
    quantum = max(0.005, d_max / (2 ** q_bits - 2))
    q = np.rint(np.where(ok, dist, 0.0) / quantum).astype(np.int64)
    rows = np.arange(r1 - r0, dtype=np.int64)[:, None]  # (rows, 1)
    key = np.where(ok, (q << (row_bits + LABEL_BITS)) | (rows << LABEL_BITS), int(NO_KEY)).astype(np.int32)
    xs, ys = grid.centers
    cell_dist = np.hypot(xs - cx, ys - cy).reshape(-1)[cells].astype(np.float32)
    return ColumnRaster(float(hc), (r0, r1), key, np.where(ok, dist, np.inf).astype(np.float32),
                        daz.astype(np.float32), quantum, grid.resolution, row_bits, (pixels % w).astype(np.int64),
                        cell_dist)


class ColumnOcclusion:
    """:class:`~.occlusion.OcclusionModel`'s priors and face rule, evaluated per image column.

    Args:
        model: the occlusion model (height and footprint priors).
    """

    def __init__(self, model: OcclusionModel) -> None:
        self.model = model
        occludes = np.zeros(256, bool)
        occludes[: len(model.heights) - 1] = model.heights[:-1] > 0
        self.occludes = occludes  # (256,) label id -> occludes
        #: label id -> the value added to a pixel's key: its label, or NO_KEY (no occluder)
        self._key_lut = np.where(occludes, np.arange(256), int(NO_KEY)).astype(np.int32)

    def hidden(self, cr: ColumnRaster, labels: np.ndarray, ids: np.ndarray,
               margin: float) -> np.ndarray | None:
        """The camera's seen cells hidden from it: ``(k,)`` increasing indices into its gather
        order; ``None`` when none is.

        Args:
            cr: the camera's :class:`ColumnRaster`.
            labels: ``(h, w)`` the camera's label image.
            ids: ``(n,)`` the label id each seen cell takes (the gather of ``labels``).
            margin: slack in metres added to each near edge's footprint depth.
        """
        if ids.dtype != np.uint8:
            ids = np.minimum(ids, 255).astype(np.uint8)
        cand = np.flatnonzero(self.occludes[ids])  # only a cell showing an occluder can be hidden
        if not len(cand):
            return None
        r0, r1 = cr.rows
        part = labels[r0:r1]
        if part.dtype != np.uint8:
            part = np.minimum(part, 255).astype(np.uint8)
        key = cr.key + cv2.LUT(part, self._key_lut)  # (rows, w) int32; >= NO_KEY: no occluder
        first = key.min(axis=0)  # (w,) each column's nearest occluding pixel
        m = self.model
        col, dist = cr.cell_column[cand], cr.cell_dist[cand]
        hidden = np.zeros(len(cand), bool)
        shift = cr.row_bits + LABEL_BITS
        slack = COLUMN_SLACK_CELLS * cr.resolution
        w = key.shape[1]
        cols = np.flatnonzero(first < NO_KEY)
        for _ in range(MAX_EDGES):
            if not len(cols):
                break
            k = first[cols].astype(np.int64)
            d0 = ((k >> shift) * cr.quantum).astype(np.float32)
            row0 = (k >> LABEL_BITS) & ((1 << cr.row_bits) - 1)
            lab0 = k & ((1 << LABEL_BITS) - 1)
            h = m.heights[lab0]
            lateral = d0 * cr.dazimuth[row0, cols]
            # the polar raster breaks a face where its near edge jumps by more than FACE_BREAK_M
            # from one ray to the next; between two columns it steps once per image row
            face_break = (FACE_BREAK_M + COLUMN_FACE_BREAK_CELLS * cr.resolution) * np.maximum(np.abs(np.diff(row0)), 1)
            near = np.full(w, np.inf, np.float32)  # object claims cells up to here
            far = np.full(w, -np.inf, np.float32)  # shadow end
            near[cols] = d0 + m._face_depth(cols, d0, lab0, lateral, face_break) + margin + slack
            with np.errstate(divide="ignore"):
                far[cols] = np.where(h >= cr.height, np.inf,
                                     d0 * cr.height / np.maximum(cr.height - h, 1e-6))
            hidden |= (dist > near[col]) & (dist <= far[col])
            cols = cols[np.isfinite(far[cols])]
            if not len(cols):
                break
            # the next near edge: the nearest occluding pixel beyond the shadow's end
            sub = key[:, cols]  # (rows, k)
            first = np.full(w, NO_KEY, np.int32)
            first[cols] = np.where(cr.dist[:, cols] > far[cols][None], sub, NO_KEY).min(axis=0)
            cols = cols[first[cols] < NO_KEY]
        return cand[hidden] if hidden.any() else None
