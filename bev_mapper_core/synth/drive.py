"""Synthetic drives: per-frame camera images, ego motion and BEV ground truth.

Ground truth comes from the very world that is rendered: the flat classes are the ground
raster's labels at the BEV cell centres (nearest cell, the same lookup the renderer uses for
ground pixels), vehicle / pedestrian are the footprints of their boxes.

Visibility of a cell: some camera sees its point (the cell centre on the ground, or, inside an
object's footprint, the point at half that object's height) and nothing is in front of it.
The occlusion test reads the camera's depth and box buffers at the pixel the point projects to
(nearest pixel): the segment from the camera to the point is blocked when that pixel shows a
box of another object closer than the point. This is the exact segment test at pixel
resolution, without a second round of ray/box intersections.

``SynthFrame.ground_visibility`` is the same mask without the cells under objects (their ground
is hidden inside the object): use it to score flat classes (drivable, crossings, ...) of methods
that see the ground, such as IPM; ``visibility`` counts a parked car's cells as seen when the
car is, which is what vehicle / pedestrian layers need.
"""

from __future__ import annotations

from collections.abc import Iterator
from dataclasses import dataclass

import numpy as np

from ..errors import ConfigError
from ..geometry.grid import BevGrid
from ..geometry.rig import Rig
from ..geometry.transforms import invert_transform
from ..labels.classes import BEV_CLASSES, label_lut
from .config import SynthConfig
from .objects import Boxes
from .render import CameraRenderer
from .styles import resolve_style, style_look
from .world import World, build_world

#: depth tolerance (m) of the occlusion test
OCCLUSION_TOL = 0.1


@dataclass
class CameraFrame:
    """One camera's images of a frame."""

    rgb: np.ndarray  # (H, W, 3) uint8
    labels: np.ndarray  # (H, W) uint8 Label ids
    stamp_ns: int  # frame stamp + this camera's jitter


@dataclass
class SynthFrame:
    """Everything generated for one frame."""

    index: int
    stamp_ns: int
    world_from_ego: np.ndarray  # (4, 4) odom <- base_link
    linear_velocity: np.ndarray  # (3,) base_link, m/s
    angular_velocity: np.ndarray  # (3,) rad/s
    cameras: dict
    gt: np.ndarray  # (C, H, W) bool, BEV_CLASSES order
    visibility: np.ndarray  # (H, W) bool
    #: (H, W) bool: the cell's *ground* point is seen (False under vehicles, pedestrians, ...);
    #: the right mask to compare flat classes (drivable, ...) from ground-plane methods against
    ground_visibility: np.ndarray | None = None


