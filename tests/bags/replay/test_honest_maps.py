"""Issue #11 "Honest maps": full truth in synthetic bags, whole-grid scores, IPM that says unknown.

Hand-made scenes throughout: a car hidden behind a car (the truth has it, no camera sees it), a
4x4 grid whose occluded claims are counted by hand, an ECE worked out by hand, and a box in front
of a level camera whose shadow IPM must leave unknown.
"""

from __future__ import annotations

import json
import math

import numpy as np
import pytest

from bags.cli.main import main
from bags.io import topics as T
from bags.io.reader import BagReader
from bags.io.writer import write_drive
from bags.replay import METRICS_FILE, RELIABILITY_FILE
from bev_mapper_core.geometry.camera import CameraModel
from bev_mapper_core.geometry.grid import BevGrid
from bev_mapper_core.geometry.rig import Rig, RigCamera, preset_rig
from bev_mapper_core.geometry.transforms import ego_from_optical, transform_points
from bev_mapper_core.labels.classes import BEV_CLASS_NAMES, BEV_CLASSES, Label, label_lut
from bev_mapper_core.mapper import MapperConfig
from bev_mapper_core.methods.ipm.mapper import IpmMapper
from bev_mapper_core.metrics import WholeGridAccumulator, expected_calibration_error

pytest.importorskip("bev_mapper_core.synth")
from bev_mapper_core.synth import DriveRenderer, SynthConfig, build_world, generate_drive  # noqa: E402
from bev_mapper_core.synth.objects import Boxes  # noqa: E402

CI = {n: i for i, n in enumerate(BEV_CLASS_NAMES)}
GRID = BevGrid(-10.0, 30.0, -10.0, 10.0, 0.25)


# ------------------------------------------------------------------ 1. full truth in the bag
@pytest.fixture(scope="module")
def car_behind_car(tmp_path_factory):
    """A front camera, a 1.8 m tall car 10 m ahead and a lower, narrower car right behind it;
    the frame written as a bag and read back."""
    cfg = SynthConfig(frames=1, seed=3, vehicle_density=0, pedestrian_density=0,
                      obstacle_density=0, building_density=0)
    world = build_world(cfg)
    rig = preset_rig("front1").scaled(0.5)
    dr = DriveRenderer(world, rig, GRID)
    pose = world.ego_pose(0)
    yaw = math.atan2(pose[1, 0], pose[0, 0])
    front = transform_points(pose, np.array([[10.0, 0.0, 0.0]]))[0, :2]
    behind = transform_points(pose, np.array([[17.0, 0.0, 0.0]]))[0, :2]
    obj = int(world.parts.obj.max()) + 1 if len(world.parts) else 0
    boxes = Boxes.concat([
        Boxes.make([front], 0.0, (4.5, 2.2, 1.8), yaw, Label.VEHICLE, (200, 0, 0), obj=obj),
        Boxes.make([behind], 0.0, (4.0, 1.6, 1.3), yaw, Label.VEHICLE, (0, 0, 200), obj=obj + 1),
    ])
    frame = dr.frame(0, boxes=boxes)
    bag = tmp_path_factory.mktemp("honest") / "car_behind_car"
    write_drive(bag, rig, GRID, [frame])
    with BagReader(bag) as reader:
        (read,) = list(reader.frames(rgb=False))
    return world, pose, frame, read


def test_full_truth_has_the_hidden_car_and_the_raster(car_behind_car):
    world, pose, frame, read = car_behind_car
    xs, ys = GRID.centers
    hidden_car = (np.abs(xs - 17.0) < 1.8) & (np.abs(ys) < 0.6)
    front_car = (np.abs(xs - 10.0) < 2.0) & (np.abs(ys) < 0.9)
    veh = read.truth[CI["vehicle"]] == 1.0
    assert veh[hidden_car].all() and veh[front_car].all()  # both cars are in the truth
    assert not read.visibility[hidden_car].any()  # ... the hidden one is seen by no camera
    assert read.visibility[front_car].all()
    assert not read.gt_known[CI["vehicle"]][hidden_car].any()  # so its GT is -1
    # nothing but the two footprints is a vehicle
    assert veh.sum() == frame.gt[CI["vehicle"]].sum() and not veh[~(np.abs(ys) < 1.2)].any()
    # the flat classes of the truth are the world raster at every cell centre, seen or not
    pts = transform_points(pose, GRID.points(0.0))
    flat = label_lut(BEV_CLASSES)[world.ground.labels(pts[:, 0], pts[:, 1]).reshape(GRID.shape)]
    for c in range(5):
        np.testing.assert_array_equal(read.truth[c] == 1.0, flat[..., c])
    # /bev/gt is the truth where it is known, and known exactly where /bev/visibility/any says
    np.testing.assert_array_equal(read.gt_known, np.broadcast_to(read.visibility, read.gt_known.shape))
    np.testing.assert_array_equal(read.gt[read.gt_known], read.truth[read.gt_known])


