"""Occlusion reasoning for IPM: cells hidden behind an object's near edge become unknown.

IPM places every pixel on the ground. A pixel showing an object (a car, a pedestrian, a
building) lands on the ground cell where its ray would have met the ground, i.e. *behind* the
point where the ray actually hit the object: the flat-ground smear. This module finds, per
camera, which BEV cells that camera cannot have seen.

Along each camera ray (in BEV: a direction from the camera's ground point), the ground cells in
front of the first object-labelled cell are seen as ground (their pixels show ground, so the
ray to them is unobstructed); the first object-labelled cell is the **near edge** of the
object's footprint at distance ``d0`` from the camera's ground point. With a height prior ``h``
for the object's label (:data:`OBJECT_HEIGHT_M`) and the camera at height ``hc``, the ray to a
ground cell at distance ``d > d0`` passes the near edge at height ``hc * (1 - d0 / d)``; it is
blocked by the object when that height is ``<= h``, i.e. for every ``d`` when ``h >= hc`` and
for ``d <= d0 * hc / (hc - h)`` otherwise (the object's *shadow*). Cells in the shadow farther
than ``d0 + depth`` (how far beyond its near edge the object itself is assumed to extend,
from the label's footprint prior :data:`OBJECT_FOOTPRINT_M` and the width of the face the ray
hits, plus :data:`NEAR_EDGE_SLACK_CELLS` cells) are **occluded** when their own pixel shows the
object too (a cell whose pixel shows ground was seen: the ray to it is clear, e.g. over an object
lower than its prior): that camera gives them no value, and a cell no camera sees unoccluded is
unknown.

The rays are evaluated on a polar raster per camera (angle x range, built once per
calibration): the camera's warped labels are resampled onto it with ``cv2.remap`` (nearest),
the first occluder of each ray is found with an ``argmax`` along range, and every cell reads its
ray back. Only the first near edge of a ray and, when its shadow ends (objects lower than the
camera), the next one are used (:data:`MAX_EDGES`).

Since issue #28 IPM finds the near edges per image column instead (:mod:`.columns`, the same
priors and face rule, about 2x faster); the polar raster here remains the learned methods' line
of sight and IPM's with ``IpmMapper.occlusion_columns = False``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numpy as np

from bev_mapper_core.geometry.grid import BevGrid
from bev_mapper_core.geometry.rig import RigCamera
from bev_mapper_core.labels.classes import NUM_LABELS, Label

#: Height prior (m) per label that occludes: an object of that label is assumed this tall.
#: Cars are 1.2-1.5 m in the synthetic world (vans up to 2.4 m), pedestrians 1.5-1.85 m,
#: street furniture mostly about 1 m (bins, bollards, cones; light poles are taller but thin),
#: buildings 4-30 m. With cameras at 1.4-1.6 m (the shipped rigs), vehicles, pedestrians and
#: buildings hide everything behind their near edge; a 1 m obstacle 10 m away hides the ground
#: up to 25-30 m. Labels not listed (ground classes, sky) do not occlude.
OBJECT_HEIGHT_M: dict[int, float] = {
    Label.VEHICLE: 1.5,
    Label.PEDESTRIAN: 1.7,
    Label.OBSTACLE: 1.0,
    Label.BUILDING: 10.0,
}
#: Footprint prior (m) per occluding label: ``(width, length)``, the smallest and largest
#: horizontal extent of such an object (cars 1.7-2.1 m x 3.9-6 m, pedestrians about 0.3-0.5 m,
#: bins and bollards about 0.6 m). How far an object reaches beyond its near edge along a ray
#: (its *depth*) depends on how it is turned, which one ray cannot tell; but the rays hitting
#: one face tell its lateral width ``e``, and the mean chord of a ``width x length`` rectangle
#: over its lateral width is its area over that width. So the depth assumed on the rays of a
#: face is ``clip(width * length / e, width, length)``: a car seen end-on (``e`` = 1.8 m) is
#: 4.5 m deep, one seen from the side (``e`` = 4.5 m) 1.8 m. Cells in that depth keep the
#: camera's label (object); farther cells in the shadow are occluded.
OBJECT_FOOTPRINT_M: dict[int, tuple[float, float]] = {
    Label.VEHICLE: (1.8, 4.5),
    Label.PEDESTRIAN: (0.5, 0.5),
    Label.OBSTACLE: (0.6, 0.6),
    Label.BUILDING: (1.0, 1.0),
}
#: Depth (m) a learned method's line of sight allows an object beyond its near edge, per
#: occluding label, when the method maps that label (:func:`learned_footprints`): a learned model
#: draws the footprint itself, so only cells that cannot belong to the object are withheld.
#: Vehicles: a typical car's length (4.5 m; on the validation bags, seeds 900000010-12, the
#: shipped surround6 model scored 80.5 visible mIoU and 25.7 m^2/frame of false vehicle claims
#: with it, 79.7 and 16.8 with the face-width rule, 80.8 and 40.8 with 6 m). Buildings: the
#: synthetic town's deepest (24 m; Cam2BEV's ``static`` class covers them). Pedestrians: 1.0 m,
#: twice a person's footprint (issue #39): the near edge comes from the label image's lowest
#: pedestrian pixel, whose ground footprint grows with range, and at IPM's 0.5 m the gate withheld
#: pedestrian cells a camera sees (validation drives 900000010-11, 100 frames each: the visible
#: pedestrian cells withheld lay a median 0.94 m beyond the nearest pedestrian near edge; see
#: docs/RESULTS.md "The visibility gate keeps what a camera sees").
OBJECT_MAX_DEPTH_M: dict[int, float] = {
    Label.VEHICLE: 4.5,
    Label.PEDESTRIAN: 1.0,
    Label.OBSTACLE: 0.6,
    Label.BUILDING: 24.0,
}


def learned_footprints(mapped_labels) -> dict[int, tuple[float, float]]:
    """Footprint priors of a learned method's line of sight (an :class:`OcclusionModel`'s
    ``footprints``): a label the method maps (in ``mapped_labels``) may extend its
    :data:`OBJECT_MAX_DEPTH_M` on every ray; the others keep IPM's face-width rule
    (:data:`OBJECT_FOOTPRINT_M`), since no output layer needs their cells.
    """
    mapped = {int(x) for x in mapped_labels}
    return {label: (OBJECT_MAX_DEPTH_M[label],) * 2 if int(label) in mapped else fp
            for label, fp in OBJECT_FOOTPRINT_M.items()}


#: Rays whose near edges differ by more than this (m) belong to different faces.
FACE_BREAK_M = 0.5
#: Near edges evaluated per ray (the first, and the next after a finite shadow).
MAX_EDGES = 2
#: The near edge is only known to a cell: a cell counts as occluded only this many cells beyond
#: the object's assumed depth.
NEAR_EDGE_SLACK_CELLS = 1.5
#: Angular step of the polar raster: the ray spacing at 60 m is 0.06 m (below a 0.15 m cell).
ANGLE_STEP_RAD = 0.001


def _prior_table(priors: dict[int, float]) -> np.ndarray:
    """``(NUM_LABELS + 1,)`` float32 lookup; 0 for labels without a prior (and the last entry,
    used for label ids outside :class:`Label`).
    """
    lut = np.zeros(NUM_LABELS + 1, np.float32)
    for label, value in priors.items():
        lut[int(label)] = value
    return lut


@dataclass(frozen=True)
class RayRaster:
    """A camera's rays on the BEV grid, built once per calibration.

    Attributes:
        height: camera height above the ground plane (m).
        dist: ``(H, W)`` float32 horizontal distance of each cell centre from the camera's
            ground point (m).
        ray: ``(H, W)`` int32 polar row (ray) of each cell.
        to_cell_x, to_cell_y: ``(rays, samples)`` float32 grid column / row of every polar
            sample, for ``cv2.remap`` (-1 outside the grid).
        step: range step of the polar samples (m).
        cells: ``(n,)`` flat indices of the cells the camera looks at (``valid``); the
            per-frame shadow test runs on these only.
    """

    height: float
    dist: np.ndarray
    ray: np.ndarray
    to_cell_x: np.ndarray
    to_cell_y: np.ndarray
    step: float
    cells: np.ndarray | None = None


def ray_raster(camera: RigCamera, grid: BevGrid, valid: np.ndarray) -> RayRaster:
    """The polar raster of ``camera``'s rays over the cells it sees (``valid``, ``(H, W)``)."""
    T = camera.ego_from_cam_array
    cx, cy, hc = float(T[0, 3]), float(T[1, 3]), float(T[2, 3])
    # heading of the optical axis, so that the camera's cells never straddle the +-pi cut
    yaw0 = math.atan2(T[1, 2], T[0, 2])
    xs, ys = grid.centers
    dx, dy = xs - cx, ys - cy
    dist = np.hypot(dx, dy)
    ang = np.angle(np.exp(1j * (np.arctan2(dy, dx) - yaw0)))  # (H, W) in (-pi, pi]
    step = grid.resolution / 2
    if valid.any():
        lo, hi = float(ang[valid].min()), float(ang[valid].max())
        d_max = float(dist[valid].max()) + grid.resolution
    else:
        lo, hi, d_max = 0.0, 0.0, grid.resolution
    n_rays = int(math.ceil((hi - lo) / ANGLE_STEP_RAD)) + 1
    n_samples = int(math.ceil(d_max / step)) + 1
    a = yaw0 + lo + ANGLE_STEP_RAD * np.arange(n_rays)  # (rays,)
    r = step * np.arange(n_samples)  # (samples,)
    px = cx + np.cos(a)[:, None] * r[None, :]  # (rays, samples)
    py = cy + np.sin(a)[:, None] * r[None, :]
    # cv2.remap samples pixel (col, row) at integer coordinates = cell centres
    col = (px - grid.x_min) / grid.resolution - 0.5
    row = (py - grid.y_min) / grid.resolution - 0.5
    ray = np.clip(np.rint((ang - lo) / ANGLE_STEP_RAD), 0, n_rays - 1).astype(np.int32)
    return RayRaster(hc, dist.astype(np.float32), ray, col.astype(np.float32),
                     row.astype(np.float32), step, np.flatnonzero(valid))