class DriveRenderer:
    """Renders frames of a built :class:`World` for a rig and a grid."""

    def __init__(self, world: World, rig: Rig, grid: BevGrid) -> None:
        self.world, self.rig, self.grid = world, rig, grid
        self.config = world.config
        self.cams = [CameraRenderer(c) for c in rig.cameras]
        #: the appearance style of the drive (``config.style``, ``mixed`` resolved) and its look
        self.style = resolve_style(self.config.style, self.config.seed)
        self.look = style_look(self.style, self.config.seed, self.config.image_noise)
        self.lut = label_lut(BEV_CLASSES)  # (NUM_LABELS, C)
        self.cell_points = grid.points(0.0)  # (H*W, 3) ego frame

    def frame(self, k: int, boxes: Boxes | None = None) -> SynthFrame:
        """Frame ``k``; ``boxes`` (world frame) replaces the world's objects if given."""
        cfg, world = self.config, self.world
        pose = world.ego_pose(k)
        if boxes is None:
            boxes = world.boxes_at(k, cfg.cull_distance)
        stamp = cfg.frame_stamp_ns(k)
        jit = np.random.default_rng([cfg.seed, k, 11]).uniform(-1.0, 1.0, len(self.cams))
        cameras, renders, moved = {}, [], []
        for ci, cam in enumerate(self.cams):
            rng = np.random.default_rng([cfg.seed, k, ci, 13])
            fire_s = cfg.stagger_ms * 1e-3 * ci / max(len(self.cams) - 1, 1)  # 0 without stagger
            at = world.ego_pose_after(k, fire_s) if fire_s else pose
            out = cam.render(at, boxes, world.ground, self.look, rng)
            renders.append(out)
            moved.append(invert_transform(pose) @ at if fire_s else None)  # ego at the frame <- ego as it fired
            cameras[cam.name] = CameraFrame(out.rgb, out.labels,
                                            stamp + int(round(fire_s * 1e9)) + int(round(jit[ci] * cfg.jitter_ms * 1e6)))
        gt, own, zpt = self.ground_truth(pose, boxes)
        vis, ground_vis = self.visibility(renders, boxes, own, zpt, moved)
        return SynthFrame(k, stamp, pose, np.array([world.ego_speed[k], 0.0, 0.0]),
                          np.array([0.0, 0.0, world.ego_yaw_rate[k]]), cameras, gt, vis, ground_vis)

    def ground_truth(self, pose: np.ndarray, boxes: Boxes):
        """``gt (C, H, W)`` bool, plus per cell the object whose footprint holds it (-1 none) and
        the height of its sample point (``(H, W)`` each).

        Footprints are those of the parts standing on the ground (a car body, not its cabin; not
        a street light's overhanging arm), which hold the parts above them.
        """
        grid = self.grid
        H, W = grid.shape
        pts = self.cell_points
        wx = pose[0, 0] * pts[:, 0] + pose[0, 1] * pts[:, 1] + pose[0, 3]
        wy = pose[1, 0] * pts[:, 0] + pose[1, 1] * pts[:, 1] + pose[1, 3]
        lab = self.world.ground.labels(wx, wy).reshape(H, W)  # (H*W,) -> (H, W)
        gt = np.moveaxis(self.lut[lab], -1, 0).copy()  # (H, W, C) -> (C, H, W)
        own = np.full((H, W), -1, np.int64)
        zpt = np.zeros((H, W))
        if not len(boxes):
            return gt, own, zpt
        inv = invert_transform(pose)
        ctr = boxes.center @ inv[:2, :2].T + inv[:2, 3]  # (N, 2) ego frame
        yaw = boxes.yaw + np.arctan2(inv[1, 0], inv[0, 0])
        rad = boxes.radius()
        inside = (boxes.z0 < 0.05) & ((ctr[:, 0] + rad >= grid.x_min) & (ctr[:, 0] - rad < grid.x_max)
                  & (ctr[:, 1] + rad >= grid.y_min) & (ctr[:, 1] - rad < grid.y_max))
        order = np.flatnonzero(inside)
        order = order[np.argsort(-(boxes.size[order, 0] * boxes.size[order, 1]), kind="stable")]
        xs, ys = grid.centers
        res = grid.resolution
        for i in order:  # large footprints first: smaller parts on top set the sample point
            r0, c0 = grid.metric_to_cell(ctr[i, 0] - rad[i], ctr[i, 1] - rad[i])
            r1, c1 = grid.metric_to_cell(ctr[i, 0] + rad[i] + res, ctr[i, 1] + rad[i] + res)
            r0, c0, r1, c1 = max(int(r0), 0), max(int(c0), 0), min(int(r1), H), min(int(c1), W)
            dx, dy = xs[r0:r1, c0:c1] - ctr[i, 0], ys[r0:r1, c0:c1] - ctr[i, 1]
            c, s = np.cos(yaw[i]), np.sin(yaw[i])
            m = ((np.abs(c * dx + s * dy) <= boxes.size[i, 0] / 2)
                 & (np.abs(-s * dx + c * dy) <= boxes.size[i, 1] / 2))
            if not m.any():
                continue
            own[r0:r1, c0:c1][m] = boxes.obj[i]
            zpt[r0:r1, c0:c1][m] = boxes.z0[i] + boxes.size[i, 2] / 2
            gt[:, r0:r1, c0:c1][:, m] |= self.lut[boxes.label[i]][:, None]
        return gt, own, zpt

    def visibility(self, renders, boxes: Boxes, own: np.ndarray, zpt: np.ndarray, moved=None):
        """``(visibility, ground_visibility)``, each ``(H, W)`` bool; ``moved``: per camera, the
        ego's motion from the frame to the camera's firing (4x4, None: none).

        ``visibility``: the cell's sample point (on the object whose footprint holds the cell,
        else on the ground) is seen, unoccluded, by at least one camera. ``ground_visibility``:
        the cell's ground point is seen; the same except under objects, whose solid hides it.
        """
        pts = self.cell_points.copy()
        pts[:, 2] = zpt.ravel()
        vis = self._seen(renders, boxes, pts, own.ravel(), moved)
        vis = vis.reshape(self.grid.shape)  # (H*W,) -> (H, W)
        return vis, vis & (own < 0)

    def _seen(self, renders, boxes: Boxes, pts: np.ndarray, own: np.ndarray, moved=None) -> np.ndarray:
        """``(N,)`` bool: ego-frame points ``pts`` seen by a camera, not hidden by a box of an
        object other than ``own``; ``moved``: per camera, where the ego was when it fired.
        """
        vis = np.zeros(len(pts), bool)
        for ci, (cam, out) in enumerate(zip(self.cams, renders)):
            D = None if moved is None else moved[ci]
            cam_from_ego = invert_transform(cam.ego_from_cam if D is None else D @ cam.ego_from_cam)
            pc = pts @ cam_from_ego[:3, :3].T + cam_from_ego[:3, 3]
            uv, front = cam.model.project(pc)
            ok = front & cam.model.in_image(uv)
            idx = np.flatnonzero(ok & ~vis)
            if not len(idx):
                continue
            u = np.clip(np.rint(uv[idx, 0]).astype(np.int64), 0, cam.w - 1)
            v = np.clip(np.rint(uv[idx, 1]).astype(np.int64), 0, cam.h - 1)
            part = out.part[v, u]
            seen_obj = np.where(part >= 0, boxes.obj[np.maximum(part, 0)] if len(boxes) else -1, -1)
            clear = ((seen_obj < 0) | (seen_obj == own[idx])
                     | (out.depth[v, u] >= pc[idx, 2] - OCCLUSION_TOL))
            vis[idx[clear]] = True
        return vis


