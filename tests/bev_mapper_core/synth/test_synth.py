"""Synthetic drive generator: determinism, geometry exactness, occlusion, ground truth, motion."""

import math

import numpy as np
import pytest

from bev_mapper_core.errors import ConfigError
from bev_mapper_core.geometry.grid import BevGrid
from bev_mapper_core.geometry.rig import preset_rig
from bev_mapper_core.geometry.transforms import transform_points
from bev_mapper_core.labels.classes import BEV_CLASS_NAMES, BEV_CLASSES, Label, label_lut
from bev_mapper_core.synth import (
    CameraFrame,
    DriveRenderer,
    SynthConfig,
    SynthFrame,
    build_world,
    generate_drive,
)
from bev_mapper_core.synth.config import EPOCH_NS
from bev_mapper_core.synth.objects import Boxes, obb_overlap
from bev_mapper_core.synth.populate import EGO_HALF, EGO_OFFSET

CI = {n: i for i, n in enumerate(BEV_CLASS_NAMES)}
GRID = BevGrid()


@pytest.fixture(scope="module")
def small_rig():
    return preset_rig("surround6").scaled(0.25)  # 100x56 images


@pytest.fixture(scope="module")
def drive(small_rig):
    return list(generate_drive(small_rig, GRID, SynthConfig(frames=3, seed=5, jitter_ms=4.0)))


def _same(a: SynthFrame, b: SynthFrame) -> bool:
    if not all(np.array_equal(getattr(a, f), getattr(b, f)) for f in
               ("world_from_ego", "linear_velocity", "angular_velocity", "gt", "visibility")):
        return False
    return all(np.array_equal(a.cameras[n].rgb, b.cameras[n].rgb)
               and np.array_equal(a.cameras[n].labels, b.cameras[n].labels)
               and a.cameras[n].stamp_ns == b.cameras[n].stamp_ns for n in a.cameras)


def test_config_validation():
    for bad in (dict(frames=0), dict(rate_hz=0.0), dict(min_speed=10.0, max_speed=5.0),
                dict(jitter_ms=60.0), dict(vehicle_density=-1.0), dict(seed=-1),
                dict(frames=2.5), dict(rate_hz=float("nan")), dict(turn_probability=2.0)):
        with pytest.raises(ConfigError):
            SynthConfig(**bad)
    with pytest.raises(ConfigError):
        generate_drive(preset_rig("front1"), GRID, {"frames": 2})


def test_shapes_dtypes_and_stamps(drive, small_rig):
    assert [f.index for f in drive] == [0, 1, 2]
    for k, f in enumerate(drive):
        assert isinstance(f, SynthFrame)
        assert f.stamp_ns == EPOCH_NS + k * 100_000_000
        assert f.world_from_ego.shape == (4, 4)
        assert np.allclose(f.world_from_ego[:3, :3] @ f.world_from_ego[:3, :3].T, np.eye(3))
        assert f.world_from_ego[2, 3] == 0.0
        assert f.linear_velocity.shape == f.angular_velocity.shape == (3,)
        assert f.gt.shape == (len(BEV_CLASSES), *GRID.shape) and f.gt.dtype == bool
        assert f.visibility.shape == GRID.shape and f.visibility.dtype == bool
        assert set(f.cameras) == set(small_rig.names)
        for cam in small_rig.cameras:
            c = f.cameras[cam.name]
            assert isinstance(c, CameraFrame)
            w, h = cam.model.image_size
            assert c.rgb.shape == (h, w, 3) and c.rgb.dtype == np.uint8
            assert c.labels.shape == (h, w) and c.labels.dtype == np.uint8
            assert c.labels.max() <= max(Label)
            assert abs(c.stamp_ns - f.stamp_ns) <= 4_000_000
        stamps = {c.stamp_ns for c in f.cameras.values()}
        assert len(stamps) > 1  # jitter differs per camera


def test_deterministic_per_seed_and_different_across_seeds(drive, small_rig):
    again = list(generate_drive(small_rig, GRID, SynthConfig(frames=3, seed=5, jitter_ms=4.0)))
    assert all(_same(a, b) for a, b in zip(drive, again))
    other = next(generate_drive(small_rig, GRID, SynthConfig(frames=3, seed=6, jitter_ms=4.0)))
    assert not np.array_equal(other.world_from_ego, drive[0].world_from_ego)
    assert not np.array_equal(other.gt, drive[0].gt)
    assert not np.array_equal(other.cameras["front"].rgb, drive[0].cameras["front"].rgb)


def test_layouts_vary_across_seeds():
    worlds = [build_world(SynthConfig(frames=2, seed=s)) for s in range(4)]
    bounds = {tuple(np.round(w.net.bounds, 3)) for w in worlds}
    assert len(bounds) == 4
    counts = [(len(w.net.roads), len(w.parts)) for w in worlds]
    assert len(set(counts)) > 1
    lanes = {r.lanes for w in worlds for r in w.net.roads}
    assert lanes >= {1, 2}
    assert any(w.net.nodes[i].degree >= 3 for w in worlds for i in range(len(w.net.nodes)))


