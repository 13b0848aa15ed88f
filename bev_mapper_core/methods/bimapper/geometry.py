"""Per-calibration lookup tables of Bi-Mapper, built once with the core geometry.

Three warps connect the spaces of Bi-Mapper (Sec. III of the paper); all are computed here, in
numpy, from the core functions only (:func:`~bev_mapper_core.methods.ipm.mapper.remap_table`,
:func:`~bev_mapper_core.geometry.transforms.transform_points`, :class:`~bev_mapper_core.geometry.grid.BevGrid`),
and applied in torch with ``grid_sample``:

1. **IPM, image -> camera plane** (LV input): every cell of a camera's plane grid, as a 3-D point
   in the optical frame, is moved to the ego frame with ``ego_from_cam`` and projected into the
   (rescaled) camera by ``remap_table``.
2. **Ego grid -> camera plane** (ASL targets): the same plane points' ego ``(x, y)`` index the
   full-resolution ground-truth grid.
3. **Camera plane -> ego feature grid** (LV merge): for each cell of the reduced BEV feature grid,
   the plane point directly above or below its centre (the vertical ego line through the centre,
   moved into the optical frame with ``cam_from_ego``, intersected with the plane). This is the
   exact inverse of 2., so a plane cell and the ego cell it lands in correspond both ways. The
   merge samples bilinearly; ``merge_weight`` is the bilinear sample of the plane's "seen by the
   camera" mask there, used to normalise (see :func:`~.lv.merge_planes_to_ego`).

The camera plane (paper: "y is 1 m in the camera coordinate system", x in (-5, 5) m, z in
(3, 29) m) is the plane ``y_optical = height`` of each camera. By default the height is the
camera's own height above the ground (``ego_from_cam[2, 3]``), so for a level camera the plane is
the ground; :attr:`PlaneSpec.height` fixes it instead (the paper's 1 m). Plane images are
indexed ``[row, col]`` with rows along +z (row 0 nearest the camera) and columns along +x
(right), cell centres at ``z_min + (row + 0.5) * dz`` and ``x_min + (col + 0.5) * dx``.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from bev_mapper_core.errors import ConfigError
from bev_mapper_core.geometry.grid import BevGrid
from bev_mapper_core.geometry.projection import ground_tables, remap_table
from bev_mapper_core.geometry.rig import Rig, RigCamera, scaled_camera
from bev_mapper_core.geometry.transforms import transform_points


@dataclass(frozen=True)
class PlaneSpec:
    """The camera-plane grid of the LV stream.

    Args:
        x_range: lateral extent (optical x, right) in metres.
        z_range: forward extent (optical z) in metres.
        shape: ``(rows along z, cols along x)``.
        height: plane offset along optical +y (down) in metres; ``None`` = the camera's height
            above the ground from its extrinsics.
    """

    x_range: tuple[float, float] = (-5.0, 5.0)
    z_range: tuple[float, float] = (3.0, 29.0)
    shape: tuple[int, int] = (104, 40)
    height: float | None = None

    def __post_init__(self) -> None:
        if not (self.x_range[1] > self.x_range[0] and self.z_range[1] > self.z_range[0]):
            raise ConfigError(f"empty camera plane: x {self.x_range}, z {self.z_range}")
        if self.z_range[0] <= 0:
            raise ConfigError(f"camera plane must lie in front of the camera, z {self.z_range}")
        if min(self.shape) < 1:
            raise ConfigError(f"camera plane shape must be positive, got {self.shape}")
        if self.height is not None and self.height <= 0:
            raise ConfigError(f"camera plane height must be > 0 (below the camera), got {self.height}")

    def plane_height(self, camera: RigCamera) -> float:
        """Offset along optical +y of ``camera``'s plane."""
        if self.height is not None:
            return float(self.height)
        h = float(camera.ego_from_cam_array[2, 3])
        if h <= 0:
            raise ConfigError(f"camera {camera.name!r} is not above the ground (z = {h} m); set plane height")
        return h

    def centers(self) -> tuple[np.ndarray, np.ndarray]:
        """Cell-centre coordinates ``(xs, zs)`` of the plane, each ``(rows, cols)``."""
        rows, cols = self.shape
        dx = (self.x_range[1] - self.x_range[0]) / cols
        dz = (self.z_range[1] - self.z_range[0]) / rows
        xs = self.x_range[0] + (np.arange(cols) + 0.5) * dx
        zs = self.z_range[0] + (np.arange(rows) + 0.5) * dz
        zz, xx = np.meshgrid(zs, xs, indexing="ij")  # (rows, cols) each
        return xx, zz

    def points_cam(self, camera: RigCamera) -> np.ndarray:
        """Plane cell centres as optical-frame points ``(rows * cols, 3)``, row-major."""
        xx, zz = self.centers()
        h = self.plane_height(camera)
        # (rows, cols) x 2 -> (rows * cols, 3)
        return np.stack([xx.ravel(), np.full(xx.size, h), zz.ravel()], axis=1)

    def to_normalized(self, x: np.ndarray, z: np.ndarray) -> np.ndarray:
        """``grid_sample`` coordinates (align_corners=False) of plane points ``(x, z)``: (..., 2)."""
        gx = 2.0 * (x - self.x_range[0]) / (self.x_range[1] - self.x_range[0]) - 1.0
        gz = 2.0 * (z - self.z_range[0]) / (self.z_range[1] - self.z_range[0]) - 1.0
        return np.stack([gx, gz], axis=-1)


