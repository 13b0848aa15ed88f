"""Tiny RGB runs of the BEV methods that augment their camera images (issue #24: S2G2, FocusBEV,
Bi-Mapper on RGB input), in memory, and spies on what their model sees and what their loss reads."""

from __future__ import annotations

import json

import numpy as np
import pytest
import torch
from safetensors.torch import load_file

from bev_mapper_core.errors import ConfigError
from bev_mapper_core.geometry.rig import preset_rig
from bev_mapper_core.training.config import TrainConfig
from bev_mapper_core.training.data import FrameSet
from bev_mapper_core.training.method import method_class
from bev_mapper_core.training.sources import InMemorySource, TrainData, with_window
from bev_mapper_core.training.trainer import train

GRID = [0.0, 16.0, -8.0, 8.0, 0.5]  # 32 x 32 cells ahead
CLASSES = ("drivable", "vehicle", "lane_divider")
#: per method: tiny run keys (as bev-train flags give them), frames per drive (windows: poses), unlabeled frames
RUNS = {
    "s2g2": (dict(method="s2g2", rig="front1", input_width=32, width_mult=0.25, depth_mult=0.25, encoder_stages=3,
                  bev_downsample=4, decoder_channels=8, encoder_init="none", consistency_ramp_steps=4), None, True),
    "focusbev": (dict(method="focusbev", rig="front1", input="rgb", input_width=64, backbone_width=8, fpn_levels=2,
                      channels=16, decoder_layers=1, heads=2, window=2, decoder_channels=8, stride=3), 3, False),
    "bimapper": (dict(method="bimapper", rig="front1", input="rgb", input_width=48, width_mult=0.25, depth_mult=0.25,
                      encoder_stages=3, neck_channels=16, bev_channels=8, bev_downsample=4, unet_channels=8,
                      decoder_channels=16, gv_hidden=16), None, False),
}
#: ``loss_total`` per epoch of :func:`tiny_run` ``(name, augment=False)``, recorded with the code before
#: any of these methods augmented (commit 9d6d173; the same run then, bit for bit): --no-augment is that run.
BEFORE = {
    "s2g2": [1.3004830280939739, 1.2694988648096721],
    "focusbev": [0.7721917033195496, 0.7638417879740397],
    "bimapper": [1.662850260734558, 1.632400671641032],
}


