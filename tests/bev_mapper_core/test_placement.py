"""The mapper kept on each set's time-placed rig (bev_mapper_core/placement.py): IPM mapping with
per-camera placement equals IPM on a rig built by hand from the same poses; the static path is
today's (no set_rig, the same output); tables rebuilt only when the rounded placement changes;
a learned method keeps its calibrated rig and its moved images are warped (counted); bad poses
counted, the rest mapped."""

from __future__ import annotations

import math

import numpy as np
import pytest

from bev_mapper_core.geometry.grid import BevGrid
from bev_mapper_core.geometry.rig import preset_rig
from bev_mapper_core.geometry.time_placement import TimePlacementConfig
from bev_mapper_core.geometry.transforms import rpy_to_rot
from bev_mapper_core.mapper import MapperConfig, create_mapper
from bev_mapper_core.placement import RigPlacer

MS = 1_000_000
T0 = 1_700_000_000 * 10**9
GRID = BevGrid(x_min=-12, x_max=12, y_min=-8, y_max=8, resolution=0.25)
RIG = preset_rig("surround6").scaled(0.25)  # 100x56 images


def pose(x=0.0, y=0.0, yaw=0.0) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = rpy_to_rot(0.0, 0.0, yaw)
    T[:3, 3] = (x, y, 0.0)
    return T


def turning(t_ns: int) -> np.ndarray:
    """An ego driving 9 m/s while turning left at 0.5 rad/s (arc)."""
    s = (t_ns - T0) / 1e9
    yaw = 0.5 * s
    return pose(9.0 / 0.5 * math.sin(yaw), 9.0 / 0.5 * (1 - math.cos(yaw)), yaw)


def labels(seed: int = 0) -> dict[str, np.ndarray]:
    rng = np.random.default_rng(seed)
    out = {}
    for c in RIG.cameras:
        w, h = c.model.image_size
        out[c.name] = rng.integers(0, 12, (h, w), dtype=np.uint8)
    return out


STAMPS = {c.name: T0 + i * 8 * MS for i, c in enumerate(RIG.cameras)}  # 0..40 ms, rig order


@pytest.mark.parametrize("occlusion", [True, False])
def test_ipm_with_each_camera_at_its_time_equals_ipm_on_the_rig_built_by_hand(occlusion):
    cfg = MapperConfig(method="ipm", ipm_occlusion=occlusion)
    mapper = create_mapper(RIG, GRID, cfg)
    placer = RigPlacer(GRID, TimePlacementConfig(step_cells=0))
    placer.set_base(RIG)
    images = labels()
    p, notes = placer.place(mapper, STAMPS, T0, turning)
    assert notes == [] and p.placed == RIG.names[1:] and p.static == RIG.names[:1]
    got = mapper.map(images, turning(T0), T0)
    # by hand: inv(world_from_ego(ref)) @ world_from_ego(t_cam) @ ego_from_cam, per camera
    hand = RIG
    for c in RIG.cameras:
        E = np.linalg.inv(turning(T0)) @ turning(STAMPS[c.name]) @ c.ego_from_cam_array
        hand = hand.with_camera(type(c)(c.name, c.model, E, c.frame_id))
    want = create_mapper(hand, GRID, cfg).map(images)
    np.testing.assert_array_equal(got.known, want.known)
    np.testing.assert_array_equal(got.probs, want.probs)
    static = create_mapper(RIG, GRID, cfg).map(images)
    assert not np.array_equal(got.known, static.known)  # the placement changed the map
    assert placer.counts["sets_placed"] == 1 and placer.counts["rebuilds"] == 1
    assert placer.counts["max_offset_m"] > 0.3


