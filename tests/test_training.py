"""Training / evaluation machinery on a tiny configuration (tiny grid, tiny model, few frames)."""

from __future__ import annotations

import json

import numpy as np
import pytest

torch = pytest.importorskip("torch")

from bags import train_cli as cli  # noqa: E402
from bev_mapper_core.errors import ConfigError  # noqa: E402
from bev_mapper_core.grid import BevGrid  # noqa: E402
from bev_mapper_core.models import BiMapper, load_state  # noqa: E402
from bev_mapper_core.rig import preset_rig  # noqa: E402
from bev_mapper_core.training.config import TrainConfig  # noqa: E402
from bev_mapper_core.training.data import (  # noqa: E402
    VAL_SEED_BASE,
    check_disjoint,
    drive_path,
    drive_spec,
    resize_labels,
    synth_frameset,
    train_seeds,
    val_seeds,
)
from bev_mapper_core.training.trainer import train  # noqa: E402

TINY_GRID = (-8.0, 8.0, -4.0, 4.0, 0.5)  # 16 m x 8 m at 0.5 m: 32 x 16 cells
RIG = "cam2bev4"


def tiny_cfg(tmp_path, **kw) -> TrainConfig:
    """A tiny run from flat keys (as flags and old YAML give them)."""
    base = dict(rig=RIG, classes="cam2bev", out=str(tmp_path / "run"), epochs=2, batch=2, lr=1e-3, seed=3,
                train_drives=1, val_drives=1, frames_per_drive=3, stride=2, cache=str(tmp_path / "cache"),
                threads=1, input_width=48, gv_hidden=16, grid=TINY_GRID, progress=False)
    base.update(kw)
    return TrainConfig.from_dict(base)


@pytest.fixture(scope="module")
def tiny_data(tmp_path_factory):
    """(train, val) FrameSets of one 3-frame drive each, labels at the model input size."""
    cache = tmp_path_factory.mktemp("cache")
    cfg = TrainConfig.from_dict(dict(rig=RIG, classes="cam2bev", train_drives=1, val_drives=1, input_width=48,
                                     gv_hidden=16, grid=TINY_GRID, progress=False, seed=3))
    rig, grid = preset_rig(RIG), cfg.grid
    size = BiMapper(cfg.model, rig, grid).input_size
    tr = synth_frameset(rig, grid, cfg.class_names, train_seeds(3, 1), 3, 2, cache, size)
    va = synth_frameset(rig, grid, cfg.class_names, val_seeds(1), 3, 2, cache, size)
    return tr, va, cache


