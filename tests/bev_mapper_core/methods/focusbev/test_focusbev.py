"""FocusBEV: its blocks, geometry, losses, weights, memory bank and training (issue #14)."""

from __future__ import annotations

import json
from dataclasses import replace

import numpy as np
import pytest
import torch
from model_helpers import memory_focusbev

from bev_mapper_core.errors import ConfigError
from bev_mapper_core.geometry.grid import BevGrid
from bev_mapper_core.geometry.rig import preset_rig, scaled_camera
from bev_mapper_core.mapper import MapperConfig, create_mapper
from bev_mapper_core.methods.focusbev.blocks import (
    ColumnTransformer,
    EgoMotionFusion,
    depth_ranges,
    feature_grid,
    polar_grids,
    polar_to_cartesian,
)
from bev_mapper_core.methods.focusbev.losses import FocusBEVLossConfig, focusbev_loss, occupancy_agnostic_iou_loss, uncertainty_loss
from bev_mapper_core.methods.focusbev.model import FocusBEV, FocusBEVConfig, input_size
from bev_mapper_core.methods.focusbev.weights import load_focusbev, read_focusbev_metadata, save_focusbev
from bev_mapper_core.nn.bev_warp import warp_batch
from bev_mapper_core.nn.resnet import FPN, ResNet
from bev_mapper_core.nn.weights import WeightsError
from bev_mapper_core.training.config import TrainConfig
from bev_mapper_core.training.data import FrameSet, drive_poses, render_drive
from bev_mapper_core.training.sources import DataNeeds, InMemorySource
from bev_mapper_core.training.trainer import train

torch.set_num_threads(1)
RIG = preset_rig("front1")
GRID = BevGrid(0.0, 16.0, -8.0, 8.0, 0.5)  # 32 x 32 cells ahead
CLASSES = ("drivable", "vehicle", "lane_divider")
TINY = FocusBEVConfig(classes=CLASSES, input_width=64, backbone_width=8, fpn_levels=2, channels=16, decoder_layers=1,
                      heads=2, window=2, decoder_channels=8)


def _rgb(seed: int = 0) -> np.ndarray:
    w, h = RIG.cameras[0].model.image_size
    return np.random.default_rng(seed).integers(0, 256, (h, w, 3), dtype=np.uint8)


def _pose(x: float, yaw: float = 0.0) -> np.ndarray:
    T = np.eye(4)
    T[:2, :2] = [[np.cos(yaw), -np.sin(yaw)], [np.sin(yaw), np.cos(yaw)]]
    T[0, 3] = x
    return T


@pytest.fixture(scope="module")
def weights(tmp_path_factory):
    torch.manual_seed(0)
    model = FocusBEV(TINY, RIG, GRID)
    for p in model.parameters():  # random BatchNorm statistics too: every block matters to the output
        p.data.normal_(0, 0.2)
    path = tmp_path_factory.mktemp("fb") / "tiny.safetensors"
    save_focusbev(model.eval(), path, memory_interval_s=0.3)
    return path


# ------------------------------------------------------------------------ blocks
def test_resnet_and_fpn_strides_and_the_paper_size():
    x = torch.randn(1, 3, 64, 96)
    for depth in (18, 50):
        net = ResNet(depth, width=8)
        feats = net(x)
        assert [tuple(f.shape[-2:]) for f in feats] == [(16, 24), (8, 12), (4, 6), (2, 3)]
        levels = FPN(net.out_channels, 16, 4)(feats)
        assert [tuple(f.shape) for f in levels] == [(1, 16, 8, 12), (1, 16, 4, 6), (1, 16, 2, 3), (1, 16, 1, 2)]
    paper = FocusBEVConfig.paper()
    assert (paper.backbone_depth, paper.backbone_width, paper.channels, paper.decoder_layers, paper.heads,
            paper.window) == (50, 64, 256, 2, 4, 2)
    # the paper-size ResNet-50 itself, on a small input (its stage widths are the published ones)
    assert ResNet(50, 64).out_channels == [256, 512, 1024, 2048]