def grid_normalized(grid: BevGrid, x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """``grid_sample`` coordinates (align_corners=False) of ego points in a BEV layer (cols = x)."""
    gx = 2.0 * (x - grid.x_min) / (grid.x_max - grid.x_min) - 1.0
    gy = 2.0 * (y - grid.y_min) / (grid.y_max - grid.y_min) - 1.0
    return np.stack([gx, gy], axis=-1)


def pixel_normalized(map_x: np.ndarray, map_y: np.ndarray, size: tuple[int, int]) -> np.ndarray:
    """``grid_sample`` coordinates (align_corners=False) of pixel centres in a ``(w, h)`` image."""
    w, h = size
    return np.stack([(2.0 * map_x + 1.0) / w - 1.0, (2.0 * map_y + 1.0) / h - 1.0], axis=-1)


def _bilinear_weight(mask: np.ndarray, coords: np.ndarray) -> np.ndarray:
    """Bilinear sample (align_corners=False, zero outside) of a bool ``(Hp, Wp)`` mask at
    normalised ``coords`` (h, w, 2); same convention as ``grid_sample``.
    """
    Hp, Wp = mask.shape
    m = np.pad(mask.astype(np.float64), 1)  # zero border: index +1
    px = (coords[..., 0] + 1.0) * Wp / 2.0 - 0.5  # pixel coordinates (h, w)
    py = (coords[..., 1] + 1.0) * Hp / 2.0 - 0.5
    x0, y0 = np.floor(px), np.floor(py)
    fx, fy = px - x0, py - y0
    out = np.zeros(px.shape)
    for dy, wy in ((0, 1.0 - fy), (1, fy)):
        for dx, wx in ((0, 1.0 - fx), (1, fx)):
            yi = np.clip(y0 + dy + 1, 0, Hp + 1).astype(np.int64)
            xi = np.clip(x0 + dx + 1, 0, Wp + 1).astype(np.int64)
            out += wy * wx * m[yi, xi]
    return out


def feature_grid(grid: BevGrid, downsample: int) -> BevGrid:
    """The reduced BEV grid of the feature maps: same extent, ``downsample`` times coarser."""
    if grid.height % downsample or grid.width % downsample:
        raise ConfigError(
            f"grid {grid.height}x{grid.width} cells is not divisible by bev_downsample {downsample}"
        )
    return replace(grid, resolution=grid.resolution * downsample)


class BiMapperGeometry:
    """All calibration-dependent tables of a Bi-Mapper model for one rig and grid.

    Attributes (numpy; N cameras in rig order, plane ``(Hp, Wp)``, feature grid ``(h, w)``):
        input_size: ``(height, width)`` of every camera's model input.
        ipm_grid (N, Hp, Wp, 2), ipm_valid (N, Hp, Wp): plane cell -> input pixel.
        gt_grid (N, Hp, Wp, 2), gt_valid (N, Hp, Wp): plane cell -> full ego grid (ASL targets);
            valid where the camera sees the plane cell and it lies inside the grid.
        merge_grid (N, h, w, 2): ego feature cell -> plane (-2 where it is off the plane);
        merge_weight (N, h, w): seen fraction of the bilinear footprint there (0..1).
        frustum (N, H, W): full-grid ground cells inside each camera's image.
        prior_index (N, H*W) int64: for every full-grid cell (row-major), the flat index of the
            pixel of the camera-size image the ground IPM reads (``cv2.remap`` nearest: round
            half to even, edges replicated), so a gather reproduces :class:`IpmMapper`.
        raw_sizes: ``(width, height)`` of each camera's delivered image.
    """

    def __init__(self, rig: Rig, grid: BevGrid, input_width: int, plane: PlaneSpec, bev_downsample: int,
                 any_aspect: bool = False) -> None:
        self.rig, self.grid, self.plane = rig, grid, plane
        self.feat_grid = feature_grid(grid, bev_downsample)
        cams = [scaled_camera(c, input_width) for c in rig.cameras]
        sizes = {c.model.image_size for c in cams}
        if len(sizes) != 1 and any_aspect:
            # a model without per-camera parameters (Bi-Mapper's LV stream) batches cameras of other
            # aspect ratios at the first camera's input size: each image is resized to it, and its
            # normalised IPM coordinates are the same at any size
            sizes = {cams[0].model.image_size}
        if len(sizes) != 1:
            raise ConfigError(
                f"rig {rig.name!r}: cameras give different input sizes {sorted(sizes)} at width "
                f"{input_width}; Bi-Mapper batches all cameras through one encoder"
            )
        w_in, h_in = sizes.pop()
        self.input_size = (h_in, w_in)
        ipm_g, ipm_v, gt_g, gt_v, mg_g, mg_w = [], [], [], [], [], []
        feat_pts = self.feat_grid.points(0.0)  # (h*w, 3)
        up = feat_pts + np.array([0.0, 0.0, 1.0])
        for cam in cams:
            pts_ego = transform_points(cam.ego_from_cam_array, plane.points_cam(cam))  # (Hp*Wp, 3)
            table = remap_table(cam, pts_ego, plane.shape)
            ipm_g.append(pixel_normalized(table.map_x, table.map_y, cam.model.image_size))
            ipm_v.append(table.valid)
            x, y = pts_ego[:, 0].reshape(plane.shape), pts_ego[:, 1].reshape(plane.shape)  # (Hp, Wp)
            gt_g.append(grid_normalized(grid, x, y))
            gt_v.append(table.valid & grid.contains(x, y))
            # vertical ego line through each feature cell centre, intersected with y_opt = height
            a = transform_points(cam.cam_from_ego, feat_pts)  # (h*w, 3)
            b = transform_points(cam.cam_from_ego, up)
            dy = b[:, 1] - a[:, 1]
            ok = np.abs(dy) > 1e-6
            t = (plane.plane_height(cam) - a[:, 1]) / np.where(ok, dy, 1.0)
            p = a + t[:, None] * (b - a)  # (h*w, 3) optical
            xz_n = plane.to_normalized(p[:, 0], p[:, 2])  # (h*w, 2)
            inside = ok & np.all(np.abs(xz_n) <= 1.0, axis=1)
            mg_g.append(np.where(inside[:, None], xz_n, -2.0).reshape(*self.feat_grid.shape, 2))  # (h*w, 2) -> (h, w, 2)
            mg_w.append(_bilinear_weight(table.valid, mg_g[-1]))
        self.ipm_grid = np.stack(ipm_g).astype(np.float32)
        self.ipm_valid = np.stack(ipm_v)
        self.gt_grid = np.stack(gt_g).astype(np.float32)
        self.gt_valid = np.stack(gt_v)
        self.merge_grid = np.stack(mg_g).astype(np.float32)
        self.merge_weight = np.stack(mg_w).astype(np.float32)
        tables = ground_tables(rig, grid)
        self.frustum = np.stack([tables[c.name].valid for c in rig.cameras])
        self.raw_sizes = tuple(c.model.image_size for c in rig.cameras)
        index = []
        for c, (w, h) in zip(rig.cameras, self.raw_sizes):
            t = tables[c.name]
            ix = np.clip(np.rint(t.map_x), 0, w - 1).astype(np.int64)
            iy = np.clip(np.rint(t.map_y), 0, h - 1).astype(np.int64)
            index.append((iy * w + ix).ravel())  # (H, W) -> (H*W,)
        self.prior_index = np.stack(index)

    def arrays(self) -> dict[str, np.ndarray]:
        """The tables by name, for registering as (non-persistent) torch buffers."""
        return {
            "ipm_grid": self.ipm_grid, "ipm_valid": self.ipm_valid,
            "gt_grid": self.gt_grid, "gt_valid": self.gt_valid,
            "merge_grid": self.merge_grid, "merge_weight": self.merge_weight,
            "frustum": self.frustum, "prior_index": self.prior_index,
        }