class OcclusionModel:
    """Per-frame occlusion of one camera's warped labels (see the module docstring).

    Args:
        heights: label id -> height prior in metres (default :data:`OBJECT_HEIGHT_M`).
        footprints: label id -> ``(width, length)`` prior in metres (default
            :data:`OBJECT_FOOTPRINT_M`).
    """

    def __init__(self, heights: dict[int, float] | None = None,
                 footprints: dict[int, tuple[float, float]] | None = None) -> None:
        self.heights = _prior_table(OBJECT_HEIGHT_M if heights is None else heights)
        footprints = OBJECT_FOOTPRINT_M if footprints is None else footprints
        self.widths = _prior_table({k: v[0] for k, v in footprints.items()})
        self.lengths = _prior_table({k: v[1] for k, v in footprints.items()})
        self._occluder_lut = np.zeros(256, np.uint8)  # label id -> 1 if it occludes
        self._occluder_lut[: len(self.heights)] = self.heights > 0

    def _face_depth(self, rays: np.ndarray, d0: np.ndarray, lab0: np.ndarray,
                    lateral: np.ndarray | None = None, face_break: np.ndarray | float = FACE_BREAK_M) -> np.ndarray:
        """Assumed depth (m) of the object beyond the near edge ``d0`` of each ray in ``rays``
        (sorted ray indices; ``lab0`` the near edges' labels).

        Adjacent rays whose near edges have the same label and lie within :data:`FACE_BREAK_M`
        of each other form a face; its lateral width ``e`` is the sum of ``d0 * ANGLE_STEP_RAD``
        over its rays (or of ``lateral``, each ray's own width at its near edge, when given),
        and its depth ``clip(w * l / e, w, l)`` (see :data:`OBJECT_FOOTPRINT_M`). ``face_break``:
        the largest jump of the near edge within a face, between each ray and the next (scalar, or
        ``(len(rays) - 1,)``).
        """
        same = ((rays[1:] == rays[:-1] + 1) & (lab0[1:] == lab0[:-1])
                & (np.abs(d0[1:] - d0[:-1]) <= face_break))
        face = np.concatenate([[0], np.cumsum(~same)])  # face id of each ray
        if lateral is None:
            lateral = d0 * ANGLE_STEP_RAD
        e = np.bincount(face, weights=lateral)[face]  # lateral width of its face
        w, length = self.widths[lab0], self.lengths[lab0]
        return np.clip(w * length / np.maximum(e, 1e-6), w, length).astype(np.float32)

    def occluded(self, rr: RayRaster, labels: np.ndarray, valid: np.ndarray,
                 margin: float) -> np.ndarray:
        """``(H, W)`` bool: cells of ``valid`` hidden from the camera.

        Args:
            rr: the camera's :class:`RayRaster`.
            labels: ``(H, W)`` label ids the camera's pixels give the cells (IPM's warp).
            valid: ``(H, W)`` bool, cells the camera looks at.
            margin: slack in metres added to each near edge's footprint depth.
        """
        lab = np.where(valid & (labels < NUM_LABELS), labels, NUM_LABELS).astype(np.uint8)
        # the shadow test runs on the cells the camera looks at (all cells if not known)
        cells = np.flatnonzero(valid) if rr.cells is None else rr.cells
        # occluders only (other cells 0, which is no occluder): the (H, W) cells are far fewer
        # than the polar samples, so the lookup runs here, before the remap
        occ_lab = cv2.LUT(lab, self._occluder_lut) * lab  # (H, W) uint8: the label where it occludes
        if not occ_lab.reshape(-1)[cells].any():
            return np.zeros(lab.shape, bool)  # nothing the camera sees hides anything
        # (H, W) -> (rays, samples) along each ray; outside the grid: nothing
        polar = cv2.remap(occ_lab, rr.to_cell_x, rr.to_cell_y, cv2.INTER_NEAREST,
                          borderMode=cv2.BORDER_CONSTANT, borderValue=0)
        occ = polar > 0  # (rays, samples) bool, True = occluder (polar holds its label)
        n_rays, n_samples = occ.shape
        dist, ray = rr.dist.reshape(-1)[cells], rr.ray.reshape(-1)[cells]  # (n,) each
        hidden = np.zeros(len(cells), bool)
        rays = np.arange(n_rays)  # rays still searched for a near edge
        j_from = np.zeros(n_rays, np.int64)  # ... from this sample on
        for _ in range(MAX_EDGES):
            part = occ if len(rays) == n_rays else occ[rays]  # the first pass reads every ray in place
            if j_from.any():  # samples before the previous shadow's end do not count
                part = part & (np.arange(n_samples)[None, :] >= j_from[:, None])
            j0 = part.argmax(axis=1)  # (rays,) first occluder sample
            has = part[np.arange(len(rays)), j0] > 0
            rays, j0 = rays[has], j0[has]
            if not len(rays):
                break
            d0 = (rr.step * j0).astype(np.float32)
            lab0 = polar[rays, j0]
            h = self.heights[lab0]
            near = np.full(n_rays, np.inf, np.float32)  # object claims cells up to here
            far = np.full(n_rays, -np.inf, np.float32)  # shadow end
            near[rays] = d0 + self._face_depth(rays, d0, lab0) + margin
            with np.errstate(divide="ignore"):
                far[rays] = np.where(h >= rr.height, np.inf, d0 * rr.height / np.maximum(rr.height - h, 1e-6))
            # per cell: its ray's near edge and shadow end
            hidden |= (dist > near[ray]) & (dist <= far[ray])
            finite = np.isfinite(far[rays])
            rays = rays[finite]
            j_from = np.ceil(far[rays] / rr.step).astype(np.int64) + 1
            if not len(rays):
                break
        # a cell whose own pixel shows no occluder was seen: the ray to its ground point is clear
        out = np.zeros(lab.size, bool)
        out[cells] = hidden & valid.reshape(-1)[cells] & (self.heights[lab.reshape(-1)[cells]] > 0)
        return out.reshape(lab.shape)