@pytest.mark.parametrize("layers", [0, 1, 2])
def test_column_transformer_reads_its_own_column_only(layers):
    torch.manual_seed(layers)
    t = ColumnTransformer(8, key_len=5, query_len=7, columns=4, layers=layers, heads=2)
    keys = torch.randn(2, 8, 5, 4, requires_grad=True)
    out = t(keys)
    assert out.shape == (2, 8, 7, 4)
    out[:, :, :, 1].sum().backward()  # column 1 of the output ...
    grad = keys.grad.abs().sum((0, 1, 2))
    assert grad[1] > 0 and torch.all(grad[[0, 2, 3]] == 0)  # ... depends on column 1 of the keys alone
    with pytest.raises(ValueError, match="expects"):
        t(torch.randn(1, 8, 6, 4))


def test_polar_resampling_lands_each_image_column_on_the_cells_the_camera_sees_there():
    """A one-hot image column and depth bin of the polar map light up exactly the Cartesian cells
    the core camera model projects onto that column at that depth (bilinear weights, computed
    here independently from ``CameraModel.project``)."""
    cam = scaled_camera(RIG.cameras[0], 64)
    fgrid = feature_grid(GRID, 2)
    ranges = depth_ranges(1.0, 20.0, 2)
    grids, valid = polar_grids(cam, fgrid, ranges)
    W_in = cam.model.image_size[0]
    D, Wl, j, d = 12, 8, 5, 3
    polar = torch.zeros(1, 1, D, Wl)
    polar[0, 0, d, j] = 1.0
    out = polar_to_cartesian([polar, torch.zeros(1, 1, D, Wl)], torch.from_numpy(grids), torch.from_numpy(valid))[0, 0]
    # the expectation from the camera model
    p = fgrid.points(0.0) @ np.linalg.inv(cam.ego_from_cam_array)[:3, :3].T + np.linalg.inv(cam.ego_from_cam_array)[:3, 3]
    uv, front = cam.model.project(p)
    z0, z1 = ranges[0]
    col = (uv[:, 0] + 0.5) * Wl / W_in - 0.5  # feature column coordinate of each cell
    row = (p[:, 2] - z0) / (z1 - z0) * D - 0.5
    want = np.clip(1 - np.abs(col - j), 0, None) * np.clip(1 - np.abs(row - d), 0, None)
    inside = front & (uv[:, 0] >= -0.5) & (uv[:, 0] < W_in - 0.5) & (p[:, 2] >= z0) & (p[:, 2] < z1)
    want = np.where(inside, want, 0.0).reshape(fgrid.shape)
    np.testing.assert_allclose(out.numpy(), want, atol=1e-5)
    assert (want > 0.5).sum() >= 1  # the ray does hit cells of this grid
    # the levels' ranges tile [min, max] (finest level farthest) and no cell is in two of them
    assert ranges[0][1] == pytest.approx(20.0) and ranges[-1][0] == pytest.approx(1.0)
    assert not (valid[0] & valid[1]).any()


def test_warping_by_a_known_ego_motion_moves_a_marker_by_the_exact_number_of_cells():
    g = BevGrid(0.0, 8.0, -4.0, 4.0, 0.5)  # 16 x 16
    feat = torch.zeros(2, 1, 16, 16)
    feat[:, 0, 8, 10] = 1.0
    # sample 0: the ego drove 2 cells forward since; sample 1: 3 cells to the left
    motion = torch.from_numpy(np.stack([_pose(1.0), _pose(0.0)]))
    motion[1, 1, 3] = 1.5
    moved, valid = warp_batch(feat, g, motion)
    assert moved[0, 0, 8, 8] == 1.0 and moved[0].sum() == 1.0  # forward: the marker comes 2 columns closer
    assert moved[1, 0, 5, 10] == 1.0 and moved[1].sum() == 1.0  # left: the marker moves 3 rows right (-y)
    assert not valid[0, :, -2:].any() and valid[0, :, :-2].all()  # cells beyond the old grid's edge


def test_ego_motion_fusion_uses_the_reference_where_history_is_missing():
    torch.manual_seed(0)
    g = BevGrid(0.0, 4.0, -2.0, 2.0, 1.0)
    fuse = EgoMotionFusion(4, 3, g).eval()
    cur, old = torch.randn(1, 4, 4, 4), torch.randn(1, 4, 4, 4)
    eye = torch.eye(4, dtype=torch.float64)[None]
    alone = fuse(cur, [])
    absent = fuse(cur, [(old, eye, torch.tensor([False])), (old, eye, torch.tensor([False]))])
    torch.testing.assert_close(alone, absent)  # an absent history frame is the reference itself
    present = fuse(cur, [(old, eye, torch.tensor([True]))])
    assert not torch.allclose(present, alone)
    hist = old.clone().requires_grad_(True)
    fuse.train()(cur, [(hist, eye, torch.tensor([True]))]).sum().backward()
    assert hist.grad is None  # no gradient into the history


