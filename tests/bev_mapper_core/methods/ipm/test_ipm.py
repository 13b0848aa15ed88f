"""IPM baseline on analytic scenes, and the Mapper interface contract."""

import math

import numpy as np
import pytest

from bev_mapper_core.errors import ConfigError, InputError
from bev_mapper_core.geometry.camera import CameraModel
from bev_mapper_core.geometry.grid import BevGrid
from bev_mapper_core.geometry.projection import ground_tables
from bev_mapper_core.geometry.rig import Rig, RigCamera
from bev_mapper_core.geometry.transforms import ego_from_optical, transform_points
from bev_mapper_core.labels.classes import BEV_CLASS_NAMES, Label
from bev_mapper_core.mapper import MapperConfig, available_methods, create_mapper
from bev_mapper_core.methods.ipm.mapper import IpmMapper, code_bits

GRID = BevGrid(x_min=-10, x_max=20, y_min=-6, y_max=6, resolution=0.25)


def flat_world_label(x, y):
    """Road for |y| < 3 with a divider line at y in [0, 0.25); sidewalk beyond."""
    lab = np.where(np.abs(y) < 3.0, Label.ROAD, Label.SIDEWALK).astype(np.uint8)
    lab[(y >= 0.0) & (y < 0.25) & (np.abs(y) < 3.0)] = Label.LANE_DIVIDER
    return lab


def render_flat(cam: RigCamera) -> np.ndarray:
    """Label image of the flat world by casting every pixel's ray onto z = 0."""
    rays = cam.model.pixel_rays()  # (H, W, 3) optical
    h, w, _ = rays.shape
    R = cam.ego_from_cam_array[:3, :3]
    o = cam.ego_from_cam_array[:3, 3]
    d = rays.reshape(-1, 3) @ R.T  # (H*W, 3) ego directions
    with np.errstate(divide="ignore", invalid="ignore"):
        t = -o[2] / d[:, 2]
    hit = (d[:, 2] < -1e-9) & (t > 0)
    x = o[0] + t * d[:, 0]
    y = o[1] + t * d[:, 1]
    lab = np.where(hit, flat_world_label(np.where(hit, x, 0), np.where(hit, y, 0)), Label.UNLABELED)
    return lab.reshape(h, w).astype(np.uint8)


def make_rig():
    model = CameraModel(K=((200.0, 0, 160), (0, 200.0, 120), (0, 0, 1)), width=320, height=240)
    front = RigCamera("front", model, ego_from_optical((1.5, 0.0, 1.6), pitch=math.radians(12)))
    back = RigCamera("back", model, ego_from_optical((-0.5, 0.0, 1.6), yaw=math.pi, pitch=math.radians(12)))
    return Rig("test2", (front, back))


def test_ipm_table_hits_the_projected_pixel():
    rig = make_rig()
    tables = ground_tables(rig, GRID)
    cam = rig["front"]
    r, c = GRID.metric_to_cell(8.1, -1.1)
    x, y = GRID.cell_to_metric(r, c)
    uv, _ = cam.model.project(transform_points(cam.cam_from_ego, np.array([[x, y, 0.0]])))
    t = tables["front"]
    assert t.valid[r, c]
    np.testing.assert_allclose([t.map_x[r, c], t.map_y[r, c]], uv[0], atol=1e-3)
    # Behind the front camera nothing is valid.
    rb, cb = GRID.metric_to_cell(-5.0, 0.0)
    assert not t.valid[rb, cb]


def test_ipm_recovers_flat_classes():
    rig = make_rig()
    mapper = create_mapper(rig, GRID, MapperConfig(method="ipm"))
    images = {cam.name: render_flat(cam) for cam in rig.cameras}
    pred = mapper.map(images)
    assert pred.probs.shape == (len(BEV_CLASS_NAMES), *GRID.shape) and pred.probs.dtype == np.float32
    xs, ys = GRID.centers
    truth = flat_world_label(xs, ys)
    known = pred.known
    # A stretch of road ahead and behind is inside the cameras' views.
    assert known[(np.abs(np.abs(xs) - 8) < 1) & (np.abs(ys) < 2)].all()
    drivable = pred.layer("drivable") >= 0.5
    want = np.isin(truth, [Label.ROAD, Label.LANE_DIVIDER])
    acc = (drivable == want)[known].mean()
    assert acc > 0.98
    sidewalk = pred.layer("sidewalk") >= 0.5
    assert (sidewalk == (truth == Label.SIDEWALK))[known].mean() > 0.98
    # The divider lies on drivable (multi-label), and is found where it is painted.
    div = pred.layer("lane_divider") >= 0.5
    assert (div & known).sum() > 20
    assert (drivable[div & known]).all()
    assert (np.abs(ys[div & known] - 0.125) <= 0.25).all()
    # Cells beside the ego, under no camera's view, are unknown with zero probability.
    r0, c0 = GRID.metric_to_cell(0.5, 0.0)
    assert not known[r0, c0] and pred.probs[:, r0, c0].max() == 0


