"""Vehicle and pedestrian layers from nuScenes' ``sample_annotation`` boxes.

Categories (:func:`object_class`): ``vehicle`` is every ``vehicle.*`` category (car, truck, bus
bendy and rigid, construction, emergency ambulance and police, trailer, motorcycle, bicycle), as
LSS's and CVT's vehicle class; ``pedestrian`` every ``human.pedestrian.*`` category (adult,
child, construction worker, police officer, personal mobility, stroller, wheelchair). Animals,
movable and static objects make no class.

A box is kept when its visibility level (the ``visibility`` table: 1 = 0-40 % ... 4 = 80-100 % of
the object visible in the six images) is at least :attr:`BoxFilter.min_visibility` and it holds at
least :attr:`BoxFilter.min_points` lidar and radar points together (the devkit's detection
evaluation drops boxes with none: ``filter_eval_boxes``). A box left out is not scored: its cells
are -1 in its class's layer (unless a kept box covers them), never 0.

The box's bottom face is taken into the ego frame (the key frame's ego pose) and filled with the
map polygons' convention (vertices rounded to cells, ``cv2.fillPoly``; LSS's ``get_binimg``).
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from bev_mapper_core.errors import ConfigError
from bev_mapper_core.geometry.grid import BevGrid
from bev_mapper_core.geometry.transforms import invert_transform, make_transform, quat_to_rot

from .tables import NuScenesTables, field

OBJECT_CLASSES = ("vehicle", "pedestrian")


def object_class(category: str) -> str | None:
    """The package's class of a nuScenes category name, or ``None``."""
    if category.startswith("vehicle."):
        return "vehicle"
    if category.startswith("human.pedestrian."):
        return "pedestrian"
    return None


@dataclass(frozen=True)
class BoxFilter:
    """Which annotation boxes are scored (see the module docstring).

    Args:
        min_visibility: lowest visibility level kept, 1 (all) to 4 (80-100 % visible).
        min_points: fewest lidar + radar points in the box (1: the devkit's evaluation filter; 0: all).
    """

    min_visibility: int = 1
    min_points: int = 1

    def __post_init__(self) -> None:
        if self.min_visibility not in (1, 2, 3, 4):
            raise ConfigError(f"min_visibility must be 1, 2, 3 or 4, got {self.min_visibility}")
        if self.min_points < 0:
            raise ConfigError(f"min_points must be >= 0, got {self.min_points}")

    def keeps(self, ann: dict) -> bool:
        """Whether the annotation record passes the filter."""
        try:
            vis = int(ann.get("visibility_token") or 0)
        except ValueError:
            vis = 0
        points = int(ann.get("num_lidar_pts", 0)) + int(ann.get("num_radar_pts", 0))
        return vis >= self.min_visibility and points >= self.min_points


def footprint(ann: dict, ego_from_world: np.ndarray) -> np.ndarray:
    """The ``(4, 2)`` ego-frame xy corners of the annotation box's bottom face."""
    w, length, h = (float(v) for v in field(ann, "size", "sample_annotation"))
    qw, qx, qy, qz = (float(v) for v in field(ann, "rotation", "sample_annotation"))
    world_from_box = make_transform(quat_to_rot(qx, qy, qz, qw), [float(v) for v in field(ann, "translation", "sample_annotation")])
    corners = np.array([[length / 2, w / 2, -h / 2, 1.0], [length / 2, -w / 2, -h / 2, 1.0],
                        [-length / 2, -w / 2, -h / 2, 1.0], [-length / 2, w / 2, -h / 2, 1.0]])  # (4, 4) homogeneous
    pts = (ego_from_world @ world_from_box @ corners.T).T  # (4, 4)
    return pts[:, :2]


def to_cells(grid: BevGrid, xy: np.ndarray) -> np.ndarray:
    """Ego-frame points ``(N, 2)`` -> rounded canvas vertices ``(N, 2)`` int32 (column, row)."""
    u = (xy[:, 0] - grid.x_min) * (grid.width / (grid.x_max - grid.x_min))
    v = (xy[:, 1] - grid.y_min) * (grid.height / (grid.y_max - grid.y_min))
    return np.round(np.stack([u, v], axis=1)).astype(np.int32)  # (N, 2)


def object_layers(tables: NuScenesTables, anns: list[dict], grid: BevGrid, world_from_ego: np.ndarray,
                  flt: BoxFilter) -> tuple[dict[str, tuple[np.ndarray, np.ndarray]], int]:
    """``(class -> (present, known) (H, W) bool, boxes left out)`` of a key frame's annotations."""
    ego_from_world = invert_transform(np.asarray(world_from_ego, dtype=np.float64))
    present = {c: np.zeros(grid.shape, np.uint8) for c in OBJECT_CLASSES}
    hidden = {c: np.zeros(grid.shape, np.uint8) for c in OBJECT_CLASSES}
    left_out = 0
    for ann in anns:
        inst = tables.get("instance", field(ann, "instance_token", "sample_annotation"))
        cat = tables.get("category", field(inst, "category_token", "instance"))
        cls = object_class(str(field(cat, "name", "category")))
        if cls is None:
            continue
        kept = flt.keeps(ann)
        left_out += not kept
        cv2.fillPoly((present if kept else hidden)[cls], [to_cells(grid, footprint(ann, ego_from_world))], 1)
    out = {}
    for c in OBJECT_CLASSES:
        p = present[c].astype(bool)
        out[c] = (p, p | ~hidden[c].astype(bool))
    return out, left_out


__all__ = ["OBJECT_CLASSES", "BoxFilter", "footprint", "object_class", "object_layers", "to_cells"]