def test_model_forward_backward_for_every_ablation_row():
    x = torch.randn(2, 3, *input_size(TINY, RIG))
    for over in ({}, dict(decoder_layers=0), dict(cycle=False), dict(window=1), dict(window=3)):
        torch.manual_seed(0)
        model = FocusBEV(replace(TINY, **over), RIG, GRID)
        out = model(x)
        assert out["logits"].shape == (2, 3, *GRID.shape) and out["bev"].shape == (2, 16, *model.fgrid.shape)
        out["logits"].mean().backward()
        unused = [n for n, p in model.named_parameters() if p.grad is None and "temporal" not in n]
        assert not unused, unused
    assert FocusBEV(replace(TINY, cycle=False), RIG, GRID).to_pv is None
    for bad in (dict(decoder_layers=9), dict(channels=15), dict(window=0), dict(backbone_depth=20),
                dict(min_depth=0.0), dict(max_depth=0.5), dict(cycle="yes")):
        with pytest.raises(ConfigError):
            replace(TINY, **bad)
    assert FocusBEVConfig.from_dict(json.loads(json.dumps(TINY.to_dict()))) == TINY


def test_losses():
    torch.manual_seed(0)
    logits = torch.randn(2, 3, 8, 8, requires_grad=True)
    target = (torch.rand(2, 3, 8, 8) > 0.7).float()
    mask = torch.rand(2, 8, 8) > 0.3
    total, parts = focusbev_loss(logits, target, mask, FocusBEVLossConfig(), torch.tensor([1.0, 2.0, 3.0]))
    total.backward()
    assert set(parts) == {"bce", "uncertainty", "iou", "total"} and logits.grad.abs().sum() > 0
    # uncertainty: 0 at p = 0.5 on the unseen cells, 1 where they are certain; seen cells do not count
    half = torch.zeros(1, 1, 2, 2)
    seen = torch.tensor([[[True, False], [False, False]]])
    assert uncertainty_loss(half, seen) == pytest.approx(0.0, abs=1e-6)
    assert uncertainty_loss(torch.full((1, 1, 2, 2), 30.0), seen) == pytest.approx(1.0, abs=1e-4)
    sure = torch.tensor([[[[30.0, 30.0], [-30.0, -30.0]]]])
    assert uncertainty_loss(sure, torch.tensor([[[False, True], [True, True]]])) == pytest.approx(1.0, abs=1e-4)
    # OA-IoU: 0 for a perfect map, 1 for a disjoint one, and it reads every cell (no mask)
    gt = torch.tensor([[[[1.0, 1.0], [0.0, 0.0]]]])
    assert occupancy_agnostic_iou_loss(sure, gt) == pytest.approx(0.0, abs=1e-4)
    assert occupancy_agnostic_iou_loss(-sure, gt) == pytest.approx(1.0, abs=1e-4)


# ------------------------------------------------------------------- weights + mapper
def test_weights_round_trip_and_refusals(weights, tmp_path):
    meta = read_focusbev_metadata(weights)
    assert meta["memory_interval_s"] == 0.3 and meta["config"]["window"] == 2
    model, _ = load_focusbev(weights, RIG, GRID)
    with pytest.raises(WeightsError, match="grid"):
        load_focusbev(weights, RIG, BevGrid(0.0, 16.0, -8.0, 8.0, 0.25))
    bad = tmp_path / "bad.safetensors"
    bad.write_bytes(b"\x80\x04not a safetensors file")
    with pytest.raises(WeightsError):
        read_focusbev_metadata(bad)
    with pytest.raises(ConfigError, match="FocusBEV is monocular"):
        create_mapper(preset_rig("surround6"), GRID, MapperConfig(method="focusbev", input_kind="rgb",
                                                                  weights=str(weights)))