def test_the_static_path_is_todays_and_tables_are_rebuilt_only_when_the_placement_changes():
    cfg = MapperConfig(method="ipm")
    mapper = create_mapper(RIG, GRID, cfg)
    tables = mapper.tables
    placer = RigPlacer(GRID)  # rounded to one cell (0.25 m)
    placer.set_base(RIG)
    images = labels(1)
    today = create_mapper(RIG, GRID, cfg).map(images)
    still = lambda t: pose(3.0, 1.0, 0.2)  # noqa: E731  (standing: zero offsets)
    p, _ = placer.place(mapper, STAMPS, T0, still)
    assert p.rig is RIG and mapper.rig is RIG and mapper.tables is tables  # no set_rig at all
    np.testing.assert_array_equal(mapper.map(images).probs, today.probs)
    moving = lambda t: pose(9.0 * (t - T0) / 1e9)  # noqa: E731  (9 m/s straight)
    for k in range(3):  # the same offsets every set (a steady speed): one rebuild
        shift = k * 100 * MS
        placer.place(mapper, {n: s + shift for n, s in STAMPS.items()}, T0 + shift, moving)
    assert placer.counts["rebuilds"] == 1 and placer.counts["sets_placed"] == 3
    assert mapper.rig is not RIG
    placer.place(mapper, STAMPS, T0, still)  # standing again: back to the calibrated rig's tables
    assert mapper.rig is RIG and placer.counts["rebuilds"] == 2 and placer.counts["sets_static"] == 2
    np.testing.assert_array_equal(mapper.map(images).probs, today.probs)
    # mode off: nothing placed, nothing counted
    off = RigPlacer(GRID, TimePlacementConfig(mode="off"))
    off.set_base(RIG)
    assert off.place(mapper, STAMPS, T0, moving) == (None, [])


def test_bad_poses_are_counted_and_the_rest_placed():
    mapper = create_mapper(RIG, GRID, MapperConfig(method="ipm", ipm_occlusion=False))
    placer = RigPlacer(GRID, TimePlacementConfig(step_cells=0))
    placer.set_base(RIG)
    back_lost = lambda t: None if t == STAMPS["back"] else turning(t)  # noqa: E731
    stamps = {**STAMPS, "front_left": T0 - 900 * MS}  # a stamp that jumped back
    p, notes = placer.place(mapper, stamps, T0, back_lost)
    assert p.no_pose == ("back",) and p.jumped == ("front_left",)
    assert mapper.rig["back"] == RIG["back"] and mapper.rig["front_left"] == RIG["front_left"]
    assert mapper.rig["front_right"] != RIG["front_right"]
    assert [k for k, _ in notes] == ["placement_set:no_pose", "placement_set:jump"]
    pred = mapper.map(labels(2))
    assert pred.known.any()
    # no pose at all: said once, counted every set, the calibrated rig
    for _ in range(2):
        p, notes2 = placer.place(mapper, STAMPS, T0, lambda t: None)
        assert mapper.rig is RIG
    assert [k for k, _ in notes2] == [] and placer.counts["sets_without_pose"] == 2
    assert placer.values()["placement_cameras_without_pose"] == str(1 + 2 * 6)
    assert placer.values()["placement_stamp_jumps"] == "1"


def test_a_learned_method_keeps_its_calibrated_rig_and_its_moved_images_are_warped():
    mapper = create_mapper(RIG.scaled(4.0), BevGrid(), MapperConfig(method="bimapper", backend="torch", threads=1))
    rig = mapper.rig
    placer = RigPlacer(BevGrid())
    placer.set_base(rig)
    stamps = {c.name: STAMPS[c.name] for c in rig.cameras}
    p, notes = placer.place(mapper, stamps, T0, turning)
    assert mapper.rig is rig and p is not None and p.placed  # the model keeps its rig
    assert [k for k, _ in notes] == ["placement:method"] and "bimapper" in notes[0][1] and "warped" in notes[0][1]
    assert placer.counts["sets_warped"] == 1 and placer.counts["sets_placed"] == 1
    imgs = {c.name: np.random.default_rng(3).integers(0, 11, c.model.image_size[::-1], dtype=np.uint8)
            for c in rig.cameras}
    out = placer.warp(imgs)
    for name, img in imgs.items():  # moved cameras' images warped, the others as given
        assert (name in p.placed) == (not np.array_equal(out[name], img))
    built = placer.counts["rebuilds"]
    _, notes = placer.place(mapper, stamps, T0, turning)
    assert notes == [] and placer.counts["sets_warped"] == 2 and placer.counts["rebuilds"] == built  # maps kept
    placer.place(mapper, stamps, T0, lambda t: pose())  # standing still: nothing to warp
    out = placer.warp(imgs)
    assert all(out[k] is imgs[k] for k in imgs)
