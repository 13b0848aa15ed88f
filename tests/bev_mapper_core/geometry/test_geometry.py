"""Geometry core: camera models, transforms, grid and rig conventions."""

import math

import cv2
import numpy as np
import pytest

from bev_mapper_core.errors import CalibrationError, GridError
from bev_mapper_core.geometry.camera import CameraModel, Roi
from bev_mapper_core.geometry.grid import BevGrid
from bev_mapper_core.geometry.rig import preset_rig
from bev_mapper_core.geometry.transforms import (
    ego_from_optical,
    invert_transform,
    make_transform,
    quat_to_rot,
    rot_to_quat,
    rpy_to_rot,
    transform_points,
    validate_transform,
)

K = ((500.0, 0.0, 320.5), (0.0, 480.0, 240.25), (0.0, 0.0, 1.0))
MODELS = {
    "plumb_bob": (-0.28, 0.07, 0.0012, -0.0009, -0.008),
    "rational_polynomial": (0.35, -0.12, 0.0008, 0.0011, 0.02, 0.62, -0.05, 0.09),
    "equidistant": (0.08, -0.015, 0.004, -0.001),
}


def random_points(rng, n=500, half_fov=0.6):
    """Points in front of the camera within a moderate field of view."""
    z = rng.uniform(1.0, 40.0, n)
    x = rng.uniform(-half_fov, half_fov, n) * z
    y = rng.uniform(-half_fov * 0.75, half_fov * 0.75, n) * z
    return np.stack([x, y, z], axis=1)


@pytest.mark.parametrize("model", sorted(MODELS))
def test_project_matches_opencv(model):
    cam = CameraModel(K=K, D=MODELS[model], distortion_model=model, width=640, height=480)
    pts = random_points(np.random.default_rng(1))
    uv, ok = cam.project(pts)
    assert ok.all()
    if model == "equidistant":
        ref, _ = cv2.fisheye.projectPoints(pts.reshape(-1, 1, 3), np.zeros(3), np.zeros(3), cam.K_array, cam.D_array)
    else:
        ref, _ = cv2.projectPoints(pts, np.zeros(3), np.zeros(3), cam.K_array, cam.D_array)
    np.testing.assert_allclose(uv, ref.reshape(-1, 2), atol=1e-6)


@pytest.mark.parametrize("model", sorted(MODELS))
def test_project_unproject_round_trip(model):
    cam = CameraModel(K=K, D=MODELS[model], distortion_model=model, width=640, height=480)
    pts = random_points(np.random.default_rng(2))
    uv, _ = cam.project(pts)
    rays = cam.unproject(uv)
    np.testing.assert_allclose(rays[:, 2], 1.0)
    np.testing.assert_allclose(rays[:, :2], pts[:, :2] / pts[:, 2:3], atol=1e-7)
    uv2, _ = cam.project(rays * 7.0)
    np.testing.assert_allclose(uv2, uv, atol=1e-6)


def test_points_behind_camera_are_flagged():
    cam = CameraModel(K=K, width=640, height=480)
    uv, ok = cam.project(np.array([[0.0, 0.0, -1.0], [0.0, 0.0, 2.0]]))
    assert ok.tolist() == [False, True]
    assert np.isnan(uv[0]).all()
    np.testing.assert_allclose(uv[1], [320.5, 240.25])


def test_hand_computed_pinhole_projection():
    cam = CameraModel(K=K, width=640, height=480)
    # x right 2 m, y down 1 m at 10 m: u = 500 * 0.2 + 320.5, v = 480 * 0.1 + 240.25
    uv, _ = cam.project(np.array([[2.0, 1.0, 10.0]]))
    np.testing.assert_allclose(uv[0], [420.5, 288.25])


def test_binning_and_roi_follow_image_geometry():
    full = CameraModel(K=K, width=640, height=480)
    binned = CameraModel(K=K, width=640, height=480, binning_x=2, binning_y=4)
    assert binned.image_size == (320, 120)
    pts = random_points(np.random.default_rng(3), 50)
    uv_full, _ = full.project(pts)
    uv_bin, _ = binned.project(pts)
    np.testing.assert_allclose(uv_bin, uv_full / [2.0, 4.0], atol=1e-9)
    roi = CameraModel(K=K, width=640, height=480, roi=Roi(100, 50, 200, 150))
    assert roi.image_size == (200, 150)
    uv_roi, _ = roi.project(pts)
    np.testing.assert_allclose(uv_roi, uv_full - [100.0, 50.0], atol=1e-9)