# ---------------------------------------------------------------- 2. whole-grid scores
def test_occluded_claims_counted_on_a_hand_made_grid():
    grid = BevGrid(0.0, 1.0, 0.0, 1.0, 0.5)  # 2 x 2 cells of 0.25 m^2
    acc = WholeGridAccumulator(grid, ("vehicle", "drivable"))
    visible = np.array([[True, False], [False, False]])  # 3 hidden cells
    known = np.array([[True, True], [True, False]])  # one hidden cell published unknown
    probs = np.zeros((2, 2, 2), np.float32)
    probs[0] = [[0.9, 0.7], [0.5, 1.0]]  # vehicle claimed in the 2 hidden known cells
    probs[1] = [[0.2, 0.4], [0.0, 0.0]]  # drivable claimed nowhere hidden
    truth = np.zeros((2, 2, 2), bool)
    truth[0, 0, 1] = True  # one claim is right, the other (cell (1, 0)) false
    truth[1, 1, 0] = True
    gt = truth.copy()
    acc.update(probs, known, visible, gt, truth)
    r = acc.result()
    occ = r["occlusion"]
    assert occ["hidden_share"] == 0.75
    assert occ["unknown_recall"] == pytest.approx(1 / 3)
    assert occ["known_precision"] == pytest.approx(1 / 3)  # 3 known cells, 1 visible
    v, d = occ["classes"]["vehicle"], occ["classes"]["drivable"]
    assert v["claim_share"] == pytest.approx(2 / 3) and v["false_share"] == 0.5
    assert v["claim_m2_per_frame"] == 0.5 and v["false_m2_per_frame"] == 0.25
    assert d["claim_share"] == 0.0 and d["false_share"] is None and d["false_m2_per_frame"] == 0.0
    # a second frame without full truth: claims count, false claims are not guessed
    acc.update(probs, known, visible, gt)
    r = acc.result()
    v = r["occlusion"]["classes"]["vehicle"]
    assert r["frames"] == 2 and r["frames_with_truth"] == 1
    assert v["claim_m2_per_frame"] == 0.5 and v["false_m2_per_frame"] == 0.25 and v["false_share"] == 0.5
    json.dumps(r, allow_nan=False)


def test_ece_worked_out_by_hand():
    # 10 cells at p = 0.8 of which 6 hold the class, 10 at p = 0.2 of which 2 do, and 5 at
    # p = 1.0 (last bin, closed at 1) that all do: |0.6 - 0.8| * 10 / 25 = 0.08
    p = np.array([0.8] * 10 + [0.2] * 10 + [1.0] * 5, np.float32)
    y = np.array([1] * 6 + [0] * 4 + [1] * 2 + [0] * 8 + [1] * 5, bool)
    probs, truth = p.reshape(1, 5, 5), y.reshape(1, 5, 5)
    assert expected_calibration_error(probs, truth)[0] == pytest.approx(0.08)
    # per bin, not per cell: 0.05 and 0.09 share bin 0 (mean 0.07, frequency 0.5)
    p2 = np.array([[[0.05, 0.09]]], np.float32)
    assert expected_calibration_error(p2, np.array([[[True, False]]]))[0] == pytest.approx(0.5 - 0.07)
    # the accumulator gives the same, over the visible known cells only, with its reliability
    grid = BevGrid(0.0, 5.0, 0.0, 5.0, 1.0)
    acc = WholeGridAccumulator(grid, ("vehicle",))
    everything = np.ones((5, 5), bool)
    acc.update(probs, everything, everything, truth)
    hidden_wrong = probs.copy()
    hidden_wrong[0, 0, 0] = 0.0  # a cell that does not count: hidden ...
    seen = everything.copy()
    seen[0, 0] = False
    unknown = everything.copy()
    unknown[0, 1] = False  # ... and one published unknown
    acc.update(hidden_wrong, unknown, seen, truth)
    cal = acc.result()["calibration"]
    rel = cal["classes"]["vehicle"]["reliability"]
    assert cal["bins"] == 10 and cal["classes"]["vehicle"]["cells"] == 25 + 23
    assert rel["count"][8] == 18 and rel["frequency"][8] == pytest.approx(10 / 18)
    assert rel["count"][9] == 10 and rel["frequency"][9] == 1.0 and rel["confidence"][9] == 1.0
    assert rel["count"][0] == 0 and rel["frequency"][0] is None
    assert cal["mean_ece"] == pytest.approx(abs(10 - 0.8 * 18) / 48)


