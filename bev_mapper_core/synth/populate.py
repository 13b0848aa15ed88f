"""Placing the objects of the synthetic world: parked and moving cars, pedestrians, street
furniture and buildings, all derived from the road network so that they stand where they belong
(cars in parking strips and lanes, furniture and pedestrians on sidewalks, buildings behind).
"""

from __future__ import annotations

import math

import cv2
import numpy as np

from ..display import EGO_CENTER_X_M, EGO_LENGTH_M, EGO_WIDTH_M
from ..labels.classes import Label
from .objects import FACADE, Boxes, car_parts, obb_overlap, obstacle_parts, pedestrian_parts
from .raster import GroundRaster
from .roads import Road, RoadNetwork
from .trajectory import PathMotion

CAR_COLORS = np.array([(235, 235, 235), (25, 25, 28), (170, 172, 176), (100, 102, 108),
                       (150, 20, 25), (30, 55, 120), (35, 70, 45), (200, 185, 150), (210, 120, 30)])
#: ego footprint in base_link (the one drawn in pictures): centre 1.3 m ahead of the rear axle,
#: 4.6 m x 1.9 m
EGO_OFFSET, EGO_HALF = EGO_CENTER_X_M, (EGO_LENGTH_M / 2, EGO_WIDTH_M / 2)
#: movers only have to avoid each other where they could be seen (farther ones are culled)
SEEN_RADIUS = 150.0


class Catalog:
    """Accumulates objects: their parts (object frame) and their static pose."""

    def __init__(self) -> None:
        self.parts: list[tuple] = []
        self.poses: list[tuple[float, float, float]] = []

    def add(self, parts, pose) -> int:
        """Add an object; returns its id."""
        oid = len(self.poses)
        self.poses.append(tuple(float(v) for v in pose))
        self.parts += [(oid, *p) for p in parts]
        return oid

    def boxes(self) -> Boxes:
        """All parts as :class:`Boxes` in their object frames."""
        p = self.parts
        return Boxes.make([(q[1], q[2]) for q in p], [q[3] for q in p], [q[4:7] for q in p],
                          np.zeros(len(p)), [q[7] for q in p], [q[8] for q in p],
                          [q[9] for q in p], [q[0] for q in p])


def car_color(rng: np.random.Generator) -> np.ndarray:
    """A plausible car paint colour."""
    return np.clip(CAR_COLORS[int(rng.integers(len(CAR_COLORS)))] * rng.uniform(0.85, 1.1), 0, 255)


def road_poses(r: Road, s, lat):
    """World ``(x, y, yaw)`` (arrays) at arcs ``s`` and lateral offsets ``lat`` along road ``r``."""
    s = np.asarray(s, np.float64)
    c = [np.interp(s, r.s, r.center[:, i]) for i in (0, 1)]
    n = [np.interp(s, r.s, r.normal[:, i]) for i in (0, 1)]
    norm = np.hypot(n[0], n[1])
    nx, ny = n[0] / norm, n[1] / norm
    return c[0] + nx * lat, c[1] + ny * lat, np.arctan2(-nx, ny)


def _free_range(r: Road, margin: float) -> tuple[float, float]:
    lo = (r.crossing_range(0)[1] if r.crossing[0] else 0.0) + margin
    hi = (r.crossing_range(1)[0] if r.crossing[1] else r.length) - margin
    return lo, hi


def add_parked_cars(net: RoadNetwork, cat: Catalog, rng, density: float) -> None:
    """Cars in the parking strips, facing the traffic of their side."""
    for r in net.roads:
        for side in (1, -1):
            w = r.park[0 if side > 0 else 1]
            if w == 0:
                continue
            lo, hi = _free_range(r, 6.0)
            s = lo + rng.uniform(0.0, 3.0)
            while True:
                parts = car_parts(rng, car_color(rng))
                L = parts[0][3]
                if s + L > hi:
                    break
                if rng.random() < min(1.0, 0.55 * density):
                    lat = side * (r.lanes * r.lane_width + w / 2 + rng.uniform(-0.1, 0.1))
                    x, y, yaw = road_poses(r, s + L / 2, lat)
                    yaw += (math.pi if side > 0 else 0.0) + rng.normal(0.0, 0.02)
                    cat.add(parts, (x, y, yaw))
                s += L + rng.uniform(0.8, 3.0)