def frames(rig: str, hw: tuple[int, int], n: int, seed: int, per: int | None = None) -> FrameSet:
    """``n`` frames of random RGB images at ``hw`` and random targets on :data:`GRID`; ``per``:
    drives of that many frames with poses 0.8 m apart (windows)."""
    rng = np.random.default_rng(seed)
    names = preset_rig(rig).names
    h, w = hw
    kw = {}
    if per:
        poses = np.tile(np.eye(4), (n, 1, 1))
        poses[:, 0, 3] = 0.8 * (np.arange(n) % per)
        kw = dict(poses=poses, stamps=np.tile(np.arange(per) * 300_000_000, n // per),
                  drives=np.repeat(np.arange(n // per), per))
    return FrameSet(np.zeros((n, len(names), h, w), np.uint8), rng.random((n, 3, 32, 32)) > 0.6,
                    np.ones((n, 32, 32), bool), camera_names=names,
                    rgb=rng.integers(0, 256, (n, len(names), h, w, 3), dtype=np.uint8), **kw)


def tiny_cfg(name: str, out, **extra) -> TrainConfig:
    keys, _, _ = RUNS[name]
    base = dict(classes=",".join(CLASSES), epochs=2, batch=2, lr=1e-3, seed=1, threads=1, progress=False, grid=GRID,
                out=str(out))
    return TrainConfig.from_dict({**base, **keys, **extra})


def tiny_data(cfg: TrainConfig) -> tuple[FrameSet, ...]:
    """Training (6), held-out (3) and, for S2G2, unlabeled (6) frames at the method's input size."""
    _, per, unlabeled = RUNS[cfg.method]
    hw = method_class(cfg.method)(cfg, preset_rig(cfg.rig), cfg.grid).model.input_size
    sets = [frames(cfg.rig, hw, 6, 0, per), frames(cfg.rig, hw, 3, 1, per)]
    return tuple(sets + ([frames(cfg.rig, hw, 6, 2)] if unlabeled else []))


def tiny_run(name: str, out, **extra) -> tuple[list[float], dict[str, torch.Tensor]]:
    """Train :func:`tiny_cfg` on :func:`tiny_data`: ``(loss_total per epoch, last weights)``."""
    cfg = tiny_cfg(name, out, **extra)
    doc = train(cfg, log=lambda m: None, data=InMemorySource(*tiny_data(cfg)))
    return [r["loss_total"] for r in doc["history"]], load_file(str(out / "last.safetensors"))


def resume_check(name: str, tmp_path) -> None:
    """With augmentation on (the default), 1 epoch + ``--resume`` to 2 gives the weights of 2 epochs
    at once, and losses other than the --no-augment run's."""
    losses, a = tiny_run(name, tmp_path / "a")
    tiny_run(name, tmp_path / "b", epochs=1)
    _, b = tiny_run(name, tmp_path / "b", resume=True)
    assert a.keys() == b.keys() and all(torch.equal(a[k], b[k]) for k in a)
    assert losses != pytest.approx(BEFORE[name], rel=1e-4)


def no_augment_check(name: str, tmp_path) -> None:
    """--no-augment: the losses of the run before augmentation existed (:data:`BEFORE`), to float rounding."""
    losses, _ = tiny_run(name, tmp_path / "plain", augment=False)
    assert losses == pytest.approx(BEFORE[name], rel=1e-5, abs=1e-6)


def flag_check(name: str, training_type, tmp_path, base: tuple[str, ...] = ()) -> None:
    """``augment`` is a ``--augment/--no-augment`` flag of ``bev-train --method NAME`` and a YAML
    key of the method's training settings, default on, validated."""
    from bags.cli.train.train import train_parser  # noqa: PLC0415

    args = vars(train_parser(name).parse_args(["--method", name, *base, "--no-augment"]))
    cfg = TrainConfig.from_dict(args)
    assert cfg.loss == training_type(augment=False)
    assert TrainConfig.from_dict(json.loads(json.dumps(cfg.to_dict()))) == cfg  # last.json reads back
    assert vars(train_parser(name).parse_args(["--method", name, "--augment"]))["augment"] is True
    assert TrainConfig.from_dict({"method": name}).loss.augment is True and training_type().augment is True
    y = tmp_path / "run.yaml"
    y.write_text(f"method: {name}\naugment: false\n")
    assert TrainConfig.from_yaml(y).loss == training_type(augment=False)
    assert TrainConfig.from_yaml(y, augment=True).loss.augment is True  # a flag over the YAML key
    with pytest.raises(ConfigError, match="augment"):
        training_type(augment="yes")


class Spy:
    """Records the images a method's model is fed (``(B, ..., H, W, 3)`` raw, at ``preprocess`` or
    the model's ``forward``) and the target its loss function reads, by patching ``module.<loss_fn>``."""

    def __init__(self, monkeypatch, module, loss_fn: str, target_arg: int, model, at: str = "preprocess") -> None:
        self.images, self.targets = [], []
        fn = getattr(module, loss_fn)

        def loss(*a, **kw):
            t = a[target_arg]
            self.targets.append((t["target"] if isinstance(t, dict) else t).detach().clone())
            return fn(*a, **kw)

        monkeypatch.setattr(module, loss_fn, loss)
        if at == "preprocess":
            pre = model.preprocess

            def preprocess(images, *a, **kw):
                self.images.append(images.detach().clone())
                return pre(images, *a, **kw)

            monkeypatch.setattr(model, "preprocess", preprocess)
        else:
            model.register_forward_pre_hook(lambda mod, args: self.images.append(args[0].detach().clone()))


def method_and_batch(name: str, tmp_path, **extra):
    """A built and prepared method of :func:`tiny_cfg` and the first training batch of :func:`tiny_data`."""
    torch.manual_seed(0)
    cfg = tiny_cfg(name, tmp_path / "m", **extra)
    m = method_class(name)(cfg, preset_rig(cfg.rig), cfg.grid)
    data = with_window(TrainData(*tiny_data(cfg)), m.data_needs())
    m.prepare(data, lambda s: None)
    m.model.train()
    return m, next(data.batches(cfg.batch, cfg.seed, 0))


def snapshot(batch: dict) -> dict:
    """A deep copy of a batch's tensors (to show the loss leaves them alone)."""
    return {k: snapshot(v) if isinstance(v, dict) else v.clone() for k, v in batch.items()}


def same(a: dict, b: dict) -> bool:
    return a.keys() == b.keys() and all(same(a[k], b[k]) if isinstance(a[k], dict) else torch.equal(a[k], b[k])
                                        for k in a)
