"""Bi-Mapper model, geometry tables, losses, weights files and the Mapper adapter (tiny configs, CPU)."""

import math
import pickle
from dataclasses import replace

import cv2
import numpy as np
import pytest
import torch
from model_helpers import CAM_MODEL, CLASSES, GRID, RIG, TINY, batch, flat_label, random_labels, render

from bev_mapper_core.errors import BevMapperError, ConfigError
from bev_mapper_core.geometry.grid import BevGrid
from bev_mapper_core.geometry.projection import ground_tables, remap_table
from bev_mapper_core.geometry.rig import Rig
from bev_mapper_core.geometry.transforms import ego_from_optical, transform_points
from bev_mapper_core.labels.classes import label_lut, resolve_classes
from bev_mapper_core.mapper import MapperConfig
from bev_mapper_core.methods.bimapper.config import BiMapperConfig
from bev_mapper_core.methods.bimapper.geometry import BiMapperGeometry
from bev_mapper_core.methods.bimapper.losses import BiMapperLossConfig, bimapper_loss, mutual_loss, mutual_teachers, warp_target_to_planes
from bev_mapper_core.methods.bimapper.lv import merge_planes_to_ego, warp_to_planes
from bev_mapper_core.methods.bimapper.mapper import BiMapperMapper
from bev_mapper_core.methods.bimapper.model import BiMapper
from bev_mapper_core.methods.bimapper.weights import load_bimapper, load_state, save_weights
from bev_mapper_core.methods.ipm.mapper import IpmMapper
from bev_mapper_core.nn.config import RGB_MEAN, RGB_STD
from bev_mapper_core.nn.efficientnet import EfficientNet, EfficientNetConfig, round_filters
from bev_mapper_core.nn.weights import WeightsError

# One thread: on this project's 2 shared cores, 2 OpenMP threads spin-wait for a busy core
# (this module took 24-30 s with 2 threads and 4-7 s with 1, back to back under load).
torch.set_num_threads(1)


# ----------------------------------------------------------------- encoder
def test_efficientnet_b0_table_and_truncation():
    b0 = EfficientNet(EfficientNetConfig.variant("b0"))
    assert len(b0.blocks) == 16
    assert b0.endpoint_channels == (16, 24, 40, 112, 320) and b0.endpoint_strides == (2, 4, 8, 16, 32)
    assert len(EfficientNet(EfficientNetConfig.variant("b4")).blocks) == 32
    assert round_filters(320, 1.4) == 448 and round_filters(32, 0.25) == 8
    small = EfficientNet(EfficientNetConfig.variant("b0", width_mult=0.5, num_stages=4, in_channels=11))
    outs = small(torch.zeros(1, 11, 63, 112))
    assert [tuple(o.shape[-2:]) for o in outs] == [(32, 56), (16, 28), (8, 14), (4, 7)]
    with pytest.raises(ConfigError):
        EfficientNetConfig.variant("b9")


def test_paper_b0_config_forward_at_tiny_input():
    grid = BevGrid(x_min=-6, x_max=6, y_min=-3, y_max=3, resolution=0.15)  # 40 x 80
    cfg = BiMapperConfig.paper(classes=CLASSES, input_width=64, plane_shape=(32, 16))
    model = BiMapper(cfg, RIG, grid).eval()
    trunk = model.cam_encoder.trunk
    assert trunk.endpoint_channels[-1] == 320 and len(trunk.blocks) == 16 and model.feat_hw == (8, 16)
    assert model.cam_encoder.stride == 16 and cfg.plane_height == 1.0 and cfg.bev_downsample == 5
    with torch.no_grad():
        out = model(batch(1)["images"])
    assert out["logits"].shape == (1, 3, 40, 80)
    assert out["lv_plane_logits"].shape == (1, 2, 3, 32, 16)


# ------------------------------------------------------ streams and losses
@pytest.mark.parametrize("streams,fusion,kind", [("gv", "sum", "labels"), ("lv", "sum", "labels"),
                                                 ("both", "sum", "labels"), ("both", "concat", "rgb")])
