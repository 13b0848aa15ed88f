"""Each camera at its own time (bev_mapper_core/geometry/time_placement.py): the correction against
hand-computed transforms, rounding, and bad input (a camera without a pose, a set without one,
a stamp that jumped, a pose that is no rigid transform) mapped as calibrated and listed."""

from __future__ import annotations

import math

import numpy as np
import pytest

from bev_mapper_core.errors import ConfigError
from bev_mapper_core.geometry.grid import BevGrid
from bev_mapper_core.geometry.rig import preset_rig
from bev_mapper_core.geometry.time_placement import (
    TimePlacementConfig,
    camera_correction,
    place_cameras,
    quantize_correction,
)
from bev_mapper_core.geometry.transforms import rpy_to_rot, yaw_of

MS = 1_000_000
T0 = 1_700_000_000 * 10**9
GRID = BevGrid(x_min=-10, x_max=20, y_min=-6, y_max=6, resolution=0.25)
EXACT = TimePlacementConfig(step_cells=0)


def pose(x=0.0, y=0.0, yaw=0.0) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = rpy_to_rot(0.0, 0.0, yaw)
    T[:3, 3] = (x, y, 0.0)
    return T


def driving(speed=10.0, heading=math.pi / 2, x0=5.0, y0=-3.0):
    """``pose_at`` of an ego driving straight at ``speed`` m/s along world ``heading``."""
    def at(stamp_ns):
        s = speed * (stamp_ns - T0) / 1e9
        return pose(x0 + s * math.cos(heading), y0 + s * math.sin(heading), heading)
    return at


def test_the_correction_is_the_ego_motion_between_the_stamps_in_the_reference_frame():
    # facing world +y: 0.4 m further along world y is 0.4 m ahead (ego +x) of the reference pose
    D = camera_correction(pose(5.0, -3.0, math.pi / 2), pose(5.0, -2.6, math.pi / 2))
    np.testing.assert_allclose(D, pose(0.4, 0.0, 0.0), atol=1e-12)
    # a turn: the later pose 10 degrees left, 1 m ahead and 0.1 m left of the reference, at any heading
    ref = pose(2.0, 7.0, 1.0)
    later = ref @ pose(1.0, 0.1, math.radians(10))
    D = camera_correction(ref, later)
    np.testing.assert_allclose(D[:3, 3], [1.0, 0.1, 0.0], atol=1e-12)
    assert yaw_of(D) == pytest.approx(math.radians(10), abs=1e-12)


def test_each_camera_is_placed_with_the_pose_of_its_own_stamp():
    rig = preset_rig("surround6")
    stamps = {"front": T0, "front_right": T0 + 20 * MS, "back": T0 + 40 * MS}  # others not in the set
    p = place_cameras(rig, stamps, T0, driving(10.0), GRID, EXACT)
    assert p.placed == ("front_right", "back") and p.static == ("front",)
    assert p.no_pose == p.jumped == ()
    # by hand: the ego moved 0.2 m and 0.4 m ahead; each camera's mount moves with it
    for name, ahead in (("front_right", 0.2), ("back", 0.4)):
        want = pose(ahead) @ rig[name].ego_from_cam_array
        np.testing.assert_allclose(p.rig[name].ego_from_cam_array, want, atol=1e-9)
    for name in ("front", "front_left", "back_left", "back_right"):
        assert p.rig[name] == rig[name]
    assert p.max_offset_m == pytest.approx(0.4, abs=1e-9)
    # a camera that fired before the reference stamp sits behind it
    early = place_cameras(rig, {"front": T0 - 30 * MS}, T0, driving(10.0), GRID, EXACT)
    np.testing.assert_allclose(early.rig["front"].ego_from_cam_array,
                               pose(-0.3) @ rig["front"].ego_from_cam_array, atol=1e-9)


def test_corrections_are_rounded_to_the_step_and_those_under_half_a_step_skipped():
    rig = preset_rig("surround6")
    cfg = TimePlacementConfig(step_cells=1.0)  # 0.25 m on GRID
    stamps = {"front": T0 + 40 * MS, "back": T0 + 10 * MS}  # 0.4 m and 0.1 m at 10 m/s
    p = place_cameras(rig, stamps, T0, driving(10.0), GRID, cfg)
    assert p.placed == ("front",) and p.static == ("back",)
    np.testing.assert_allclose(p.rig["front"].ego_from_cam_array,
                               pose(0.5) @ rig["front"].ego_from_cam_array, atol=1e-9)  # 0.4 -> 2 steps
    assert p.key == (("front", (2, 0, 0, 0, 0, 0)),)
    assert p.max_offset_m == pytest.approx(0.4, abs=1e-9)  # said before rounding
    # the same motion a set later gives the same key (the mapper keeps its tables)
    q = place_cameras(rig, {"front": T0 + 1000 * MS, "back": T0 + 970 * MS}, T0 + 960 * MS, driving(10.0), GRID, cfg)
    assert q.key == p.key
    # yaw: its step moves the grid's farthest corner by one step
    D = pose(0.0, 0.0, 0.26 / math.hypot(20, 6))
    Dq, key = quantize_correction(D, 0.25, 0.25 / math.hypot(20, 6))
    assert key == (0, 0, 0, 0, 0, 1) and yaw_of(Dq) == pytest.approx(0.25 / math.hypot(20, 6))
    # nothing moved: the static rig itself, key ()
    still = place_cameras(rig, {"front": T0 + 40 * MS}, T0, driving(0.0), GRID, cfg)
    assert still.rig is rig and still.key == () and still.static == ("front",)