def test_ground_truth_multilabel_relations(drive):
    for f in drive:
        g = f.gt
        assert not (g[CI["lane_divider"]] & ~g[CI["drivable"]]).any()
        assert not (g[CI["ped_crossing"]] & ~g[CI["drivable"]]).any()
        assert not (g[CI["road_boundary"]] & g[CI["drivable"]]).any()
        assert not (g[CI["sidewalk"]] & g[CI["drivable"]]).any()
        assert g[CI["drivable"]].mean() > 0.1
    assert any(f.gt[CI["lane_divider"]].any() for f in drive)


def test_ground_truth_samples_the_raster_at_cell_centres():
    w = build_world(SynthConfig(frames=2, seed=1))
    f = DriveRenderer(w, preset_rig("front1").scaled(0.25), GRID).frame(1)
    pts = transform_points(f.world_from_ego, GRID.points(0.0))
    lab = w.ground.labels(pts[:, 0], pts[:, 1]).reshape(GRID.shape)
    flat = label_lut(BEV_CLASSES)[lab]  # (H, W, C)
    for c in range(5):  # the flat classes come from the raster alone
        assert np.array_equal(f.gt[c], flat[..., c]), BEV_CLASS_NAMES[c]


def test_ground_pixels_carry_the_raster_label_of_their_ground_point():
    rig = preset_rig("surround6").scaled(0.5)
    w = build_world(SynthConfig(frames=3, seed=2))
    f = DriveRenderer(w, rig, GRID).frame(2)
    checked = 0
    boxes = [Label.VEHICLE, Label.PEDESTRIAN, Label.OBSTACLE, Label.BUILDING, Label.UNLABELED]
    for cam in rig.cameras:
        labels = f.cameras[cam.name].labels
        h, wd = labels.shape
        us, vs = np.meshgrid(np.arange(wd), np.arange(h))
        rays = cam.model.unproject(np.stack([us.ravel(), vs.ravel()], 1))  # (h*w, 3) optical
        M = f.world_from_ego @ cam.ego_from_cam_array
        d = rays @ M[:3, :3].T
        down = d[:, 2] < 0
        t = -M[2, 3] / d[down, 2]
        x, y = M[0, 3] + t * d[down, 0], M[1, 3] + t * d[down, 1]
        expect = w.ground.lookup(x, y, center=f.world_from_ego[:2, 3]) & 15
        got = labels.ravel()[down]
        on_ground = ~np.isin(got, boxes)
        assert np.array_equal(got[on_ground], expect[on_ground]), cam.name
        assert np.isin(labels.ravel()[~down], boxes).all()  # rays going up: sky or objects
        checked += on_ground.sum()
    assert checked > 20000


def test_box_in_front_occludes_ground_and_is_labelled():
    cfg = SynthConfig(frames=1, seed=3, vehicle_density=0, pedestrian_density=0, obstacle_density=0)
    w = build_world(cfg)
    rig = preset_rig("front1").scaled(0.5)
    dr = DriveRenderer(w, rig, GRID)
    T = dr.world.ego_pose(0)
    yaw = math.atan2(T[1, 0], T[0, 0])
    before = dr.frame(0)
    # a 4 m x 3 m x 2.5 m vehicle 12 m ahead of the ego, centred on its axis
    c = transform_points(T, np.array([[12.0, 0.0, 0.0]]))[0, :2]
    obj = int(w.parts.obj.max()) + 1
    mine = Boxes.make([c], 0.0, (4.0, 3.0, 2.5), yaw, Label.VEHICLE, (200, 0, 0), obj=obj)
    after = dr.frame(0, boxes=Boxes.concat([w.boxes_at(0, cfg.cull_distance), mine]))
    cam = rig.cameras[0]
    uv, _ = cam.model.project(transform_points(cam.cam_from_ego, np.array([[10.0, 0.0, 1.2]])))
    u, v = np.rint(uv[0]).astype(int)
    assert after.cameras["front"].labels[v, u] == Label.VEHICLE
    assert before.cameras["front"].labels[v, u] != Label.VEHICLE
    xs, ys = GRID.centers
    behind = (xs > 14.5) & (xs < 18.0) & (np.abs(ys) < 0.6)
    assert before.visibility[behind].all()
    assert not after.visibility[behind].any()
    fp = (np.abs(xs - 12.0) < 1.8) & (np.abs(ys) < 1.3)
    assert after.gt[CI["vehicle"]][fp].all() and not before.gt[CI["vehicle"]][fp].any()
    assert after.visibility[fp].all()  # the object itself is seen ...
    assert not after.ground_visibility[fp].any()  # ... the ground under it is not
    front = (xs > 7.0) & (xs < 9.0) & (np.abs(ys) < 0.6)
    assert after.visibility[front].all()