# ------------------------------------------------------------- 3. IPM that says "unknown"
def _level_rig() -> Rig:
    model = CameraModel(K=((300.0, 0, 320), (0, 300.0, 240), (0, 0, 1)), width=640, height=480)
    return Rig("level1", (RigCamera("front", model, ego_from_optical((0.0, 0.0, 1.5))),))


def _render(cam: RigCamera, boxes) -> np.ndarray:
    """Label image of a flat road with upright boxes ``(x0, x1, y0, y1, height, label)``:
    every pixel's ray cast onto the boxes (slab test) and the ground."""
    rays = cam.model.pixel_rays()
    h, w, _ = rays.shape
    T_ = cam.ego_from_cam_array
    d = rays.reshape(-1, 3) @ T_[:3, :3].T  # (H*W, 3) ego directions
    o = T_[:3, 3]
    with np.errstate(divide="ignore", invalid="ignore"):
        t_ground = np.where(d[:, 2] < -1e-9, -o[2] / d[:, 2], np.inf)
        lab = np.where(np.isfinite(t_ground), Label.ROAD, Label.UNLABELED).astype(np.uint8)
        best = t_ground.copy()
        for x0, x1, y0, y1, top, label in boxes:
            lo = np.full(len(d), -np.inf)
            hi = np.full(len(d), np.inf)
            for axis, a, b in ((0, x0, x1), (1, y0, y1), (2, 0.0, top)):
                ta, tb = (a - o[axis]) / d[:, axis], (b - o[axis]) / d[:, axis]
                lo = np.maximum(lo, np.minimum(ta, tb))
                hi = np.minimum(hi, np.maximum(ta, tb))
            hit = (lo <= hi) & (hi > 0) & (lo < best)
            best = np.where(hit, lo, best)
            lab[hit] = label
    return lab.reshape(h, w)


@pytest.fixture(scope="module")
def box_scene():
    """A 2 m tall car-sized box 8..12 m ahead (|y| < 1 m) and a 0.5 m obstacle 4 m to the
    left, seen by a level camera 1.5 m above the ground."""
    rig = _level_rig()
    labels = _render(rig["front"], [(8.0, 12.0, -1.0, 1.0, 2.0, Label.VEHICLE),
                                    (8.0, 8.5, 3.75, 4.25, 0.5, Label.OBSTACLE)])
    grid = BevGrid(0.0, 40.0, -10.0, 10.0, 0.25)
    preds = {occ: IpmMapper(rig, grid, MapperConfig(method="ipm", ipm_occlusion=occ)).map(
        {"front": labels}) for occ in (False, True)}
    return grid, preds


def test_ipm_leaves_the_cells_behind_a_box_unknown(box_scene):
    grid, preds = box_scene
    xs, ys = grid.centers
    veh, drv = BEV_CLASS_NAMES.index("vehicle"), BEV_CLASS_NAMES.index("drivable")
    honest, classic = preds[True], preds[False]
    front = (xs > 3.0) & (xs < 7.5) & (np.abs(ys) < 0.6)
    footprint = (xs > 8.2) & (xs < 11.5) & (np.abs(ys) < 0.6)
    behind = (xs > 13.5) & (np.abs(ys) < 0.5) & classic.known
    beside = (xs > 9.0) & (xs < 15.0) & (np.abs(ys) > 2.5) & (np.abs(ys) < 3.5)
    assert behind.sum() > 300  # the smear reaches the end of the grid in the classical IPM
    assert (classic.probs[veh][behind] == 1.0).all()
    # with occlusion reasoning: in front the road is known, the box's depth is vehicle, the
    # shadow behind it is unknown, and the ground beside it stays known
    assert honest.known[front].all() and (honest.probs[drv][front] == 1.0).all()
    assert (honest.probs[veh][front] == 0.0).all()
    assert honest.known[footprint].all() and (honest.probs[veh][footprint] == 1.0).all()
    assert not honest.known[behind].any()
    assert honest.known[beside].all() and (honest.probs[drv][beside] == 1.0).all()


