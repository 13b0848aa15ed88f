"""Issue #13: S2G2 (semi-supervised monocular BEV): blocks, losses, EMA, ramp, weights, the
training plug-in with unlabeled synthetic drives, and the mapper (tiny models, CPU)."""

import json
import math
from dataclasses import replace

import numpy as np
import pytest
import torch
from safetensors.torch import load_file, save_file
from torch.nn import functional as F

from bags.cli.train.main import main as bev_train
from bags.cli.train.train import train_parser
from bev_mapper_core.errors import ConfigError, GridError
from bev_mapper_core.geometry.grid import BevGrid, grid_preset
from bev_mapper_core.geometry.rig import preset_rig
from bev_mapper_core.labels.classes import NUM_LABELS, S2G2_CLASSES, Label, label_lut
from bev_mapper_core.mapper import MapperConfig, available_methods, create_mapper
from bev_mapper_core.methods import WEIGHTS_DIR
from bev_mapper_core.methods.bimapper.config import BiMapperConfig
from bev_mapper_core.methods.bimapper.model import BiMapper
from bev_mapper_core.methods.bimapper.weights import save_weights
from bev_mapper_core.methods.s2g2.blocks import (
    CrossViewAttention,
    InterViewAttention,
    ViewTransform,
    grid_to_image_layout,
    image_to_grid_layout,
)
from bev_mapper_core.methods.s2g2.losses import (
    S2G2LossConfig,
    bev_tie_loss,
    consistency_loss,
    cycle_loss,
    ema_decay_at,
    ema_update,
    s2g2_loss,
    sigmoid_rampup,
)
from bev_mapper_core.methods.s2g2.mapper import shipped_s2g2
from bev_mapper_core.methods.s2g2.model import S2G2, S2G2Config, input_size
from bev_mapper_core.methods.s2g2.train import S2G2Training
from bev_mapper_core.methods.s2g2.weights import load_s2g2, read_s2g2_metadata, save_s2g2
from bev_mapper_core.methods.segmenter.stage import TRUNK_SEGMENTER
from bev_mapper_core.methods.segmenter.weights import load_segmenter
from bev_mapper_core.nn.weights import WeightsError
from bev_mapper_core.training.config import TrainConfig
from bev_mapper_core.training.data import FrameSet
from bev_mapper_core.training.method import method_class, train_methods
from bev_mapper_core.training.sources import DataNeeds, InMemorySource, SynthSource, TrainData
from bev_mapper_core.training.trainer import train

torch.set_num_threads(1)
RIG = preset_rig("front1")
GRID = BevGrid(0.0, 16.0, -8.0, 8.0, 0.5)  # 16 m ahead, +-8 m: 32 x 32 cells
CLASSES = ("drivable", "vehicle", "lane_divider")
TINY = S2G2Config(classes=CLASSES, input_width=32, width_mult=0.25, depth_mult=0.25, encoder_stages=3,
                  bev_downsample=4, decoder_channels=8)
#: flat training keys of a tiny run (as bev-train flags give them)
TINY_RUN = dict(method="s2g2", rig="front1", classes=",".join(CLASSES), epochs=5, batch=2, lr=3e-3, seed=3,
                train_drives=1, val_drives=1, unlabeled_drives=1, unlabeled_style="dusk", frames_per_drive=4,
                stride=2, threads=1, input_width=32, width_mult=0.25, depth_mult=0.25, encoder_stages=3,
                bev_downsample=4, decoder_channels=8, consistency_ramp_steps=4, grid=[0.0, 16.0, -8.0, 8.0, 0.5],
                encoder_init="none", optimizer="sgd", progress=False)


def _rgb(n: int = 2, seed: int = 0) -> torch.Tensor:
    """(n, 1, H, W, 3) uint8 camera-size images of the front1 camera."""
    w, h = RIG.cameras[0].model.image_size
    return torch.from_numpy(np.random.default_rng(seed).integers(0, 256, (n, 1, h, w, 3), dtype=np.uint8))


# ----------------------------------------------------------------------------- model
def test_config_bounds_round_trip_and_paper_sizes():
    assert S2G2Config.from_dict(json.loads(json.dumps(TINY.to_dict()))) == TINY
    for bad in (dict(input_kind="depth"), dict(view_transform="mlp"), dict(bev_downsample=0),
                dict(decoder_channels=10**6), dict(input_width=8), dict(encoder_variant="b9"),
                dict(cross_view_attention="yes"), dict(classes=("roads",))):
        with pytest.raises(ConfigError):
            replace(TINY, **bad)
    with pytest.raises(ConfigError, match="unknown S2G2Config fields"):
        S2G2Config.from_dict({**TINY.to_dict(), "extra": 1})
    paper = S2G2Config.paper(input_width=64)  # B4 at a small input: a quick forward
    model = S2G2(paper, RIG, BevGrid(0.0, 32.0, -16.0, 16.0, 0.5)).eval()  # the paper's 64 x 64 grid
    assert model.encoder.out_channels == 448 and model.encoder.endpoint_strides[-1] == 32  # Table I: B4
    assert model.bev_hw == (8, 8)
    with torch.no_grad():
        out = model(model.preprocess(_rgb(1)))
    assert out["active_logits"].shape == out["passive_logits"].shape == (1, 7, 64, 64)


