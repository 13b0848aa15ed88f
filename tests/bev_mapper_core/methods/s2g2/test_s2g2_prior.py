"""S2G2's ``prior_skip`` (issue #39): segipm's map of the image enters both branches; an untrained
model maps as segipm does; training caches the prior once and gives the uncached losses; the
mapper runs it from a weights file."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from model_helpers import prior_losses, random_rgb_data, tiny_run

from bev_mapper_core.errors import ConfigError
from bev_mapper_core.geometry.grid import BevGrid
from bev_mapper_core.geometry.rig import preset_rig
from bev_mapper_core.mapper import MapperConfig, create_mapper
from bev_mapper_core.methods.s2g2.model import PRIOR_LOGIT_SCALE, S2G2, S2G2Config
from bev_mapper_core.methods.s2g2.weights import save_s2g2
from bev_mapper_core.methods.segipm.prior import SegIpmPrior
from bev_mapper_core.training.config import TrainConfig
from bev_mapper_core.training.data import render_drive
from bev_mapper_core.training.method import method_class
from bev_mapper_core.training.sources import TrainData

torch.set_num_threads(1)
RIG = preset_rig("front1")
GRID = BevGrid(0.0, 16.0, -8.0, 8.0, 0.5)
CLASSES = ("drivable", "vehicle", "pedestrian")
SMALL = dict(input_width=32, width_mult=0.25, depth_mult=0.25, encoder_stages=3, bev_downsample=4,
             decoder_channels=8)
RUN = dict(method="s2g2", rig="front1", input="rgb", classes=",".join(CLASSES), batch=2, lr=3e-3, seed=3,
           consistency_ramp_steps=4, grid=[0.0, 16.0, -8.0, 8.0, 0.5], encoder_init="none", optimizer="adam",
           progress=False, augment=False, frozen_encoder=True, prior_skip=True, **SMALL)


@pytest.fixture(scope="module")
def drive():
    """Two rendered front1 frames with their camera-size RGB images."""
    w, h = RIG.cameras[0].model.image_size
    return render_drive(RIG, GRID, CLASSES, seed=900000003, frames=2, stride=6, rgb=(h, w))


@pytest.mark.parametrize("pool", [False, True])
def test_untrained_prior_skip_model_gives_the_priors_logits(pool):
    model = S2G2(S2G2Config(classes=CLASSES, prior_skip=True, prior_pool=pool, **SMALL), RIG, GRID).eval()
    assert model.prior_channels == len(CLASSES) + 1
    x = torch.randn(2, 3, *model.input_size)
    prior = torch.rand(2, len(CLASSES) + 1, *GRID.shape)
    for branch in ("active", "passive"):
        logits = model.logits(x, branch, prior)
        assert logits.shape == (2, len(CLASSES), *GRID.shape)
        torch.testing.assert_close(logits, PRIOR_LOGIT_SCALE * prior[:, :-1] - PRIOR_LOGIT_SCALE / 2)
    out = model(x, prior=prior)
    assert out["active_logits"].shape == out["passive_logits"].shape == (2, len(CLASSES), *GRID.shape)
    with pytest.raises(ValueError, match="needs the prior"):
        model.logits(x)
    with pytest.raises(ValueError, match="needs the prior"):
        model.logits(x, prior=prior[:, :2])
    with pytest.raises(ConfigError, match="input_kind 'rgb'"):
        S2G2Config(input_kind="labels", prior_skip=True)
    with pytest.raises(ConfigError, match="needs prior_skip"):
        S2G2Config(prior_pool=True)
    if pool:  # the pooled prior reaches the branch's first layer: its input is C + K + 1 wide
        assert model.active.stem[0][0].in_channels == model.encoder.out_channels + len(CLASSES) + 1


def test_prior_is_segipms_map(drive):
    prior = SegIpmPrior(RIG, GRID, CLASSES)
    segipm = create_mapper(RIG, GRID, MapperConfig(method="segipm", input_kind="rgb", classes=CLASSES))
    img = drive["rgb"][0, 0]
    p = prior.one(img)
    ref = segipm.map({RIG.names[0]: img})
    assert p.shape == (len(CLASSES) + 1, *GRID.shape) and p.dtype == np.float32
    np.testing.assert_array_equal(p[:-1], ref.probs)
    np.testing.assert_array_equal(p[-1], ref.known.astype(np.float32))
    assert p[0].max() == 1.0  # the road is mapped
    both = prior.batch(torch.from_numpy(drive["rgb"]))
    assert both.shape == (2, len(CLASSES) + 1, *GRID.shape)
    torch.testing.assert_close(both[0], torch.from_numpy(p))


def test_mapper_with_untrained_prior_weights_decides_as_segipm(tmp_path, drive):
    model = S2G2(S2G2Config(classes=CLASSES, prior_skip=True, **SMALL), RIG, GRID)
    path = save_s2g2(model, tmp_path / "s2g2_prior.safetensors")
    mapper = create_mapper(RIG, GRID, MapperConfig(method="s2g2", input_kind="rgb", weights=str(path),
                                                   backend="torch"))
    segipm = create_mapper(RIG, GRID, MapperConfig(method="segipm", input_kind="rgb", classes=CLASSES))
    for i in range(2):
        img = {RIG.names[0]: drive["rgb"][i, 0]}
        got, ref = mapper.map(img), segipm.map(img)
        assert got.classes == CLASSES
        np.testing.assert_array_equal(got.probs > 0.5, ref.probs > 0.5)


def _data(drive) -> TrainData:
    return random_rgb_data(drive["rgb"], CLASSES, GRID, RIG.names)


def _losses(drive, copies: int, steps: int = 4):
    cfg = TrainConfig.from_dict({**RUN, "feature_copies": copies})
    return prior_losses("s2g2", cfg, RIG, _data(drive), steps, epochs=4)


def test_cached_prior_and_features_give_the_uncached_losses(drive):
    uncached, m0 = _losses(drive, 0)
    cached, m1 = _losses(drive, 1)
    assert len(cached) == len(uncached) == 4
    np.testing.assert_allclose(cached, uncached, rtol=1e-5, atol=1e-6)
    prior = m1._priors["train"]
    assert prior.shape == (4, len(CLASSES) + 1, *GRID.shape)
    torch.testing.assert_close(prior[:1], m1._prior_fn.batch(m1_data_rgb(drive, 0)))
    # the prior's projection trains with the rest
    assert not torch.equal(m1.model.prior_proj.weight, S2G2(m1.model.config, RIG, GRID).prior_proj.weight)
    m1.model.eval()
    with torch.no_grad():
        probs, known = m1.predict({"rgb": torch.from_numpy(drive["rgb"][:1])})
    assert probs.shape == (1, len(CLASSES), *GRID.shape) and known.shape == (1, *GRID.shape)


def m1_data_rgb(drive, seed_frame: int) -> torch.Tensor:
    """The RGB image of the first training frame of :func:`_data` ``(1, 1, H, W, 3)``."""
    idx = np.random.default_rng(0).integers(0, 2, 4)
    return torch.from_numpy(drive["rgb"][idx[seed_frame:seed_frame + 1]])


def test_class_pos_weights_override_the_auto_weights(drive):
    from bev_mapper_core.methods.s2g2.train import S2G2Training

    assert S2G2Training(pos_weight_classes="pedestrian=10, vehicle=2.5").class_pos_weights() == {
        "pedestrian": 10.0, "vehicle": 2.5}
    for bad in ("pedestrian", "pedestrian=0.5", "=3", "vehicle=x"):
        with pytest.raises(ConfigError, match="name=weight"):
            S2G2Training(pos_weight_classes=bad)
    with pytest.raises(ConfigError, match="needs pos_weight 'auto'"):
        S2G2Training(pos_weight="none", pos_weight_classes="pedestrian=10")
    cfg = TrainConfig.from_dict({**RUN, "pos_weight_max": 1.5, "pos_weight_classes": "pedestrian=7"})
    m = method_class("s2g2")(cfg, RIG, cfg.grid)
    data = _data(drive)
    m.prepare(data, lambda _: None)
    pw = dict(zip(CLASSES, m.loss_cfg.pos_weight))
    assert pw["pedestrian"] == 7.0 and 1.0 <= pw["vehicle"] <= 1.5 and pw["drivable"] <= 1.5
    bad = TrainConfig.from_dict({**RUN, "pos_weight_classes": "cyclist=3"})
    with pytest.raises(ConfigError, match="cyclist"):
        method_class("s2g2")(bad, RIG, bad.grid).prepare(data, lambda _: None)


def _run(drive, out, logs=None, **extra):
    """A tiny prior_skip run through the trainer on :func:`_data` (two cached, augmented copies):
    ``(loss_total per epoch, last weights)``; ``logs`` collects the trainer's messages."""
    return tiny_run({**RUN, "augment": True, "feature_copies": 2, "epochs": 2, "threads": 1, **extra},
                    _data(drive), out, logs)


@pytest.mark.slow
def test_resume_with_the_prior_equals_an_uninterrupted_run(tmp_path, drive):
    losses, a = _run(drive, tmp_path / "a")
    _run(drive, tmp_path / "b", epochs=1)
    logs: list[str] = []
    losses_b, b = _run(drive, tmp_path / "b", logs, resume=True)
    assert any(m.startswith("resumed") and "after epoch 1" in m for m in logs)  # only epoch 2 trained here
    assert len(losses) == 2 and losses_b == losses
    assert a.keys() == b.keys() and all(torch.equal(a[k], b[k]) for k in a)
    assert "prior_proj.weight" in a