def test_ipm_sees_the_ground_again_beyond_a_low_obstacle(box_scene):
    """The 0.5 m obstacle's near edge is 8.9 m away along the ray through its middle; it hides
    the ground up to about 9.5 * 1.5 / (1.5 - 0.5) = 14.3 m (its far top edge), not the 26.8 m
    its 1 m height prior allows: farther the camera sees the road over it, and those cells, whose
    own pixels show road, stay known."""
    grid, preds = box_scene
    xs, ys = grid.centers
    drv = BEV_CLASS_NAMES.index("drivable")
    honest = preds[True]
    bearing = np.arctan2(ys, xs)
    ray = np.abs(bearing - math.atan2(4.0, 8.0)) < 0.01  # through the obstacle's near face
    dist = np.hypot(xs, ys)
    shadow = ray & (dist > 10.5) & (dist < 13.5)  # the obstacle's smear beyond its depth
    over = ray & (dist > 15.5) & (dist < 22.0)
    assert shadow.sum() > 5 and not honest.known[shadow].any()
    assert over.sum() > 20 and honest.known[over].all() and (honest.probs[drv][over] == 1.0).all()


# ---------------------------------------------------------------------- 4. replay, old bags
@pytest.fixture(scope="module")
def bags(tmp_path_factory):
    """One small synthetic drive written with the full truth and as an old bag without it."""
    root = tmp_path_factory.mktemp("honest_bags")
    rig = preset_rig("surround6").scaled(0.5)
    frames = list(generate_drive(rig, GRID, SynthConfig(frames=3, seed=950000008)))
    write_drive(root / "new", rig, GRID, frames)
    write_drive(root / "old", rig, GRID, frames, truth=False)
    return root


def _replay(bag, out, *extra) -> dict:
    assert main(["replay", str(bag), "--out", str(out), "--quiet", "--method", "ipm",
                 "--no-pictures", *extra]) == 0
    return json.loads((out / METRICS_FILE).read_text())


def test_old_bags_without_the_new_topics_replay(bags, tmp_path, capsys):
    with BagReader(bags / "old") as r:
        assert T.ANY_VISIBILITY not in r.topics and not r.truth_classes
        assert all(f.truth is None and f.visibility is None for f in r.frames(rgb=False))
    old = _replay(bags / "old", tmp_path / "old")
    new = _replay(bags / "new", tmp_path / "new")
    assert "Whole grid" in capsys.readouterr().out
    # the visible-cell scores do not depend on the new layers; the hidden cells come from the
    # GT's -1 in old bags, from /bev/visibility/any in new ones: the same cells
    for key in ("classes", "miou", "map", "iou_by_range", "calibration"):
        assert old[key] == new[key], key
    for key in ("hidden_share", "unknown_recall", "known_precision"):
        assert old["occlusion"][key] == new["occlusion"][key]
    assert old["occlusion"]["frames_with_truth"] == 0 and new["occlusion"]["frames_with_truth"] == 3
    v_old, v_new = old["occlusion"]["classes"]["vehicle"], new["occlusion"]["classes"]["vehicle"]
    assert v_old["claim_m2_per_frame"] == v_new["claim_m2_per_frame"]
    assert v_old["false_share"] is None and v_new["false_m2_per_frame"] is not None
    assert (tmp_path / "new" / RELIABILITY_FILE).read_bytes()[:4] == b"\x89PNG"
    assert "Honest maps" in (tmp_path / "new" / "report.html").read_text()


def test_replay_flag_turns_the_occlusion_reasoning_off(bags, tmp_path):
    honest = _replay(bags / "new", tmp_path / "on")
    classic = _replay(bags / "new", tmp_path / "off", "--no-ipm-occlusion")
    h, c = honest["occlusion"], classic["occlusion"]
    assert h["unknown_recall"] > c["unknown_recall"] + 0.3
    assert h["known_precision"] > c["known_precision"]
    hv, cv = h["classes"]["vehicle"], c["classes"]["vehicle"]
    assert hv["false_m2_per_frame"] < 0.3 * cv["false_m2_per_frame"]


