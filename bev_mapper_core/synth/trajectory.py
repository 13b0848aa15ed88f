"""Smooth motion along a route polyline: speed profile with curvature and acceleration limits."""

from __future__ import annotations

import math

import numpy as np

from .roads import arclength


def _smooth(v: np.ndarray, n: int) -> np.ndarray:
    """Centred moving average over ``n`` samples (odd), edges padded with the end values."""
    if n <= 1 or len(v) < 2:
        return v
    pad = n // 2
    vp = np.concatenate([np.full(pad, v[0]), v, np.full(pad, v[-1])])
    return np.convolve(vp, np.ones(n) / n, mode="valid")


class PathMotion:
    """A vehicle driving along ``pts`` (``(N, 2)``, ~0.5 m spacing) from its first point.

    Speeds stay in ``[v_min, v_max]``: a piecewise cruise speed drawn from ``rng``, capped by
    the lateral acceleration ``a_lat`` in curves and by ``cap`` (per point, e.g. slower across
    intersections), then made reachable with the longitudinal limits ``a_acc`` / ``a_dec``
    (m/s^2).
    """

    def __init__(self, pts: np.ndarray, v_min: float, v_max: float, rng: np.random.Generator,
                 a_lat: float = 2.5, a_acc: float = 1.5, a_dec: float = 2.5,
                 cruise_span: tuple[float, float] = (40.0, 120.0),
                 cap: np.ndarray | None = None) -> None:
        self.pts = pts
        self.s = s = arclength(pts)
        ds = float(np.median(np.diff(s))) if len(s) > 1 else 0.5
        tang = np.gradient(pts, axis=0)
        yaw = np.unwrap(np.arctan2(tang[:, 1], tang[:, 0]))
        self.yaw = _smooth(yaw, max(1, int(round(2.0 / ds)) | 1))
        self.kappa = _smooth(np.gradient(self.yaw, s), max(1, int(round(3.0 / ds)) | 1))
        cruise = np.empty_like(s)
        pos = 0.0
        lo = v_min + 0.35 * (v_max - v_min)
        while pos <= s[-1]:
            span = rng.uniform(*cruise_span)
            cruise[(s >= pos) & (s < pos + span)] = rng.uniform(lo, v_max)
            pos += span
        with np.errstate(divide="ignore"):
            curve = np.sqrt(a_lat / np.maximum(np.abs(self.kappa), 1e-9))
        if cap is not None:
            curve = np.minimum(curve, cap)
        v = np.clip(np.minimum(cruise, curve), v_min, v_max)
        dseg = np.diff(s)
        for i in range(1, len(v)):  # acceleration limit
            v[i] = min(v[i], math.sqrt(v[i - 1] ** 2 + 2 * a_acc * dseg[i - 1]))
        for i in range(len(v) - 2, -1, -1):  # braking limit
            v[i] = min(v[i], math.sqrt(v[i + 1] ** 2 + 2 * a_dec * dseg[i]))
        self.v = v
        self.t = np.concatenate([[0.0], np.cumsum(2 * dseg / (v[1:] + v[:-1]))])

    @property
    def duration(self) -> float:
        """Time to drive the whole path, s."""
        return float(self.t[-1])

    def sample(self, times: np.ndarray):
        """State at ``times`` (s): ``x, y, yaw, speed, yaw_rate``, each ``(T,)``.

        Past the end of the path the vehicle stops at its last point.
        """
        times = np.asarray(times, np.float64)
        s = np.interp(times, self.t, self.s)
        x = np.interp(s, self.s, self.pts[:, 0])
        y = np.interp(s, self.s, self.pts[:, 1])
        yaw = np.interp(s, self.s, self.yaw)
        v = np.where(times <= self.t[-1], np.interp(s, self.s, self.v), 0.0)
        return x, y, yaw, v, v * np.interp(s, self.s, self.kappa)