def test_forward_backward_every_stream(streams, fusion, kind):
    torch.manual_seed(0)
    model = BiMapper(replace(TINY, streams=streams, fusion=fusion, input_kind=kind), RIG, GRID)
    b = batch(2, kind)
    out = model(b["images"])
    assert out["logits"].shape == (2, 3, *GRID.shape)
    loss, parts = bimapper_loss(out, b, epoch=10)
    loss.backward()
    assert math.isfinite(parts["total"]) and parts["bce"] > 0
    assert (parts["asl"] > 0) == (streams != "gv") and (parts["mutual"] > 0) == (streams == "both")
    groups = {"gv": ["cam_encoder", "gv"], "lv": ["lv"], "both": ["cam_encoder", "gv", "lv"]}[streams]
    for g in groups + ["decoder"]:
        grads = [p.grad for p in getattr(model, g).parameters()]
        assert all(gr is not None for gr in grads), g
        assert sum(float(gr.abs().sum()) for gr in grads) > 0, g


def test_mutual_schedule_switches_at_epoch_n():
    assert [mutual_teachers(e, 4) for e in range(6)] == [(True, False)] * 4 + [(True, True)] * 2
    assert mutual_teachers(0, 4, "sync") == (True, True) and mutual_teachers(9, 4, "none") == (False, False)
    assert mutual_teachers(9, 4, "lv") == (True, False) and mutual_teachers(0, 4, "gv") == (False, True)
    # Before N the LV teacher is detached: the mutual loss moves GV only; from N it moves LV too.
    torch.manual_seed(0)
    model = BiMapper(TINY, RIG, GRID)
    out = model(batch(1)["images"])
    for epoch, lv_learns in ((3, False), (4, True)):
        model.zero_grad()
        lv_t, gv_t = mutual_teachers(epoch, 4)
        mutual_loss(out["gv_fg_logits"], out["lv_fg_logits"], out["lv_coverage"], lv_t, gv_t).backward(retain_graph=True)
        lv_grad = sum(float(p.grad.abs().sum()) for p in model.lv.parameters() if p.grad is not None)
        gv_grad = sum(float(p.grad.abs().sum()) for p in model.gv.parameters() if p.grad is not None)
        assert gv_grad > 0 and (lv_grad > 0) == lv_learns