def test_seed_splits_are_disjoint():
    tr = train_seeds(7, 50)
    va = val_seeds(10)
    assert not set(tr) & set(va)
    assert all(s < VAL_SEED_BASE for s in tr)
    check_disjoint(tr, va)
    with pytest.raises(ConfigError):
        check_disjoint(tr, (tr[3],))
    with pytest.raises(ConfigError):  # explicit val seeds overlapping the training drives
        TrainConfig(seed=0, train_drives=5, val_seeds=(2,))
    with pytest.raises(ConfigError):  # a run seed so large that training seeds reach the val range
        train_seeds(VAL_SEED_BASE // 100_000, 1)


def test_dataset_is_deterministic_per_seed(tmp_path):
    rig, grid = preset_rig(RIG), BevGrid(*TINY_GRID)
    classes = ("road", "vehicle", "static")
    a = synth_frameset(rig, grid, classes, [11], 2, 2, None)
    b = synth_frameset(rig, grid, classes, [11], 2, 2, tmp_path)  # rendered, then cached
    c = synth_frameset(rig, grid, classes, [11], 2, 2, tmp_path)  # read from the cache
    d = synth_frameset(rig, grid, classes, [12], 2, 2, None)
    assert drive_path(tmp_path, drive_spec(rig, grid, classes, 2, 2), 11).is_file()
    for x in (b, c):
        assert np.array_equal(a.labels, x.labels) and np.array_equal(a.target, x.target)
        assert np.array_equal(a.mask, x.mask)
    assert not np.array_equal(a.labels, d.labels)
    assert a.labels.shape == (2, 4, 302, 482) and a.target.shape == (2, 3, 16, 32)
    # batch order: a function of (seed, epoch)
    o1 = [b_["target"].sum().item() for b_ in a.batches(1, 5, 0)]
    o2 = [b_["target"].sum().item() for b_ in a.batches(1, 5, 0)]
    assert o1 == o2


def test_resized_cache_matches_model_preprocess():
    rig = preset_rig(RIG)
    cfg = TrainConfig.from_dict(dict(rig=RIG, classes="cam2bev", input_width=48, gv_hidden=16, grid=TINY_GRID))
    model = BiMapper(cfg.model, rig, cfg.grid)
    rng = np.random.default_rng(0)
    full = rng.integers(0, 14, size=(1, 4, 302, 482)).astype(np.uint8)  # includes ids >= NUM_LABELS
    small = resize_labels(full, model.input_size)
    a = model.preprocess(torch.from_numpy(full))
    b = model.preprocess(torch.from_numpy(small))
    assert torch.equal(a, b)


def test_short_training_lowers_the_loss(tmp_path, tiny_data):
    tr, va, _ = tiny_data
    cfg = tiny_cfg(tmp_path, epochs=6, lr=3e-3, val_frames=2)
    doc = train(cfg, log=lambda s: None, data=(tr, va))
    losses = [h["loss_total"] for h in doc["history"]]
    assert len(losses) == 6 and all(np.isfinite(losses))
    assert losses[-1] < losses[0]
    out = tmp_path / "run"
    for name in ("last.safetensors", "last.json", "last_optim.safetensors", "best.safetensors", "best.json", "metrics.jsonl"):
        assert (out / name).is_file(), name
    assert not any(out.glob("*.pt")) and not any(out.glob("*.pkl"))
    assert json.loads((out / "last.json").read_text())["config"]["epochs"] == 6


def test_resume_continues_from_the_saved_epoch(tmp_path, tiny_data):
    tr, va, _ = tiny_data
    full = train(tiny_cfg(tmp_path / "a", epochs=3, out=str(tmp_path / "a")), log=lambda s: None, data=(tr, va))
    part = train(tiny_cfg(tmp_path / "b", epochs=2, out=str(tmp_path / "b")), log=lambda s: None, data=(tr, va))
    assert part["epoch"] == 1 and part["step"] == 4
    logs = []
    resumed = train(tiny_cfg(tmp_path / "b", epochs=3, out=str(tmp_path / "b"), resume=True), log=logs.append, data=(tr, va))
    assert any("resumed" in s and "epoch 2" in s for s in logs)
    assert resumed["epoch"] == full["epoch"] == 2 and resumed["step"] == full["step"] == 6
    rig, cfg = preset_rig(RIG), tiny_cfg(tmp_path)
    ma, mb = (BiMapper(cfg.model, rig, cfg.grid) for _ in range(2))
    load_state(ma, tmp_path / "a" / "last.safetensors")
    load_state(mb, tmp_path / "b" / "last.safetensors")
    for (ka, va_), (kb, vb) in zip(ma.state_dict().items(), mb.state_dict().items()):
        assert ka == kb and torch.allclose(va_, vb, atol=1e-6), ka
    # a run directory is never silently overwritten; resuming needs the same configuration
    from bev_mapper_core.training.trainer import TrainingError

    with pytest.raises(TrainingError):
        train(tiny_cfg(tmp_path / "b", epochs=3, out=str(tmp_path / "b")), log=lambda s: None, data=(tr, va))
    with pytest.raises(TrainingError):
        train(tiny_cfg(tmp_path / "b", epochs=4, lr=5e-4, out=str(tmp_path / "b"), resume=True), log=lambda s: None,
              data=(tr, va))


@pytest.mark.parametrize("argv", [
    ["--epochs", "0"],
    ["--epochs", "two"],
    ["--rig", "nowhere"],
    ["--streams", "both3"],
    ["--lr", "-1"],
    ["--bogus-flag"],
    ["--val-seeds", "1,x"],
    ["--seed", "0", "--train-drives", "5", "--val-seeds", "3"],
    ["--classes", "drivable,nonsense"],
])
def test_cli_rejects_bad_flags(argv, capsys, tmp_path):
    rc = cli.main(argv + ["--out", str(tmp_path / "r"), "--no-progress"])
    err = capsys.readouterr().err
    assert rc != 0
    assert "error:" in err
    assert not (tmp_path / "r" / "last.json").exists()


def test_cli_resume_without_checkpoint_is_an_error(capsys, tmp_path):
    rc = cli.main(["--out", str(tmp_path / "none"), "--resume", "--no-progress"])
    assert rc == 1 and "error:" in capsys.readouterr().err


def test_config_from_yaml(tmp_path):
    p = tmp_path / "c.yaml"
    p.write_text("rig: cam2bev4\nepochs: 3\nstreams: gv\nval_seeds: [900000005]\n")
    cfg = TrainConfig.from_yaml(p, epochs=4)
    assert cfg.rig == "cam2bev4" and cfg.epochs == 4 and cfg.model.streams == "gv" and cfg.val_seeds == (900000005,)
    assert cfg.class_names == cfg.model.classes == ("road", "vehicle", "static")
    p.write_text("epochs: 3\nwhat: 1\n")
    with pytest.raises(ConfigError):
        TrainConfig.from_yaml(p)
    # paper schedule scaled: lr step at 10/30, mutual both ways from the 5th of 30 epochs
    assert TrainConfig(epochs=30).lr_step == 10 and TrainConfig(epochs=30).loss.mutual_start(30) == 4
    assert TrainConfig(epochs=9).lr_step == 3


def test_training_on_a_bag_with_gt(tmp_path, capsys):
    pytest.importorskip("rosbags")
    from bags.cli import main as bag_main

    bag = tmp_path / "bag"
    g = [str(v) for v in TINY_GRID]
    assert bag_main(["synth", str(bag), "--rig", RIG, "--frames", "3", "--grid-x-min", g[0], "--grid-x-max", g[1],
                     "--grid-y-min", g[2], "--grid-y-max", g[3], "--grid-res", g[4]]) == 0
    from bags.train_data import bag_frameset, bag_rig_grid

    rig, grid = bag_rig_grid(bag)
    assert rig.names == preset_rig(RIG).names and grid == BevGrid(*TINY_GRID)
    fs = bag_frameset([bag], ("drivable", "vehicle"), rig, grid)
    assert len(fs) == 3 and fs.target.shape == (3, 2, 16, 32) and fs.labels.shape[1] == 4 and fs.mask.any()
    out = tmp_path / "run"
    rc = cli.main(["--bag", str(bag), "--val-bag", str(bag), "--rig", RIG, "--classes", "drivable,vehicle", "--epochs", "1",
                   "--batch", "2", "--input-width", "48", "--gv-hidden", "16", "--threads", "1", "--out", str(out),
                   "--no-progress"])
    assert rc == 0 and (out / "best.safetensors").is_file()
    with pytest.raises(ConfigError):  # a class the bag has no GT topic for
        bag_frameset([bag], ("road",), rig, grid)