def test_bad_poses_and_stamps_leave_those_cameras_as_calibrated_and_are_listed():
    rig = preset_rig("surround6")
    moving = driving(10.0)
    missing_back = lambda t: None if t == T0 + 30 * MS else moving(t)  # noqa: E731
    stamps = {"front": T0 + 20 * MS, "back": T0 + 30 * MS, "front_left": T0 + 3000 * MS}
    p = place_cameras(rig, stamps, T0, missing_back, GRID, EXACT)
    assert p.placed == ("front",) and p.no_pose == ("back",) and p.jumped == ("front_left",)
    assert p.rig["back"] == rig["back"] and p.rig["front_left"] == rig["front_left"]
    # no pose at the reference stamp: every camera of the set as calibrated
    none_at_ref = place_cameras(rig, stamps, T0, lambda t: None if t == T0 else moving(t), GRID, EXACT)
    assert none_at_ref.rig is rig and none_at_ref.no_pose == ("front", "back", "front_left")
    # a pose that is no rigid transform counts as none (never a traceback)
    broken = lambda t: np.full((4, 4), np.nan) if t == T0 + 20 * MS else moving(t)  # noqa: E731
    assert place_cameras(rig, stamps, T0, broken, GRID, EXACT).no_pose == ("front",)
    # a stamp out of order (a camera stamped before the reference) is placed, not refused
    assert place_cameras(rig, {"back": T0 - 40 * MS}, T0, moving, GRID, EXACT).placed == ("back",)


@pytest.mark.parametrize("kwargs", [{"mode": "on"}, {"step_cells": -1}, {"step_cells": float("nan")},
                                    {"max_offset_s": True}, {"max_offset_s": 11}])
def test_the_config_refuses_bad_values(kwargs):
    with pytest.raises(ConfigError):
        TimePlacementConfig(**kwargs)
    assert not TimePlacementConfig(mode="off").enabled and TimePlacementConfig().enabled


def test_a_pose_that_jumped_leaves_its_camera_as_calibrated():
    rig = preset_rig("surround6")
    moving = driving(10.0)

    def lookup(t):
        if t == T0 + 20 * MS:  # 5 m off in 20 ms: a relocalization, not motion
            return moving(t) @ pose(5.0)
        if t == T0 + 30 * MS:  # turned 30 degrees in 30 ms
            return moving(t) @ pose(yaw=math.radians(30))
        return moving(t)
    stamps = {"front": T0 + 20 * MS, "back": T0 + 30 * MS, "back_left": T0 + 40 * MS}
    p = place_cameras(rig, stamps, T0, lookup, GRID, EXACT)
    assert p.jumped == ("front", "back") and p.placed == ("back_left",)
    assert p.rig["front"] == rig["front"] and p.rig["back"] == rig["back"]


@pytest.mark.parametrize("seed", range(20))
def test_fuzzed_poses_and_stamps_never_raise_and_each_camera_has_one_outcome(seed):
    """Issue #41: poses missing, broken or jumping for some cameras, stamps out of order, missing
    or far off: no traceback, every camera of the set in exactly one of placed / static / no_pose
    / jumped, placed cameras a proper mount, the others as calibrated."""
    rng = np.random.default_rng(seed)
    rig = preset_rig("surround6")
    moving = driving(float(rng.uniform(0, 20)), heading=float(rng.uniform(-3, 3)))
    bad = [None, np.full((4, 4), np.nan), np.eye(3), np.full((4, 4), np.inf), "pose",
           pose(1e9), pose(yaw=2.0)]
    kinds, good = {}, object()

    def lookup(t):
        k = kinds.get(t, good)
        return moving(t) if k is good else (moving(t) @ k if isinstance(k, np.ndarray) and k.shape == (4, 4)
                                              and np.isfinite(k).all() else k)
    stamps = {}
    for c in rig.names:
        r = rng.random()
        t = None if r < 0.1 else T0 + int(rng.choice([rng.integers(-60, 60), rng.integers(-10**4, 10**4)]) * MS)
        stamps[c] = t
        if t is not None and rng.random() < 0.4:
            kinds[t] = bad[int(rng.integers(len(bad)))]
    cfg = TimePlacementConfig(step_cells=float(rng.choice([0.0, 0.5, 1.0])))
    p = place_cameras(rig, stamps, T0, lookup, GRID, cfg)
    present = [c for c in rig.names if stamps[c] is not None]
    outcomes = p.placed + p.static + p.no_pose + p.jumped
    assert sorted(outcomes) == sorted(present)
    for c in rig.names:
        if c in p.placed:
            assert np.isfinite(p.rig[c].ego_from_cam_array).all()
            assert abs(stamps[c] - T0) <= cfg.max_offset_s * 1e9
        else:
            assert p.rig[c] == rig[c]