def test_bimapper_on_labels_withholds_the_cells_no_ray_reaches(box_scene, tmp_path):
    """Bi-Mapper on label input (an untrained tiny model: only ``known`` is checked): with
    ``ipm_occlusion`` the cells farther than a car's length behind the box's near edge are
    unknown, while the box's footprint up to that length, the road in front and the ground
    beside it stay known; without it, ``known`` is the frustum."""
    from dataclasses import replace

    import torch
    from model_helpers import TINY

    from bev_mapper_core.methods.bimapper.mapper import BiMapperMapper
    from bev_mapper_core.methods.bimapper.model import BiMapper
    from bev_mapper_core.methods.bimapper.weights import save_weights
    from bev_mapper_core.methods.ipm.occlusion import OBJECT_MAX_DEPTH_M

    grid, _ = box_scene
    rig = _level_rig()
    labels = _render(rig["front"], [(8.0, 12.0, -1.0, 1.0, 2.0, Label.VEHICLE),
                                    (8.0, 8.5, 3.75, 4.25, 0.5, Label.OBSTACLE)])
    torch.manual_seed(0)
    path = tmp_path / "box.safetensors"
    save_weights(BiMapper(replace(TINY, ipm_skip=True, classes=("drivable", "vehicle")), rig, grid).eval(), path)
    preds = {occ: BiMapperMapper(rig, grid, MapperConfig(backend="torch", weights=str(path), ipm_occlusion=occ)).map(
        {"front": labels}) for occ in (False, True)}
    xs, ys = grid.centers
    frustum = preds[False].known
    length = OBJECT_MAX_DEPTH_M[Label.VEHICLE]
    front = (xs > 3.0) & (xs < 7.5) & (np.abs(ys) < 0.6)
    depth = (xs > 8.2) & (xs < 8.0 + length - 0.2) & (np.abs(ys) < 0.6)  # may be the car: the model decides
    behind = (xs > 8.0 + length + 1.0) & (np.abs(ys) < 0.5) & frustum
    beside = (xs > 9.0) & (xs < 15.0) & (np.abs(ys) > 2.5) & (np.abs(ys) < 3.5)
    assert behind.sum() > 300 and frustum[front | depth | beside].all()
    honest = preds[True].known
    assert honest[front | depth | beside].all()
    assert not honest[behind].any()
    assert not (honest & ~frustum).any()  # the gate only removes cells
    np.testing.assert_array_equal(preds[True].probs, preds[False].probs)  # and changes no probability
    # a model that does not map vehicles keeps IPM's face-width depth: the box, seen end-on
    # (2 m wide), may reach 1.8 * 4.5 / 2 = 4.05 m, so the cells from 12.5 m on are withheld
    drivable_only = BiMapperMapper(rig, grid, MapperConfig(backend="torch", weights=str(path), classes=("drivable",)))
    known = drivable_only.map({"front": labels}).known
    assert known[depth & (xs < 11.5)].all()
    assert not known[depth & (xs > 12.6)].any()


def test_bimapper_keeps_a_pedestrian_a_camera_sees_and_withholds_its_shadow(tmp_path):
    """Issue #39: a 1.7 m pedestrian (0.4 m deep) 8 m ahead of a camera 1.5 m high hides every
    ground cell behind it. The cells up to the learned pedestrian depth beyond its near edge
    stay known, also those between IPM's 0.5 m footprint and that depth (withheld before,
    though the model maps a pedestrian seen there), and the farther cells of its shadow, whose
    pixel shows the pedestrian, are unknown."""
    from dataclasses import replace

    import torch
    from model_helpers import TINY

    from bev_mapper_core.methods.bimapper.mapper import BiMapperMapper
    from bev_mapper_core.methods.bimapper.model import BiMapper
    from bev_mapper_core.methods.bimapper.weights import save_weights
    from bev_mapper_core.methods.ipm.occlusion import NEAR_EDGE_SLACK_CELLS, OBJECT_FOOTPRINT_M, OBJECT_MAX_DEPTH_M

    grid = BevGrid(0.0, 40.0, -10.0, 10.0, 0.25)
    rig = _level_rig()
    labels = _render(rig["front"], [(8.0, 8.4, -0.2, 0.2, 1.7, Label.PEDESTRIAN)])
    torch.manual_seed(0)
    path = tmp_path / "ped.safetensors"
    save_weights(BiMapper(replace(TINY, ipm_skip=True, classes=("drivable", "pedestrian")), rig, grid).eval(), path)
    preds = {occ: BiMapperMapper(rig, grid, MapperConfig(backend="torch", weights=str(path), ipm_occlusion=occ)).map(
        {"front": labels}) for occ in (False, True)}
    xs, ys = grid.centers
    frustum = preds[False].known
    slack = NEAR_EDGE_SLACK_CELLS * grid.resolution
    ipm_end = 8.0 + OBJECT_FOOTPRINT_M[Label.PEDESTRIAN][1] + slack  # IPM's footprint reaches this far
    depth_end = 8.0 + OBJECT_MAX_DEPTH_M[Label.PEDESTRIAN] + slack
    column = np.abs(ys) < 0.2  # the cells right behind the pedestrian
    front = column & (xs > 3.0) & (xs < 7.8)
    body = column & (xs > 8.0) & (xs < 8.4)
    beyond_ipm = column & (xs > ipm_end + 0.1) & (xs < ipm_end + 0.4)  # unknown with IPM's 0.5 m
    shadow = column & (xs > max(depth_end, ipm_end + 0.4) + 0.5) & frustum
    assert beyond_ipm.sum() >= 2 and shadow.sum() > 100 and frustum[front | body | beyond_ipm].all()
    honest = preds[True].known
    assert honest[front | body | beyond_ipm].all()
    assert not honest[shadow].any()
    assert not (honest & ~frustum).any()
    np.testing.assert_array_equal(preds[True].probs, preds[False].probs)