def add_furniture(net: RoadNetwork, cat: Catalog, rng, density: float) -> None:
    """Street lights, bins, bollards and cones along the curb side of the sidewalks."""
    for r in net.roads:
        lo, hi = _free_range(r, 2.0)
        for side in (1, -1):
            s = lo + rng.uniform(3.0, 15.0)
            while s < hi:
                u = rng.random()
                what = "light" if u < 0.55 else "bin" if u < 0.75 else "bollard" if u < 0.9 else "cone"
                if rng.random() < min(1.0, 0.8 * density):
                    x, y, yaw = road_poses(r, s, side * (r.half_width(side) + 0.45))
                    yaw = yaw - side * math.pi / 2  # local +x (the lamp arm) towards the road
                    cat.add(obstacle_parts(rng, what), (x, y, yaw))
                s += rng.uniform(12.0, 30.0)


def add_buildings(net: RoadNetwork, cat: Catalog, rng, density: float, ground: GroundRaster) -> None:
    """Buildings behind the sidewalks, never on a road, sidewalk or another building."""
    res = ground.coarse_res
    free = ((ground.coarse & 15) == Label.TERRAIN).astype(np.uint8)
    grow = int(math.ceil(1.0 / res))
    occupied = cv2.dilate(1 - free, np.ones((2 * grow + 1, 2 * grow + 1), np.uint8))
    h_lo, h_hi = [(4.0, 10.0), (6.0, 18.0), (10.0, 30.0)][int(rng.integers(3))]
    palette = rng.uniform(60, 230, (5, 3)) * 0.6 + rng.uniform(90, 220, (5, 1)) * 0.4
    for r in net.roads:
        for side in (1, -1):
            base = r.half_width(side) + r.sidewalk
            s = rng.uniform(0.0, 6.0)
            while s < r.length:
                f = rng.uniform(10.0, 28.0)
                lat = base + 1.5 + rng.uniform(0.0, 3.0)  # front line of the plot
                for row in range(2):  # a second row behind, where there is room
                    depth, height = rng.uniform(10.0, 24.0), rng.uniform(h_lo, h_hi)
                    color = palette[int(rng.integers(len(palette)))]
                    if rng.random() > min(1.0, (0.9 if row == 0 else 0.5) * density):
                        break
                    for size in (f, f / 2):  # a smaller one where the plot is cramped
                        x, y, yaw = road_poses(r, s + size / 2, side * (lat + depth / 2))
                        box = Boxes.make([(x, y)], 0.0, (size, depth, height), yaw, 0, 0)
                        corners = box.corners()[0, :4, :2]
                        px = np.rint((corners - (ground.x0, ground.y0)) / res - 0.5).astype(np.int32)
                        if _claim(occupied, px):
                            cat.add([(0.0, 0.0, 0.0, size, depth, height, Label.BUILDING, color,
                                      FACADE)], (x, y, yaw))
                            break
                    lat += depth + rng.uniform(1.0, 6.0)
                s += f + rng.uniform(0.5, 4.0)


def _claim(occupied: np.ndarray, px: np.ndarray) -> bool:
    """Mark polygon ``px`` (coarse pixels) occupied if it is inside the raster and free."""
    h, w = occupied.shape
    x0, y0 = px.min(0) - 1
    x1, y1 = px.max(0) + 2
    if x0 < 0 or y0 < 0 or x1 > w or y1 > h:
        return False
    mask = np.zeros((y1 - y0, x1 - x0), np.uint8)
    cv2.fillPoly(mask, [px - (x0, y0)], 1)
    crop = occupied[y0:y1, x0:x1]
    if (crop & mask).any():
        return False
    crop |= mask
    return True


