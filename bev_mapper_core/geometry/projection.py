"""Projection tables: 3-D points (BEV cell centres on the ground, or a plane's cells) -> each
camera's pixels, built once per calibration. IPM warps label images with them; the learned
methods build their view-transform tables and frustum masks from them.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from .grid import BevGrid
from .rig import Rig, RigCamera
from .transforms import transform_points


@dataclass(frozen=True)
class RemapTable:
    """Pixel lookup for a set of 3-D points seen by one camera.

    Attributes:
        map_x, map_y: float32 arrays of the target shape; pixel coordinates for ``cv2.remap``
            (-1 where the point is not seen).
        valid: bool array of the target shape: the point is in front of the camera, inside
            its image and not on the camera's ego mask (the ego vehicle's own body).
    """

    map_x: np.ndarray
    map_y: np.ndarray
    valid: np.ndarray

    def warp(self, image: np.ndarray, interpolation: int = cv2.INTER_NEAREST) -> np.ndarray:
        """Sample ``image`` at the table's pixels (edges replicated; mask with ``valid``)."""
        return cv2.remap(
            image, self.map_x, self.map_y, interpolation,
            borderMode=cv2.BORDER_REPLICATE,
        )


def remap_table(camera: RigCamera, points_ego: np.ndarray, shape: tuple[int, int]) -> RemapTable:
    """Project ego-frame points ``(N, 3)`` into ``camera``; arrange the result as ``shape``.

    ``N`` must equal ``shape[0] * shape[1]`` (points in row-major order of the target). Points
    whose pixel lies on ``camera.ego_mask`` are not seen (``valid`` False).
    """
    if points_ego.shape != (shape[0] * shape[1], 3):
        raise ValueError(f"points {points_ego.shape} do not fill target shape {shape}")
    pts_cam = transform_points(camera.cam_from_ego, points_ego)
    uv, in_front = camera.model.project(pts_cam)
    valid = in_front & camera.model.in_image(uv)
    if camera.ego_mask is not None:
        valid &= ~camera.ego_mask.covers(uv, camera.model.image_size)
    uv = np.where(valid[:, None], uv, -1.0)
    # (N, 2) -> two (H, W) maps
    map_x = uv[:, 0].reshape(shape).astype(np.float32)
    map_y = uv[:, 1].reshape(shape).astype(np.float32)
    return RemapTable(map_x, map_y, valid.reshape(shape))


def ground_tables(rig: Rig, grid: BevGrid, z: float = 0.0) -> dict[str, RemapTable]:
    """Lookup tables from every BEV cell centre (at height ``z``) to each camera's pixels."""
    pts = grid.points(z)
    return {cam.name: remap_table(cam, pts, grid.shape) for cam in rig.cameras}