def test_ego_trajectory_is_realistic():
    cfg = SynthConfig(frames=150, seed=4, rate_hz=10.0)
    w = build_world(cfg)
    v = w.ego_speed
    assert (v >= cfg.min_speed - 1e-9).all() and (v <= cfg.max_speed + 1e-9).all()
    dt = 1.0 / cfg.rate_hz
    assert np.abs(np.diff(v) / dt).max() < 3.5  # m/s^2
    step = np.hypot(*np.diff(w.ego[:, :2], axis=0).T)
    assert np.allclose(step, (v[1:] + v[:-1]) / 2 * dt, rtol=0.05, atol=0.02)
    dyaw = (np.diff(w.ego[:, 2]) + np.pi) % (2 * np.pi) - np.pi
    assert np.allclose(dyaw / dt, (w.ego_yaw_rate[1:] + w.ego_yaw_rate[:-1]) / 2, atol=0.05)
    # the ego drives on drivable ground
    lab = w.ground.labels(w.ego[:, 0], w.ego[:, 1])
    assert np.isin(lab, list(BEV_CLASSES[0].labels)).all()


def test_vehicles_never_overlap_the_ego_and_stand_where_they_belong():
    cfg = SynthConfig(frames=120, seed=7, vehicle_density=2.5, pedestrian_density=2.0)
    w = build_world(cfg)
    for k in range(0, cfg.frames, 3):
        b = w.boxes_at(k, 40.0)
        x, y, yaw = w.ego[k]
        ego_c = np.array([[x + EGO_OFFSET * math.cos(yaw), y + EGO_OFFSET * math.sin(yaw)]])
        for i in np.flatnonzero(np.isin(b.label, [Label.VEHICLE, Label.PEDESTRIAN])):
            assert not obb_overlap(ego_c, yaw, EGO_HALF, b.center[i:i + 1], b.yaw[i],
                                   b.size[i, :2] / 2)[0], (k, i)
    label = np.zeros(len(w.obj_pose), np.uint8)
    label[w.parts.obj] = w.parts.label  # object -> label of its parts
    ground = w.ground.labels(w.obj_pose[:, 0], w.obj_pose[:, 1])
    veh = label == Label.VEHICLE
    assert np.isin(ground[veh], list(BEV_CLASSES[0].labels)).mean() > 0.97
    assert (ground[label == Label.OBSTACLE] == Label.SIDEWALK).mean() > 0.95
    assert (ground[label == Label.BUILDING] == Label.TERRAIN).all()
    ped = ground[label == Label.PEDESTRIAN]
    assert (ped == Label.SIDEWALK).mean() > 0.8
    assert np.isin(ped, [Label.SIDEWALK, Label.ROAD, Label.PED_CROSSING, Label.ROAD_BOUNDARY]).all()


def test_movers_come_and_go_out_of_sight_and_keep_the_streets_busy():
    cfg = SynthConfig(frames=900, seed=8)  # 90 s
    w = build_world(cfg)
    far = cfg.cull_distance + 10.0
    for oid, poses in w.tracks.items():
        present = np.isfinite(poses[:, 0])
        assert present.any()
        change = np.flatnonzero(np.diff(present.astype(int)))  # frame before each change
        for k in change:
            k = k + 1 if present[k + 1] else k  # the frame the object is there
            assert np.hypot(*(poses[k, :2] - w.ego[k, :2])) > far, (oid, k)
    label = np.zeros(len(w.obj_pose), np.uint8)
    label[w.parts.obj] = w.parts.label
    moving_cars = [i for i in w.tracks if label[i] == Label.VEHICLE]
    counts = [sum(np.isfinite(w.tracks[i][k, 0]) for i in moving_cars) for k in (0, 450, 899)]
    assert min(counts) > 0.5 * max(counts) > 10


def test_stamps_without_jitter():
    f = next(generate_drive(preset_rig("front1").scaled(0.25), GRID, SynthConfig(frames=1, seed=1)))
    assert f.cameras["front"].stamp_ns == f.stamp_ns == EPOCH_NS


def test_visibility_is_plausible(drive):
    for f in drive:
        assert 0.3 < f.visibility.mean() < 0.99
        r, c = GRID.metric_to_cell(1.0, 0.0)
        assert not f.visibility[r, c]  # under the ego: below every camera's view
        assert (f.ground_visibility & ~f.visibility).mean() < 1e-3
        veh = f.gt[CI["vehicle"]]
        veh[[0, -1]] = veh[:, [0, -1]] = False
        inner = veh.copy()  # footprint cells at least 2 cells inside the footprint outline
        for ax in (0, 1):
            for sh in (-2, -1, 1, 2):
                inner &= np.roll(veh, sh, axis=ax)
        assert (inner & f.visibility).sum() > 50
        assert not f.ground_visibility[inner].any()


def test_preview_mosaic(drive):
    from bev_mapper_core.synth.preview import mosaic

    img = mosaic(drive[0], GRID)
    assert img.dtype == np.uint8 and img.ndim == 3 and img.shape[0] == 2 * 2 * 56
