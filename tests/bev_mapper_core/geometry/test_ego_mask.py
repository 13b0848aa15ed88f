"""Ego-body masks: loading and checking, ground tables that leave masked pixels out, and IPM
that no longer maps a hood painted as a vehicle into the cells near the ego."""

import math

import cv2
import numpy as np
import pytest

from bev_mapper_core.geometry.camera import CameraModel
from bev_mapper_core.geometry.ego_mask import (
    EgoMask,
    EgoMaskError,
    attach_ego_masks,
    load_ego_mask,
    mask_notes,
    polygon_mask,
    with_ego_masks,
)
from bev_mapper_core.geometry.ego_mask_proposal import StaticPixels
from bev_mapper_core.geometry.grid import BevGrid
from bev_mapper_core.geometry.projection import ground_tables
from bev_mapper_core.geometry.rig import Rig, RigCamera, scaled_camera
from bev_mapper_core.geometry.transforms import ego_from_optical
from bev_mapper_core.labels.classes import Label
from bev_mapper_core.mapper import MapperConfig, create_mapper

GRID = BevGrid(x_min=-12, x_max=20, y_min=-8, y_max=8, resolution=0.25)
W, H = 320, 240
HOOD_ROWS = 50


def make_rig() -> Rig:
    model = CameraModel(K=((200.0, 0, 160), (0, 200.0, 120), (0, 0, 1)), width=W, height=H)
    front = RigCamera("front", model, ego_from_optical((1.5, 0.0, 1.6), pitch=math.radians(20)))
    back = RigCamera("back", model, ego_from_optical((-0.5, 0.0, 1.6), yaw=math.pi, pitch=math.radians(20)))
    return Rig("test2", (front, back))


def hood() -> EgoMask:
    px = np.zeros((H, W), bool)
    px[-HOOD_ROWS:] = True
    return EgoMask(px, "hood")


def road_images(rig: Rig, hood_in: tuple[str, ...] = ("front",)) -> dict[str, np.ndarray]:
    """Road everywhere below the horizon; a hood painted as vehicle into the bottom rows."""
    out = {}
    for cam in rig.cameras:
        img = np.full((H, W), Label.ROAD, np.uint8)
        if cam.name in hood_in:
            img[-HOOD_ROWS:] = Label.VEHICLE
        out[cam.name] = img
    return out


def near_ego(grid: BevGrid, radius: float = 10.0) -> np.ndarray:
    xs, ys = _centres(grid)
    return np.hypot(xs, ys) < radius


def _centres(grid: BevGrid):
    pts = grid.points(0.0).reshape(*grid.shape, 3)
    return pts[..., 0], pts[..., 1]


@pytest.mark.parametrize("occlusion", [True, False])
def test_ipm_maps_no_hood_with_the_mask(occlusion):
    rig = make_rig()
    cfg = MapperConfig(method="ipm", ipm_occlusion=occlusion)
    images = road_images(rig)
    plain = create_mapper(rig, GRID, cfg).map(images)
    near = near_ego(GRID)
    false_vehicle = (plain.layer("vehicle") > 0.5) & plain.known & near
    assert false_vehicle.sum() > 20  # the hood mapped as a vehicle next to the ego

    masked_rig = with_ego_masks(rig, {"front": hood()})
    pred = create_mapper(masked_rig, GRID, cfg).map(images)
    assert not ((pred.layer("vehicle") > 0.5) & pred.known).any()
    seen_only_through_hood = plain.known & ~ground_tables(masked_rig, GRID)["front"].valid \
        & ground_tables(rig, GRID)["front"].valid & ~ground_tables(rig, GRID)["back"].valid
    assert seen_only_through_hood.sum() > 20
    assert not pred.known[seen_only_through_hood].any()  # unknown, not road
    assert (pred.known & ~plain.known).sum() == 0