# --------------------------------------------------------------- moving things
def _ego_boxes(ego: np.ndarray):
    """Ego footprint centres ``(T, 2)`` and yaws from base_link poses ``(T, 3)``."""
    c = ego[:, :2] + EGO_OFFSET * np.stack([np.cos(ego[:, 2]), np.sin(ego[:, 2])], 1)
    return c, ego[:, 2]


def _conflicts(poses: np.ndarray, half, others, relevant: np.ndarray) -> bool:
    """True if a track ``(T, 3)`` with half size ``half`` overlaps any of ``others`` at a frame
    where ``relevant`` (near enough to the ego to be seen).

    ``others``: list of (centres (T, 2), yaws (T,), half sizes (2,)).
    """
    idx = np.flatnonzero(relevant)
    if not len(idx):
        return False
    mine = poses[idx]
    for c, yaw, h in others:
        c = c[idx]
        near = np.hypot(*(c - mine[:, :2]).T) < np.hypot(*half) + np.hypot(*h) + 0.1
        if near.any() and obb_overlap(mine[near, :2], mine[near, 2], half, c[near], yaw[idx][near],
                                      h).any():
            return True
    return False


def _near_ego(poses: np.ndarray, ego: np.ndarray) -> np.ndarray:
    """Frames at which a track is within :data:`SEEN_RADIUS` of the ego (NaN poses: never)."""
    return np.hypot(*(poses[:, :2] - ego[:, :2]).T) < SEEN_RADIUS


def _activate(poses: np.ndarray, ego: np.ndarray, times: np.ndarray, t0: float, t1: float,
              far: float):
    """Poses with NaN outside the frames of times ``[t0, t1]``, the window shrunk so that the
    object appears and vanishes only farther than ``far`` from the ego (except at the first
    and last frame of the drive). None if nothing is left.
    """
    T = len(poses)
    first = int(np.searchsorted(times, t0))
    last = int(np.searchsorted(times, t1, side="right")) - 1
    dist = np.hypot(*(poses[:, :2] - ego[:, :2]).T)
    ok = dist > far
    if first > 0:
        later = np.flatnonzero(ok[first:last + 1])
        first = first + int(later[0]) if len(later) else T
    if last < T - 1:
        earlier = np.flatnonzero(ok[first:last + 1])
        last = first + int(earlier[-1]) if len(earlier) else -1
    if last < first:
        return None
    out = np.full_like(poses, np.nan)
    out[first:last + 1] = poses[first:last + 1]
    return out


def add_moving_cars(net: RoadNetwork, cat: Catalog, rng, density: float, times: np.ndarray,
                    ego: np.ndarray, tracks: dict, far: float) -> list:
    """Cars driving along their own random routes for a while (40-100 s each, appearing and
    vanishing out of sight, i.e. beyond ``far`` m); any that would come within ~0.5 m of the
    ego or (where it could be seen) of an earlier car is dropped.

    Returns the kept vehicle tracks (ego first) for the crossing pedestrians' checks.
    """
    lane_len = sum(r.length * 2 * r.lanes for r in net.roads)
    ec, eyaw = _ego_boxes(ego)
    vehicles = [(ec, eyaw, (EGO_HALF[0] + 0.5, EGO_HALF[1] + 0.5))]
    duration = float(times[-1])
    for _ in range(int(rng.poisson(density * lane_len / 130.0 * (duration + 70.0) / 70.0))):
        r = net.roads[int(rng.integers(len(net.roads)))]
        d, k = int(rng.choice([-1, 1])), int(rng.integers(r.lanes))
        v_max, life = rng.uniform(6.0, 13.0), rng.uniform(40.0, 100.0)
        t_start = rng.uniform(-life, duration) if duration > 0 else -rng.uniform(0.0, life)
        t0, t1 = max(t_start, 0.0), min(t_start + life, duration)  # driving while the ego does
        route = net.route(rng, r.index, d, k, rng.uniform(0.0, r.length),
                          max(t1 - t0, 0.0) * v_max + 20.0, 0.4)
        cap = net.intersection_caps(route, rng, 4.0, 8.0)
        x, y, yaw, _, _ = PathMotion(route, 3.0, v_max, rng, cap=cap).sample(times - t0)
        parts = car_parts(rng, car_color(rng))
        poses = _activate(np.stack([x, y, yaw], 1), ego, times, t_start, t_start + life, far)
        if poses is None:
            continue
        half = (parts[0][3] / 2 + 0.3, parts[0][4] / 2 + 0.3)
        if _conflicts(poses, half, vehicles, _near_ego(poses, ego)):
            continue
        vehicles.append((poses[:, :2], poses[:, 2], half))
        tracks[cat.add(parts, np.nan_to_num(poses[np.isfinite(poses[:, 0])][0]))] = poses
    return vehicles