def test_ipm_missing_camera_only_loses_its_cells():
    rig = make_rig()
    mapper = IpmMapper(rig, GRID, MapperConfig(method="ipm"))
    images = {cam.name: render_flat(cam) for cam in rig.cameras}
    both = mapper.map(images)
    front_only = mapper.map({"front": images["front"]})
    xs, _ = GRID.centers
    assert front_only.known[xs < -3].sum() == 0 < both.known[xs < -3].sum()
    np.testing.assert_array_equal(front_only.probs[:, xs > 5], both.probs[:, xs > 5])


@pytest.mark.parametrize(
    "images, message",
    [
        ({"front": np.zeros((10, 10), np.uint8)}, "calibration says 320x240"),
        ({"front": np.zeros((240, 320, 3), np.uint8)}, "label image must be"),
        ({"front": np.zeros((240, 320), np.float32)}, "label image must be"),
        ({"left": np.zeros((240, 320), np.uint8)}, "unknown camera"),
        ({}, "no camera image"),
    ],
)
def test_ipm_rejects_bad_input(images, message):
    mapper = IpmMapper(make_rig(), GRID, MapperConfig(method="ipm"))
    with pytest.raises(InputError, match=message):
        mapper.map(images)


def test_ipm_refuses_rgb_and_unknown_methods():
    with pytest.raises(ConfigError, match="label images only"):
        IpmMapper(make_rig(), GRID, MapperConfig(input_kind="rgb"))
    with pytest.raises(ConfigError, match="unknown method"):
        MapperConfig(method="nope")
    with pytest.raises(ConfigError, match="unknown BEV class"):
        MapperConfig(classes=("drivable", "unicorn"))
    assert "ipm" in available_methods()


def test_ipm_class_subset_and_rgb_mosaic():
    rig = make_rig()
    mapper = IpmMapper(rig, GRID, MapperConfig(classes=("sidewalk", "drivable")))
    images = {cam.name: render_flat(cam) for cam in rig.cameras}
    pred = mapper.map(images)
    assert pred.classes == ("sidewalk", "drivable") and pred.probs.shape[0] == 2
    rgb = {n: np.dstack([img * 20, img * 10, img]) .astype(np.uint8) for n, img in images.items()}
    mosaic, known = mapper.warp_rgb(rgb)
    assert mosaic.shape == (*GRID.shape, 3) and (known == pred.known).all()
    xs, ys = GRID.centers
    cell = known & (np.abs(ys) > 4) & (np.abs(xs - 6) < 2)
    assert np.abs(mosaic[cell][:, 0].astype(int) - Label.SIDEWALK * 20).max() <= 1


def test_calibration_change_recomputes_tables():
    rig = make_rig()
    mapper = IpmMapper(rig, GRID, MapperConfig(method="ipm"))
    before = mapper.tables["front"].map_y.copy()
    lifted = rig.with_camera(RigCamera("front", rig["front"].model,
                                       ego_from_optical((1.5, 0.0, 2.0), pitch=math.radians(12))))
    mapper.set_rig(lifted)
    assert not np.allclose(before, mapper.tables["front"].map_y)


def _ipm_by_whole_image_warps(mapper: IpmMapper, images) -> tuple[np.ndarray, np.ndarray]:
    """IPM as it was before the gather tables: cv2.remap of every image, masked accumulation."""
    import cv2

    H, W = mapper.grid.shape
    acc = np.zeros((H, W, len(mapper.classes)), np.float32)
    count = np.zeros((H, W), np.float32)
    lut = mapper._lut
    for name, labels in images.items():
        warped = mapper.tables[name].warp(labels, cv2.INTER_NEAREST)
        valid = mapper.sight.camera_valid(name, warped, labels)
        warped = np.where(warped < lut.shape[0], warped, 0)
        acc[valid] += lut[warped[valid]]
        count += valid
    return np.moveaxis(acc / np.maximum(count, 1.0)[..., None], -1, 0), count > 0