def generate_drive(rig: Rig, grid: BevGrid,
                   config: SynthConfig | None = None, classes=BEV_CLASSES) -> Iterator[SynthFrame]:
    """Generate a synthetic drive: ``config.frames`` :class:`SynthFrame` s, lazily.

    ``classes`` are the GT layers of each frame's ``gt`` (default: the standard classes; the
    renderer only uses them for the GT, the images do not depend on them).

    The world is built (and the arguments checked) when this is called; frames are rendered as
    they are iterated. Same ``(rig, grid, config)`` -> bit-identical frames.

    Raises:
        ConfigError: arguments of the wrong type.
    """
    if not isinstance(rig, Rig):
        raise ConfigError(f"rig must be a bev_mapper_core.geometry.rig.Rig, got {type(rig).__name__}")
    if not isinstance(grid, BevGrid):
        raise ConfigError(f"grid must be a BevGrid, got {type(grid).__name__}")
    if config is None:
        config = SynthConfig()
    if not isinstance(config, SynthConfig):
        raise ConfigError(f"config must be a SynthConfig, got {type(config).__name__}")
    renderer = DriveRenderer(build_world(config), rig, grid)
    renderer.lut = label_lut(tuple(classes))  # (NUM_LABELS, C): GT of the requested classes

    def frames() -> Iterator[SynthFrame]:
        for k in range(config.frames):
            yield renderer.frame(k)

    return frames()