def test_mapper_equals_the_model_and_fuses_the_frame_one_interval_back(weights):
    cfg = MapperConfig(backend="torch", method="focusbev", input_kind="rgb", weights=str(weights))
    a, b = _rgb(1), _rgb(2)
    fresh = create_mapper(RIG, GRID, cfg)
    single = fresh.map({"front": b}, _pose(0.0), 10**9)
    assert single.frames == 1 and single.note == "" and single.known.any() and not single.known.all()
    model, _ = load_focusbev(weights, RIG, GRID)
    with torch.no_grad():
        want = torch.sigmoid(model(model.preprocess(torch.from_numpy(b)[None, None]))["logits"])[0].numpy()
    np.testing.assert_allclose(single.probs, want, atol=1e-5)  # no history: the reference stands in

    m = create_mapper(RIG, GRID, cfg)
    m.map({"front": a}, _pose(0.0), 10**9)
    fused = m.map({"front": b}, _pose(2.0), 10**9 + 300_000_000)  # one interval later, 2 m on
    assert fused.frames == 2 and fused.note == ""
    assert np.abs(fused.probs - single.probs).max() > 1e-4  # the history changed the map
    with torch.no_grad():  # ... as the model fuses it: frame a's feature warped by the ego motion
        fa = model.bev_features(model.preprocess(torch.from_numpy(a)[None, None]))
        hist = [(fa, torch.from_numpy(np.linalg.inv(_pose(0.0)) @ _pose(2.0))[None], torch.tensor([True]))]
        fb = model.bev_features(model.preprocess(torch.from_numpy(b)[None, None]))
        want = torch.sigmoid(model.head(model.temporal(fb, hist))[0])[0].numpy()
    np.testing.assert_allclose(fused.probs, want, atol=1e-5)
    # a frame much closer in time than the interval is not used as that history
    m.reset()
    m.map({"front": a}, _pose(0.0), 10**9)
    near = m.map({"front": b}, _pose(0.1), 10**9 + 50_000_000)
    assert near.frames == 1


def test_memory_bank_resets_on_a_backward_stamp_and_without_a_pose(weights):
    cfg = MapperConfig(backend="torch", method="focusbev", input_kind="rgb", weights=str(weights))
    a, b = _rgb(1), _rgb(2)
    alone = create_mapper(RIG, GRID, cfg).map({"front": b}, _pose(0.0), 10**9)
    m = create_mapper(RIG, GRID, cfg)
    for k in range(4):
        m.map({"front": a}, _pose(0.5 * k), 10**9 + k * 100_000_000)
    looped = m.map({"front": b}, _pose(0.0), 10**9)  # a bag loop: back to the first stamp
    assert looped.frames == 1 and "stamp went back" in looped.note
    np.testing.assert_allclose(looped.probs, alone.probs, atol=1e-6)
    m.map({"front": a}, _pose(0.0), 2 * 10**9)
    nopose = m.map({"front": b}, None, 2 * 10**9 + 300_000_000)
    assert nopose.frames == 1 and "no ego pose" in nopose.note
    np.testing.assert_allclose(nopose.probs, alone.probs, atol=1e-6)
    after = m.map({"front": b}, _pose(0.0), 2 * 10**9 + 600_000_000)  # the bank was dropped with the pose
    assert after.frames == 1 and after.note == ""
    bad = m.map({"front": b}, np.full((4, 4), np.nan), 3 * 10**9)
    assert "not a finite rigid" in bad.note
    jump = create_mapper(RIG, GRID, cfg)
    jump.map({"front": a}, _pose(0.0), 10**9)
    assert "jumped" in jump.map({"front": b}, _pose(40.0), 10**9 + 300_000_000).note
    # a short camera drop-out keeps the bank (the frame 0.3 s back is still there), a long one drops it
    gap = create_mapper(RIG, GRID, cfg)
    for k in (0, 1, 2):
        gap.map({"front": a}, _pose(0.5 * k), 10**9 + k * 100_000_000)
    assert gap.map({"front": b}, _pose(2.5), 10**9 + 500_000_000).frames == 2  # 0.3 s of missing frames
    late = gap.map({"front": b}, _pose(3.0), 10**9 + 1_500_000_000)  # 1 s without a frame
    assert late.frames == 1 and "since the previous frame" in late.note