def test_the_compiled_counting_is_built():
    """``pip install -e .`` (scripts/setup_venv.sh) builds it; without it IPM is slower."""
    import bev_mapper_core.methods.ipm.mapper as ipm_mapper

    assert ipm_mapper._compiled is not None, "bev_mapper_core/methods/ipm/_counts.c was not built: pip install -e ."


def test_the_compiled_counting_refuses_mismatched_buffers():
    """Wrong sizes are a ValueError and a cell outside the grid an IndexError, never a write
    outside the counts."""
    import bev_mapper_core.methods.ipm.mapper as ipm_mapper

    kernel = ipm_mapper._compiled
    if kernel is None:
        pytest.skip("not built")
    counts, table = np.zeros((10, 8), np.uint8), np.zeros((256, 8), np.uint8)
    table[:, 7] = 1
    cells, ids, none = np.array([0, 9], np.int64), np.array([3, 4], np.uint8), np.zeros(0, np.int64)
    kernel.add(counts, 8, cells, ids, table, none)
    assert counts[[0, 9], 7].tolist() == [1, 1]
    with pytest.raises(IndexError):
        kernel.add(counts, 8, np.array([0, 10], np.int64), ids, table, none)
    for args in [(counts, 8, cells.astype(np.int32), ids, table, none),  # cells not int64
                 (counts, 8, cells, ids[:1], table, none),  # ids of another length
                 (counts, 8, cells, ids, table[:255], none),  # a table short of a label
                 (counts, 6, cells, ids, table, none)]:  # a stride not a multiple of 8
        with pytest.raises(ValueError):
            kernel.add(*args)
    probs, known = np.empty((7, 10), np.float32), np.empty(10, np.uint8)
    kernel.divide(counts, 8, 7, probs, known)
    assert known.tolist() == [1] + [0] * 8 + [1]
    with pytest.raises(ValueError):
        kernel.divide(counts, 8, 7, probs[:6], known)


@pytest.mark.parametrize("counting", ["compiled", "numpy"])
@pytest.mark.parametrize("occlusion", [True, False])
def test_gather_tables_give_the_whole_image_warps_cell_for_cell(occlusion, counting, monkeypatch):
    """The per-frame gather (``GatherTable``) gives exactly what warping whole images with
    ``cv2.remap`` and accumulating them gave: every camera of surround6 on synthetic frames with
    cars and pedestrians, a label id unknown to the package, and a camera missing; counted by the
    compiled kernel and by each of the numpy paths."""
    import bev_mapper_core.methods.ipm.mapper as ipm_mapper
    from bev_mapper_core.geometry.rig import preset_rig
    from bev_mapper_core.synth import SynthConfig, generate_drive

    if counting == "numpy":
        monkeypatch.setattr(ipm_mapper, "_compiled", None)

    rig, grid = preset_rig("surround6"), BevGrid()
    mapper = create_mapper(rig, grid, MapperConfig(method="ipm", ipm_occlusion=occlusion))
    for f in generate_drive(rig, grid, SynthConfig(frames=2, seed=950_000_016)):
        images = {n: c.labels.copy() for n, c in f.cameras.items()}
        images["front"][:20, :20] = 250  # ids outside Label: unlabeled
        for subset in (images, {n: v for n, v in images.items() if n != "back"}):
            pred = mapper.map(subset)
            probs, known = _ipm_by_whole_image_warps(mapper, subset)
            np.testing.assert_array_equal(pred.known, known)
            np.testing.assert_array_equal(pred.probs, probs)
            assert pred.probs.flags.c_contiguous and pred.probs.dtype == np.float32
    # 7 classes and the camera count, 6 cameras: packed a byte per field; then 4 bits per field
    # (more classes), then the float path (too many fields or cameras for one uint64)
    assert mapper._codes is not None and mapper._bits == 8 == code_bits(7 + 1, 6)
    assert code_bits(12, 6) == 4 and code_bits(12, 20) is None and code_bits(17, 2) is None
    expected = _ipm_by_whole_image_warps(mapper, images)
    for bits in (4, None) if counting == "numpy" else ():
        mapper._pack(bits)
        pred = mapper.map(images)
        np.testing.assert_array_equal(pred.probs, expected[0])
        np.testing.assert_array_equal(pred.known, expected[1])
