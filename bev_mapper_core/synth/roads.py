"""Procedural road network: a jittered grid of intersections joined by straight or curved roads.

Right-hand traffic, world frame ``odom`` (x, y in metres on the ground z = 0). A :class:`Road`
runs from node ``a`` to node ``b``; its centre line is trimmed where the intersection areas of
its end nodes begin. Its left normal points to the side of the traffic driving from b to a:
lane ``k`` (0 = next to the centre line) of direction +1 (a -> b) lies at lateral offset
``-(k + 0.5) * lane_width``, of direction -1 at ``+(k + 0.5) * lane_width``. Optional parking
strips lie outside the outermost lanes, sidewalks outside the carriageway.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

PARK_WIDTH = 2.3  # m, parking strip next to the curb


# ------------------------------------------------------------------ polylines
def arclength(pts: np.ndarray) -> np.ndarray:
    """Cumulative arc length ``(N,)`` of a polyline ``(N, 2)``."""
    seg = np.hypot(*np.diff(pts, axis=0).T)
    return np.concatenate([[0.0], np.cumsum(seg)])


def normals(pts: np.ndarray) -> np.ndarray:
    """Unit left normals ``(N, 2)`` of a polyline (central-difference tangents)."""
    t = np.gradient(pts, axis=0)
    t /= np.linalg.norm(t, axis=1, keepdims=True)
    return np.stack([-t[:, 1], t[:, 0]], axis=1)


def resample(pts: np.ndarray, step: float) -> np.ndarray:
    """The polyline resampled at (about) uniform arc-length ``step``."""
    s = arclength(pts)
    n = max(2, int(math.ceil(s[-1] / step)) + 1)
    ss = np.linspace(0.0, s[-1], n)
    return np.stack([np.interp(ss, s, pts[:, 0]), np.interp(ss, s, pts[:, 1])], axis=1)


def sub_polyline(pts: np.ndarray, s: np.ndarray, s0: float, s1: float) -> np.ndarray:
    """Portion of polyline ``pts`` (arc lengths ``s``) between arcs ``s0 < s1``, ends interpolated."""
    inner = (s > s0) & (s < s1)
    ends = [np.array([[np.interp(v, s, pts[:, 0]), np.interp(v, s, pts[:, 1])]]) for v in (s0, s1)]
    return np.concatenate([ends[0], pts[inner], ends[1]])


def bezier(p0, t0, p1, t1, step: float = 0.5) -> np.ndarray:
    """Cubic Bezier from ``p0`` (heading ``t0``) to ``p1`` (heading ``t1``), ``(M, 2)``."""
    d = float(np.hypot(*(p1 - p0)))
    c0, c1 = p0 + t0 * 0.39 * d, p1 - t1 * 0.39 * d
    u = np.linspace(0.0, 1.0, max(3, int(math.ceil(d / step)) + 1))[:, None]
    return (1 - u) ** 3 * p0 + 3 * (1 - u) ** 2 * u * c0 + 3 * (1 - u) * u**2 * c1 + u**3 * p1


def convex_hull(points: np.ndarray) -> np.ndarray:
    """Convex hull (counter-clockwise, float64) of ``(N, 2)`` points (monotone chain)."""
    pts = sorted(map(tuple, np.asarray(points, dtype=np.float64)))

    def half(seq):
        out = []
        for p in seq:
            while len(out) >= 2 and (
                (out[-1][0] - out[-2][0]) * (p[1] - out[-2][1])
                - (out[-1][1] - out[-2][1]) * (p[0] - out[-2][0])
            ) <= 0:
                out.pop()
            out.append(p)
        return out

    lower, upper = half(pts), half(reversed(pts))
    return np.array(lower[:-1] + upper[:-1])


# ---------------------------------------------------------------------- model
@dataclass
class Road:
    """A road between two nodes; see the module docstring for the conventions."""

    index: int
    a: int
    b: int
    center: np.ndarray  # (N, 2) trimmed centre line, ~1 m spacing, from a to b
    lanes: int
    lane_width: float
    park: tuple[float, float]  # parking strip width on the (left, right) side, 0 = none
    sidewalk: float
    crossing: list = field(default_factory=lambda: [False, False])  # at the a end, the b end
    crossing_width: float = 4.0

    def __post_init__(self) -> None:
        self.s = arclength(self.center)
        self.normal = normals(self.center)

    @property
    def length(self) -> float:
        """Arc length of the centre line, metres."""
        return float(self.s[-1])

    def half_width(self, side: int) -> float:
        """Carriageway half width on side +1 (left) or -1 (right)."""
        return self.lanes * self.lane_width + self.park[0 if side > 0 else 1]

    def offset(self, lat: float, s0: float = 0.0, s1: float | None = None) -> np.ndarray:
        """Polyline ``(M, 2)`` parallel to the centre line at lateral offset ``lat``."""
        s1 = self.length if s1 is None else s1
        inner = (self.s > s0) & (self.s < s1)
        ss = np.concatenate([[s0], self.s[inner], [s1]])
        c = np.stack([np.interp(ss, self.s, self.center[:, i]) for i in (0, 1)], axis=1)
        n = np.stack([np.interp(ss, self.s, self.normal[:, i]) for i in (0, 1)], axis=1)
        n /= np.linalg.norm(n, axis=1, keepdims=True)
        return c + n * lat

    def lane_offset(self, direction: int, lane: int) -> float:
        """Lateral offset of lane ``lane`` of travel direction +1 (a -> b) or -1."""
        return -direction * (lane + 0.5) * self.lane_width

    def lane_path(self, direction: int, lane: int) -> np.ndarray:
        """Centre of a lane as a polyline in the direction of travel."""
        p = self.offset(self.lane_offset(direction, lane))
        return p if direction > 0 else p[::-1]

    def marking_range(self) -> tuple[float, float]:
        """Arc range of lane markings: they stop before crossings and intersections."""
        lo = 1.5 + (self.crossing_width + 0.5 if self.crossing[0] else 0.0)
        hi = self.length - 1.5 - (self.crossing_width + 0.5 if self.crossing[1] else 0.0)
        return lo, max(lo, hi)

    def crossing_range(self, end: int) -> tuple[float, float]:
        """Arc range of the zebra crossing at end 0 (a) or 1 (b)."""
        if end == 0:
            return 0.5, 0.5 + self.crossing_width
        return self.length - 0.5 - self.crossing_width, self.length - 0.5

    def point_at(self, s: float) -> tuple[np.ndarray, np.ndarray]:
        """Centre point and unit tangent at arc ``s``."""
        p = np.array([np.interp(s, self.s, self.center[:, i]) for i in (0, 1)])
        n = np.array([np.interp(s, self.s, self.normal[:, i]) for i in (0, 1)])
        n /= np.linalg.norm(n)
        return p, np.array([n[1], -n[0]])


@dataclass
class Node:
    """An intersection (or a bend, for degree 2)."""

    pos: np.ndarray  # (2,)
    arms: list = field(default_factory=list)  # (road index, end): end 0 = road starts here
    radius: float = 0.0
    road_hull: np.ndarray | None = None  # (M, 2) carriageway area of the intersection
    walk_hull: np.ndarray | None = None  # (M, 2) carriageway + sidewalk area

    @property
    def degree(self) -> int:
        """Number of road arms meeting here."""
        return len(self.arms)


class RoadNetwork:
    """A connected network with every node of degree >= 2 (no dead ends)."""

    def __init__(self, rng: np.random.Generator) -> None:
        nx, ny = (int(v) for v in rng.integers(4, 7, size=2))
        xs = np.concatenate([[0.0], np.cumsum(rng.uniform(70.0, 130.0, nx - 1))])
        ys = np.concatenate([[0.0], np.cumsum(rng.uniform(70.0, 130.0, ny - 1))])
        self.nodes = [
            Node(np.array([x, y]) + rng.uniform(-7.0, 7.0, 2)) for y in ys for x in xs
        ]
        edges = [(j * nx + i, j * nx + i + 1) for j in range(ny) for i in range(nx - 1)]
        edges += [(j * nx + i, (j + 1) * nx + i) for j in range(ny - 1) for i in range(nx)]
        edges = self._thin(edges, len(self.nodes), rng, rng.uniform(0.0, 0.2))
        p_park, p_curve, p_cross = rng.uniform(0.2, 0.7), rng.uniform(0.0, 0.5), rng.uniform(0.6, 1.0)
        raws = []
        for a, b in edges:
            pa, pb = self.nodes[a].pos, self.nodes[b].pos
            L = float(np.hypot(*(pb - pa)))
            u = np.linspace(0.0, 1.0, int(math.ceil(L)) + 1)[:, None]
            nrm = np.array([-(pb - pa)[1], (pb - pa)[0]]) / L
            amp = 0.0
            if rng.random() < p_curve:
                amp = rng.uniform(6.0, max(6.5, min(18.0, 0.15 * L))) * rng.choice([-1.0, 1.0])
            raws.append(pa + u * (pb - pa) + nrm * amp * np.sin(np.pi * u))
        lanes = rng.choice([1, 2, 3], size=len(edges), p=[0.5, 0.4, 0.1])
        widths = rng.uniform(3.0, 3.6, len(edges))
        parks = (rng.random((len(edges), 2)) < p_park) * PARK_WIDTH
        walks = rng.uniform(2.5, 4.5, len(edges))
        cw = float(rng.uniform(3.0, 4.5))
        for i, (a, b) in enumerate(edges):
            self.nodes[a].arms.append((i, 0))
            self.nodes[b].arms.append((i, 1))
        hw = [lanes[i] * widths[i] + parks[i].max() for i in range(len(edges))]
        for node in self.nodes:
            self._set_radius(node, [raws[r] if e == 0 else raws[r][::-1] for r, e in node.arms],
                             max(hw[r] for r, _ in node.arms))
        self.roads = []
        for i, (a, b) in enumerate(edges):
            raw = raws[i]
            s0 = _trim_arc(raw, self.nodes[a].pos, self.nodes[a].radius)
            s1 = arclength(raw)[-1] - _trim_arc(raw[::-1], self.nodes[b].pos, self.nodes[b].radius)
            center = resample(sub_polyline(raw, arclength(raw), s0, s1), 1.0)
            cross = [self.nodes[n].degree >= 3 and rng.random() < p_cross for n in (a, b)]
            self.roads.append(Road(i, a, b, center, int(lanes[i]), float(widths[i]),
                                   (float(parks[i, 0]), float(parks[i, 1])), float(walks[i]),
                                   cross, cw))
        for node in self.nodes:
            self._set_hulls(node)
        pts = np.concatenate([n.pos[None] for n in self.nodes])
        self.bounds = (*(pts.min(axis=0) - 70.0), *(pts.max(axis=0) + 70.0))  # x0, y0, x1, y1

    # ---------------------------------------------------------------- build
    @staticmethod
    def _thin(edges, n_nodes, rng, frac):
        """Drop up to ``frac`` of the edges keeping the graph connected and degrees >= 2."""
        edges = list(edges)
        deg = np.zeros(n_nodes, int)
        for a, b in edges:
            deg[a] += 1
            deg[b] += 1
        candidates = [edges[k] for k in rng.permutation(len(edges))[: int(frac * len(edges))]]
        for a, b in candidates:
            if deg[a] < 3 or deg[b] < 3:
                continue
            trial = [e for e in edges if e != (a, b)]
            if _connected(trial, n_nodes):
                edges, deg[a], deg[b] = trial, deg[a] - 1, deg[b] - 1
        return edges

    @staticmethod
    def _set_radius(node: Node, outward: list, hw_max: float) -> None:
        """Intersection radius: far enough out that the carriageways of the arms do not overlap."""
        ang = sorted(math.atan2(*(_point_at_arc(p, 15.0) - node.pos)[::-1]) for p in outward)
        gaps = np.diff(ang + [ang[0] + 2 * math.pi])
        theta = min(float(gaps.min()), math.radians(179.0))
        node.radius = min(max(hw_max + 3.0, hw_max / math.tan(theta / 2) + 2.0), 30.0)

    def arm_end(self, road_index: int, end: int):
        """``(point, outward unit dir, half width left of outward, right of outward, sidewalk)``."""
        r = self.roads[road_index]
        if end == 0:
            d = r.center[1] - r.center[0]
            return r.center[0], d / np.linalg.norm(d), r.half_width(1), r.half_width(-1), r.sidewalk
        d = r.center[-2] - r.center[-1]
        return r.center[-1], d / np.linalg.norm(d), r.half_width(-1), r.half_width(1), r.sidewalk

    def _set_hulls(self, node: Node) -> None:
        ends = [self.arm_end(r, e) for r, e in node.arms]
        ends.sort(key=lambda t: math.atan2(t[1][1], t[1][0]))
        road, walk = [], []
        for i, (p, d, hl, hr, sw) in enumerate(ends):
            n = np.array([-d[1], d[0]])
            road += [p + n * hl, p - n * hr]
            walk += [p + n * (hl + sw), p - n * (hr + sw)]
            q, dq, _, hr_next, sw_next = ends[(i + 1) % len(ends)]
            gap = (math.atan2(dq[1], dq[0]) - math.atan2(d[1], d[0])) % (2 * math.pi)
            if gap >= math.radians(170.0):  # reflex side: square off the outer corner
                bis = math.atan2(d[1], d[0]) + gap / 2
                u = np.array([math.cos(bis), math.sin(bis)]) / math.sin(gap / 2)
                h = max(hl, hr_next)
                road.append(node.pos + u * h)
                walk.append(node.pos + u * (h + max(sw, sw_next)))
        node.road_hull = convex_hull(np.array(road))
        node.walk_hull = convex_hull(np.array(walk))

    # -------------------------------------------------------------- routing
    def end_node(self, road_index: int, direction: int) -> int:
        """Node reached when driving along road ``road_index`` in ``direction``."""
        r = self.roads[road_index]
        return r.b if direction > 0 else r.a

    def next_choices(self, road_index: int, direction: int, lane: int):
        """``[(turn angle rad (+ = left), road, direction, lane), ...]`` at the node ahead."""
        node = self.nodes[self.end_node(road_index, direction)]
        path_in = self.roads[road_index].lane_path(direction, lane)
        t_in = path_in[-1] - path_in[-2]
        out = []
        for r, e in node.arms:
            if r == road_index:
                continue
            road = self.roads[r]
            d = 1 if e == 0 else -1
            p = road.lane_path(d, 0)
            t_out = p[1] - p[0]
            ang = math.atan2(t_in[0] * t_out[1] - t_in[1] * t_out[0], float(t_in @ t_out))
            k = min(lane, road.lanes - 1) if abs(ang) < math.radians(35) else (
                0 if ang > 0 else road.lanes - 1)
            out.append((ang, r, d, k))
        return out

    def route(self, rng, road_index, direction, lane, s_start, length, turn_p) -> np.ndarray:
        """A lane-following drive of at least ``length`` m as a polyline ``(N, 2)`` (0.5 m steps).

        Starts ``s_start`` m along the lane (in the direction of travel); at each node goes
        straight when possible, turning with probability ``turn_p``.
        """
        pieces, total = [], 0.0
        path = self.roads[road_index].lane_path(direction, lane)
        path = sub_polyline(path, arclength(path), min(s_start, arclength(path)[-1] - 0.5),
                            arclength(path)[-1])
        while True:
            pieces.append(path)
            total += arclength(path)[-1]
            if total >= length:
                break
            choices = self.next_choices(road_index, direction, lane)
            straight = [c for c in choices if abs(c[0]) < math.radians(35)]
            turns = [c for c in choices if abs(c[0]) >= math.radians(35)]
            if straight and (not turns or rng.random() >= turn_p):
                pick = straight[int(rng.integers(len(straight)))]
            else:
                pick = turns[int(rng.integers(len(turns)))]
            _, road_index, direction, lane = pick
            nxt = self.roads[road_index].lane_path(direction, lane)
            t0 = path[-1] - path[-2]
            t1 = nxt[1] - nxt[0]
            conn = bezier(path[-1], t0 / np.linalg.norm(t0), nxt[0], t1 / np.linalg.norm(t1))
            pieces.append(conn[1:-1])
            total += arclength(conn)[-1]
            path = nxt
        return resample(np.concatenate(pieces), 0.5)


    def intersection_caps(self, pts: np.ndarray, rng, lo: float, hi: float) -> np.ndarray:
        """Per point of a route ``(N, 2)``: a speed cap drawn in ``[lo, hi]`` per intersection
        (degree >= 3) within 6 m of its area, ``inf`` elsewhere.
        """
        cap = np.full(len(pts), np.inf)
        for node in self.nodes:
            if node.degree < 3:
                continue
            v = rng.uniform(lo, hi)
            near = np.hypot(*(pts - node.pos).T) < node.radius + 6.0
            cap[near] = np.minimum(cap[near], v)
        return cap


def _connected(edges, n_nodes) -> bool:
    adj = [[] for _ in range(n_nodes)]
    for a, b in edges:
        adj[a].append(b)
        adj[b].append(a)
    seen, todo = {0}, [0]
    while todo:
        for m in adj[todo.pop()]:
            if m not in seen:
                seen.add(m)
                todo.append(m)
    return len(seen) == n_nodes


def _point_at_arc(pts: np.ndarray, s: float) -> np.ndarray:
    sa = arclength(pts)
    return np.array([np.interp(s, sa, pts[:, 0]), np.interp(s, sa, pts[:, 1])])


def _trim_arc(raw: np.ndarray, node: np.ndarray, radius: float) -> float:
    """Arc length along ``raw`` where its distance from ``node`` first reaches ``radius``."""
    d = np.hypot(*(raw - node).T)
    s = arclength(raw)
    i = int(np.argmax(d >= radius))
    if i == 0:
        return 0.0
    f = (radius - d[i - 1]) / max(d[i] - d[i - 1], 1e-9)
    return float(s[i - 1] + f * (s[i] - s[i - 1]))