def test_monocular_only():
    with pytest.raises(ConfigError, match="S2G2 is monocular: rig 'surround6' has 6 cameras"):
        S2G2(TINY, preset_rig("surround6"), GRID)


def test_layouts_put_the_image_bottom_near_and_its_left_at_plus_y():
    x = torch.zeros(1, 1, 3, 4)  # (B, C, hf, wf) image layout
    x[0, 0, 2, 0] = 1.0  # bottom-left pixel: near, left (+y)
    g = image_to_grid_layout(x, (4, 3))  # no resize: (wf, hf)
    assert g[0, 0, 3, 0] == 1.0 and g.sum() == 1.0  # grid row 3 = +y side, col 0 = x_min (near)
    assert torch.equal(grid_to_image_layout(g, (3, 4)), x)
    assert image_to_grid_layout(x, (8, 8)).shape == (1, 1, 8, 8)


@pytest.mark.parametrize("kind", ["conv", "fc"])
def test_blocks_forward_backward(kind):
    torch.manual_seed(0)
    front = torch.randn(2, 16, 3, 5, requires_grad=True)
    to_bev, to_front = ViewTransform(16, (3, 5), (4, 6), kind, True), ViewTransform(16, (4, 6), (3, 5), kind, False)
    bev = to_bev(front)
    cycled = to_front(bev)
    assert bev.shape == (2, 16, 4, 6) and cycled.shape == front.shape
    f_c = CrossViewAttention(16)(front, bev, cycled)
    f_i = InterViewAttention(16)(bev)
    assert f_c.shape == f_i.shape == bev.shape
    (f_c.square().mean() + f_i.square().mean() + cycle_loss(front, cycled)).backward()
    assert front.grad is not None and torch.isfinite(front.grad).all() and front.grad.abs().sum() > 0
    for block in (to_bev, to_front):
        assert all(p.grad is not None for p in block.parameters())


def test_model_forward_backward_ablations_and_passive_without_gradient():
    torch.manual_seed(0)
    model = S2G2(TINY, RIG, GRID)
    x = model.preprocess(_rgb(4))
    assert x.shape == (4, 3, *model.input_size)
    out = model(x)
    assert out["active_logits"].shape == (4, 3, *GRID.shape) and not out["passive_logits"].requires_grad
    loss, parts = s2g2_loss(out, 2, torch.rand(2, 3, *GRID.shape) > 0.5, torch.ones(2, *GRID.shape, dtype=torch.bool),
                            step=10)
    loss.backward()
    assert set(parts) == {"seg", "cycle", "bev", "con", "gamma", "total"}
    assert all(p.grad is None for p in model.passive.parameters())
    for name in ("encoder", "to_bev", "to_front", "cross_view", "inter_view", "active"):
        assert any(p.grad is not None and p.grad.abs().sum() > 0 for p in getattr(model, name).parameters()), name
    assert {id(p) for p in model.trainable_parameters()}.isdisjoint({id(p) for p in model.passive.parameters()})
    model.eval()
    with torch.no_grad():
        out = model(x)
        assert torch.allclose(model.logits(x, "active"), out["active_logits"], atol=1e-5)
        assert torch.allclose(model.logits(x, "passive"), out["passive_logits"], atol=1e-5)
    for over in (dict(cross_view_attention=False), dict(inter_view_attention=False), dict(view_transform="fc"),
                 dict(input_kind="labels")):
        m = S2G2(replace(TINY, **over), RIG, GRID)
        w, h = RIG.cameras[0].model.image_size
        raw = torch.zeros(1, 1, h, w, dtype=torch.uint8) if over.get("input_kind") else _rgb(1)
        o = m(m.preprocess(raw))
        assert o["active_logits"].shape == (1, 3, *GRID.shape)
        if "cross_view_attention" in over:
            assert o["f_c"] is o["bev"] and m.cross_view is None
        if "inter_view_attention" in over:
            assert o["f_i"] is o["bev"] and m.inter_view is None


# ---------------------------------------------------------------------------- losses
def test_losses_by_hand():
    a, b = torch.tensor([[[[1.0, -2.0]]]]), torch.tensor([[[[0.0, 2.0]]]])  # (1, 1, 1, 2)
    assert cycle_loss(a, b).item() == pytest.approx(2.5)
    assert bev_tie_loss(a, b, "l1").item() == pytest.approx(2.5)
    f_i, f_c = torch.tensor([[[[0.0]], [[math.log(3.0)]]]]), torch.zeros(1, 2, 1, 1)  # softmax(F_I) = (1/4, 3/4)
    assert bev_tie_loss(f_i, f_c, "ce").item() == pytest.approx(math.log(2.0))  # -(1/4 + 3/4) log 1/2
    act = torch.zeros(1, 1, 1, 2, requires_grad=True)
    pas = torch.tensor([[[[0.0, math.log(3.0)]]]], requires_grad=True)  # probabilities 0.5, 0.75
    con = consistency_loss(act, pas)
    assert con.item() == pytest.approx((0.25 ** 2) / 2)
    con.backward()
    assert pas.grad is None and act.grad is not None  # the passive prediction is a target
    # Eq. 6: seg (masked BCE on the labeled frames) + alpha cycle + beta bev + gamma(t) con
    out = {"active_logits": torch.zeros(2, 1, 1, 2), "passive_logits": torch.full((2, 1, 1, 2), math.log(3.0)),
           "front": a, "front_cycled": b, "f_i": f_i, "f_c": f_c}
    cfg = S2G2LossConfig(cycle_weight=2.0, bev_weight=0.5, bev_tie="ce", consistency_weight=4.0, consistency_ramp_steps=10)
    target = torch.tensor([[[[1.0, 0.0]]]])
    mask = torch.tensor([[[True, False]]])  # only the first cell counts: BCE(0, 1) = log 2
    total, parts = s2g2_loss(out, 1, target, mask, step=5, config=cfg)
    gamma = 4.0 * math.exp(-5 * 0.5 ** 2)
    assert parts["seg"] == pytest.approx(math.log(2.0)) and parts["gamma"] == pytest.approx(gamma)
    assert total.item() == pytest.approx(math.log(2.0) + 2.0 * 2.5 + 0.5 * math.log(2.0) + gamma * 0.0625, rel=1e-5)
    with pytest.raises(ValueError, match="labeled frames"):
        s2g2_loss(out, 0, target, mask, 5, cfg)


