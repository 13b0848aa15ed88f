"""3-D objects of the synthetic world: upright oriented boxes grouped into objects.

An object (a car, a pedestrian, a street light, a building) is a pose ``(x, y, yaw)`` in the
world frame plus one or more *parts*: boxes given in the object's frame (x forward, y left,
z up). Every part stands on or above the ground (``z0 >= 0``).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..labels.classes import Label

# part shading kinds
PLAIN, FACADE, GLASS, CAR_BODY = 0, 1, 2, 3


@dataclass
class Boxes:
    """``N`` oriented upright boxes in one frame (world or ego), as parallel arrays.

    Attributes:
        center: ``(N, 2)`` footprint centre xy.
        z0: ``(N,)`` base height.
        size: ``(N, 3)`` length (along the box x axis), width, height.
        yaw: ``(N,)`` heading of the box x axis.
        label: ``(N,)`` uint8 :class:`~bev_mapper_core.labels.classes.Label` ids.
        color: ``(N, 3)`` float32 base colour, RGB 0..255.
        kind: ``(N,)`` uint8 shading kind (plain, facade with windows, glass, car body).
        obj: ``(N,)`` int64 id of the object each box belongs to.
    """

    center: np.ndarray
    z0: np.ndarray
    size: np.ndarray
    yaw: np.ndarray
    label: np.ndarray
    color: np.ndarray
    kind: np.ndarray
    obj: np.ndarray

    def __len__(self) -> int:
        return len(self.yaw)

    def subset(self, idx) -> "Boxes":
        """The boxes selected by an index array or boolean mask."""
        return Boxes(*(getattr(self, f)[idx] for f in _FIELDS))

    @staticmethod
    def concat(items: list["Boxes"]) -> "Boxes":
        """All boxes of ``items`` in order."""
        return Boxes(*(np.concatenate([getattr(b, f) for b in items]) for f in _FIELDS))

    @staticmethod
    def make(center, z0, size, yaw, label, color, kind=PLAIN, obj=0) -> "Boxes":
        """Boxes from array-likes (scalars broadcast to ``N``)."""
        center = np.asarray(center, np.float64).reshape(-1, 2)  # (2,) or (N, 2) -> (N, 2)
        n = len(center)

        def arr(v, dtype, shape=()):
            return np.broadcast_to(np.asarray(v, dtype), (n, *shape)).copy()

        return Boxes(center, arr(z0, np.float64), arr(size, np.float64, (3,)), arr(yaw, np.float64),
                     arr(label, np.uint8), arr(color, np.float32, (3,)), arr(kind, np.uint8),
                     arr(obj, np.int64))

    def corners(self) -> np.ndarray:
        """The 8 corners of every box, ``(N, 8, 3)``."""
        sx = np.array([-1, 1, 1, -1, -1, 1, 1, -1]) * 0.5
        sy = np.array([-1, -1, 1, 1, -1, -1, 1, 1]) * 0.5
        sz = np.array([0, 0, 0, 0, 1, 1, 1, 1])
        lx = self.size[:, :1] * sx  # (N, 8)
        ly = self.size[:, 1:2] * sy
        c, s = np.cos(self.yaw)[:, None], np.sin(self.yaw)[:, None]
        x = self.center[:, :1] + c * lx - s * ly
        y = self.center[:, 1:] + s * lx + c * ly
        z = self.z0[:, None] + self.size[:, 2:] * sz
        return np.stack([x, y, z], axis=-1)

    def radius(self) -> np.ndarray:
        """Footprint half diagonal ``(N,)``."""
        return 0.5 * np.hypot(self.size[:, 0], self.size[:, 1])


_FIELDS = ("center", "z0", "size", "yaw", "label", "color", "kind", "obj")

# A part: (dx, dy, z0, length, width, height, label, rgb, kind) in the object frame.
Part = tuple


def car_parts(rng: np.random.Generator, color) -> list[Part]:
    """A car (body + glass cabin) or, sometimes, a van; origin at the footprint centre."""
    color = np.asarray(color, np.float32)
    V = Label.VEHICLE
    if rng.random() < 0.15:  # van
        L, W = rng.uniform(4.8, 6.0), rng.uniform(1.9, 2.1)
        return [(0.0, 0.0, 0.0, L, W, 1.1, V, color, CAR_BODY),
                (0.35 * L, 0.0, 1.1, 0.3 * L, W * 0.96, 0.75, V, (40, 48, 56), GLASS),
                (-0.15 * L, 0.0, 1.1, 0.7 * L, W, rng.uniform(1.0, 1.3), V, color, PLAIN)]
    L, W = rng.uniform(3.9, 4.9), rng.uniform(1.7, 1.95)
    hb = rng.uniform(0.75, 0.9)
    return [(0.0, 0.0, 0.0, L, W, hb, V, color, CAR_BODY),
            (-0.08 * L, 0.0, hb, rng.uniform(0.45, 0.58) * L, W * 0.86, rng.uniform(0.45, 0.6), V,
             (35, 42, 50), GLASS)]


def pedestrian_parts(rng: np.random.Generator) -> list[Part]:
    """A pedestrian: legs, torso, head."""
    k = rng.uniform(0.9, 1.08)
    P = Label.PEDESTRIAN
    shirt = rng.uniform(20, 230, 3)
    pants = rng.uniform(20, 90, 3)
    skin = np.array([224, 172, 140]) * rng.uniform(0.45, 1.05)
    return [(0.0, 0.0, 0.0, 0.32, 0.42, 0.85 * k, P, pants, PLAIN),
            (0.0, 0.0, 0.85 * k, 0.3, 0.48, 0.62 * k, P, shirt, PLAIN),
            (0.0, 0.0, 1.47 * k, 0.22, 0.2, 0.24 * k, P, skin, PLAIN)]


def obstacle_parts(rng: np.random.Generator, what: str) -> list[Part]:
    """Street furniture on the sidewalk: ``"light"`` (pole + lamp arm, arm along +x), ``"cone"``,
    ``"bin"``, ``"bollard"``.
    """
    O = Label.OBSTACLE  # noqa: E741 - the label as a one-letter colour code, as in the part tables below
    if what == "light":
        h = rng.uniform(4.5, 7.0)
        grey = np.full(3, rng.uniform(70, 140))
        return [(0.0, 0.0, 0.0, 0.18, 0.18, h, O, grey, PLAIN),
                (0.7, 0.0, h - 0.15, 1.4, 0.14, 0.15, O, grey, PLAIN)]
    if what == "cone":
        return [(0.0, 0.0, 0.0, 0.36, 0.36, 0.72, O, (235, 90, 20), PLAIN)]
    if what == "bin":
        c = [(40, 90, 50), (60, 60, 64), (30, 60, 120), (120, 90, 40)][int(rng.integers(4))]
        return [(0.0, 0.0, 0.0, 0.6, 0.6, rng.uniform(0.95, 1.2), O, c, PLAIN)]
    return [(0.0, 0.0, 0.0, 0.2, 0.2, 0.9, O, (90, 90, 95), PLAIN)]


def obb_overlap(c1, yaw1, half1, c2, yaw2, half2) -> np.ndarray:
    """Separating-axis test of 2-D oriented rectangles, vectorised over a leading axis.

    ``c*``: ``(T, 2)`` centres, ``yaw*``: ``(T,)``, ``half*``: ``(2,)`` or ``(T, 2)`` half sizes.
    Returns ``(T,)`` bool: the rectangles overlap.
    """
    c1, c2 = np.atleast_2d(c1), np.atleast_2d(c2)
    yaw1, yaw2 = np.broadcast_arrays(np.atleast_1d(np.asarray(yaw1, float)),
                                     np.atleast_1d(np.asarray(yaw2, float)))
    h1 = np.broadcast_to(np.asarray(half1, float), (len(yaw1), 2))
    h2 = np.broadcast_to(np.asarray(half2, float), (len(yaw1), 2))
    a1 = np.stack([np.cos(yaw1), np.sin(yaw1)], -1)  # (T, 2) x axis of box 1
    b1 = np.stack([-a1[:, 1], a1[:, 0]], -1)
    a2 = np.stack([np.cos(yaw2), np.sin(yaw2)], -1)
    b2 = np.stack([-a2[:, 1], a2[:, 0]], -1)
    d = c2 - c1
    sep = np.zeros(len(yaw1), bool)
    for u in (a1, b1, a2, b2):
        r1 = h1[:, 0] * np.abs((a1 * u).sum(1)) + h1[:, 1] * np.abs((b1 * u).sum(1))
        r2 = h2[:, 0] * np.abs((a2 * u).sum(1)) + h2[:, 1] * np.abs((b2 * u).sum(1))
        sep |= np.abs((d * u).sum(1)) > r1 + r2
    return ~sep
