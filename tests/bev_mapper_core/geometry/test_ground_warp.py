"""The ground-plane warp (issue #38): an image a camera took from where it really was, warped,
equals the image it would have taken of the same ground from its calibrated pose (reference:
both images rendered from a smooth ground texture by ray casting).
"""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np

from bev_mapper_core.geometry.camera import CameraModel
from bev_mapper_core.geometry.ground_warp import ground_warp_maps, warp_image
from bev_mapper_core.geometry.rig import preset_rig
from bev_mapper_core.geometry.transforms import make_transform, rpy_to_rot


def ground_view(cam, ego_from_cam: np.ndarray, reach: float = 40.0) -> np.ndarray:
    """RGB image ``(H, W, 3)`` uint8 of a smooth texture on the ground (0 where a ray misses it,
    or meets it farther than ``reach``) seen by ``cam``'s intrinsics from ``ego_from_cam``.
    """
    w, h = cam.model.image_size
    us, vs = np.meshgrid(np.arange(w, dtype=np.float64), np.arange(h, dtype=np.float64))
    rays = cam.model.unproject(np.stack([us.ravel(), vs.ravel()], axis=1)) @ ego_from_cam[:3, :3].T
    o = ego_from_cam[:3, 3]
    with np.errstate(divide="ignore", invalid="ignore"):
        s = np.where(rays[:, 2] < -1e-9, -o[2] / rays[:, 2], np.nan)
    x, y = np.nan_to_num(o[0] + s * rays[:, 0]), np.nan_to_num(o[1] + s * rays[:, 1])
    hit = np.isfinite(s) & (s > 0) & (np.hypot(x - o[0], y - o[1]) < reach)
    tex = np.stack([128 + 100 * np.sin(1.5 * x), 128 + 100 * np.cos(1.5 * y), 128 + 60 * np.sin(x + y)], 1)
    return np.where(hit[:, None], tex, 0).reshape(h, w, 3).round().astype(np.uint8)  # (H*W, 3) -> (H, W, 3)


def _moved(E: np.ndarray, dx: float, dy: float, dyaw: float) -> np.ndarray:
    return make_transform(rpy_to_rot(0.0, 0.0, dyaw), (dx, dy, 0.0)) @ E


def _errors(cam, placed: np.ndarray) -> tuple[float, float, float]:
    """``(mean |warped - truth|, mean |unwarped - truth|, share of pixels compared)`` on the
    ground within 15 m of the calibrated camera (the texture reaches farther in the placed view).
    """
    truth, seen = ground_view(cam, cam.ego_from_cam_array, reach=15.0), ground_view(cam, placed)
    warped = warp_image(seen, ground_warp_maps(cam, placed))
    ground = truth.any(2) & warped.any(2) & seen.any(2)
    err = np.abs(warped.astype(float) - truth)[ground].mean()
    before = np.abs(seen.astype(float) - truth)[ground].mean()
    return err, before, ground.mean()


def test_the_warped_image_is_the_calibrated_view_of_the_ground():
    for name, move in (("front", (0.4, 0.0, 0.0)), ("front_left", (0.4, -0.05, math.radians(0.6))),
                       ("back", (-0.3, 0.1, math.radians(-0.5)))):
        cam = preset_rig("surround6")[name]
        cam = replace(cam, model=cam.model.scaled(0.5))  # 200 x 112 px
        err, before, share = _errors(cam, _moved(cam.ego_from_cam_array, *move))
        assert share > 0.2, name
        assert err < 4.0 and before > 4 * err, (name, err, before)  # of 0-255: bilinear sampling aside, equal


def test_distortion_and_no_motion():
    cam = preset_rig("front1")["front"]
    K = cam.model.K_array / 4
    K[2, 2] = 1.0
    model = CameraModel(K=tuple(map(tuple, K.tolist())), D=(-0.1, 0.02, 0.0, 0.0, 0.0), width=400, height=225)
    cam = replace(cam, model=model)
    E = cam.ego_from_cam_array
    mx, my = ground_warp_maps(cam, E)  # no motion: the identity, distortion and all
    w, h = model.image_size
    us, vs = np.meshgrid(np.arange(w), np.arange(h))
    assert np.abs(mx - us).max() < 1e-3 and np.abs(my - vs).max() < 1e-3
    err, before, _ = _errors(cam, _moved(E, 0.3, 0.0, 0.0))
    assert err < 4.0 and before > 4 * err
    labels = (ground_view(cam, E)[..., 0] // 64).astype(np.uint8)  # label images: nearest, ids kept
    out = warp_image(labels, ground_warp_maps(cam, _moved(E, 0.3, 0.0, 0.0)))
    assert out.dtype == np.uint8 and set(np.unique(out)) <= set(np.unique(labels)) | {0}


def test_a_large_camera_is_warped_from_samples_as_exactly():
    """A 1600 x 900 camera's maps come from at most MAX_SAMPLES rays, interpolated: within a
    tenth of a pixel of the maps of every pixel, away from the horizon.
    """
    import bev_mapper_core.geometry.ground_warp as gw

    cam = preset_rig("surround6")["front_right"]
    cam = replace(cam, model=cam.model.scaled(4.0))  # 1600 x 900
    warp = gw.GroundWarp(cam)
    assert warp.step > 1
    placed = _moved(cam.ego_from_cam_array, 0.4, -0.05, math.radians(0.6))
    mx, my = warp.maps(placed)
    full = gw.GroundWarp.__new__(gw.GroundWarp)
    saved = gw.MAX_SAMPLES
    try:
        gw.MAX_SAMPLES = 10**9  # every pixel
        full.__init__(cam)
    finally:
        gw.MAX_SAMPLES = saved
    fx, fy = full.maps(placed)
    assert fx.shape == mx.shape == (900, 1600)
    near = np.zeros_like(fx, bool)
    near[600:] = True  # the ground below the horizon band
    assert np.abs(mx - fx)[near].max() < 0.1 and np.abs(my - fy)[near].max() < 0.1