def test_preflight_refuses_what_the_weights_cannot_serve(weights):
    from bev_mapper_core.mapper import preflight

    cfg = MapperConfig(backend="torch", method="focusbev", input_kind="rgb", weights=str(weights))
    preflight(cfg, "front1", GRID, ("front",))
    with pytest.raises(WeightsError, match="grid"):
        preflight(cfg, "front1", BevGrid(0.0, 32.0, -16.0, 16.0, 0.25), ("front",))
    with pytest.raises(WeightsError, match="configured input is 'labels'"):
        preflight(replace(cfg, input_kind="labels"), "front1", GRID, ("front",))
    with pytest.raises(WeightsError, match="classes"):
        preflight(replace(cfg, classes=("sidewalk",)), "front1", GRID, ("front",))
    with pytest.raises(ConfigError, match="FocusBEV is monocular"):
        preflight(cfg, "surround6", GRID, ("front", "back"))
    with pytest.raises(ConfigError, match="no FocusBEV weights given and none shipped for rig 'front1' / input 'labels'"):
        preflight(replace(cfg, weights=None, input_kind="labels"), "front1", GRID, ("front",))


# ------------------------------------------------------------------------- training
def test_windows_stay_inside_their_drive():
    n = 5
    fs = FrameSet(np.zeros((n, 1, 2, 2), np.uint8), np.zeros((n, 1, 2, 2), bool), np.ones((n, 2, 2), bool),
                  camera_names=("front",), poses=np.stack([_pose(float(i)) for i in range(n)]),
                  stamps=np.arange(n, dtype=np.int64), drives=np.array([0, 0, 0, 1, 1]))
    ids, present = fs.windows(np.array([0, 2, 3, 4]), 3)
    assert ids.tolist() == [[0, 0, 0], [0, 1, 2], [3, 3, 3], [4, 3, 4]]  # absent: the frame itself
    assert present.tolist() == [[False, False, True], [True, True, True], [False, False, True], [False, True, True]]
    fs.window = 3
    b = fs.batch(np.array([4]))
    assert b["images"].shape == (1, 3, 1, 2, 2) and b["poses"].shape == (1, 3, 4, 4) and b["target"].shape == (1, 1, 2, 2)


def test_cached_drives_carry_the_poses_of_their_world():
    d = render_drive(RIG, GRID, CLASSES, seed=5, frames=3, stride=2)
    poses, stamps = drive_poses(5, 3, 2)
    np.testing.assert_array_equal(d["poses"], poses)
    np.testing.assert_array_equal(d["stamps"], stamps)
    assert np.all(np.diff(stamps) == 200_000_000)  # 2 steps at 10 Hz


def test_training_run_on_windows_through_the_trainer(tmp_path):
    """A tiny run on in-memory drives with poses: the trainer feeds windows, and the saved weights
    map through ``create_mapper`` with their memory interval."""
    rng = np.random.default_rng(0)
    h, w = input_size(TINY, RIG)

    def frames(n_drives, per=3):
        n = n_drives * per
        poses = np.stack([_pose(0.8 * (i % per)) for i in range(n)])
        return FrameSet(np.zeros((n, 1, h, w), np.uint8), rng.random((n, 3, *GRID.shape)) > 0.6,
                        np.ones((n, *GRID.shape), bool), camera_names=("front",),
                        rgb=rng.integers(0, 256, (n, 1, h, w, 3), dtype=np.uint8), poses=poses,
                        stamps=np.tile(np.arange(per) * 300_000_000, n_drives),
                        drives=np.repeat(np.arange(n_drives), per))

    cfg = TrainConfig.from_dict(dict(method="focusbev", rig="front1", classes=",".join(CLASSES), epochs=2, batch=2,
                                     lr=1e-3, seed=1, stride=3, threads=1, progress=False, input="rgb",
                                     grid=[0.0, 16.0, -8.0, 8.0, 0.5], out=str(tmp_path / "run"),
                                     **{k: v for k, v in TINY.to_dict().items() if k not in ("classes", "input_kind")}))
    src = InMemorySource(frames(2), frames(1))
    src.check(DataNeeds(sequence_length=2, poses=True, rgb=True))
    doc = train(cfg, log=lambda m: None, data=src)
    assert doc["epoch"] == 1 and doc["step"] == 6  # 0-based: 2 epochs of 3 windows of 2
    meta = read_focusbev_metadata(tmp_path / "run" / "best.safetensors")
    assert meta["memory_interval_s"] == pytest.approx(0.3) and meta["config"]["window"] == 2
    m = create_mapper(RIG, GRID, MapperConfig(backend="torch", method="focusbev", input_kind="rgb",
                                              weights=str(tmp_path / "run" / "best.safetensors")))
    assert m.map({"front": _rgb()}, _pose(0.0), 1).probs.shape == (3, *GRID.shape)


