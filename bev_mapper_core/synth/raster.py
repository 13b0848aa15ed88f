"""The flat ground of the synthetic world as a lazily tiled world-frame raster.

Each cell holds one byte: the ground :class:`~bev_mapper_core.labels.classes.Label` in the low four
bits and a :class:`Mat` (surface material, for colour) in the high four. Cell ``(iy, ix)`` covers
``[x0 + ix * res, x0 + (ix + 1) * res) x [y0 + iy * res, ...)``; a world point is looked up by
flooring, so the renderer and the ground truth read exactly the same cell for the same point.

Near the ego the raster is fine (``res``, default 0.05 m) and built tile by tile on demand;
beyond ``near_radius`` a coarse raster of the whole world (0.4 m) is used, only by far pixels.
"""

from __future__ import annotations

import math
from collections import OrderedDict
from dataclasses import dataclass
from enum import IntEnum

import cv2
import numpy as np

from ..labels.classes import Label
from .roads import RoadNetwork

TILE = 1024  # cells per fine tile edge


class Mat(IntEnum):
    """Ground surface materials (index into the per-seed ground palette)."""

    GRASS = 0
    DIRT = 1
    CONCRETE = 2
    ASPHALT = 3
    CURB = 4
    WHITE = 5
    YELLOW = 6


NUM_MATS = len(Mat)
DEFAULT = int(Label.TERRAIN) | (int(Mat.GRASS) << 4)


