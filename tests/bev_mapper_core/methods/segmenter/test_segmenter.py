"""Issue #12 part 1: the 2-D segmenter, its weights, ``segipm`` and chained RGB input (tiny
models, CPU)."""

from dataclasses import replace

import numpy as np
import pytest
import torch
from model_helpers import GRID, RIG, TINY
from safetensors.torch import load_file, save_file

from bev_mapper_core.errors import ConfigError
from bev_mapper_core.labels.classes import NUM_LABELS, Label
from bev_mapper_core.mapper import MapperConfig, create_mapper
from bev_mapper_core.methods.bimapper.mapper import BiMapperMapper
from bev_mapper_core.methods.bimapper.model import BiMapper
from bev_mapper_core.methods.bimapper.weights import save_weights
from bev_mapper_core.methods.ipm.mapper import IpmMapper
from bev_mapper_core.methods.segmenter.model import Segmenter, SegmenterConfig, class_weights, pixel_iou
from bev_mapper_core.methods.segmenter.stage import SegmenterStage
from bev_mapper_core.methods.segmenter.weights import load_segmenter, save_segmenter
from bev_mapper_core.nn.weights import WeightsError

torch.set_num_threads(1)
SMALL = SegmenterConfig(input_width=32, width_mult=0.25, depth_mult=0.25, encoder_stages=3, decoder_channels=8)