def test_scaled_camera_matches_resized_image():
    cam = CameraModel(K=K, width=640, height=480)
    half = cam.scaled(0.5)
    assert half.image_size == (320, 240)
    # Pixel centre convention of cv2.resize: u_half = (u + 0.5) / 2 - 0.5
    uv, _ = cam.project(np.array([[1.0, -0.5, 5.0]]))
    uv_half, _ = half.project(np.array([[1.0, -0.5, 5.0]]))
    np.testing.assert_allclose(uv_half, (uv + 0.5) * 0.5 - 0.5)


def test_undistort_maps_straighten_projected_points():
    cam = CameraModel(K=K, D=MODELS["plumb_bob"], width=640, height=480)
    pinhole = CameraModel(K=K, width=640, height=480)
    map_x, map_y = cam.undistort_maps()
    pts = random_points(np.random.default_rng(4), 30, half_fov=0.4)
    uv_pin, _ = pinhole.project(pts)
    uv_dist, _ = cam.project(pts)
    u, v = np.round(uv_pin).astype(int).T
    # The map at an undistorted pixel points at where that ray lands in the distorted image.
    ok = (u >= 0) & (u < 640) & (v >= 0) & (v < 480)
    sampled = np.stack([map_x[v[ok], u[ok]], map_y[v[ok], u[ok]]], axis=1)
    target, _ = cam.project(pinhole.unproject(np.stack([u[ok], v[ok]], axis=1).astype(float)))
    np.testing.assert_allclose(sampled, target, atol=0.05)
    assert np.abs(uv_dist - uv_pin).max() > 1.0  # distortion is not negligible here


@pytest.mark.parametrize(
    "kwargs, message",
    [
        (dict(K=((0.0, 0, 0), (0, 0.0, 0), (0, 0, 0))), "focal"),
        (dict(K=((math.nan, 0, 1), (0, 1.0, 1), (0, 0, 1))), "non-finite"),
        (dict(K=K, distortion_model="kannala"), "unsupported distortion"),
        (dict(K=K, D=(0.1,) * 6), "takes 5"),
        (dict(K=K, D=(math.inf,)), "non-finite"),
        (dict(K=K, width=0), "image size"),
        (dict(K=K, roi=Roi(600, 0, 100, 10)), "roi"),
    ],
)
def test_camera_model_rejects_broken_calibration(kwargs, message):
    args = dict(width=640, height=480)
    args.update(kwargs)
    with pytest.raises(CalibrationError, match=message):
        CameraModel(**args)


# ------------------------------------------------------------------ transforms
def test_quaternion_round_trip_and_inverse():
    rng = np.random.default_rng(5)
    for _ in range(20):
        q = rng.normal(size=4)
        q /= np.linalg.norm(q)
        R = quat_to_rot(*q)
        np.testing.assert_allclose(R @ R.T, np.eye(3), atol=1e-12)
        q2 = rot_to_quat(R)
        assert np.allclose(q2, q) or np.allclose(q2, -q)
        T = make_transform(R, rng.normal(size=3))
        np.testing.assert_allclose(invert_transform(T) @ T, np.eye(4), atol=1e-12)


def test_quaternion_hand_case_yaw_90():
    s = math.sqrt(0.5)
    np.testing.assert_allclose(quat_to_rot(0, 0, s, s) @ [1, 0, 0], [0, 1, 0], atol=1e-12)
    np.testing.assert_allclose(rpy_to_rot(0, 0, math.pi / 2) @ [1, 0, 0], [0, 1, 0], atol=1e-12)


def test_optical_frame_convention():
    # Camera 2 m up at x=1 looking forward: a point 10 m ahead, 1 m left, at camera height is at
    # optical x = -1 (x right), y = 0 (y down), z = 10 (z forward).
    ego_from_cam = ego_from_optical((1.0, 0.0, 2.0))
    p_cam = transform_points(invert_transform(ego_from_cam), np.array([[11.0, 1.0, 2.0]]))
    np.testing.assert_allclose(p_cam[0], [-1.0, 0.0, 10.0], atol=1e-12)
    # Yawed 90 deg (looking left): its optical z axis is ego +y; pitched down: z tilts to -z.
    left = ego_from_optical((0, 0, 0), yaw=math.pi / 2)
    np.testing.assert_allclose(left[:3, 2], [0, 1, 0], atol=1e-12)
    down = ego_from_optical((0, 0, 0), pitch=0.3)
    assert down[2, 2] < 0 and down[0, 2] > 0