# ------------------------------------------------------------------------- the bag tool
@pytest.mark.slow
def test_replay_maps_a_front1_bag_with_focusbev_and_its_memory(tmp_path):
    """``bev-bag replay --method focusbev --input rgb`` on a front1 bag with odometry: weights with a
    memory bank (the shipped file maps each frame alone), the bag's frames in order with their
    poses; the output grids equal the core mapper fed the same frames in order, and from the third
    frame on the memory bank is used."""
    from bags.cli.main import main
    from bags.io.reader import BagReader
    from bags.replay import BAG_DIR, METRICS_FILE
    from bev_mapper_core.geometry.grid import grid_preset

    bag, out = tmp_path / "bag", tmp_path / "out"
    assert main(["synth", str(bag), "--rig", "front1", "--grid", "ahead", "--frames", "4", "--seed", "950000015"]) == 0
    weights = memory_focusbev(tmp_path / "focusbev_w2.safetensors")
    assert main(["replay", str(bag), "--out", str(out), "--method", "focusbev", "--backend", "torch", "--input", "rgb", "--no-pictures",
                 "--no-report", "--quiet", "--weights", weights]) == 0
    m = json.loads((out / METRICS_FILE).read_text())
    assert m["method"] == "focusbev" and 0.0 < m["miou"] <= 1.0
    # FocusBEV's own memory is counted (issue #29): 1 + 1 + 2 + 2 frames fused, nothing reset
    assert m["temporal"]["method"] == {"fused_frames": 6, "resets": 0, "frames_without_pose": 0}
    assert sum(m["temporal"]["odometry_problems"].values()) == 0
    with BagReader(bag) as r:
        mapper = create_mapper(r.rig(), r.grid(), MapperConfig(backend="torch", method="focusbev", input_kind="rgb",
                                                               weights=weights))
        preds = [(f.stamp_ns, mapper.map(f.rgb, f.odom.world_from_ego, f.stamp_ns)) for f in r.frames(labels=False)]
    assert [p.frames for _, p in preds] == [1, 1, 2, 2]
    with BagReader(out / BAG_DIR) as r:
        got = {}
        for msg in r.messages(["/bev/drivable"]):
            got[msg.msg.header.stamp.sec * 1_000_000_000 + msg.msg.header.stamp.nanosec] = np.asarray(msg.msg.data)
    assert sorted(got) == [s for s, _ in preds]
    ci = mapper.class_names.index("drivable")
    for stamp, pred in preds:
        np.testing.assert_array_equal(got[stamp], grid_preset("ahead").to_occupancy(pred.probs[ci], pred.known))


@pytest.mark.slow
def test_replay_counts_focusbevs_frames_without_odometry(tmp_path):
    """A front1 bag without /odom (issue #29): FocusBEV maps every frame alone and says so in
    ``metrics.json``: ``temporal.method.frames_without_pose`` and ``odometry_problems.no_pose``."""
    from bags.cli.main import main
    from bags.io import topics as T
    from bags.io.reader import BagReader
    from bags.io.writer import BagWriter
    from bags.replay import METRICS_FILE

    bag, out = tmp_path / "bag", tmp_path / "out"
    assert main(["synth", str(bag), "--rig", "front1", "--grid", "ahead", "--frames", "3", "--seed", "950000016"]) == 0
    bare = tmp_path / "no_odom"
    with BagReader(bag) as r, BagWriter(bare) as w:
        for key, value in r.custom_data.items():
            w.set_custom_data(key, value)
        for topic, info in r.topics.items():
            if topic not in (T.ODOM, T.TF):
                w.add_topic(topic, info.msgtype, latched=topic in r.latched_topics)
        for msg in r.messages():
            if msg.topic not in (T.ODOM, T.TF):
                w.write(msg.topic, msg.msg, msg.log_ns)
    assert main(["replay", str(bare), "--out", str(out), "--method", "focusbev", "--backend", "torch", "--input", "rgb",
                 "--no-pictures", "--no-report", "--quiet",  # torch: no ONNX export on a fresh machine
                 "--weights", memory_focusbev(tmp_path / "focusbev_w2.safetensors")]) == 0
    m = json.loads((out / METRICS_FILE).read_text())
    assert m["temporal"]["method"] == {"fused_frames": 3, "resets": 0, "frames_without_pose": 3}
    assert m["temporal"]["odometry_problems"]["no_pose"] == 3