def unpack(packed: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``(labels, materials)`` of packed raster values."""
    return packed & 15, packed >> 4


@dataclass(frozen=True)
class Feature:
    """A filled polygon or a thick open polyline painted onto the ground.

    ``label`` None leaves the label as is (paint that is not its own class, e.g. zebra stripes).
    """

    kind: str  # "poly" | "line"
    pts: np.ndarray  # (N, 2) world xy
    label: int | None
    mat: int
    width: float = 0.0  # line width in m
    road: bool = False  # part of the carriageway (the curb is drawn along its boundary)


def ground_features(net: RoadNetwork, rng: np.random.Generator) -> list[Feature]:
    """Paint list of the network's ground, in drawing order (later features win)."""
    feats: list[Feature] = []
    x0, y0, x1, y1 = net.bounds
    for _ in range(int((x1 - x0) * (y1 - y0) / 3000.0)):  # dirt patches on the verges
        c = rng.uniform([x0, y0], [x1, y1])
        ang = np.sort(rng.uniform(0, 2 * np.pi, 9))
        rad = rng.uniform(2.0, 10.0) * rng.uniform(0.6, 1.0, 9)
        feats.append(Feature("poly", c + np.stack([np.cos(ang), np.sin(ang)], 1) * rad[:, None],
                             Label.TERRAIN, Mat.DIRT))
    for node in net.nodes:
        feats.append(Feature("poly", node.walk_hull, Label.SIDEWALK, Mat.CONCRETE))
    for r in net.roads:
        poly = np.concatenate([r.offset(r.half_width(1) + r.sidewalk),
                               r.offset(-r.half_width(-1) - r.sidewalk)[::-1]])
        feats.append(Feature("poly", poly, Label.SIDEWALK, Mat.CONCRETE))
    for node in net.nodes:
        feats.append(Feature("poly", node.road_hull, Label.ROAD, Mat.ASPHALT, road=True))
    for r in net.roads:
        poly = np.concatenate([r.offset(r.half_width(1)), r.offset(-r.half_width(-1))[::-1]])
        feats.append(Feature("poly", poly, Label.ROAD, Mat.ASPHALT, road=True))
    centre_style = int(rng.integers(3))  # single white, single yellow, double yellow
    dash, gap = (3.0, 6.0) if rng.random() < 0.6 else (2.0, 4.0)
    for r in net.roads:
        hl, hr = r.half_width(1), r.half_width(-1)
        for end in (0, 1):
            if not r.crossing[end]:
                continue
            s0, s1 = r.crossing_range(end)
            poly = np.concatenate([r.offset(hl, s0, s1), r.offset(-hr, s0, s1)[::-1]])
            feats.append(Feature("poly", poly, Label.PED_CROSSING, Mat.ASPHALT))
            for lat in np.arange(-hr + 0.45, hl - 0.2, 1.0):
                feats.append(Feature("line", r.offset(lat, s0 + 0.25, s1 - 0.25), None, Mat.WHITE, 0.5))
        lo, hi = r.marking_range()
        if hi - lo < 1.0:
            continue
        for end, s, sign in ((0, lo - 0.4, 1.0), (1, hi + 0.4, -1.0)):
            if net.nodes[r.a if end == 0 else r.b].degree >= 3:  # stop line of the incoming lanes
                stop = np.stack([r.offset(0.0, s, s + 0.01)[0],
                                 r.offset(sign * r.lanes * r.lane_width, s, s + 0.01)[0]])
                feats.append(Feature("line", stop, None, Mat.WHITE, 0.4))
        if centre_style == 2:
            for lat in (-0.12, 0.12):
                feats.append(Feature("line", r.offset(lat, lo, hi), Label.LANE_DIVIDER, Mat.YELLOW,
                                     0.12))
        else:
            mat = Mat.WHITE if centre_style == 0 else Mat.YELLOW
            feats.append(Feature("line", r.offset(0.0, lo, hi), Label.LANE_DIVIDER, mat, 0.18))
        for k in range(1, r.lanes):
            for lat in (-k * r.lane_width, k * r.lane_width):
                for s in np.arange(lo, hi - dash, dash + gap):
                    feats.append(Feature("line", r.offset(lat, s, s + dash), Label.LANE_DIVIDER,
                                         Mat.WHITE, 0.15))
    return feats


def rasterize(feats: list[Feature], bboxes: np.ndarray, x0: float, y0: float, res: float,
              w: int, h: int) -> np.ndarray:
    """Packed raster ``(h, w)`` uint8 of cells ``[x0 + i * res, ...)``, ``[y0 + j * res, ...)``."""
    pad = int(math.ceil(0.3 / res)) + 2  # room for the curb morphology at the tile border
    ox, oy = x0 - pad * res, y0 - pad * res
    H, W = h + 2 * pad, w + 2 * pad
    lab = np.full((H, W), int(Label.TERRAIN), np.uint8)
    mat = np.full((H, W), int(Mat.GRASS), np.uint8)
    road = np.zeros((H, W), np.uint8)
    m = 1.0
    hit = ((bboxes[:, 2] >= ox - m) & (bboxes[:, 0] <= ox + W * res + m)
           & (bboxes[:, 3] >= oy - m) & (bboxes[:, 1] <= oy + H * res + m))
    for i in np.flatnonzero(hit):
        f = feats[i]
        # world -> pixel coordinates (pixel centres at integers), 4 fractional bits
        px = np.rint(((f.pts - (ox, oy)) / res - 0.5) * 16.0).astype(np.int32)[None]
        targets = [(lab, int(f.label))] if f.label is not None else []
        targets.append((mat, int(f.mat)))
        if f.road:
            targets.append((road, 1))
        for img, val in targets:
            if f.kind == "poly":
                cv2.fillPoly(img, px, val, lineType=cv2.LINE_8, shift=4)
            else:
                t = max(1, int(round(f.width / res)))
                cv2.polylines(img, px, False, val, thickness=t, lineType=cv2.LINE_8, shift=4)
    r = int(round(0.15 / res))
    if r >= 1:  # a 0.3 m curb band centred on the carriageway boundary
        k = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * r + 1, 2 * r + 1))
        band = (cv2.dilate(road, k) > 0) & ~(cv2.erode(road, k, borderValue=1) > 0)
    else:  # coarse raster: one cell outside the carriageway
        band = (cv2.dilate(road, np.ones((3, 3), np.uint8)) > 0) & (road == 0)
    lab[band] = Label.ROAD_BOUNDARY
    mat[band] = Mat.CURB
    packed = lab | (mat << 4)
    return packed[pad:pad + h, pad:pad + w]


