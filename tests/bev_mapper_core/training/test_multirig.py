"""Training on random rigs (issue #38): batches never mix rigs, a rig-free Bi-Mapper trains on
them, its weights say "any rig" and map rigs no training drive used (other camera counts, image
sizes and aspect ratios), and the default lookup falls back to them for a rig without weights.
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

torch = pytest.importorskip("torch")

import bev_mapper_core.methods as methods  # noqa: E402
from bev_mapper_core.errors import ConfigError  # noqa: E402
from bev_mapper_core.geometry.camera import CameraModel  # noqa: E402
from bev_mapper_core.geometry.grid import BevGrid  # noqa: E402
from bev_mapper_core.geometry.random_rig import random_rig  # noqa: E402
from bev_mapper_core.geometry.rig import preset_rig  # noqa: E402
from bev_mapper_core.mapper import MapperConfig, create_mapper  # noqa: E402
from bev_mapper_core.methods.bimapper.config import BiMapperConfig  # noqa: E402
from bev_mapper_core.methods.bimapper.model import BiMapper  # noqa: E402
from bev_mapper_core.methods.bimapper.weights import ANY_RIG, WeightsFile  # noqa: E402
from bev_mapper_core.training.config import TrainConfig  # noqa: E402
from bev_mapper_core.training.data import FrameSet  # noqa: E402
from bev_mapper_core.training.multirig import MultiRigFrames  # noqa: E402
from bev_mapper_core.training.trainer import train  # noqa: E402

TINY_GRID = (-8.0, 8.0, -4.0, 4.0, 0.5)  # 32 x 16 cells


def _frames(n: int, cams: int, tag: int) -> FrameSet:
    labels = np.full((n, cams, 6, 8), tag, np.uint8)
    return FrameSet(labels, np.zeros((n, 2, 4, 4), bool), np.ones((n, 4, 4), bool))


def test_batches_come_from_one_rig_and_cover_every_frame_once():
    rigs = [random_rig(s) for s in (1, 2, 3)]
    parts = [(r, _frames(n, len(r.cameras), i)) for i, (r, n) in enumerate(zip(rigs, (5, 3, 7)))]
    mr = MultiRigFrames(parts)
    assert len(mr) == 15
    seen = []
    for b in mr.batches(4, seed=0, epoch=1):
        tags = set(b["images"].flatten().tolist())
        assert len(tags) == 1 and b["rig"] is rigs[tags.pop()]  # one rig a batch, the right one
        assert b["images"].shape[1] == len(b["rig"].cameras)
        seen += b["index"].tolist()
    assert sorted(seen) == list(range(15))
    again = [b["index"].tolist() for b in mr.batches(4, seed=0, epoch=1)]
    other = [b["index"].tolist() for b in mr.batches(4, seed=0, epoch=2)]
    assert again != other  # the order is a function of (seed, epoch)
    assert sum(len(b["index"]) for b in mr.batches(4, 0, 1, limit=6)) == 6
    groups = list(mr.scoring_batches(4, 15))
    assert [g.tolist() for g in groups][:3] == [[0, 1, 2, 3], [4], [5, 6, 7]]
    assert mr.target[6].shape == (2, 4, 4) and mr.mask[14].shape == (4, 4)
    with pytest.raises(ConfigError, match="one rig"):
        mr.batch(np.array([4, 5]))


def _odd_rig():
    """A 2-camera rig of two image sizes and aspect ratios (640x480 beside the rig's own)."""
    rig = random_rig(950000021)
    base = rig.cameras[0]
    f = base.model.K_array[0, 0]
    odd = replace(base, name="odd", model=CameraModel(K=((f, 0.0, 320.0), (0.0, f, 240.0), (0.0, 0.0, 1.0)),
                                                        D=(0.0,) * 5, width=640, height=480),
                  ego_from_cam=tuple(map(tuple, rig.cameras[-1].ego_from_cam_array.tolist())))
    return replace(rig, name="mixed", cameras=(base, odd))


@pytest.mark.slow  # renders a few drives and trains
def test_a_rig_free_model_trains_on_random_rigs_and_maps_any_rig(tmp_path, monkeypatch):
    cfg = TrainConfig.from_dict(dict(
        rig="random", out=str(tmp_path / "run"), epochs=1, batch=2, seed=3, train_drives=2, val_drives=1,
        frames_per_drive=2, stride=2, cache=str(tmp_path / "cache"), threads=1, input_width=48, grid=TINY_GRID,
        progress=False, streams="lv", ipm_skip=True, plane_shape=[16, 12], pos_weight="none", asl=False,
        mutual="none"))
    logs = []
    doc = train(cfg, log=logs.append)
    assert doc["step"] == 2 and any("random rigs: 2" in m for m in logs)
    path = tmp_path / "run" / "last.safetensors"
    wf = WeightsFile.open(path)
    assert wf.rig_name == ANY_RIG and wf.cameras == ()
    wf.validate()
    grid = BevGrid(*TINY_GRID)
    for rig in (random_rig(950000020), preset_rig("front1"), preset_rig("surround6"), _odd_rig()):
        m = create_mapper(rig, grid, MapperConfig(method="bimapper", weights=str(path), backend="torch"))
        imgs = {c.name: np.full(c.model.image_size[::-1], 1, np.uint8) for c in rig.cameras}  # all road
        pred = m.map(imgs)
        assert pred.probs.shape == (7, *grid.shape) and pred.known.any()
        assert pred.layer("drivable")[pred.known].mean() > 0.5  # the IPM skip: road seen is drivable
    # the default lookup: a rig without weights of its own takes the weights for any rig
    monkeypatch.setattr(methods, "WEIGHTS_DIR", tmp_path / "shipped")
    (tmp_path / "shipped").mkdir()
    (tmp_path / "shipped" / "bimapper_any_labels.safetensors").write_bytes(path.read_bytes())
    m = create_mapper(random_rig(950000022), grid, MapperConfig(method="bimapper"))
    assert m.weights_path.name == "bimapper_any_labels.safetensors"
    assert any("bimapper (its shipped weights for any rig" in r for r in methods.runnable_methods("labels", "mine"))


def test_random_rigs_refuse_a_model_with_per_camera_parameters(tmp_path):
    cfg = TrainConfig.from_dict(dict(rig="random", out=str(tmp_path / "run"), streams="both", grid=TINY_GRID,
                                     input_width=48, gv_hidden=16, progress=False, threads=1))
    with pytest.raises(ConfigError, match="--streams lv"):
        train(cfg, log=lambda m: None)
    assert not (tmp_path / "run").exists()


def test_the_prior_of_cameras_of_different_sizes_equals_each_camera_alone():
    grid = BevGrid(*TINY_GRID)
    rig = _odd_rig()
    model = BiMapper(BiMapperConfig(streams="lv", ipm_skip=True, input_width=48, plane_shape=(16, 12)), rig, grid)
    rng = np.random.default_rng(0)
    imgs = [torch.from_numpy(rng.integers(0, 11, (1, *c.model.image_size[::-1]), dtype=np.uint8)) for c in rig.cameras]
    prior = model.ipm_prior(imgs)  # (1, C + 1, H, W)
    for n, cam in enumerate(rig.cameras):
        alone = BiMapper(model.config, replace(rig, cameras=(cam,)), grid)
        ref = alone.ipm_prior(imgs[n][:, None])  # (1, 1, H, W) batched as usual
        only = model.frustum[n] & ~model.frustum[1 - n]  # cells only this camera covers
        assert only.any()
        assert torch.equal(prior[0][:, only], ref[0][:, only])
    same = BiMapper(model.config, random_rig(950000020), grid)
    x = torch.from_numpy(rng.integers(0, 11, (1, len(same.rig.cameras), *same.raw_hw), dtype=np.uint8))
    assert torch.equal(same.ipm_prior(x), same.ipm_prior([x[:, i] for i in range(x.shape[1])]))
    with pytest.raises(ValueError, match="sizes"):
        model.ipm_prior(imgs[::-1])


def test_switching_rigs_with_kept_tables_never_writes_into_them():
    """A rig-free model switched between rigs whose tables the caller keeps (the trainer does, per
    rig): a table registered anew must not alias the kept one, or the next switch overwrites it.
    """
    grid = BevGrid(*TINY_GRID)
    a, b, c = random_rig(7), random_rig(8), random_rig(9)
    model = BiMapper(BiMapperConfig(streams="lv", ipm_skip=True, input_width=48, plane_shape=(16, 12)), a, grid)
    kept = {r.name: model.geometry(r) for r in (a, b, c)}
    fresh = {r.name: model.geometry(r).prior_index.copy() for r in (a, b, c)}
    for r in (b, c, a, b, c, b, a):
        model.set_rig(r, kept[r.name])
        assert np.array_equal(model.prior_index.numpy(), fresh[r.name])
    assert all(np.array_equal(kept[n].prior_index, fresh[n]) for n in kept)


def _aspect_4_3(cam):
    """``cam`` delivering 400 x 300 images (4:3) with its focal length."""
    K = cam.model.K_array
    model = CameraModel(K=((K[0, 0] / 4, 0.0, 200.0), (0.0, K[1, 1] / 4, 150.0), (0.0, 0.0, 1.0)), D=(0.0,) * 5,
                        width=400, height=300)
    return replace(cam, model=model)


def test_a_preset_name_whose_cameras_do_not_fit_its_weights_maps_with_the_weights_for_any_rig():
    """Issue #38: 'surround6' with two of its cameras, or with 4:3 images, does not fit the shipped
    surround6 weights (camera list, trained input size): the default takes the weights for any
    rig and says so once; explicit weights are never replaced.
    """
    s6 = preset_rig("surround6")
    grid = BevGrid()
    two = replace(s6, cameras=(s6["front"], s6["back"]))
    wide = replace(s6, cameras=tuple(_aspect_4_3(c) for c in s6.cameras))
    for rig, why in ((two, "cameras"), (wide, "model input 112x63")):
        m = create_mapper(rig, grid, MapperConfig(method="bimapper", backend="torch"))
        assert m.weights_path.name == "bimapper_any_labels.safetensors"
        assert len(m.notes) == 1 and why in m.notes[0] and "bimapper_surround6_labels.safetensors" in m.notes[0]
        pred = m.map({c.name: np.full(c.model.image_size[::-1], 1, np.uint8) for c in rig.cameras})
        assert pred.known.any()
    m = create_mapper(s6, grid, MapperConfig(method="bimapper", backend="torch"))
    assert m.weights_path.name == "bimapper_surround6_labels.safetensors" and m.notes == ()
    explicit = str(methods.WEIGHTS_DIR / "bimapper_surround6_labels.safetensors")
    with pytest.raises(Exception, match="cameras"):
        create_mapper(two, grid, MapperConfig(method="bimapper", weights=explicit))
