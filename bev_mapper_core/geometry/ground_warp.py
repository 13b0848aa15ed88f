"""Moving a camera's image instead of its calibration: the ground-plane warp (issue #38).

A camera that fired while the ego was elsewhere saw the ground from ``placed`` (its pose at the
set's reference stamp, :mod:`.time_placement`), not from its calibrated pose. A method whose
calibration is baked into a model (Bi-Mapper, the monocular methods: a new rig would re-export
it) keeps its calibrated rig; :func:`ground_warp_maps` instead turns the image into the one the
calibrated camera would have taken of the same ground: for each pixel of the calibrated view, the
ground point its ray meets (``z = 0`` in ``base_link``) is projected into the placed camera, and
the image is sampled there (``cv2.remap``). Exact for the ground, which is what BEV maps are
made of; a point above the ground (a car's roof) is moved as if it were on the ground under its
ray, i.e. slightly less than it should be (a few cm for the 0.1-0.5 m corrections of a set).
Rays that never meet the ground, or meet it beyond :data:`FAR_M`, are moved by the rotation alone
(points at infinity). Lens distortion is honoured both ways (``CameraModel.unproject`` /
``project``).
"""

from __future__ import annotations

import cv2
import numpy as np

from .rig import RigCamera

#: Ground points farther than this (m) are treated as at infinity (rotation only).
FAR_M = 500.0


def ground_warp_maps(camera: RigCamera, placed_ego_from_cam: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``(map_x, map_y)`` float32 ``(H, W)`` for ``cv2.remap``: sampling an image that ``camera``
    took from ``placed_ego_from_cam`` (4x4, ``base_link`` at the reference stamp) with them gives
    the image ``camera`` would have taken from its calibrated pose (see the module docstring).
    Pixels whose source lies behind the placed camera get -1 (outside: the border value).
    """
    model = camera.model
    w, h = model.image_size
    us, vs = np.meshgrid(np.arange(w, dtype=np.float64), np.arange(h, dtype=np.float64))
    rays = model.unproject(np.stack([us.ravel(), vs.ravel()], axis=1))  # (H*W, 3) optical, z = 1
    E = camera.ego_from_cam_array
    d = rays @ E[:3, :3].T  # directions in base_link
    o = E[:3, 3]
    with np.errstate(divide="ignore", invalid="ignore"):
        s = np.where(d[:, 2] < -1e-9, -o[2] / d[:, 2], np.inf)  # ray parameter where z = 0
    finite = np.isfinite(s) & (s > 0) & (s * np.linalg.norm(d, axis=1) < FAR_M)
    P = np.asarray(placed_ego_from_cam, dtype=np.float64)
    R_inv = P[:3, :3].T
    pts = np.where(finite[:, None], (o + np.where(finite, s, 0.0)[:, None] * d - P[:3, 3]) @ R_inv.T, d @ R_inv.T)
    uv, front = model.project(pts)
    uv = np.where(front[:, None], uv, -1.0)
    return (uv[:, 0].reshape(h, w).astype(np.float32),  # (H*W,) -> (H, W)
            uv[:, 1].reshape(h, w).astype(np.float32))


def warp_image(image: np.ndarray, maps: tuple[np.ndarray, np.ndarray]) -> np.ndarray:
    """``image`` (``(H, W)`` label ids: nearest; ``(H, W, 3)`` RGB: bilinear) resampled by
    :func:`ground_warp_maps`; pixels from outside the image are 0 (unlabeled / black).
    """
    interp = cv2.INTER_NEAREST if image.ndim == 2 else cv2.INTER_LINEAR
    return cv2.remap(np.ascontiguousarray(image), maps[0], maps[1], interp,
                     borderMode=cv2.BORDER_CONSTANT, borderValue=0)


__all__ = ["FAR_M", "ground_warp_maps", "warp_image"]
