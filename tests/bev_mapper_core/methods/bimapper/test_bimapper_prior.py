"""RGB Bi-Mapper's ``prior_skip`` (issue #39): segipm's map of every camera enters the decoder head;
an untrained model maps as segipm does, through the mapper too (torch and an exported backend);
training caches the prior of the training and validation frames once, and a validation batch of
other images gets its own prior."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest
import torch
from model_helpers import RIG, TINY, random_rgb_data, step_losses

from bev_mapper_core.errors import ConfigError
from bev_mapper_core.geometry.grid import BevGrid
from bev_mapper_core.mapper import MapperConfig, create_mapper
from bev_mapper_core.methods.bimapper.config import BiMapperConfig
from bev_mapper_core.methods.bimapper.model import BiMapper
from bev_mapper_core.methods.bimapper.weights import save_weights
from bev_mapper_core.methods.segipm.prior import SegIpmPrior
from bev_mapper_core.nn.prior_skip import PRIOR_LOGIT_SCALE
from bev_mapper_core.training.config import TrainConfig
from bev_mapper_core.training.data import render_drive
from bev_mapper_core.training.method import method_class
from bev_mapper_core.training.sources import InMemorySource
from bev_mapper_core.training.trainer import train

torch.set_num_threads(1)
GRID = BevGrid(-8.0, 8.0, -4.0, 4.0, 0.5)  # 16 x 32 cells around the two cameras
CLASSES = ("drivable", "vehicle", "pedestrian")
CFG = replace(TINY, classes=CLASSES, input_kind="rgb", prior_skip=True)
RUN = dict(method="bimapper", rig="surround6", input="rgb", classes=",".join(CLASSES), batch=2, lr=3e-3, seed=3,
           grid=[-8.0, 8.0, -4.0, 4.0, 0.5], encoder_init="none", progress=False, augment=False,
           prior_skip=True, input_width=48, width_mult=0.25, depth_mult=0.25, encoder_stages=3, bev_downsample=4)


@pytest.fixture(scope="module")
def drive():
    """Two frames of the two-camera rig rendered with their RGB images ``(2, 2, 40, 64, 3)``."""
    w, h = RIG.cameras[0].model.image_size
    return render_drive(RIG, GRID, CLASSES, seed=900000003, frames=2, stride=6, rgb=(h, w))


def _images(drive, i: int) -> dict[str, np.ndarray]:
    return {name: drive["rgb"][i, n] for n, name in enumerate(RIG.names)}


def test_untrained_prior_skip_model_gives_the_priors_logits():
    model = BiMapper(CFG, RIG, GRID).eval()
    assert model.prior_channels == len(CLASSES) + 1
    raw = torch.randint(0, 256, (2, 2, 40, 64, 3), dtype=torch.uint8)
    prior = torch.rand(2, len(CLASSES) + 1, *GRID.shape)
    with torch.no_grad():
        logits = model(raw, prior=prior)["logits"]
    assert logits.shape == (2, len(CLASSES), *GRID.shape)
    torch.testing.assert_close(logits, PRIOR_LOGIT_SCALE * prior[:, :-1] - PRIOR_LOGIT_SCALE / 2)
    with pytest.raises(ValueError, match="needs the prior"):
        model(raw)
    with pytest.raises(ValueError, match="needs the prior"):
        model(raw, prior=prior[:, :2])
    with pytest.raises(ConfigError, match="input_kind 'rgb'"):
        BiMapperConfig(prior_skip=True)
    with pytest.raises(ConfigError, match="choose one"):
        replace(CFG, ipm_skip=True)
    with pytest.raises(ConfigError, match="true or false"):
        replace(CFG, prior_skip=1)
    assert replace(CFG, streams="none").streams == "none"  # the prior alone is an input


def test_prior_of_two_cameras_is_segipms_map(drive):
    prior = SegIpmPrior(RIG, GRID, CLASSES)
    segipm = create_mapper(RIG, GRID, MapperConfig(method="segipm", input_kind="rgb", classes=CLASSES))
    for images in (_images(drive, 0), {"back": drive["rgb"][0, 1]}):  # both cameras; one absent
        p, ref = prior.frame(images), segipm.map(images)
        assert p.shape == (len(CLASSES) + 1, *GRID.shape) and p.dtype == np.float32
        np.testing.assert_array_equal(p[:-1], ref.probs)
        np.testing.assert_array_equal(p[-1], ref.known.astype(np.float32))
    assert prior.frame(_images(drive, 0))[-1].sum() > prior.frame({"back": drive["rgb"][0, 1]})[-1].sum()
    both = prior.batch(torch.from_numpy(drive["rgb"]))
    assert both.shape == (2, len(CLASSES) + 1, *GRID.shape)
    torch.testing.assert_close(both[1], torch.from_numpy(prior.frame(_images(drive, 1))))
    with pytest.raises(ValueError, match=r"\(B, 2, H, W, 3\)"):
        prior.batch(torch.from_numpy(drive["rgb"][:, :1]))


@pytest.mark.parametrize("backend", ["torch", "openvino"])  # openvino: auto's pick, the model exported with the prior
def test_mapper_with_untrained_prior_weights_decides_as_segipm(tmp_path, drive, backend):
    pytest.importorskip(backend)
    path = save_weights(BiMapper(CFG, RIG, GRID), tmp_path / "bimapper_prior.safetensors")
    mapper = create_mapper(RIG, GRID, MapperConfig(method="bimapper", input_kind="rgb", weights=str(path),
                                                   backend=backend))
    assert mapper.stage is None and mapper.prior is not None  # the segmenter feeds the prior, not the model
    segipm = create_mapper(RIG, GRID, MapperConfig(method="segipm", input_kind="rgb", classes=CLASSES))
    for images in (_images(drive, 0), _images(drive, 1), {"front": drive["rgb"][1, 0]}):
        got, ref = mapper.map(images), segipm.map(images)
        assert got.classes == CLASSES
        np.testing.assert_array_equal(got.probs > 0.5, ref.probs > 0.5)
    with pytest.raises(ConfigError, match="segmenter is 'none'"):
        create_mapper(RIG, GRID, MapperConfig(method="bimapper", input_kind="rgb", weights=str(path),
                                              segmenter="none"))


def _method(drive, **extra):
    cfg = TrainConfig.from_dict({**RUN, **extra})
    torch.manual_seed(0)
    m = method_class("bimapper")(cfg, RIG, cfg.grid)
    data = random_rgb_data(drive["rgb"], CLASSES, GRID, RIG.names, unlabeled=False)
    return m, data, cfg


def test_training_caches_the_prior_of_training_and_validation_frames(drive):
    m, data, cfg = _method(drive, pos_weight_max=2.0, pos_weight_classes="pedestrian=9")
    assert m.data_needs().image_size is None  # the prior reads camera-size images
    m.prepare(data, lambda _: None)
    assert dict(zip(CLASSES, m.loss_cfg.pos_weight))["pedestrian"] == 9.0
    assert max(m.loss_cfg.pos_weight[:2]) <= 2.0
    for name, fs in (("train", data.train), ("val", data.val)):
        cached = m._priors[name]
        assert cached.shape == (len(fs), len(CLASSES) + 1, *GRID.shape)
        torch.testing.assert_close(cached[1], m._prior_fn.batch(fs.rgb[1:2])[0])
    losses = step_losses(m, data, cfg, steps=3, epochs=2)
    assert len(losses) == 3 and all(np.isfinite(losses))
    assert not torch.equal(m.model.prior_proj.weight, BiMapper(m.model.config, RIG, GRID).prior_proj.weight)
    m.model.eval()
    with torch.no_grad():
        probs, _ = m.predict(data.val.batch(np.arange(2)))
        # a batch of other images than the cached validation frames gets its own prior
        other = {"rgb": torch.from_numpy(np.ascontiguousarray(drive["rgb"][::-1])), "index": torch.arange(2)}
        own = m._prior(other, "val")
    assert probs.shape == (2, len(CLASSES), *GRID.shape)
    torch.testing.assert_close(own, m._prior_fn.batch(other["rgb"]))
    with pytest.raises(ConfigError, match="not with --rig random"):
        _method(drive, rig="random", streams="lv")[0].build_model()


class _TwoCameras(InMemorySource):
    """The frames in memory, for the two-camera rig."""

    def rig_grid(self, cfg):
        return RIG, cfg.grid


def _run(drive, out, **extra) -> tuple[list[float], dict]:
    """A tiny ``prior_skip`` run through the trainer: ``(loss_total per epoch, last weights)``."""
    from safetensors.torch import load_file

    data = random_rgb_data(drive["rgb"], CLASSES, GRID, RIG.names, unlabeled=False)
    cfg = TrainConfig.from_dict({**RUN, "augment": True, "epochs": 2, "threads": 1, "out": str(out), **extra})
    doc = train(cfg, log=lambda _: None, data=_TwoCameras(data.train, data.val))
    return [r["loss_total"] for r in doc["history"]], load_file(str(out / "last.safetensors"))


@pytest.mark.slow
def test_resume_with_the_prior_equals_an_uninterrupted_run(tmp_path, drive):
    losses, a = _run(drive, tmp_path / "a")
    _run(drive, tmp_path / "b", epochs=1)
    losses_b, b = _run(drive, tmp_path / "b", resume=True)
    assert len(losses) == 2 and losses_b == losses
    assert a.keys() == b.keys() and all(torch.equal(a[k], b[k]) for k in a)
    assert "prior_proj.weight" in a
