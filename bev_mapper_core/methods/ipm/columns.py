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

Per frame: each column's first near edge, the occluding pixel with the smallest key (its
label and row); the face rule and shadow of :class:`~.occlusion.OcclusionModel` on the columns
(a few hundred per camera), and each cell whose own pixel shows an occluder reads its column's
near edge and shadow end. A second near edge is searched, like the polar raster's, beyond a
finite shadow (:data:`~.occlusion.MAX_EDGES`), in the columns with a pixel beyond it.

All cameras of a frame run these steps together (:class:`RigColumns`: their columns side by
side), so each numpy step runs once per frame, not once per camera. Where every column's keys
fall from row to row (every shipped camera: a nearer ground point lies lower in the image), a
column's first near edge is its lowest occluding pixel, found with a uint8 range test and a
maximum, with no int32 key image; otherwise the minimum of the keys. Both give the same cells.

The result differs from the polar raster's in the cells where the two discretisations of a ray
disagree (a column is about 4 mrad wide, a polar ray 1 mrad; the near edge is a pixel's ground
point here, a 0.075 m range sample there); ``experiments/ipm_occlusion_columns.py`` scores both
on held-out drives of every rig (docs/RESULTS.md, "Occlusion per image column").
"""

from __future__ import annotations

from collections.abc import Mapping
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


@dataclass(frozen=True)
class RigColumns:
    """A rig's :class:`ColumnRaster` s side by side, so each per-frame step of the column search
    runs once for all cameras instead of once per camera. Built once per calibration.

    Camera ``c``'s image column ``u`` is joint column ``offset[c] + u``; one column of no keys
    follows each camera, so no face of the face rule spans two cameras. Camera ``c``'s raster
    rows are the joint rows ``0 .. r1 - r0``, padded below with no keys to the rig's most rows.

    Attributes:
        names: the cameras, in rig order.
        rasters: camera name -> its :class:`ColumnRaster`.
        offset: camera name -> its first joint column.
        key: ``(R, Wt)`` int32 the cameras' ``key`` side by side (:data:`NO_KEY` in padding).
        dist: ``(R, Wt)`` float32 their ``dist`` (``inf`` in padding).
        dist_max: ``(Wt,)`` float32 each column's largest finite ``dist`` (``-inf``: none).
        dazimuth: ``(R, Wt)`` float32 their ``dazimuth`` (0 in padding).
        row_code: ``(R, Wt)`` uint8 ``row + 1`` where a pixel has a key, else 0; ``None`` unless
            every column's keys fall strictly from row to row (a near pixel lies lower in the
            image): then a column's smallest key among occluders is its lowest occluder's.
        shift: ``(Wt,)`` int64 per joint column, its camera's ``row_bits + LABEL_BITS``.
        row_mask: ``(Wt,)`` int64 its camera's ``(1 << row_bits) - 1``.
        quantum: ``(Wt,)`` float64 its camera's ``quantum``.
        height: ``(Wt,)`` float64 its camera's ``height``; ``height32`` the same in float32.
        resolution: the grid's cell size (m).
        cell_column: camera name -> ``(n,)`` int64 joint column of each seen cell (gather order).
        all_column, all_dist: ``(N,)`` every camera's ``cell_column`` and ``cell_dist``,
            concatenated in rig order; ``all_offsets`` ``(cameras + 1,)`` where each starts.
    """

    names: tuple[str, ...]
    rasters: dict[str, ColumnRaster]
    offset: dict[str, int]
    key: np.ndarray
    dist: np.ndarray
    dist_max: np.ndarray
    dazimuth: np.ndarray
    row_code: np.ndarray | None
    shift: np.ndarray
    row_mask: np.ndarray
    quantum: np.ndarray
    height: np.ndarray
    height32: np.ndarray
    resolution: float
    cell_column: dict[str, np.ndarray]
    all_column: np.ndarray
    all_dist: np.ndarray
    all_offsets: np.ndarray


def rig_columns(rasters: dict[str, ColumnRaster]) -> RigColumns:
    """The joint raster of ``rasters`` (camera name -> its :class:`ColumnRaster`, rig order)."""
    names = tuple(rasters)
    widths = [cr.key.shape[1] for cr in rasters.values()]
    starts = np.concatenate([[0], np.cumsum(np.add(widths, 1))])  # each camera, then a gap column
    R, Wt = max([cr.key.shape[0] for cr in rasters.values()] or [1]), int(starts[-1])
    key = np.full((R, Wt), NO_KEY, np.int32)
    dist = np.full((R, Wt), np.inf, np.float32)
    daz = np.zeros((R, Wt), np.float32)
    shift, row_mask = np.full(Wt, LABEL_BITS, np.int64), np.zeros(Wt, np.int64)
    quantum, height = np.ones(Wt), np.ones(Wt)
    offset, cell_column = {}, {}
    for (name, cr), s, w in zip(rasters.items(), starts, widths):
        n, s = cr.key.shape[0], int(s)
        key[:n, s:s + w], dist[:n, s:s + w], daz[:n, s:s + w] = cr.key, cr.dist, cr.dazimuth
        shift[s:s + w], row_mask[s:s + w] = cr.row_bits + LABEL_BITS, (1 << cr.row_bits) - 1
        quantum[s:s + w], height[s:s + w] = cr.quantum, cr.height
        offset[name], cell_column[name] = s, cr.cell_column + s
    has = key < NO_KEY  # (R, Wt)
    dist_max = np.where(has, dist, -np.inf).max(axis=0).astype(np.float32)
    # the keys of a column, its keyed pixels from the top down: falling strictly?
    down = np.where(has, key.astype(np.int64), -1)[::-1]  # (R, Wt), rows bottom up, -1: no key
    seen = np.maximum.accumulate(down, axis=0)  # the largest key below each row (bottom up)
    falling = R < 255 and not (has[::-1][1:] & (down[1:] <= seen[:-1])).any()
    row_code = np.where(has, np.arange(1, R + 1)[:, None], 0).astype(np.uint8) if falling else None
    resolution = next(iter(rasters.values())).resolution if rasters else 1.0
    counts = [len(cell_column[n]) for n in names]
    return RigColumns(names, dict(rasters), offset, key, dist, dist_max, daz, row_code, shift, row_mask,
                      quantum, height, height.astype(np.float32), resolution, cell_column,
                      np.concatenate([cell_column[n] for n in names] or [np.zeros(0, np.int64)]),
                      np.concatenate([rasters[n].cell_dist for n in names] or [np.zeros(0, np.float32)]),
                      np.concatenate([[0], np.cumsum(counts, dtype=np.int64)]))


def _uint8(a: np.ndarray) -> np.ndarray:
    """``a`` as uint8 label ids (ids above 255 become 255)."""
    return a if a.dtype == np.uint8 else np.minimum(a, 255).astype(np.uint8)


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
        self._occludes_ff = occludes.astype(np.uint8) * np.uint8(255)  # label id -> 0xFF if it occludes
        ids = np.flatnonzero(occludes)
        #: ``(lo, hi)`` when the occluding ids are exactly lo..hi (the default priors): range
        #: tests then, several times faster than the lookups of the general case
        self._range = (int(ids[0]), int(ids[-1])) if len(ids) and ids[-1] - ids[0] + 1 == len(ids) else None
        #: label id -> the value added to a pixel's key: its label, or NO_KEY (no occluder)
        self._key_lut = np.where(occludes, np.arange(256), int(NO_KEY)).astype(np.int32)
        self._blank = np.uint8(np.flatnonzero(~occludes)[0])  # a label id that occludes nothing

    def _occluding(self, ids: np.ndarray) -> np.ndarray:
        """``(n,)`` bool: which of the uint8 label ids ``(n,)`` occlude."""
        if self._range is None:
            return self.occludes[ids]
        lo, hi = self._range
        return (ids - np.uint8(lo)) <= np.uint8(hi - lo)  # uint8 wraps below lo

    def _occluder_mask(self, image: np.ndarray) -> np.ndarray:
        """``(R, Wt)`` uint8: 255 where the uint8 label image ``(R, Wt)`` shows an occluder, else 0."""
        if self._range is None:
            return cv2.LUT(image, self._occludes_ff)
        return cv2.inRange(image, *self._range)

    def hidden(self, rc: RigColumns, labels: Mapping[str, np.ndarray], ids: Mapping[str, np.ndarray],
               margin: float) -> dict[str, np.ndarray | None]:
        """The seen cells hidden from each camera of ``labels``: camera name -> ``(k,)``
        increasing indices into its gather order, ``None`` when none is.

        Args:
            rc: the rig's :class:`RigColumns`.
            labels: camera name -> ``(h, w)`` its label image (any subset of ``rc.names``).
            ids: camera name -> ``(n,)`` the label id each of its seen cells takes (the gather
                of its ``labels``).
            margin: slack in metres added to each near edge's footprint depth.
        """
        names = [n for n in rc.names if n in labels]
        out: dict[str, np.ndarray | None] = dict.fromkeys(names)
        if not names:
            return out
        if len(names) == len(rc.names):
            column, dist, starts = rc.all_column, rc.all_dist, rc.all_offsets
        else:
            column = np.concatenate([rc.cell_column[n] for n in names])
            dist = np.concatenate([rc.rasters[n].cell_dist for n in names])
            starts = np.concatenate([[0], np.cumsum([len(rc.cell_column[n]) for n in names])])
        # only a cell showing an occluder can be hidden; (N,) over the cameras' cells in turn
        cand = np.flatnonzero(self._occluding(np.concatenate([_uint8(ids[n]) for n in names])))
        if not len(cand):
            return out
        per_camera = np.searchsorted(cand, starts)  # (cameras + 1,) where each camera's begin
        # the joint label image: cameras with no candidate keep the blank label (no occluder)
        image = np.full(rc.key.shape, self._blank, np.uint8)  # (R, Wt)
        for i, name in enumerate(names):
            if per_camera[i + 1] > per_camera[i]:
                cr, s = rc.rasters[name], rc.offset[name]
                (r0, r1), w = cr.rows, cr.key.shape[1]
                image[:r1 - r0, s:s + w] = _uint8(labels[name][r0:r1])  # (a wrong width raises)
        hidden = self._search(rc, image, column[cand], dist[cand], margin)
        if hidden is None:
            return out
        hid = cand[hidden]
        bounds = np.searchsorted(hid, starts)
        for i, name in enumerate(names):
            if bounds[i + 1] > bounds[i]:
                out[name] = hid[bounds[i]:bounds[i + 1]] - starts[i]
        return out

    def _near_edges(self, rc: RigColumns, image: np.ndarray) -> tuple[np.ndarray, np.ndarray | None, np.ndarray]:
        """Each column's first near edge in ``image`` (``(R, Wt)`` the joint label image):
        ``(cols, key, kcols)``: ``cols`` ``(k,)`` the columns with one, ``kcols`` ``(k,)`` int32
        its key; ``key`` ``(R, Wt)`` int32 every pixel's key (``None`` where ``rc.row_code``
        finds the edges without it).
        """
        if rc.row_code is not None:  # a column's nearest occluder is its lowest: no key image
            lowest = cv2.bitwise_and(self._occluder_mask(image), rc.row_code).max(axis=0)  # (Wt,)
            cols = np.flatnonzero(lowest)
            rows = lowest[cols].astype(np.intp) - 1
            return cols, None, rc.key[rows, cols] + self._key_lut[image[rows, cols]]
        key = cv2.LUT(image, self._key_lut)  # (R, Wt) int32; >= NO_KEY: no occluder
        key += rc.key
        first = key.min(axis=0)  # (Wt,) each column's nearest occluding pixel
        cols = np.flatnonzero(first < NO_KEY)
        return cols, key, first[cols]

    def _search(self, rc: RigColumns, image: np.ndarray, col: np.ndarray, dist: np.ndarray,
                margin: float) -> np.ndarray | None:
        """``(n,)`` bool: which of the candidate cells (joint column ``col``, distance ``dist``
        from their camera) lie in a shadow; ``None`` when none does. ``image``: ``(R, Wt)`` the
        joint label image of this frame.
        """
        cols, key, kcols = self._near_edges(rc, image)
        m = self.model
        hidden = np.zeros(len(col), bool)
        slack = COLUMN_SLACK_CELLS * rc.resolution
        w = image.shape[1]
        for edge in range(MAX_EDGES):
            if not len(cols):
                break
            k = kcols.astype(np.int64)
            d0 = ((k >> rc.shift[cols]) * rc.quantum[cols]).astype(np.float32)
            row0 = (k >> LABEL_BITS) & rc.row_mask[cols]
            lab0 = k & ((1 << LABEL_BITS) - 1)
            h = m.heights[lab0]
            lateral = d0 * rc.dazimuth[row0, cols]
            # the polar raster breaks a face where its near edge jumps by more than FACE_BREAK_M
            # from one ray to the next; between two columns it steps once per image row
            face_break = (FACE_BREAK_M + COLUMN_FACE_BREAK_CELLS * rc.resolution) * np.maximum(np.abs(np.diff(row0)), 1)
            near = np.full(w, np.inf, np.float32)  # object claims cells up to here
            far = np.full(w, -np.inf, np.float32)  # shadow end
            near[cols] = d0 + m._face_depth(cols, d0, lab0, lateral, face_break) + margin + slack
            height = rc.height[cols]
            with np.errstate(divide="ignore"):
                far[cols] = np.where(h >= height, np.inf,
                                     d0 * rc.height32[cols] / np.maximum(height - h, 1e-6))
            hidden |= (dist > near[col]) & (dist <= far[col])
            if edge == MAX_EDGES - 1:
                break
            # the next near edge: the nearest occluding pixel beyond the shadow's end, in the
            # columns with a keyed pixel beyond it (an infinite shadow has none)
            cols = cols[far[cols] < rc.dist_max[cols]]
            if not len(cols):
                break
            sub = key[:, cols] if key is not None else rc.key[:, cols] + self._key_lut[image[:, cols]]  # (R, k)
            kcols = np.where(rc.dist[:, cols] > far[cols][None], sub, NO_KEY).min(axis=0)
            cols, kcols = cols[kcols < NO_KEY], kcols[kcols < NO_KEY]
        return hidden if hidden.any() else None
