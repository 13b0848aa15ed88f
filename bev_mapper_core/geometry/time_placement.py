"""Each camera at its own time (issue #38): a set's cameras placed with the ego pose of their stamps.

Cameras fire at their own times (nuScenes' six over ~43 ms: 0.4 m at 9 m/s), while a mapper
maps a set with one static rig. With ego poses (odometry or TF), camera ``c`` stamped ``t_c``
is placed in ``base_link`` at the set's reference stamp ``t_ref`` by

    ego_ref_from_cam = inv(world_from_ego(t_ref)) @ world_from_ego(t_c) @ ego_from_cam

(:func:`camera_correction` is the ``inv(world_from_ego(t_ref)) @ world_from_ego(t_c)`` part).
:func:`place_cameras` does this for a whole set and reports it (:class:`Placement`).

Rebuilding a method's calibration tables costs (IPM ~0.2 s for surround6, Bi-Mapper's set_rig a
re-export on an exported backend), so each correction is **quantized**
(``TimePlacementConfig.step_cells``): its translation to a multiple of the step, its roll, pitch
and yaw to a multiple of the angle that moves the grid's farthest corner by the step. A
correction that rounds to nothing leaves its camera as calibrated (counted as ``static``), a set
whose every correction does so is mapped with the static rig itself (the ordinary path, bit for
bit), and at a steady speed consecutive sets round to the same rig, so the tables are rebuilt
only when the rounded placement changes (:class:`~bev_mapper_core.placement.RigPlacer`).

Bad input never raises here: a camera without a pose at its stamp (or a set without a pose at
its reference stamp) stays as calibrated and is listed in ``no_pose``; a camera stamped farther
than ``max_offset_s`` from the reference (a stamp that jumped), or whose pose lies farther from
the reference pose than an ego moves in that time (:data:`MAX_SPEED_MPS`, :data:`MAX_TURN_RADPS`:
a pose that jumped), stays as calibrated and is listed in ``jumped``.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Mapping
from dataclasses import dataclass, replace
from functools import cached_property

import numpy as np

from ..errors import ConfigError
from .grid import BevGrid
from .rig import Rig
from .transforms import invert_transform, make_transform, rpy_to_rot

#: ``TimePlacementConfig.mode`` choices.
PLACEMENT_MODES = ("auto", "off")

#: The fastest an ego moves and turns (m/s, rad/s): a correction beyond them over its stamps'
#: offset (at least 10 ms of it) is a pose that jumped, not motion.
MAX_SPEED_MPS, MAX_TURN_RADPS = 60.0, 3.0

#: A pose lookup: ``world_from_ego`` (4x4) at a stamp in ns, or None when there is none.
PoseAt = Callable[[int], "np.ndarray | None"]


@dataclass(frozen=True)
class TimePlacementConfig:
    """Placing each camera of a set with the ego pose of its own stamp.

    Args:
        mode: ``auto`` (the default: place the cameras where ego poses exist, odometry or TF: a
            placed rig, or for a method that keeps its rig the moved images warped,
            :mod:`~bev_mapper_core.placement`; without poses map as calibrated, said once) or
            ``off`` (always the static rig).
        step_cells: the quantization step, in grid cells: a correction's translation is rounded
            to a multiple of ``step_cells * grid.resolution`` m and its angles to the angle that
            moves the grid's farthest corner by that much. A correction under half a step (at the
            default 1 cell: 0.075 m on the 0.15 m grid, 9 m/s cameras 8 ms apart) is skipped,
            counted as ``static``. 0 = exact (tables rebuilt for every set: slow, for tests).
        max_offset_s: a camera stamped farther than this from the set's reference stamp (a stamp
            that jumped) is mapped as calibrated and counted (``stamp_jumps``).
    """

    mode: str = "auto"
    step_cells: float = 1.0
    max_offset_s: float = 0.1

    def __post_init__(self) -> None:
        if self.mode not in PLACEMENT_MODES:
            raise ConfigError(f"time placement mode must be one of {PLACEMENT_MODES}, got {self.mode!r}")
        for name, hi in (("step_cells", 100.0), ("max_offset_s", 10.0)):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v) or not 0 <= v <= hi:
                raise ConfigError(f"time placement {name} must be a number in [0, {hi:g}], got {v!r}")

    @property
    def enabled(self) -> bool:
        """Placement is wanted (``mode`` is not ``off``)."""
        return self.mode != "off"


@dataclass(frozen=True)
class Placement:
    """What :func:`place_cameras` made of one set.

    Attributes:
        base: the calibrated rig.
        key: the rounded corrections of the moved cameras, ``((name, (6 ints)), ...)``; ``()``
            for the static rig. Equal keys are equal rigs.
        placed: cameras moved to their own time.
        static: cameras with a pose whose correction rounded to nothing.
        no_pose: cameras without an ego pose at their stamp (or every camera, when the reference
            stamp has none), mapped as calibrated.
        jumped: cameras stamped farther than ``max_offset_s`` from the reference, or whose pose
            jumped (see the module docstring), as calibrated.
        max_offset_m: the largest displacement a correction (before rounding) gives a point of the
            grid's corners or the camera's centre, over the cameras with a pose; 0 without.
        moves: ``(name, rounded ego_ref_from_ego_cam 4x4)`` of the placed cameras.
    """

    base: Rig
    key: tuple = ()
    placed: tuple[str, ...] = ()
    static: tuple[str, ...] = ()
    no_pose: tuple[str, ...] = ()
    jumped: tuple[str, ...] = ()
    max_offset_m: float = 0.0
    moves: tuple = ()

    @cached_property
    def rig(self) -> Rig:
        """The rig to map the set with (``base`` itself when no camera moved); built on first use
        (a caller whose mapper already holds the rig of this ``key`` never builds it).
        """
        out = self.base
        for name, D in self.moves:
            cam = out[name]
            out = out.with_camera(replace(cam, ego_from_cam=D @ cam.ego_from_cam_array))
        return out


def camera_correction(ref_pose: np.ndarray, cam_pose: np.ndarray) -> np.ndarray:
    """``ego_ref_from_ego_cam`` (4x4): ``inv(world_from_ego(t_ref)) @ world_from_ego(t_cam)``;
    a camera's ``ego_from_cam`` left-multiplied by it is its placement at the reference stamp.
    """
    return invert_transform(ref_pose) @ np.asarray(cam_pose, dtype=np.float64)


def _rpy(R: np.ndarray) -> tuple[float, float, float]:
    """``(roll, pitch, yaw)`` of a rotation, the inverse of :func:`rpy_to_rot`."""
    pitch = math.asin(max(-1.0, min(1.0, -float(R[2, 0]))))
    return math.atan2(R[2, 1], R[2, 2]), pitch, math.atan2(R[1, 0], R[0, 0])


def quantize_correction(D: np.ndarray, step_m: float, step_rad: float) -> tuple[np.ndarray, tuple[int, ...]]:
    """``D`` rounded: translation to multiples of ``step_m``, roll/pitch/yaw to multiples of
    ``step_rad``; returns ``(rounded 4x4, its 6 integer steps)``. A zero step keeps ``D`` exactly
    (its key then holds the 12 values of ``D - I``'s top rows to 1e-9: all 0 for no motion).
    """
    if step_m <= 0 or step_rad <= 0:  # exact, but float noise (a nm, a nrad) is no motion
        key = tuple(float(v) + 0.0 for v in np.round((D - np.eye(4))[:3].ravel(), 9))
        return (D if any(key) else np.eye(4)), key
    t = np.rint(D[:3, 3] / step_m).astype(np.int64)
    a = np.rint(np.array(_rpy(D[:3, :3])) / step_rad).astype(np.int64)
    key = tuple(int(v) for v in (*t, *a))
    if not any(key):
        return np.eye(4), key
    roll, pitch, yaw = (float(v) * step_rad for v in a)
    return make_transform(rpy_to_rot(roll, pitch, yaw), t * step_m), key


def _offset_m(D: np.ndarray, points: np.ndarray) -> float:
    """Largest displacement ``D`` gives any of ``points`` ``(N, 3)``."""
    moved = points @ D[:3, :3].T + D[:3, 3]
    return float(np.max(np.linalg.norm(moved - points, axis=1)))


def grid_corners(grid: BevGrid) -> np.ndarray:
    """``(4, 3)`` the grid's corners on the ground."""
    return np.array([[x, y, 0.0] for x in (grid.x_min, grid.x_max) for y in (grid.y_min, grid.y_max)])


def steps(grid: BevGrid, config: TimePlacementConfig) -> tuple[float, float]:
    """``(step_m, step_rad)`` of ``config`` on ``grid`` (0, 0 for exact placement)."""
    step_m = config.step_cells * grid.resolution
    reach = float(np.max(np.linalg.norm(grid_corners(grid), axis=1)))
    return step_m, step_m / reach


def place_cameras(rig: Rig, stamps: Mapping[str, int | None], ref_stamp_ns: int, pose_at: PoseAt,
                  grid: BevGrid, config: TimePlacementConfig = TimePlacementConfig()) -> Placement:
    """Place each camera of ``rig`` stamped in ``stamps`` with the ego pose of its stamp, in
    ``base_link`` at ``ref_stamp_ns`` (see the module docstring). Cameras missing from
    ``stamps`` (or stamped None: not in the set) are left as calibrated and not reported.

    ``pose_at(stamp_ns)`` gives ``world_from_ego`` (rigid) or None; a pose it returns that is
    not a finite 4x4 array counts as none. Never raises on bad poses or stamps.
    """
    ref = _checked(pose_at(int(ref_stamp_ns)))
    cams = [c for c in rig.cameras if stamps.get(c.name) is not None]
    if ref is None:
        return Placement(rig, no_pose=tuple(c.name for c in cams))
    if all(int(stamps[c.name]) == ref_stamp_ns for c in cams):  # one stamp for all: nothing moves
        return Placement(rig, static=tuple(c.name for c in cams))
    step_m, step_rad = steps(grid, config)
    corners = grid_corners(grid)
    limit_ns = config.max_offset_s * 1e9
    placed, static, no_pose, jumped, key, moves = [], [], [], [], [], []
    worst = 0.0
    for cam in cams:
        stamp = int(stamps[cam.name])
        if stamp == ref_stamp_ns:  # taken at the set's stamp: in place (what the correction, I, would say)
            static.append(cam.name)
            continue
        if abs(stamp - ref_stamp_ns) > limit_ns:
            jumped.append(cam.name)
            continue
        pose = _checked(pose_at(stamp))
        if pose is None:
            no_pose.append(cam.name)
            continue
        D = camera_correction(ref, pose)
        dt = max(abs(stamp - ref_stamp_ns) / 1e9, 0.01)
        turn = math.acos(max(-1.0, min(1.0, (float(np.trace(D[:3, :3])) - 1.0) / 2.0)))
        if float(np.linalg.norm(D[:3, 3])) > MAX_SPEED_MPS * dt or turn > MAX_TURN_RADPS * dt:
            jumped.append(cam.name)
            continue
        E = cam.ego_from_cam_array
        worst = max(worst, _offset_m(D, np.vstack([corners, E[:3, 3]])))
        Dq, k = quantize_correction(D, step_m, step_rad)
        if not any(k):
            static.append(cam.name)
            continue
        moves.append((cam.name, Dq))
        placed.append(cam.name)
        key.append((cam.name, k))
    return Placement(rig, tuple(key), tuple(placed), tuple(static), tuple(no_pose), tuple(jumped), worst,
                     tuple(moves))


def _checked(pose) -> np.ndarray | None:
    """``pose`` as a finite 4x4 float64 array, or None (none given, not numbers, another shape,
    a NaN or an infinity). Rigidity is the lookup's to check (the pose buffer and TF check it as poses
    arrive): the full check here would cost more than the rest of a set's placement.
    """
    if pose is None:
        return None
    try:
        T = np.asarray(pose, dtype=np.float64)
    except (TypeError, ValueError):  # not numbers at all
        return None
    return T if T.shape == (4, 4) and np.isfinite(T).all() else None


__all__ = [
    "MAX_SPEED_MPS",
    "MAX_TURN_RADPS",
    "PLACEMENT_MODES",
    "Placement",
    "PoseAt",
    "TimePlacementConfig",
    "camera_correction",
    "grid_corners",
    "place_cameras",
    "quantize_correction",
    "steps",
]