def test_ema_update_by_hand_on_a_two_parameter_model():
    active, passive = torch.nn.Linear(1, 1), torch.nn.Linear(1, 1)
    with torch.no_grad():
        active.weight.fill_(3.0)
        active.bias.fill_(4.0)
        passive.weight.fill_(1.0)
        passive.bias.fill_(2.0)
    ema_update(passive, active, 0.9)  # 0.9 * 1 + 0.1 * 3, 0.9 * 2 + 0.1 * 4
    assert passive.weight.item() == pytest.approx(1.2) and passive.bias.item() == pytest.approx(2.2)
    ema_update(passive, active, 0.999)
    assert passive.weight.item() == pytest.approx(0.999 * 1.2 + 0.001 * 3.0)
    assert active.weight.item() == 3.0 and active.bias.item() == 4.0  # the active module is untouched
    ema_update(passive, active, 0.0)
    assert passive.weight.item() == 3.0 and passive.bias.item() == 4.0
    with pytest.raises(ValueError, match="same parameters"):
        ema_update(torch.nn.Linear(2, 1), active, 0.5)
    with pytest.raises(ValueError, match="decay"):
        ema_update(passive, active, 1.5)
    # Mean Teacher's warm-up: the plain average until the decay is the smaller
    assert [ema_decay_at(s, 0.999, True) for s in (1, 3, 999, 5000)] == [0.5, 0.75, 0.999, 0.999]
    assert ema_decay_at(1, 0.999, False) == 0.999


def test_sigmoid_rampup_values():
    assert sigmoid_rampup(0, 100) == pytest.approx(math.exp(-5.0))
    assert sigmoid_rampup(50, 100) == pytest.approx(math.exp(-1.25))
    assert sigmoid_rampup(80, 100) == pytest.approx(math.exp(-0.2))
    assert sigmoid_rampup(100, 100) == sigmoid_rampup(250, 100) == 1.0
    assert sigmoid_rampup(0, 0) == 1.0
    assert S2G2LossConfig(consistency_weight=2.0).gamma(50) == pytest.approx(2.0 * math.exp(-1.25))
    values = [sigmoid_rampup(s, 100) for s in range(0, 101, 10)]
    assert values == sorted(values)