@pytest.mark.slow  # a training run
def test_short_training_lowers_the_loss():
    torch.manual_seed(0)
    model = BiMapper(TINY, RIG, GRID)
    b = batch(2)
    opt = torch.optim.Adam(model.parameters(), 3e-3)
    losses = []
    for step in range(30):
        loss, _ = bimapper_loss(model(b["images"]), b, epoch=step // 10, config=BiMapperLossConfig(mutual_start_epoch=2))
        opt.zero_grad()
        loss.backward()
        opt.step()
        losses.append(loss.item())
    assert np.mean(losses[-3:]) < 0.6 * np.mean(losses[:3]), losses


# ----------------------------------------------------------------- geometry
def test_asl_target_warp_agrees_with_core_projection():
    spec = replace(TINY.plane_spec(), shape=(104, 40))  # 0.25 m plane cells, finer than the 0.5 m grid
    geo = BiMapperGeometry(RIG, GRID, TINY.input_width, spec, TINY.bev_downsample)
    gt_grid, gt_valid = torch.from_numpy(geo.gt_grid), torch.from_numpy(geo.gt_valid)
    for n, cam in enumerate(RIG.cameras):
        x, y = (8.2, -1.3) if cam.name == "front" else (-9.7, 1.8)
        r, c = GRID.metric_to_cell(x, y)
        tgt = torch.zeros(1, 1, *GRID.shape)
        tgt[0, 0, r, c] = 1.0
        warped, valid = warp_target_to_planes(tgt, gt_grid, gt_valid)
        hot = (warped[0, n, 0] > 0.5).numpy() & valid[0, n].numpy()
        assert hot.sum() == 4 and not (warped[0, 1 - n, 0] > 0.5).any()  # 2x2 plane cells per grid cell
        # Independently: the cell centre's pixel (camera.project) vs the hot plane cells' pixels (remap_table).
        scaled = replace(cam, model=cam.model.scaled(TINY.input_width / cam.model.image_size[0]))
        cx, cy = GRID.cell_to_metric(r, c)
        uv, front = scaled.model.project(transform_points(scaled.cam_from_ego, np.array([[cx, cy, 0.0]])))
        table = remap_table(scaled, transform_points(cam.ego_from_cam_array, spec.points_cam(cam)), spec.shape)
        assert front[0] and table.valid[hot].all()
        centroid = np.array([table.map_x[hot].mean(), table.map_y[hot].mean()])
        assert np.linalg.norm(centroid - uv[0]) < 0.5, (centroid, uv)  # within plane-cell quantisation
        corners = np.array([[cx + dx, cy + dy, 0.0] for dx in (-0.25, 0.25) for dy in (-0.25, 0.25)])
        quad, _ = scaled.model.project(transform_points(scaled.cam_from_ego, corners))  # the cell's footprint
        for u, v in zip(table.map_x[hot], table.map_y[hot]):
            assert quad[:, 0].min() < u < quad[:, 0].max() and quad[:, 1].min() < v < quad[:, 1].max()


def test_merge_puts_plane_feature_into_expected_ego_cell():
    model = BiMapper(TINY, RIG, GRID)
    spec = TINY.plane_spec()
    fgrid = replace(GRID, resolution=GRID.resolution * TINY.bev_downsample)
    checked = 0
    for n, cam in enumerate(RIG.cameras):
        pts = transform_points(cam.ego_from_cam_array, spec.points_cam(cam)).reshape(*spec.shape, 3)
        for i, j in [(0, 2), (3, 5), (6, 1), (4, 8), (9, 3)]:
            ex, ey = pts[i, j, 0], pts[i, j, 1]
            if not (fgrid.contains(ex, ey) and model.ipm_valid[n, i, j]):
                continue
            planes = torch.zeros(1, 2, 1, *spec.shape)
            planes[0, n, 0, i, j] = 1.0
            ego, cov = merge_planes_to_ego(planes, model.merge_grid, model.merge_weight)
            flat = int(ego[0, 0].argmax())
            assert ego[0, 0].max() > 0 and divmod(flat, fgrid.width) == fgrid.metric_to_cell(ex, ey), (cam.name, i, j)
            checked += 1
    assert checked >= 6
    # Overlapping cameras are averaged; absent cameras are left out.
    g = torch.zeros(2, 1, 1, 2)
    planes = torch.stack([torch.full((1, 2, 2), 1.0), torch.full((1, 2, 2), 3.0)])[None]  # (1, 2, 1, 2, 2)
    ego, cov = merge_planes_to_ego(planes, g, torch.ones(2, 1, 1))
    assert float(ego) == pytest.approx(2.0) and float(cov) == 1.0
    ego, _ = merge_planes_to_ego(planes, g, torch.ones(2, 1, 1), torch.tensor([[True, False]]))
    assert float(ego) == pytest.approx(1.0)


def test_lv_ipm_input_matches_flat_world():
    model = BiMapper(TINY, RIG, GRID)
    x = model.preprocess(batch(1)["images"])
    lab = warp_to_planes(x, model.ipm_grid, model.ipm_valid, "nearest")[0].argmax(1).numpy()  # (N, Hp, Wp)
    spec = TINY.plane_spec()
    _, zz = spec.centers()
    for n, cam in enumerate(RIG.cameras):
        pts = transform_points(cam.ego_from_cam_array, spec.points_cam(cam))
        exp = flat_label(pts[:, 0], pts[:, 1]).reshape(spec.shape)
        v = model.ipm_valid[n].numpy() & (zz < 12)  # 48 px wide input: far cells alias
        assert v.sum() > 50 and (lab[n][v] == exp[v]).mean() > 0.9


def test_lv_full_res_samples_the_camera_size_images():
    """lv_full_res: same tables (normalised coordinates), camera-size input: at least as exact."""
    model = BiMapper(replace(TINY, lv_full_res=True), RIG, GRID)
    raw = batch(1)["images"]  # (1, N, 40, 64): larger than the 48-px model input
    spec = TINY.plane_spec()
    acc = {}
    for name, x in (("full", model.preprocess(raw, resize=False)), ("small", model.preprocess(raw))):
        lab = warp_to_planes(x, model.ipm_grid, model.ipm_valid, "nearest")[0].argmax(1).numpy()
        hits = total = 0
        for n, cam in enumerate(RIG.cameras):
            pts = transform_points(cam.ego_from_cam_array, spec.points_cam(cam))
            exp = flat_label(pts[:, 0], pts[:, 1]).reshape(spec.shape)
            v = model.ipm_valid[n].numpy()
            hits, total = hits + (lab[n][v] == exp[v]).sum(), total + v.sum()
        acc[name] = hits / total
    assert acc["full"] >= acc["small"] and acc["full"] > 0.95, acc
    # The flag really routes the camera-size input to LV (same weights, other plane logits) ...
    plain = BiMapper(TINY, RIG, GRID)
    plain.load_state_dict(model.state_dict())
    model.eval(), plain.eval()
    with torch.no_grad():
        a, b = model(raw)["lv_plane_logits"], plain(raw)["lv_plane_logits"]
    assert a.shape == b.shape and not torch.allclose(a, b)
    # ... and trains: gradients reach the LV stream.
    model.train()
    bt = batch(2)
    loss, _ = bimapper_loss(model(bt["images"]), bt, epoch=0)
    loss.backward()
    assert sum(float(p.grad.abs().sum()) for p in model.lv.parameters() if p.grad is not None) > 0


def test_ipm_skip_starts_at_the_ipm_baseline():
    """Untrained, an ipm_skip model decides exactly as the classical IpmMapper (no occlusion
    reasoning), cell for cell: the prior's gather reproduces cv2.remap's nearest pixel and the
    camera averaging. Random labels make every geometry slip visible."""
    torch.manual_seed(0)
    model = BiMapper(replace(TINY, ipm_skip=True), RIG, GRID).eval()
    ipm = IpmMapper(RIG, GRID, MapperConfig(method="ipm", classes=CLASSES, ipm_occlusion=False))
    raw = random_labels(3)
    for present in ((True, True), (False, True), (True, False)):
        imgs = {c.name: raw[0, n].numpy() for n, c in enumerate(RIG.cameras) if present[n]}
        ref = ipm.map(imgs)
        mask = torch.tensor([present])
        with torch.no_grad():
            p = torch.sigmoid(model(raw, mask)["logits"][0]).numpy()
            prior = model.ipm_prior(raw, mask)[0].numpy()  # (L + 1, H, W)
        k = ref.known
        assert k.sum() > 100
        np.testing.assert_array_equal(prior[-1] > 0, k)
        lut = label_lut(resolve_classes(CLASSES)).astype(np.float32)  # (L, K)
        np.testing.assert_allclose(np.einsum("lk,lhw->khw", lut, prior[:-1]), ref.probs, atol=1e-6)
        assert (ref.probs[:, k] > 0.5).any() and (ref.probs[:, k] < 0.5).any()
        np.testing.assert_array_equal(p[:, k] > 0.5, ref.probs[:, k] > 0.5)


def test_ipm_skip_rgb_prior_is_the_nearest_colour_mosaic():
    model = BiMapper(replace(TINY, ipm_skip=True, input_kind="rgb"), RIG, GRID)
    rgb = np.random.default_rng(4).integers(0, 256, size=(len(RIG.cameras), 40, 64, 3), dtype=np.uint8)
    prior = model.ipm_prior(torch.from_numpy(rgb)[None])[0].numpy()  # (3 + 1, H, W)
    acc = np.zeros((*GRID.shape, 3))
    cnt = np.zeros(GRID.shape)
    for n, t in enumerate(ground_tables(RIG, GRID).values()):
        acc[t.valid] += t.warp(rgb[n], cv2.INTER_NEAREST)[t.valid] / 255.0
        cnt += t.valid
    exp = (acc / np.maximum(cnt, 1)[..., None] - np.array(RGB_MEAN)) / np.array(RGB_STD)
    k = cnt > 0
    np.testing.assert_allclose(np.moveaxis(prior[:3], 0, -1)[k], exp[k], atol=1e-4)
    np.testing.assert_array_equal(prior[3] > 0, k)


def test_ipm_skip_trains_every_part_and_needs_its_prior():
    torch.manual_seed(0)
    model = BiMapper(replace(TINY, ipm_skip=True), RIG, GRID)
    b = batch(2)
    opt = torch.optim.Adam(model.parameters(), 1e-3)
    for _ in range(2):  # step 1: only the head's zero-initialised last layer and ipm_proj move
        loss, _ = bimapper_loss(model(b["images"]), b, epoch=10)
        opt.zero_grad()
        loss.backward()
        opt.step()
    for g in ("cam_encoder", "gv", "lv", "decoder", "ipm_proj"):
        grads = [p.grad for p in getattr(model, g).parameters() if p.grad is not None]
        assert grads and sum(float(gr.abs().sum()) for gr in grads) > 0, g
    with pytest.raises(ValueError, match="IPM prior"):
        model.forward_preprocessed(model.preprocess(b["images"]))
    with pytest.raises(ValueError, match="do not match"):  # not the calibration's image size
        model(b["images"][:, :, :20])
    # the ablation control without streams: only the prior and the head learn
    with pytest.raises(ConfigError, match="needs ipm_skip"):
        replace(TINY, streams="none")
    bare = BiMapper(replace(TINY, ipm_skip=True, streams="none"), RIG, GRID)
    assert not hasattr(bare, "cam_encoder") and not hasattr(bare, "lv")
    loss, parts = bimapper_loss(bare(b["images"]), b, epoch=10)
    loss.backward()
    assert parts["asl"] == 0 and parts["mutual"] == 0 and float(bare.ipm_proj.weight.grad.abs().sum()) > 0
    other = Rig("mixed", (RIG.cameras[0], replace(RIG.cameras[1], model=CAM_MODEL.scaled(2.0))))
    with pytest.raises(ConfigError, match="different sizes"):  # the full-resolution LV input batches them
        BiMapper(replace(TINY, lv_full_res=True), other, GRID)
    mixed = BiMapper(replace(TINY, ipm_skip=True), other, GRID)  # the prior gathers each from its own image (#38)
    assert mixed.raw_hw is None


# ------------------------------------------------------------------ weights
@pytest.fixture(scope="module")
def saved(tmp_path_factory):
    torch.manual_seed(1)
    model = BiMapper(TINY, RIG, GRID)
    b = batch(2)
    opt = torch.optim.Adam(model.parameters(), 1e-3)
    for _ in range(2):  # move BN statistics away from their initial values
        loss, _ = bimapper_loss(model(b["images"]), b, epoch=0)
        opt.zero_grad()
        loss.backward()
        opt.step()
    path = tmp_path_factory.mktemp("w") / "tiny.safetensors"
    save_weights(model.eval(), path)
    return model, path


def test_weights_round_trip_is_exact(saved):
    model, path = saved
    loaded = load_bimapper(path, RIG, GRID, input_kind="labels", classes=CLASSES)
    x = batch(1)["images"]
    with torch.no_grad():
        assert torch.equal(model(x)["logits"], loaded(x)["logits"])


def test_bad_weights_files_are_rejected(saved, tmp_path):
    model, path = saved
    data = path.read_bytes()
    (tmp_path / "trunc.safetensors").write_bytes(data[: len(data) // 2])
    (tmp_path / "pickle.safetensors").write_bytes(pickle.dumps(model.state_dict()))
    torch.save(model.state_dict(), tmp_path / "torchsave.pt")
    for bad in ("trunc.safetensors", "pickle.safetensors", "torchsave.pt", "missing.safetensors"):
        with pytest.raises(WeightsError, match="safetensors|does not exist"):
            load_bimapper(tmp_path / bad, RIG)
    with pytest.raises(WeightsError, match="classes"):
        load_bimapper(path, RIG, classes=("drivable",))
    with pytest.raises(WeightsError, match="input kind"):
        load_bimapper(path, RIG, input_kind="rgb")
    with pytest.raises(WeightsError, match="rig"):
        load_bimapper(path, replace(RIG, name="other"))
    with pytest.raises(WeightsError, match="grid"):
        load_bimapper(path, RIG, replace(GRID, x_max=14.0))
    with pytest.raises(WeightsError, match="architecture differs"):
        load_state(BiMapper(replace(TINY, bev_channels=12), RIG, GRID), path)
    # Tensor-level tampering with consistent metadata: wrong shape, missing and extra tensors.
    from safetensors import safe_open
    from safetensors.torch import save_file
    with safe_open(str(path), framework="pt") as f:
        meta = f.metadata()
        tensors = {k: f.get_tensor(k) for k in f.keys()}
    cases = {
        "shape": {**tensors, "gv.b1": torch.zeros(2, 7)},
        "missing": {k: v for k, v in tensors.items() if k != "decoder.head.1.weight"},
        "unexpected": {**tensors, "extra.weight": torch.zeros(1)},
    }
    for what, ts in cases.items():
        p = tmp_path / f"{what}.safetensors"
        save_file(ts, str(p), metadata=meta)
        with pytest.raises(WeightsError, match=what):
            load_bimapper(p, RIG)
    assert issubclass(WeightsError, BevMapperError)


# ------------------------------------------------------------------- mapper
def test_mapper_adapter(saved):
    _, path = saved
    mapper = BiMapperMapper(RIG, GRID, MapperConfig(backend="torch", method="bimapper", weights=str(path)))
    assert mapper.class_names == CLASSES
    imgs = {c.name: render(c) for c in RIG.cameras}
    pred = mapper.map(imgs)
    assert pred.probs.shape == (3, *GRID.shape) and pred.probs.dtype == np.float32
    assert 0.0 <= pred.probs.min() and pred.probs.max() <= 1.0
    xs, _ = GRID.centers
    assert pred.known[xs > 4].mean() > 0.5 and pred.known[xs < -4].mean() > 0.5
    only_front = mapper.map({"front": imgs["front"]})
    assert only_front.known[xs < -4].sum() == 0 and only_front.known[xs > 4].any()
    mapper.set_rig(RIG.with_camera(replace(RIG["back"], ego_from_cam=ego_from_optical((-1.2, 0.0, 1.6), yaw=math.pi))))
    assert mapper.map(imgs).probs.shape == (3, *GRID.shape)
    with pytest.raises(ConfigError, match="segmenter is 'none'"):  # label weights on RGB need a segmenter
        BiMapperMapper(RIG, GRID, MapperConfig(method="bimapper", weights=str(path), input_kind="rgb", segmenter="none"))
    # a subset of the weights' classes, in another order: those layers only
    sub = BiMapperMapper(RIG, GRID, MapperConfig(backend="torch", method="bimapper", weights=str(path), classes=("sidewalk", "drivable")))
    part = sub.map(imgs)
    assert sub.class_names == ("sidewalk", "drivable")
    np.testing.assert_allclose(part.probs, pred.probs[[2, 0]], atol=1e-6)
    with pytest.raises(WeightsError, match="not among the weights' classes"):
        BiMapperMapper(RIG, GRID, MapperConfig(method="bimapper", weights=str(path), classes=("vehicle",)))
    with pytest.raises(WeightsError, match="trained for grid .* use weights trained for this grid; methods that run"):
        BiMapperMapper(RIG, GRID, MapperConfig(method="bimapper"))  # no weights of its own: the weights for any rig


@pytest.mark.parametrize("flag", ["ipm_skip", "lv_full_res"])
def test_mapper_feeds_camera_size_images(flag, tmp_path):
    """Models that read the camera-size images get them through the Mapper too (not only the
    model input resized for the encoder): the mapper's output equals ``model(raw)``."""
    torch.manual_seed(2)
    streams = "lv" if flag == "lv_full_res" else "both"  # LV alone: its input decides the output
    model = BiMapper(replace(TINY, streams=streams, **{flag: True}), RIG, GRID).eval()
    path = tmp_path / "w.safetensors"
    save_weights(model, path)
    mapper = BiMapperMapper(RIG, GRID, MapperConfig(backend="torch", method="bimapper", weights=str(path)))
    raw = random_labels(5)
    pred = mapper.map({c.name: raw[0, n].numpy() for n, c in enumerate(RIG.cameras)})
    with torch.no_grad():
        exp = torch.sigmoid(model(raw)["logits"][0]).numpy()
        resized_only = torch.sigmoid(model.forward_preprocessed(
            model.preprocess(raw), x_lv=None, prior=model.ipm_prior(raw) if flag == "ipm_skip" else None)["logits"][0]).numpy()
    np.testing.assert_allclose(pred.probs, exp, atol=1e-6)
    if flag == "lv_full_res":
        assert np.abs(resized_only - exp).max() > 1e-5  # 10x the agreement above: the full-size input matters
