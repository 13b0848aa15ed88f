"""FocusBEV's ``prior_skip`` on a frozen trunk (issue #39): an untrained model maps as segipm does,
through the mapper too; the cached prior and trunk features give the uncached losses; ``--resume``
is exact."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from model_helpers import prior_losses, random_rgb_data, tiny_run

from bev_mapper_core.errors import ConfigError
from bev_mapper_core.geometry.grid import BevGrid
from bev_mapper_core.geometry.rig import preset_rig
from bev_mapper_core.mapper import MapperConfig, create_mapper
from bev_mapper_core.methods.focusbev.model import FocusBEV, FocusBEVConfig
from bev_mapper_core.methods.focusbev.weights import save_focusbev
from bev_mapper_core.nn.prior_skip import PRIOR_LOGIT_SCALE
from bev_mapper_core.training.config import TrainConfig
from bev_mapper_core.training.data import render_drive
from bev_mapper_core.training.method import method_class
from bev_mapper_core.training.sources import TrainData

torch.set_num_threads(1)
RIG = preset_rig("front1")
GRID = BevGrid(0.0, 16.0, -8.0, 8.0, 0.5)
CLASSES = ("drivable", "vehicle", "pedestrian")
SMALL = dict(input_width=64, backbone="efficientnet", fpn_levels=2, channels=16, decoder_layers=1, heads=2,
             window=1, decoder_channels=8)
RUN = dict(method="focusbev", rig="front1", input="rgb", classes=",".join(CLASSES), batch=2, lr=3e-3, seed=3,
           grid=[0.0, 16.0, -8.0, 8.0, 0.5], encoder_init="none", progress=False, augment=False,
           frozen_encoder=True, prior_skip=True, **SMALL)


@pytest.fixture(scope="module")
def drive():
    """Two rendered front1 frames with their camera-size RGB images."""
    w, h = RIG.cameras[0].model.image_size
    return render_drive(RIG, GRID, CLASSES, seed=900000003, frames=2, stride=6, rgb=(h, w))


@pytest.mark.parametrize("window", [1, 2])
def test_untrained_prior_skip_model_gives_the_priors_logits(window):
    model = FocusBEV(FocusBEVConfig(classes=CLASSES, prior_skip=True, **{**SMALL, "window": window}), RIG, GRID).eval()
    assert model.prior_channels == len(CLASSES) + 1
    x = torch.randn(2, 3, *model.input_size)
    prior = torch.rand(2, len(CLASSES) + 1, *GRID.shape)
    with torch.no_grad():
        logits = model(x, prior=prior)["logits"]
    assert logits.shape == (2, len(CLASSES), *GRID.shape)
    torch.testing.assert_close(logits, PRIOR_LOGIT_SCALE * prior[:, :-1] - PRIOR_LOGIT_SCALE / 2)
    with pytest.raises(ValueError, match="needs the prior"):
        model(x)
    with pytest.raises(ConfigError, match="input_kind 'rgb'"):
        FocusBEVConfig(input_kind="labels", prior_skip=True)


def test_mapper_with_untrained_prior_weights_decides_as_segipm(tmp_path, drive):
    model = FocusBEV(FocusBEVConfig(classes=CLASSES, prior_skip=True, **{**SMALL, "window": 2}), RIG, GRID)
    path = save_focusbev(model, tmp_path / "focusbev_prior.safetensors", 0.3)
    mapper = create_mapper(RIG, GRID, MapperConfig(method="focusbev", input_kind="rgb", weights=str(path),
                                                   backend="torch"))
    segipm = create_mapper(RIG, GRID, MapperConfig(method="segipm", input_kind="rgb", classes=CLASSES))
    for i in range(2):  # the second frame is fused with the first from the memory bank
        img = {RIG.names[0]: drive["rgb"][i, 0]}
        got = mapper.map(img, ego_pose=np.eye(4), stamp_ns=i * 300_000_000)
        ref = segipm.map(img)
        assert got.classes == CLASSES and got.frames == i + 1
        np.testing.assert_array_equal(got.probs > 0.5, ref.probs > 0.5)


def _data(drive) -> TrainData:
    return random_rgb_data(drive["rgb"], CLASSES, GRID, RIG.names, unlabeled=False)


def _losses(drive, copies: int, steps: int = 3):
    cfg = TrainConfig.from_dict({**RUN, "feature_copies": copies, "pos_weight_max": 1.5,
                                 "pos_weight_classes": "pedestrian=7"})
    return prior_losses("focusbev", cfg, RIG, _data(drive), steps, epochs=3)


def test_cached_prior_and_features_give_the_uncached_losses(drive):
    uncached, m0 = _losses(drive, 0)
    cached, m1 = _losses(drive, 1)
    assert len(cached) == len(uncached) == 3
    np.testing.assert_allclose(cached, uncached, rtol=1e-5, atol=1e-6)
    assert m1._priors.shape == (4, len(CLASSES) + 1, *GRID.shape)
    pw = dict(zip(CLASSES, m1.pos_weight.tolist()))
    assert pw["pedestrian"] == 7.0 and pw["vehicle"] <= 1.5
    # the trunk stays as it started, the prior's projection trains
    fresh = FocusBEV(m1.model.config, RIG, GRID)
    assert not torch.equal(m1.model.prior_proj.weight, fresh.prior_proj.weight)
    m1.model.eval()
    with torch.no_grad():
        probs, known = m1.predict({"rgb": torch.from_numpy(drive["rgb"][:1])})
    assert probs.shape == (1, len(CLASSES), *GRID.shape) and known.shape == (1, *GRID.shape)
    for bad in ({"window": 2, "feature_copies": 1}, {"backbone": "resnet"}):
        cfg = TrainConfig.from_dict({**RUN, **bad})
        with pytest.raises(ConfigError, match="window 1|pretrained trunk"):
            method_class("focusbev")(cfg, RIG, cfg.grid)


def _run(drive, out, logs=None, **extra):
    """A tiny prior_skip run through the trainer on :func:`_data` (two cached, augmented copies):
    ``(loss_total per epoch, last weights)``."""
    return tiny_run({**RUN, "augment": True, "feature_copies": 2, "epochs": 2, "threads": 1, **extra},
                    _data(drive), out, logs)


def test_resume_with_the_prior_equals_an_uninterrupted_run(tmp_path, drive):
    losses, a = _run(drive, tmp_path / "a")
    _run(drive, tmp_path / "b", epochs=1)
    logs: list[str] = []
    losses_b, b = _run(drive, tmp_path / "b", logs, resume=True)
    assert any(m.startswith("resumed") and "after epoch 1" in m for m in logs)
    assert len(losses) == 2 and losses_b == losses
    assert a.keys() == b.keys() and all(torch.equal(a[k], b[k]) for k in a)
    assert "prior_proj.weight" in a


def test_windows_train_on_the_prior_of_their_last_frame(drive):
    """Window 2 (the memory bank, uncached trunk): each window's cached prior is its last frame's."""
    from bev_mapper_core.methods.segipm.prior import SegIpmPrior
    from bev_mapper_core.training.data import FrameSet

    rgb = drive["rgb"][[0, 1, 1, 0]]  # (4, 1, H, W, 3): drive 0 = frames 0, 1; drive 1 = frames 2, 3
    rng = np.random.default_rng(1)
    fs = FrameSet(np.zeros((4, 1, 4, 4), np.uint8), rng.random((4, len(CLASSES), *GRID.shape)) > 0.6,
                  np.ones((4, *GRID.shape), bool), camera_names=RIG.names, rgb=rgb,
                  poses=np.repeat(np.eye(4)[None], 4, 0), stamps=np.arange(4, dtype=np.int64) * 300_000_000,
                  drives=np.array([0, 0, 1, 1]))
    fs.window = 2
    cfg = TrainConfig.from_dict({**RUN, "window": 2, "feature_copies": 0})
    losses, m = prior_losses("focusbev", cfg, RIG, TrainData(fs, fs, None), 2, epochs=1)
    assert len(losses) == 2 and np.isfinite(losses).all()
    prior = SegIpmPrior(RIG, GRID, CLASSES)
    want = torch.from_numpy(np.stack([prior.one(rgb[i, 0]) for i in range(4)]))
    assert not torch.equal(want[0], want[1])  # frame 1's window also holds frame 0's image
    torch.testing.assert_close(m._priors, want)