# ---------------------------------------------------------------------------- weights
def test_weights_round_trip_and_bad_files(tmp_path):
    torch.manual_seed(2)
    model = S2G2(TINY, RIG, GRID)
    with torch.no_grad():  # the branches differ, as after training
        for p in model.passive.parameters():
            p.add_(0.1)
    model.eval()
    path = save_s2g2(model, tmp_path / "s2g2.safetensors", inference_branch="passive")
    meta = read_s2g2_metadata(path)
    assert meta["format"] == "bev_mapper.s2g2" and meta["inference_branch"] == "passive"
    assert meta["cameras"] == ["front"] and meta["input_size"] == list(model.input_size)
    loaded, _ = load_s2g2(path, RIG)
    x = model.preprocess(_rgb(1))
    with torch.no_grad():
        for branch in ("active", "passive"):
            assert torch.equal(loaded.logits(x, branch), model.logits(x, branch))
    with pytest.raises(ConfigError, match="monocular"):
        load_s2g2(path, preset_rig("surround6"))
    with pytest.raises(WeightsError, match="grid"):
        load_s2g2(path, RIG, BevGrid(0.0, 16.0, -8.0, 8.0, 0.25))
    # corrupt, pickled, another format, non-finite, missing tensors, a two-camera document
    raw = path.read_bytes()
    (tmp_path / "cut.safetensors").write_bytes(raw[: len(raw) // 2])
    (tmp_path / "junk.safetensors").write_bytes(b"\x00" * 8 + raw[8:100])
    for name in ("cut", "junk"):
        with pytest.raises(WeightsError):
            load_s2g2(tmp_path / f"{name}.safetensors", RIG)
    torch.save({"a": torch.zeros(1)}, tmp_path / "p.safetensors")
    with pytest.raises(WeightsError, match="not a valid safetensors"):
        read_s2g2_metadata(tmp_path / "p.safetensors")
    bm = save_weights(BiMapper(BiMapperConfig(input_width=32, width_mult=0.25, depth_mult=0.25, encoder_stages=3),
                               RIG, GRID), tmp_path / "bm.safetensors")
    with pytest.raises(WeightsError, match="not S2G2 weights"):
        read_s2g2_metadata(bm)
    tensors, header = load_file(str(path)), json.loads(json.dumps(meta))
    key = next(k for k, v in tensors.items() if v.is_floating_point())
    bad = dict(tensors, **{key: torch.full_like(tensors[key], float("nan"))})
    save_file(bad, str(tmp_path / "nan.safetensors"), metadata={"bev_mapper": json.dumps(header)})
    with pytest.raises(WeightsError, match="non-finite"):
        load_s2g2(tmp_path / "nan.safetensors", RIG)
    del bad[key]
    save_file(bad, str(tmp_path / "missing.safetensors"), metadata={"bev_mapper": json.dumps(header)})
    with pytest.raises(WeightsError, match="missing"):
        load_s2g2(tmp_path / "missing.safetensors", RIG)
    save_file(tensors, str(tmp_path / "two.safetensors"),
              metadata={"bev_mapper": json.dumps({**header, "cameras": ["front", "back"]})})
    with pytest.raises(WeightsError, match="exactly one camera"):
        read_s2g2_metadata(tmp_path / "two.safetensors")
    with pytest.raises(WeightsError, match="does not exist"):
        read_s2g2_metadata(tmp_path / "nope.safetensors")


# ----------------------------------------------------------------------------- mapper
def test_mapper_maps_a_frame_and_refuses_multi_camera_rigs(tmp_path):
    assert "s2g2" in available_methods() and "s2g2" in train_methods()
    torch.manual_seed(3)
    model = S2G2(TINY, RIG, GRID).eval()
    path = save_s2g2(model, tmp_path / "w.safetensors", inference_branch="passive")
    cfg = MapperConfig(backend="torch", method="s2g2", input_kind="rgb", weights=str(path), threads=1)
    mapper = create_mapper(RIG, GRID, cfg)
    assert mapper.class_names == CLASSES and mapper.branch == "passive"
    rgb = _rgb(1, seed=5)
    pred = mapper.map({"front": rgb[0, 0].numpy()})
    assert pred.probs.shape == (3, *GRID.shape) and pred.probs.dtype == np.float32
    with torch.no_grad():
        want = torch.sigmoid(model.logits(model.preprocess(rgb), "passive"))[0].numpy()
    np.testing.assert_allclose(pred.probs, want, atol=1e-6)
    assert pred.known.shape == GRID.shape and pred.known.any() and not pred.known.all()  # the camera's frustum
    sub = create_mapper(RIG, GRID, replace(cfg, classes=("vehicle",))).map({"front": rgb[0, 0].numpy()})
    np.testing.assert_allclose(sub.probs[0], pred.probs[1], atol=1e-6)
    with pytest.raises(ConfigError, match="S2G2 is monocular"):
        create_mapper(preset_rig("surround6"), GRID, cfg)
    with pytest.raises(ConfigError, match="no S2G2 weights given and none shipped for rig 'front1' / input 'labels'"):
        create_mapper(RIG, GRID, replace(cfg, weights=None, input_kind="labels"))
    with pytest.raises(WeightsError, match="configured input is 'labels'"):
        create_mapper(RIG, GRID, replace(cfg, input_kind="labels"))
    with pytest.raises(WeightsError, match="grid"):
        create_mapper(RIG, BevGrid(0.0, 16.0, -8.0, 8.0, 0.25), cfg)


# --------------------------------------------------------------------------- training
def test_unlabeled_batches_pair_each_labeled_batch():
    rng = np.random.default_rng(0)

    def frames(n):
        return FrameSet(rng.integers(0, 5, (n, 1, 4, 6), dtype=np.uint8), rng.random((n, 2, 3, 3)) > 0.5,
                        np.ones((n, 3, 3), bool), camera_names=("front",))

    data = TrainData(frames(5), frames(2), frames(3))
    batches = list(data.batches(2, seed=1, epoch=0))
    assert len(batches) == data.steps(2) == 3
    assert [len(b["labeled"]["target"]) for b in batches] == [2, 2, 1]
    assert all(set(b["unlabeled"]) == {"images", "index"} for b in batches)  # inputs and ids only: no GT
    assert [len(b["unlabeled"]["images"]) for b in batches] == [2, 2, 1]
    again = list(data.batches(2, seed=1, epoch=0))
    assert all(torch.equal(a["unlabeled"]["images"], b["unlabeled"]["images"]) for a, b in zip(batches, again))
    assert "labeled" not in next(TrainData(frames(2), frames(2)).batches(2, 1, 0))  # no unlabeled: plain batches
    src = InMemorySource(frames(2), frames(2), frames(2))
    src.check(DataNeeds(unlabeled=True))
    with pytest.raises(ConfigError, match="rgb"):
        src.check(DataNeeds(unlabeled=True, rgb=True))


def test_unlabeled_frames_leave_batchnorm_statistics_alone():
    """``unlabeled_bn`` ``running`` (default): the unlabeled frames are normalized with the running
    statistics and do not move them (dropout stays on), and the losses are those of a model that
    sees them alone in eval-mode BatchNorm; ``batch`` normalizes both kinds together (the paper)."""
    rng = np.random.default_rng(4)
    # no augmentation: the losses below are recomputed from the batch's own images
    cfg = TrainConfig.from_dict({**TINY_RUN, "input": "rgb", "drop_connect_rate": 0.0, "augment": False})
    h, w = input_size(TINY, RIG)

    def batch(n, bright):
        return {"rgb": torch.from_numpy(rng.integers(*bright, (n, 1, h, w, 3), dtype=np.uint8)),
                "target": torch.from_numpy(rng.random((n, 3, *GRID.shape)) > 0.5), "mask": None}

    labeled, unlabeled = batch(2, (100, 256)), batch(2, (0, 60))  # a bright and a dark "style"

    def step(**over):
        torch.manual_seed(0)
        m = method_class("s2g2")(replace(cfg, loss=replace(cfg.loss, **over)), RIG, GRID)
        m.loss_cfg = m.cfg.loss.loss_config()
        m.model.train()
        _, parts = m.loss({"labeled": labeled, "unlabeled": unlabeled}, 0, 50)
        bn = [b for b in m.model.encoder.modules() if isinstance(b, torch.nn.BatchNorm2d)][0]
        return m, parts, bn.running_mean.clone()

    running, parts, mean = step()
    assert running.model.training and all(b.training for b in running.model.modules())  # modes restored
    _, _, mean_labeled_only = step(supervised_only=True)
    torch.testing.assert_close(mean, mean_labeled_only)  # only the labeled frames moved the statistics
    _, parts_batch, mean_batch = step(unlabeled_bn="batch", unlabeled_into_encoder=True)
    assert not torch.allclose(mean_batch, mean) and parts_batch["cycle"] != parts["cycle"]
    # the unlabeled half of the loss is what the model computes for those frames in eval-mode BN
    model = running.model
    with torch.no_grad():
        x = model.preprocess(unlabeled["rgb"])
        out_u = model.eval()(x)
        want = F.l1_loss(out_u["front_cycled"], out_u["front"])
        model.train()
        out_l = model(model.preprocess(labeled["rgb"]))
    both = (F.l1_loss(out_l["front_cycled"], out_l["front"], reduction="sum")
            + want * out_u["front"].numel()) / (out_l["front"].numel() + out_u["front"].numel())
    assert parts["cycle"] == pytest.approx(float(both), rel=1e-4)
    with pytest.raises(ConfigError, match="unlabeled_bn"):
        S2G2Training(unlabeled_bn="target")
    with pytest.raises(ConfigError, match="needs unlabeled_into_encoder"):
        S2G2Training(unlabeled_bn="batch")


def test_cycle_loss_trains_the_view_transforms_not_the_encoder():
    """By default the cycle loss adds nothing to the encoder's gradient, and a gradient to both
    view-transform blocks; with ``cycle_into_encoder`` it reaches the encoder too."""
    rng = np.random.default_rng(5)
    cfg = TrainConfig.from_dict({**TINY_RUN, "input": "rgb", "drop_connect_rate": 0.0, "supervised_only": True,
                                 "bev_weight": 0.0, "consistency_weight": 0.0})
    h, w = input_size(TINY, RIG)
    batch = {"rgb": torch.from_numpy(rng.integers(0, 256, (2, 1, h, w, 3), dtype=np.uint8)),
             "target": torch.from_numpy(rng.random((2, 3, *GRID.shape)) > 0.5), "mask": None}

    def grads(**over):
        torch.manual_seed(0)
        m = method_class("s2g2")(replace(cfg, loss=replace(cfg.loss, **over)), RIG, GRID)
        m.loss_cfg = m.cfg.loss.loss_config()
        m.model.train()
        total, parts = m.loss(batch, 0, 0)
        total.backward()
        g = {k: p.grad.clone() for k, p in m.model.named_parameters() if p.grad is not None}
        return g, parts

    detached, parts = grads()
    without, _ = grads(cycle_weight=0.0)
    into, parts_into = grads(cycle_into_encoder=True)
    assert parts["cycle"] > 0 and parts["cycle"] == pytest.approx(parts_into["cycle"], rel=1e-5)
    enc = [k for k in without if k.startswith("encoder.")]
    assert enc and all(torch.allclose(detached[k], without[k]) for k in enc)
    assert not all(torch.allclose(into[k], without[k]) for k in enc)
    for block in ("to_bev.", "to_front."):  # (to_front also learns through the cross-view attention)
        assert not all(torch.allclose(detached[k], without[k]) for k in without if k.startswith(block))


def test_unlabeled_frames_train_what_follows_the_encoder():
    """By default the encoder's gradient does not depend on the unlabeled frames (their losses
    train the view transforms, attentions and the active branch); ``unlabeled_into_encoder``: it does."""
    rng = np.random.default_rng(6)
    cfg = TrainConfig.from_dict({**TINY_RUN, "input": "rgb", "drop_connect_rate": 0.0, "consistency_ramp_steps": 0})
    h, w = input_size(TINY, RIG)

    def frames(n):
        return {"rgb": torch.from_numpy(rng.integers(0, 256, (n, 1, h, w, 3), dtype=np.uint8)),
                "target": torch.from_numpy(rng.random((n, 3, *GRID.shape)) > 0.5), "mask": None}

    labeled, u1, u2 = frames(2), frames(2), frames(2)

    def grads(unlabeled, **over):
        torch.manual_seed(0)
        m = method_class("s2g2")(replace(cfg, loss=replace(cfg.loss, **over)), RIG, GRID)
        m.loss_cfg = m.cfg.loss.loss_config()
        m.model.train()
        m.model.passive.load_state_dict({k: v + 0.05 for k, v in m.model.active.state_dict().items()
                                         if v.is_floating_point()}, strict=False)  # the branches disagree
        m.loss({"labeled": labeled, "unlabeled": unlabeled}, 0, 10)[0].backward()
        return {k: p.grad.clone() for k, p in m.model.named_parameters() if p.grad is not None}

    a, b = grads(u1), grads(u2)
    enc = [k for k in a if k.startswith("encoder.")]
    assert enc and all(torch.allclose(a[k], b[k]) for k in enc)
    assert not all(torch.allclose(a[k], b[k]) for k in a if k.startswith("active."))
    a, b = grads(u1, unlabeled_into_encoder=True), grads(u2, unlabeled_into_encoder=True)
    assert not all(torch.allclose(a[k], b[k]) for k in enc)


def test_unlabeled_drive_settings():
    cfg = TrainConfig.from_dict(TINY_RUN)
    assert cfg.unlabeled_seeds == (300_001,) and cfg.unlabeled_style == "dusk"
    assert not set(cfg.unlabeled_seeds) & ({300_000} | set(cfg.held_out_seeds))
    with pytest.raises(ConfigError, match="unlabeled_style needs unlabeled_drives"):
        TrainConfig.from_dict({**TINY_RUN, "unlabeled_drives": 0})
    with pytest.raises(ConfigError, match="not both"):
        TrainConfig.from_dict({**TINY_RUN, "unlabeled_bag": ["some.mcap"]})
    bags = TrainConfig.from_dict({**{k: v for k, v in TINY_RUN.items() if not k.startswith("unlabeled")},
                                  "unlabeled_bag": ["some.mcap"]})
    with pytest.raises(ConfigError, match="unlabeled-bag data source"):  # the core alone cannot read bags
        SynthSource().load(bags, RIG, GRID, DataNeeds(unlabeled=True), print)
    with pytest.raises(ConfigError, match="unlabeled_drives must be an integer"):
        TrainConfig.from_dict({**TINY_RUN, "unlabeled_drives": -1})
    no_unlabeled = TrainConfig.from_dict({k: v for k, v in TINY_RUN.items() if not k.startswith("unlabeled")})
    with pytest.raises(ConfigError, match="set unlabeled_drives"):  # refused before anything is rendered
        SynthSource().load(no_unlabeled, RIG, GRID, DataNeeds(unlabeled=True), print)
    with pytest.raises(ConfigError, match="does not train on unlabeled frames"):
        SynthSource().load(cfg, RIG, GRID, DataNeeds(), print)
    # bev-train: the flags land on the configs
    a = vars(train_parser("s2g2").parse_args(
        ["--method", "s2g2", "--rig", "front1", "--unlabeled-drives", "4", "--unlabeled-style", "dusk",
         "--view-transform", "fc", "--no-inter-view-attention", "--optimizer", "adam", "--ema-decay", "0.99",
         "--inference-branch", "passive", "--consistency-ramp-steps", "50"]))
    c = TrainConfig.from_dict(a)
    assert (c.unlabeled_drives, c.unlabeled_style) == (4, "dusk")
    assert c.model == S2G2Config(view_transform="fc", inter_view_attention=False)
    assert c.loss == S2G2Training(optimizer="adam", ema_decay=0.99, inference_branch="passive",
                                  consistency_ramp_steps=50)
    assert TrainConfig.from_dict(json.loads(json.dumps(c.to_dict()))) == c


@pytest.mark.slow
def test_unlabeled_frames_from_a_bag(tmp_path):
    """``bev-train --unlabeled BAG``: a front1 bag (half-size images, style dusk) gives unlabeled
    frames at the model's input size (RGB or labels, no GT read), and a run trains on them."""
    pytest.importorskip("rosbags")
    import yaml

    from bags.cli.main import main as bag_main
    from bags.io.reader import BagReader
    from bags.io.train_data import unlabeled_frameset
    from bags.io.writer import BagWriter
    from bev_mapper_core.methods.s2g2.model import input_size

    synth = tmp_path / "synth"
    assert bag_main(["synth", str(synth), "--rig", "front1", "--frames", "3", "--scale", "0.5", "--style", "dusk"]) == 0
    bag = tmp_path / "bag"  # the camera, calibration and pose topics only: a recorded drive without any GT
    with BagReader(synth) as r, BagWriter(bag) as w:
        keep = {t: s.msgtype for t, s in r.topics.items() if not t.startswith("/bev/")}
        for t, ty in keep.items():
            w.add_topic(t, ty, latched=t in r.latched_topics)
        for m in r.messages(list(keep)):
            w.write(m.topic, m.msg, m.log_ns)
    with BagReader(bag) as r:
        assert not any(t.startswith("/bev/") for t in r.topics) and "/cameras/front/image_raw" in r.topics
    size = input_size(TINY, RIG)
    fs = unlabeled_frameset([bag], RIG, DataNeeds(image_size=size, rgb=True))
    assert len(fs) >= 2 and fs.rgb.shape == (len(fs), 1, *size, 3) and fs.rgb.any()
    assert set(next(TrainData(fs, fs, fs).batches(1, 0, 0))["unlabeled"]) == {"images", "rgb", "index"}
    labels = unlabeled_frameset([bag], RIG, DataNeeds(image_size=size))
    assert labels.rgb is None and labels.labels.shape == (len(labels), 1, *size) and labels.labels.any()
    with pytest.raises(ConfigError, match="differ from the run's"):
        unlabeled_frameset([bag], preset_rig("surround6"), DataNeeds(image_size=size))
    run = {k: v for k, v in TINY_RUN.items() if not k.startswith("unlabeled")}
    cfg_file = tmp_path / "run.yaml"
    cfg_file.write_text(yaml.safe_dump({**run, "epochs": 1, "cache": str(tmp_path / "cache")}))
    out = tmp_path / "run"
    assert bev_train(["--config", str(cfg_file), "--unlabeled", str(bag), "--out", str(out)]) == 0
    assert (out / "last.safetensors").is_file()
    assert json.loads((out / "last.json").read_text())["config"]["unlabeled_bag"] == [str(bag)]


def test_encoder_starts_from_the_shipped_segmenters_trunk(tmp_path):
    """The default S2G2 config has the segmenter's trunk sizes: on RGB input its encoder starts as
    the shipped segmenter's encoder, tensor for tensor; from scratch with ``none`` or on labels."""
    seg = load_segmenter(WEIGHTS_DIR / TRUNK_SEGMENTER).state_dict()
    base = dict(method="s2g2", rig="front1", input="rgb", classes=",".join(CLASSES), grid="ahead")

    def encoder(**over):
        cfg = TrainConfig.from_dict({**base, **over})
        torch.manual_seed(0)
        return method_class("s2g2")(cfg, RIG, cfg.grid).model.encoder.state_dict()

    pre = encoder()
    assert pre and all(torch.equal(v, seg["encoder." + k]) for k, v in pre.items())
    scratch = encoder(encoder_init="none")
    assert not all(torch.equal(v, scratch[k]) for k, v in pre.items() if v.is_floating_point())
    labels = encoder(input="labels")  # auto: no RGB trunk for one-hot label input
    assert next(iter(labels.values())).shape[1] == NUM_LABELS
    with pytest.raises(ConfigError, match="read RGB images"):
        encoder(input="labels", encoder_init="segmenter")
    with pytest.raises(ConfigError, match="does not exist"):
        encoder(encoder_init=str(tmp_path / "nope.safetensors"))
    with pytest.raises(WeightsError, match="does not fit this encoder"):
        encoder(width_mult=0.5)
    assert train_parser("s2g2").parse_args(["--encoder-init", "none"]).encoder_init == "none"


def test_named_grids_and_the_paper_class_set():
    ahead = grid_preset("ahead")
    assert ahead.shape == (128, 128) and ahead.x_min == 0.0 and grid_preset("surround") == BevGrid()
    with pytest.raises(GridError, match="named grids"):
        grid_preset("behind")
    a = train_parser("s2g2").parse_args(["--grid", "ahead", "--classes", "s2g2"])
    cfg = TrainConfig.from_dict({"method": "s2g2", "rig": "front1", **vars(a)})
    assert cfg.grid == ahead and cfg.class_names == ("road", "sidewalk", "terrain", "obstacle")
    assert TrainConfig.from_dict(cfg.to_dict()).grid == ahead  # saved with the checkpoint
    with pytest.raises(SystemExit):
        train_parser("s2g2").parse_args(["--grid", "behind"])
    # the paper's obstacle layer is everything standing on the ground, terrain the verges
    lut = label_lut(S2G2_CLASSES)
    assert lut[Label.BUILDING, 3] and lut[Label.VEHICLE, 3] and not lut[Label.ROAD, 3] and lut[Label.TERRAIN, 2]
    assert lut[Label.LANE_DIVIDER, 0] and not lut[Label.TERRAIN, 0]


@pytest.mark.slow
def test_semi_supervised_run_through_the_trainer(tmp_path):
    """The real trainer and the synthetic source: 1 labeled, 1 unlabeled (held-out style dusk)
    and 1 held-out drive of 4 frames, paper optimizer (SGD): the loss falls, the passive branch
    follows the active one, the checkpoint loads back and names its inference branch."""
    cfg = TrainConfig.from_dict({**TINY_RUN, "out": str(tmp_path / "run"), "cache": str(tmp_path / "cache")})
    logs = []
    doc = train(cfg, log=logs.append)
    assert any("4 training / 4 unlabeled / 4 held-out frames" in m for m in logs), logs
    losses = [h["loss_total"] for h in doc["history"]]
    assert len(losses) == 5 and all(np.isfinite(losses)) and losses[-1] < losses[0], losses
    assert doc["history"][-1]["loss_gamma"] == 1.0 and doc["step"] == 10
    model, meta = load_s2g2(tmp_path / "run" / "last.safetensors", RIG)
    assert meta["inference_branch"] == "active" and model.config == cfg.model
    fresh = S2G2(cfg.model, RIG, cfg.grid)
    moved = [not torch.equal(p, q) for p, q in zip(model.passive.parameters(), fresh.passive.parameters())]
    differs = [not torch.equal(p, q) for p, q in zip(model.passive.parameters(), model.active.parameters())]
    assert all(moved) and any(differs)  # an average of the active weights, not a copy
    assert not any((tmp_path / "run").glob("*.pt"))
    # resuming continues with the EMA and the SGD momentum
    more = train(replace(cfg, epochs=6, resume=True), log=lambda m: None)
    assert more["step"] == 12 and len(more["history"]) == 6


# ------------------------------------------------------------------------- the bag tool
@pytest.mark.slow
def test_replay_maps_a_front1_bag_with_the_shipped_s2g2_weights(tmp_path):
    """``bev-bag synth --rig front1 --grid ahead`` then ``bev-bag replay --method s2g2 --input rgb``:
    the shipped weights are found from the bag's rig, the bag's GT grid is the weights' grid, and
    the output grids are the core mapper's on the bag's RGB images, scored against the bag's GT."""
    from bags.cli.main import main
    from bags.io.reader import BagReader
    from bags.replay import BAG_DIR, METRICS_FILE

    bag, out = tmp_path / "bag", tmp_path / "out"
    assert main(["synth", str(bag), "--rig", "front1", "--grid", "ahead", "--frames", "3", "--seed", "950000013",
                 "--style", "dusk"]) == 0
    assert main(["replay", str(bag), "--out", str(out), "--method", "s2g2", "--backend", "torch", "--input", "rgb", "--no-pictures",
                 "--no-report", "--quiet"]) == 0
    m = json.loads((out / METRICS_FILE).read_text())
    assert m["method"] == "s2g2" and m["input"] == "rgb" and 0.0 < m["miou"] <= 1.0
    assert m["weights"] == shipped_s2g2("front1", "rgb").name  # the file that ran
    assert set(m["classes"]) == set(read_s2g2_metadata(shipped_s2g2("front1", "rgb"))["classes"])
    with BagReader(bag) as r:
        assert r.grid() == grid_preset("ahead")
        mapper = create_mapper(r.rig(), r.grid(), MapperConfig(backend="torch", method="s2g2", input_kind="rgb"))
        expected = {f.stamp_ns: mapper.map(f.rgb) for f in r.frames(labels=False)}
    with BagReader(out / BAG_DIR) as r:
        got = {}
        for msg in r.messages(["/bev/drivable"]):
            got[msg.msg.header.stamp.sec * 1_000_000_000 + msg.msg.header.stamp.nanosec] = np.asarray(msg.msg.data)
    assert sorted(got) == sorted(expected)
    ci = mapper.class_names.index("drivable")
    for stamp, pred in expected.items():
        np.testing.assert_array_equal(got[stamp], grid_preset("ahead").to_occupancy(pred.probs[ci], pred.known))


@pytest.mark.slow
def test_eval_scores_rgb_mappers_on_the_named_grid(tmp_path, capsys):
    """``bev-train eval --input rgb --style dusk --grid ahead``: the held-out drives are rendered on
    that grid with their camera images in that style, and the mapper reads the RGB images."""
    torch.manual_seed(0)
    weights = save_s2g2(S2G2(replace(TINY, classes=("drivable", "sidewalk")), RIG, grid_preset("ahead")),
                        tmp_path / "w.safetensors")
    args = ["eval", "--rig", "front1", "--grid", "ahead", "--input", "rgb", "--style", "dusk", "--val-seeds",
            "950000013", "--frames-per-drive", "2", "--cache", str(tmp_path / "cache"), "--threads", "1"]
    assert bev_train([*args, "--method", "s2g2", "--weights", str(weights), "--classes", "drivable,sidewalk",
                     "--json", str(tmp_path / "s2g2.json")]) == 0
    res = json.loads((tmp_path / "s2g2.json").read_text())
    assert res["input_kind"] == "rgb" and res["style"] == "dusk" and res["grid"] == grid_preset("ahead").to_dict()
    assert set(res["classes"]) == {"drivable", "sidewalk"} and res["frames"] == 2
    cache = list((tmp_path / "cache").iterdir())
    assert len(cache) == 1 and "rgb400_dusk" in cache[0].name  # full-size camera images, the asked style
    # the same drives through segipm (the segmenter on the RGB images) and IPM (the true labels)
    assert bev_train([*args, "--method", "segipm", "--classes", "drivable,sidewalk",
                     "--json", str(tmp_path / "segipm.json")]) == 0
    assert bev_train([*args[:5], *args[9:], "--input", "labels", "--method", "ipm", "--classes", "drivable,sidewalk",
                     "--json", str(tmp_path / "ipm.json")]) == 0
    seg, ipm = (json.loads((tmp_path / f"{n}.json").read_text()) for n in ("segipm", "ipm"))
    assert ipm["input_kind"] == "labels" and seg["input_kind"] == "rgb"
    assert ipm["miou"] > 0.5 and seg["miou"] > 0.5 and ipm["miou"] != seg["miou"]
