"""Moving a camera's image instead of its calibration: the ground-plane warp (issue #38).

A camera that fired while the ego was elsewhere saw the ground from ``placed`` (its pose at the
set's reference stamp, :mod:`.time_placement`), not from its calibrated pose. A method whose
calibration is baked into a model (Bi-Mapper, the monocular methods: a new rig would re-export
it) keeps its calibrated rig; :class:`GroundWarp` instead turns the image into the one the
calibrated camera would have taken of the same ground: for each pixel of the calibrated view, the
ground point its ray meets (``z = 0`` in ``base_link``) is projected into the placed camera, and
the image is sampled there (``cv2.remap``). Exact for the ground, which is what BEV maps are
made of; a point above the ground (a car's roof) is moved as if it were on the ground under its
ray, i.e. slightly less than it should be (a few cm for the 0.1-0.5 m corrections of a set).
Rays that never meet the ground, or meet it beyond :data:`FAR_M`, are moved by the rotation alone
(points at infinity). Lens distortion is honoured both ways (``CameraModel.unproject`` /
``project``).

The rays (the costly undistortion) are computed once per camera, on a grid of at most
:data:`MAX_SAMPLES` pixels; each move projects them (closed form) and interpolates the maps to
every pixel bilinearly: a 1600 x 900 camera costs what a 270 x 150 one does.
"""

from __future__ import annotations

import math

import cv2
import numpy as np

from .rig import RigCamera

#: Ground points farther than this (m) are treated as at infinity (rotation only).
FAR_M = 500.0
#: The most pixels a camera's warp is computed at (the maps are interpolated between them).
MAX_SAMPLES = 40_000


class GroundWarp:
    """The ground-plane warp of one calibrated camera (see the module docstring).

    Args:
        camera: the camera as calibrated (its ``ego_from_cam`` and intrinsics).
    """

    def __init__(self, camera: RigCamera) -> None:
        self.camera = camera
        w, h = camera.model.image_size
        #: sample spacing in pixels (1: every pixel)
        self.step = max(1, math.ceil(math.sqrt(w * h / MAX_SAMPLES)))
        xs = np.arange(0, w - 1 + self.step, self.step, dtype=np.float64)  # covers w - 1
        ys = np.arange(0, h - 1 + self.step, self.step, dtype=np.float64)
        self._shape = (len(ys), len(xs))
        us, vs = np.meshgrid(xs, ys)
        rays = camera.model.unproject(np.stack([us.ravel(), vs.ravel()], axis=1))  # (n, 3) optical, z = 1
        E = camera.ego_from_cam_array
        d = rays @ E[:3, :3].T  # directions in base_link
        o = E[:3, 3]
        with np.errstate(divide="ignore", invalid="ignore"):
            s = np.where(d[:, 2] < -1e-9, -o[2] / d[:, 2], np.inf)  # ray parameter where z = 0
        self._finite = np.isfinite(s) & (s > 0) & (s * np.linalg.norm(d, axis=1) < FAR_M)
        self._ground = o + np.where(self._finite, s, 0.0)[:, None] * d  # (n, 3) ground points
        self._dirs = d
        if self.step > 1:  # where each pixel falls between the samples (bilinear, in sample units)
            gx, gy = np.meshgrid(np.arange(w, dtype=np.float32) / self.step, np.arange(h, dtype=np.float32) / self.step)
            self._at = (gx, gy)

    def maps(self, placed_ego_from_cam: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """``(map_x, map_y)`` float32 ``(H, W)`` for ``cv2.remap``: sampling an image the camera
        took from ``placed_ego_from_cam`` (4x4, ``base_link`` at the reference stamp) with them
        gives the image it would have taken from its calibrated pose. Pixels whose source lies
        behind the placed camera get -1 (outside: the border value).
        """
        P = np.asarray(placed_ego_from_cam, dtype=np.float64)
        R_inv = P[:3, :3].T
        pts = np.where(self._finite[:, None], (self._ground - P[:3, 3]) @ R_inv.T, self._dirs @ R_inv.T)
        uv, front = self.camera.model.project(pts)
        uv = np.where(front[:, None], uv, -1.0).astype(np.float32)
        mx, my = uv[:, 0].reshape(self._shape), uv[:, 1].reshape(self._shape)  # (n,) -> (ny, nx)
        if self.step == 1:
            return np.ascontiguousarray(mx), np.ascontiguousarray(my)
        gx, gy = self._at
        return (cv2.remap(mx, gx, gy, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE),
                cv2.remap(my, gx, gy, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE))


def ground_warp_maps(camera: RigCamera, placed_ego_from_cam: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """:meth:`GroundWarp.maps` of a camera warped once."""
    return GroundWarp(camera).maps(placed_ego_from_cam)


def warp_image(image: np.ndarray, maps: tuple[np.ndarray, np.ndarray]) -> np.ndarray:
    """``image`` (``(H, W)`` label ids: nearest; ``(H, W, 3)`` RGB: bilinear) resampled by
    :meth:`GroundWarp.maps`; pixels from outside the image are 0 (unlabeled / black).
    """
    interp = cv2.INTER_NEAREST if image.ndim == 2 else cv2.INTER_LINEAR
    return cv2.remap(np.ascontiguousarray(image), maps[0], maps[1], interp,
                     borderMode=cv2.BORDER_CONSTANT, borderValue=0)


__all__ = ["FAR_M", "MAX_SAMPLES", "GroundWarp", "ground_warp_maps", "warp_image"]