def add_pedestrians(net: RoadNetwork, cat: Catalog, rng, density: float, times: np.ndarray,
                    ego: np.ndarray, vehicles: list, tracks: dict, far: float) -> None:
    """Pedestrians walking to and fro on sidewalks, and some crossing at zebra crossings: they
    show up at the curb, wait, cross when no vehicle is in the way, wait and go.
    """
    duration = float(times[-1])
    for r in net.roads:
        lo, hi = 1.5, r.length - 1.5
        span = hi - lo
        for side in (1, -1):
            for _ in range(int(rng.poisson(density * r.length / 35.0))):
                lat = side * (r.half_width(side) + rng.uniform(1.25, max(1.3, r.sidewalk - 0.35)))
                v = 0.0 if rng.random() < 0.25 else rng.uniform(0.9, 1.6)
                u = (rng.uniform(0.0, 2 * span) + v * times) % (2 * span)
                x, y, yaw = road_poses(r, lo + np.where(u < span, u, 2 * span - u), lat)
                yaw = np.where(u < span, yaw, yaw + math.pi) if v > 0 else yaw + rng.uniform(-3, 3)
                poses = np.stack([x, y, yaw], 1)
                tracks[cat.add(pedestrian_parts(rng), poses[0])] = poses
        for end in (0, 1):
            if not r.crossing[end]:
                continue
            c0, c1 = r.crossing_range(end)
            for _ in range(int(rng.poisson(0.6 * density * (duration + 40.0) / 40.0))):
                s = rng.uniform(c0 + 0.4, c1 - 0.4)
                a, b = r.half_width(1) + 0.9, -(r.half_width(-1) + 0.9)
                if rng.random() < 0.5:
                    a, b = b, a
                walk = abs(b - a) / rng.uniform(1.1, 1.6)
                wait0, wait1 = rng.uniform(3.0, 20.0), rng.uniform(3.0, 20.0)
                for _ in range(6):
                    t0 = rng.uniform(-walk - wait1, duration + wait0) if duration > 0 else \
                        rng.uniform(-walk, 0.0)
                    lat = a + np.clip((times - t0) / walk, 0.0, 1.0) * (b - a)
                    x, y, yaw = road_poses(r, np.full_like(times, s), lat)
                    yaw = yaw + (math.pi / 2 if b > a else -math.pi / 2)
                    poses = _activate(np.stack([x, y, yaw], 1), ego, times, t0 - wait0,
                                      t0 + walk + wait1, far)
                    if poses is not None and not _conflicts(poses, (1.1, 1.1), vehicles,
                                                            _near_ego(poses, ego)):
                        tracks[cat.add(pedestrian_parts(rng),
                                       poses[np.isfinite(poses[:, 0])][0])] = poses
                        break