class GroundRaster:
    """Label/material lookup of the flat world, fine near the ego and coarse far away."""

    def __init__(self, feats: list[Feature], bounds, res: float = 0.05, coarse_res: float = 0.4,
                 near_radius: float = 90.0, max_tiles: int = 48) -> None:
        self.feats = feats
        self.bboxes = np.array([[*f.pts.min(0) - f.width, *f.pts.max(0) + f.width] for f in feats])
        self.res, self.near_radius, self.max_tiles = float(res), float(near_radius), max_tiles
        self.x0, self.y0 = float(bounds[0]), float(bounds[1])
        self.nx = int(math.ceil((bounds[2] - self.x0) / res))
        self.ny = int(math.ceil((bounds[3] - self.y0) / res))
        self.coarse_res = float(coarse_res)
        cw = int(math.ceil((bounds[2] - self.x0) / coarse_res))
        ch = int(math.ceil((bounds[3] - self.y0) / coarse_res))
        self.coarse = rasterize(feats, self.bboxes, self.x0, self.y0, coarse_res, cw, ch)
        self._tiles: OrderedDict = OrderedDict()

    def tile(self, tx: int, ty: int) -> np.ndarray:
        """Fine tile ``(TILE, TILE)`` at tile indices ``(tx, ty)``, rasterised on first use."""
        key = (tx, ty)
        if key in self._tiles:
            self._tiles.move_to_end(key)
            return self._tiles[key]
        t = rasterize(self.feats, self.bboxes, self.x0 + tx * TILE * self.res,
                      self.y0 + ty * TILE * self.res, self.res, TILE, TILE)
        self._tiles[key] = t
        while len(self._tiles) > self.max_tiles:
            self._tiles.popitem(last=False)
        return t

    def lookup_fine(self, x: np.ndarray, y: np.ndarray) -> np.ndarray:
        """Packed values of the fine raster at world points (any shape); outside: terrain."""
        gx = np.floor((x - self.x0) / self.res).astype(np.int64)
        gy = np.floor((y - self.y0) / self.res).astype(np.int64)
        out = np.full(gx.shape, DEFAULT, np.uint8)
        inside = (gx >= 0) & (gx < self.nx) & (gy >= 0) & (gy < self.ny)
        ntx = (self.nx + TILE - 1) // TILE
        key = np.where(inside, (gy // TILE) * ntx + gx // TILE, -1)
        for k in np.flatnonzero(np.bincount(key[inside], minlength=1)):
            m = key == k
            out[m] = self.tile(int(k % ntx), int(k // ntx))[gy[m] % TILE, gx[m] % TILE]
        return out

    def lookup_coarse(self, x: np.ndarray, y: np.ndarray) -> np.ndarray:
        """Packed values of the coarse whole-world raster."""
        gx = np.floor((x - self.x0) / self.coarse_res).astype(np.int64)
        gy = np.floor((y - self.y0) / self.coarse_res).astype(np.int64)
        h, w = self.coarse.shape
        inside = (gx >= 0) & (gx < w) & (gy >= 0) & (gy < h)
        return np.where(inside, self.coarse[np.clip(gy, 0, h - 1), np.clip(gx, 0, w - 1)], DEFAULT
                        ).astype(np.uint8)

    def lookup(self, x: np.ndarray, y: np.ndarray, center=None) -> np.ndarray:
        """Packed values at world points: fine within ``near_radius`` of ``center``, else coarse."""
        if center is None:
            return self.lookup_fine(x, y)
        near = np.hypot(x - center[0], y - center[1]) <= self.near_radius
        out = self.lookup_coarse(x, y)
        out[near] = self.lookup_fine(x[near], y[near])
        return out

    def labels(self, x: np.ndarray, y: np.ndarray) -> np.ndarray:
        """Ground label ids (fine raster) at world points."""
        return self.lookup_fine(x, y) & 15