def test_tables_leave_masked_pixels_out_and_follow_scaling():
    rig = with_ego_masks(make_rig(), {"front": hood()})
    plain = ground_tables(make_rig(), GRID)["front"]
    table = ground_tables(rig, GRID)["front"]
    assert (table.valid <= plain.valid).all()
    cut = plain.valid & ~table.valid
    assert cut.any() and (table.map_y[table.valid] < H - HOOD_ROWS - 0.5).all()
    assert (plain.map_y[cut] >= H - HOOD_ROWS - 1).all()
    # a learned method's half-size input keeps the mask (looked up proportionally)
    half = Rig("half", (scaled_camera(rig["front"], W // 2),))
    half_valid = ground_tables(half, GRID)["front"].valid
    assert half["front"].ego_mask is rig["front"].ego_mask
    assert (half_valid ^ table.valid).sum() <= 0.05 * cut.sum()


def test_label_images_get_unlabeled_under_the_mask():
    rig = with_ego_masks(make_rig(), {"front": hood()})
    m = create_mapper(rig, GRID, MapperConfig(method="ipm"))
    out = m.check_images(road_images(rig))
    assert (out["front"][-HOOD_ROWS:] == Label.UNLABELED).all()
    assert (out["front"][:-HOOD_ROWS] == Label.ROAD).all()
    assert (out["back"] == Label.ROAD).all()


def test_bad_masks_refused(tmp_path):
    with pytest.raises(EgoMaskError, match="no such file"):
        load_ego_mask(tmp_path / "missing.png")
    grey = np.zeros((H, W), np.uint8)
    grey[-5:] = 255
    grey[0, 0] = 7
    cv2.imwrite(str(tmp_path / "grey.png"), grey)
    with pytest.raises(EgoMaskError, match="not binary"):
        load_ego_mask(tmp_path / "grey.png")
    colour = np.zeros((H, W, 3), np.uint8)
    colour[-5:, :, 2] = 255
    cv2.imwrite(str(tmp_path / "colour.png"), colour)
    with pytest.raises(EgoMaskError, match="not binary"):
        load_ego_mask(tmp_path / "colour.png")
    (tmp_path / "text.png").write_text("no image")
    with pytest.raises(EgoMaskError, match="not an image"):
        load_ego_mask(tmp_path / "text.png")
    small = EgoMask(np.zeros((10, 10), bool), "small")
    rig, problems = attach_ego_masks(make_rig(), {"front": small, "roof": hood()})
    assert "10x10" in problems["front"] and "320x240" in problems["front"] and "roof" in problems
    assert rig["front"].ego_mask is None and rig["back"].ego_mask is None
    with pytest.raises(EgoMaskError, match="front"):
        with_ego_masks(make_rig(), {"front": small})
    ok = np.zeros((H, W), np.uint8)
    ok[-5:] = 1
    cv2.imwrite(str(tmp_path / "ok.png"), ok)
    assert load_ego_mask(tmp_path / "ok.png").pixels.sum() == 5 * W


def test_all_masked_camera_is_said_and_the_rest_mapped():
    full = EgoMask(np.ones((H, W), bool), "full")
    rig = with_ego_masks(make_rig(), {"back": full})
    assert any("whole image" in n and "back" in n for n in mask_notes(rig))
    assert not ground_tables(rig, GRID)["back"].valid.any()
    pred = create_mapper(rig, GRID, MapperConfig(method="ipm")).map(road_images(rig, ()))
    assert pred.known.any() and not pred.known[_centres(GRID)[0] < -3].any()


def test_polygon_mask():
    m = polygon_mask([[[0, H - 1], [W - 1, H - 1], [W - 1, H - 30], [0, H - 30]]], (W, H))
    assert m.size == (W, H) and m.pixels[-30:].all() and not m.pixels[:-30].any()
    with pytest.raises(EgoMaskError, match="polygon 0"):
        polygon_mask([[[0, 0], [1, 1]]], (W, H))


def test_static_pixels_propose_the_hood():
    rng = np.random.default_rng(0)
    sp = StaticPixels()
    for _ in range(6):
        labels = rng.integers(1, 8, (H, W), dtype=np.uint8)
        labels[-HOOD_ROWS:, 40:280] = Label.VEHICLE
        labels[:30] = Label.UNLABELED  # a sky that never changes is no ego body
        rgb = rng.integers(0, 255, (H, W, 3), dtype=np.uint8)
        rgb[-HOOD_ROWS:, 40:280] = (90, 90, 100)
        sp.add(labels, rgb)
    m = sp.proposal().pixels
    truth = np.zeros((H, W), bool)
    truth[-HOOD_ROWS:, 40:280] = True
    assert (m & truth).sum() > 0.95 * truth.sum() and (m & ~truth).sum() < 0.02 * truth.sum()