def test_validate_transform_rejects_shear():
    T = np.eye(4)
    T[0, 1] = 0.5
    with pytest.raises(CalibrationError):
        validate_transform(T, "x")


def test_preset_rigs_look_where_expected():
    yaws = {}
    for cam in preset_rig("surround6").cameras:
        z_axis = cam.ego_from_cam_array[:3, 2]
        yaws[cam.name] = math.degrees(math.atan2(z_axis[1], z_axis[0]))
        assert abs(z_axis[2]) < 0.05  # roughly level
    assert abs(yaws["front"]) < 2 and abs(abs(yaws["back"]) - 180) < 2
    assert 45 < yaws["front_left"] < 65 and -65 < yaws["front_right"] < -45
    assert 100 < yaws["back_left"] < 120 and -120 < yaws["back_right"] < -100
    c2b = preset_rig("cam2bev4")
    np.testing.assert_allclose(c2b["front"].model.effective().K_array[0], [278.283 / 2, 0, 241.0])
    assert c2b["front"].model.image_size == (482, 302)


# ------------------------------------------------------------------------ grid
def test_default_grid_is_bimapper_grid():
    g = BevGrid()
    assert (g.width, g.height) == (400, 200)
    assert g.shape == (200, 400)


def test_grid_asymmetric_hand_case():
    g = BevGrid(x_min=0.0, x_max=10.0, y_min=-2.0, y_max=4.0, resolution=0.5)
    assert (g.width, g.height) == (20, 12)
    row, col = g.metric_to_cell(3.2, -1.1)
    assert (int(row), int(col)) == (1, 6)
    x, y = g.cell_to_metric(1, 6)
    assert (float(x), float(y)) == (3.25, -1.25)
    assert g.origin_xy == (0.0, -2.0)
    probs = np.zeros(g.shape)
    probs[1, 6] = 1.0
    data = g.to_occupancy(probs)
    assert data[1 * 20 + 6] == 100 and data.sum() == 100  # row-major, column along +x


def test_grid_round_trip_and_contains():
    g = BevGrid()
    rng = np.random.default_rng(6)
    rows = rng.integers(0, g.height, 1000)
    cols = rng.integers(0, g.width, 1000)
    r2, c2 = g.metric_to_cell(*g.cell_to_metric(rows, cols))
    assert (r2 == rows).all() and (c2 == cols).all()
    assert g.contains(29.99, -14.99) and not g.contains(30.0, 0.0)
    xs, ys = g.centers
    assert xs[0, 0] == pytest.approx(-29.925) and ys[0, 0] == pytest.approx(-14.925)
    assert xs[0, 1] > xs[0, 0] and ys[1, 0] > ys[0, 0]


def test_occupancy_round_trip_and_unknown():
    g = BevGrid(x_min=-1, x_max=1, y_min=-1, y_max=2, resolution=0.5)
    probs = np.random.default_rng(7).uniform(size=g.shape)
    known = np.ones(g.shape, bool)
    known[0, 0] = False
    data = g.to_occupancy(probs, known)
    assert data.dtype == np.int8 and data[0] == -1 and data.max() <= 100
    back, known2 = g.from_occupancy(data, g.width, g.height)
    assert (known2 == known).all()
    np.testing.assert_allclose(back[known], probs[known], atol=0.005 + 1e-9)
    with pytest.raises(GridError):
        g.from_occupancy(data, g.height, g.width)


def test_display_orientation_forward_up_left_left():
    g = BevGrid(x_min=0, x_max=4, y_min=-2, y_max=2, resolution=1.0)
    layer = np.zeros(g.shape)
    r, c = g.metric_to_cell(3.5, 1.5)  # far ahead, to the left
    layer[r, c] = 1
    disp = g.to_display(layer)
    assert disp.shape == (4, 4) and disp[0, 0] == 1


@pytest.mark.parametrize(
    "kwargs",
    [dict(resolution=0.0), dict(x_min=1, x_max=1), dict(resolution=0.7), dict(y_max=math.nan)],
)
def test_grid_rejects_bad_definitions(kwargs):
    with pytest.raises(GridError):
        BevGrid(**kwargs)