def _scene(n: int, h: int = 40, w: int = 64, seed: int = 0):
    """RGB images whose colour says the label: road grey below a random horizon, sky above, a
    red 'vehicle' box somewhere; and their label images."""
    rng = np.random.default_rng(seed)
    rgb = np.zeros((n, h, w, 3), np.uint8)
    lab = np.zeros((n, h, w), np.uint8)
    for i in range(n):
        hz = int(rng.integers(h // 4, h // 2))
        rgb[i, :hz] = (90, 140, 220)
        rgb[i, hz:] = (100, 100, 100)
        lab[i, hz:] = Label.ROAD
        x0, y0 = int(rng.integers(0, w - 16)), int(rng.integers(hz, h - 8))
        rgb[i, y0:y0 + 8, x0:x0 + 16] = (200, 30, 30)
        lab[i, y0:y0 + 8, x0:x0 + 16] = Label.VEHICLE
    noise = rng.integers(-10, 11, rgb.shape)
    return np.clip(rgb.astype(int) + noise, 0, 255).astype(np.uint8), lab


def test_forward_backward_and_segment_at_camera_size():
    torch.manual_seed(0)
    model = Segmenter(SMALL)
    rgb, _ = _scene(2)
    x = model.preprocess(torch.from_numpy(rgb))
    assert x.shape == (2, 3, 20, 32)  # input_width 32, height from the 64x40 aspect
    logits = model(x)
    assert logits.shape == (2, NUM_LABELS, 20, 32)
    logits.sum().backward()
    assert model.encoder.stem[0].weight.grad.abs().sum() > 0
    labels = model.eval().segment(torch.from_numpy(rgb))
    assert labels.shape == (2, 40, 64) and labels.dtype == torch.uint8


def test_short_training_lowers_the_loss_and_learns_the_scene():
    torch.manual_seed(0)
    model = Segmenter(SMALL)
    rgb, lab = _scene(8)
    x = model.preprocess(torch.from_numpy(rgb))
    target = torch.nn.functional.interpolate(torch.from_numpy(lab)[:, None].float(), size=x.shape[-2:],
                                             mode="nearest-exact")[:, 0].long()
    weight = class_weights(torch.bincount(target.flatten(), minlength=NUM_LABELS))
    opt = torch.optim.Adam(model.parameters(), 1e-2)
    losses = []
    for _ in range(40):
        loss = torch.nn.functional.cross_entropy(model(x), target, weight=weight)
        opt.zero_grad()
        loss.backward()
        opt.step()
        losses.append(loss.item())
    assert losses[-1] < 0.3 * losses[0]
    pred = model.eval().segment(torch.from_numpy(rgb))
    iou = pixel_iou(pred, torch.from_numpy(lab))
    assert iou[Label.ROAD] > 0.8 and iou[Label.UNLABELED] > 0.8


def test_class_weights_and_pixel_iou_by_hand():
    w = class_weights(torch.tensor([100, 25, 1, 0] + [0] * (NUM_LABELS - 4)))
    # median of the seen frequencies is 25/126: road 0.5, 1.0, sqrt(25) = 5, unseen: the top
    assert w[:4].tolist() == pytest.approx([0.5, 1.0, 5.0, 10.0])
    pred = torch.tensor([[0, 1], [1, 1]])
    true = torch.tensor([[0, 1], [0, 1]])
    iou = pixel_iou(pred, true, num_labels=3)
    assert iou[0] == pytest.approx(0.5) and iou[1] == pytest.approx(2 / 3) and torch.isnan(iou[2])


def test_weights_round_trip_and_bad_files(tmp_path):
    torch.manual_seed(1)
    model = Segmenter(SMALL).eval()
    path = save_segmenter(model, tmp_path / "seg.safetensors", "tiny2")
    loaded = load_segmenter(path)
    assert loaded.config == SMALL
    rgb = torch.from_numpy(_scene(1)[0])
    assert torch.equal(loaded.segment(rgb), model.segment(rgb))
    # a Bi-Mapper file, a pickle, a non-finite tensor, a missing tensor: clear errors
    bm = save_weights(BiMapper(TINY, RIG, GRID), tmp_path / "bm.safetensors")
    with pytest.raises(WeightsError, match="not segmenter weights"):
        load_segmenter(bm)
    pickled = tmp_path / "p.safetensors"
    torch.save({"a": torch.zeros(1)}, pickled)
    with pytest.raises(WeightsError, match="not a valid safetensors"):
        load_segmenter(pickled)
    from safetensors import safe_open
    with safe_open(str(path), framework="pt") as f:
        meta = f.metadata()
    tensors = load_file(str(path))
    key = next(k for k, v in tensors.items() if v.is_floating_point())
    bad = dict(tensors)
    bad[key] = torch.full_like(bad[key], float("nan"))
    save_file(bad, str(tmp_path / "nan.safetensors"), metadata=meta)
    with pytest.raises(WeightsError, match="non-finite"):
        load_segmenter(tmp_path / "nan.safetensors")
    del bad[key]
    save_file(bad, str(tmp_path / "missing.safetensors"), metadata=meta)
    with pytest.raises(WeightsError, match="missing"):
        load_segmenter(tmp_path / "missing.safetensors")
    with pytest.raises(WeightsError, match="does not exist"):
        load_segmenter(tmp_path / "nope.safetensors")


class _OracleStage:
    """The segmenter replaced by the ground-truth label images."""

    def __init__(self, labels: dict) -> None:
        self.labels = labels

    def segment(self, images: dict) -> dict:
        return {name: self.labels[name] for name in images}


def _rig_images(seed: int):
    rgb, lab = _scene(len(RIG.cameras), seed=seed)
    names = RIG.names
    return dict(zip(names, rgb)), dict(zip(names, lab))


def test_segipm_equals_ipm_on_ground_truth_labels(tmp_path):
    seg = save_segmenter(Segmenter(SMALL), tmp_path / "seg.safetensors")
    for occlusion in (True, False):
        config = MapperConfig(method="segipm", input_kind="rgb", segmenter=str(seg), ipm_occlusion=occlusion,
                              classes=("drivable", "vehicle"))
        mapper = create_mapper(RIG, GRID, config)
        rgb, lab = _rig_images(3)
        mapper.stage = _OracleStage(lab)
        got = mapper.map(rgb)
        ipm = IpmMapper(RIG, GRID, replace(config, method="ipm", input_kind="labels")).map(lab)
        np.testing.assert_array_equal(got.probs, ipm.probs)
        np.testing.assert_array_equal(got.known, ipm.known)
    # and with the real (untrained) segmenter it runs end to end on RGB
    out = create_mapper(RIG, GRID, MapperConfig(method="segipm", input_kind="rgb", segmenter=str(seg))).map(rgb)
    assert out.probs.shape[1:] == GRID.shape


def test_segipm_refuses_labels_and_missing_segmenters(tmp_path):
    with pytest.raises(ConfigError, match="segipm maps RGB"):
        create_mapper(RIG, GRID, MapperConfig(method="segipm", input_kind="labels"))
    with pytest.raises(ConfigError, match="segmenter is 'none'"):
        create_mapper(RIG, GRID, MapperConfig(method="segipm", input_kind="rgb", segmenter="none"))
    with pytest.raises(WeightsError, match="does not exist"):
        create_mapper(RIG, GRID, MapperConfig(method="segipm", input_kind="rgb", segmenter=str(tmp_path / "x")))


def test_label_bimapper_runs_chained_on_rgb(tmp_path):
    """RGB input + label weights: the segmenter's labels go into the label model, exactly as if
    those labels had been the input; RGB weights refuse an explicit segmenter."""
    torch.manual_seed(2)
    seg_path = save_segmenter(Segmenter(SMALL), tmp_path / "seg.safetensors")
    w = save_weights(BiMapper(replace(TINY, ipm_skip=True), RIG, GRID).eval(), tmp_path / "bm.safetensors")
    chained = BiMapperMapper(RIG, GRID, MapperConfig(backend="torch", input_kind="rgb", weights=str(w), segmenter=str(seg_path)))
    assert chained.stage is not None and chained.model_input == "labels"
    rgb, _ = _rig_images(4)
    labels = SegmenterStage(seg_path).segment(rgb)
    direct = BiMapperMapper(RIG, GRID, MapperConfig(backend="torch", weights=str(w))).map(labels)
    got = chained.map(rgb)
    np.testing.assert_array_equal(got.probs, direct.probs)
    np.testing.assert_array_equal(got.known, direct.known)
    with pytest.raises(ConfigError, match="segmenter is 'none'"):
        BiMapperMapper(RIG, GRID, MapperConfig(input_kind="rgb", weights=str(w), segmenter="none"))
    w_rgb = save_weights(BiMapper(replace(TINY, input_kind="rgb"), RIG, GRID), tmp_path / "rgb.safetensors")
    e2e = BiMapperMapper(RIG, GRID, MapperConfig(backend="torch", input_kind="rgb", weights=str(w_rgb)))
    assert e2e.stage is None and e2e.map(rgb).probs.shape[1:] == GRID.shape
    with pytest.raises(ConfigError, match="takes no segmenter"):
        BiMapperMapper(RIG, GRID, MapperConfig(input_kind="rgb", weights=str(w_rgb), segmenter=str(seg_path)))
    with pytest.raises(WeightsError, match="input"):
        BiMapperMapper(RIG, GRID, MapperConfig(input_kind="labels", weights=str(w_rgb)))


def test_preflight_checks_every_segmenter_tensor(tmp_path):
    """A node's start-up check (``preflight``) loads the segmenter: a file with a non-finite
    tensor is refused before any frame, for segipm and for chained Bi-Mapper."""
    from safetensors import safe_open

    from bev_mapper_core.mapper import preflight

    path = save_segmenter(Segmenter(SMALL), tmp_path / "seg.safetensors")
    with safe_open(str(path), framework="pt") as f:
        meta = f.metadata()
    tensors = load_file(str(path))
    key = next(k for k, v in tensors.items() if v.is_floating_point())
    tensors[key] = torch.full_like(tensors[key], float("inf"))
    save_file(tensors, str(tmp_path / "inf.safetensors"), metadata=meta)
    bad = str(tmp_path / "inf.safetensors")
    preflight(MapperConfig(method="segipm", input_kind="rgb", segmenter=str(path)), RIG.name)  # the good one passes
    with pytest.raises(WeightsError, match="non-finite"):
        preflight(MapperConfig(method="segipm", input_kind="rgb", segmenter=bad), RIG.name)
    w = save_weights(BiMapper(replace(TINY, ipm_skip=True), RIG, GRID), tmp_path / "bm.safetensors")
    with pytest.raises(WeightsError, match="non-finite"):
        preflight(MapperConfig(input_kind="rgb", weights=str(w), segmenter=bad), RIG.name)


def test_full_resolution_cameras_get_labels_decided_at_twice_the_input_width(tmp_path):
    """Labels are decided at most at twice the model's input width and nearest-upsampled: a
    400 x 225 camera gets exactly what it always got (scores upsampled to it, argmax); a
    1600 x 900 one the labels decided at twice the input width, and (from a box-reduced image) mostly the
    labels of the old full-size path."""
    from bev_mapper_core.methods.segmenter.model import DECISION_WIDTH_FACTOR
    from bev_mapper_core.methods.segmenter.stage import shipped_segmenter

    stage = SegmenterStage(shipped_segmenter("surround6"))
    model = stage.model
    most = DECISION_WIDTH_FACTOR * model.config.input_width
    big_hw = (round(900 * most / 1600), most)
    assert model.decision_size((225, 400)) == (225, 400) and model.decision_size((900, 1600)) == big_hw
    rng = np.random.default_rng(3)
    base = rng.integers(0, 255, (45, 80, 3), dtype=np.uint8)  # blobs, so that labels vary smoothly
    small = np.ascontiguousarray(np.repeat(np.repeat(base, 5, 0), 5, 1))  # (225, 400, 3)
    with torch.inference_mode():
        old = model(model.preprocess(torch.from_numpy(small[None])), size=(225, 400)).argmax(1)[0].numpy()
    np.testing.assert_array_equal(stage.segment({"c": small})["c"], old)  # 400 x 225: unchanged
    big = np.ascontiguousarray(np.repeat(np.repeat(base, 20, 0), 20, 1))  # (900, 1600, 3)
    got = stage.segment({"c": big})["c"]
    assert got.shape == (900, 1600) and got.dtype == np.uint8
    decided = model.segment(torch.from_numpy(big[None]), size=big_hw)[0].numpy()
    # nearest upsampling of the labels decided at twice the input width (from the image, not its box mean)
    up = torch.nn.functional.interpolate(torch.from_numpy(decided)[None, None], size=(900, 1600), mode="nearest")
    assert (got == up[0, 0].numpy()).mean() > 0.97  # the k x k box mean first changes little
    with torch.inference_mode():
        full = model(model.preprocess(torch.from_numpy(big[None])), size=(900, 1600)).argmax(1)[0].numpy()
    assert (got == full).mean() > 0.95