def test_the_visibility_head_keeps_the_objects_a_camera_sees(tmp_path):
    """Issue #39: a visibility head that calls every cell unseen (its bias at -50) still lets
    the cells through that the camera sees as an object the model maps: the car's cells up to
    IPM's face-width depth (the box seen end-on, 2 m wide: 1.8 * 4.5 / 2 = 4.05 m) and the
    pedestrian's. The open road, the ground beside them and the car's shadow stay withheld.
    Without the line of sight (``ipm_occlusion`` false) or without an object class mapped, the
    head alone decides, as before."""
    from dataclasses import replace

    import torch
    from model_helpers import TINY

    from bev_mapper_core.methods.bimapper.mapper import BiMapperMapper
    from bev_mapper_core.methods.bimapper.model import BiMapper
    from bev_mapper_core.methods.bimapper.weights import save_weights

    grid = BevGrid(0.0, 40.0, -10.0, 10.0, 0.25)
    rig = _level_rig()
    labels = _render(rig["front"], [(8.0, 12.0, -1.0, 1.0, 2.0, Label.VEHICLE),
                                    (8.0, 8.4, 4.8, 5.2, 1.7, Label.PEDESTRIAN)])
    torch.manual_seed(0)
    model = BiMapper(replace(TINY, ipm_skip=True, visibility_head=True,
                             classes=("drivable", "vehicle", "pedestrian")), rig, grid).eval()
    with torch.no_grad():
        model.decoder.vis_head[-1].weight.zero_()
        model.decoder.vis_head[-1].bias.fill_(-50.0)  # p_visible ~ 0 everywhere
    path = tmp_path / "blind_head.safetensors"
    save_weights(model, path)

    def known(**kw):
        config = MapperConfig(backend="torch", weights=str(path), **{"unknown_below": 0.05, **kw})
        return BiMapperMapper(rig, grid, config).map({"front": labels}).known

    xs, ys = grid.centers
    frustum = known(unknown_below=0.0, ipm_occlusion=False)
    car = (xs > 8.2) & (xs < 11.8) & (np.abs(ys) < 0.8)
    person = (xs > 8.0) & (xs < 8.4) & (np.abs(ys - 5.0) < 0.2)
    road = (xs > 3.0) & (xs < 7.5) & (np.abs(ys) < 3.0)
    beside = (xs > 9.0) & (xs < 15.0) & (np.abs(ys) > 2.0) & (np.abs(ys) < 3.5)
    shadow = (xs > 13.0) & (np.abs(ys) < 0.5) & frustum
    assert car.sum() > 50 and person.sum() >= 2 and frustum[car | person | road | beside].all() and shadow.sum() > 300
    honest = known()
    assert honest[car | person].all()
    assert not honest[road | beside | shadow].any()
    assert not (honest & ~frustum).any()
    assert not known(ipm_occlusion=False).any()  # the head alone: nothing is seen
    # the layers asked for change nothing (the rule follows the classes the weights map) ...
    assert np.array_equal(known(classes=("drivable",)), honest)
    # ... weights that map no object class keep no object
    blind = BiMapper(replace(TINY, ipm_skip=True, visibility_head=True, classes=("drivable",)), rig, grid).eval()
    with torch.no_grad():
        blind.decoder.vis_head[-1].weight.zero_()
        blind.decoder.vis_head[-1].bias.fill_(-50.0)
    save_weights(blind, path)
    assert not known().any()
