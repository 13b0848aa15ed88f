"""Training / evaluation machinery on a tiny configuration (tiny grid, tiny model, few frames)."""

from __future__ import annotations

import json

import numpy as np
import pytest

torch = pytest.importorskip("torch")

from bags.cli.train.eval import eval_parser  # noqa: E402
from bags.cli.train.main import main as bev_train  # noqa: E402
from bags.cli.train.train import train_parser  # noqa: E402
from bev_mapper_core.errors import ConfigError  # noqa: E402
from bev_mapper_core.geometry.grid import BevGrid  # noqa: E402
from bev_mapper_core.geometry.random_rig import RANDOM_RIGS  # noqa: E402
from bev_mapper_core.geometry.rig import preset_rig  # noqa: E402
from bev_mapper_core.methods.bimapper.model import BiMapper  # noqa: E402
from bev_mapper_core.methods.bimapper.weights import load_state  # noqa: E402
from bev_mapper_core.synth.config import SynthConfig  # noqa: E402
from bev_mapper_core.synth.styles import STYLE_CHOICES  # noqa: E402
from bev_mapper_core.training.config import TrainConfig  # noqa: E402
from bev_mapper_core.training.data import (  # noqa: E402
    VAL_SEED_BASE,
    FrameSet,
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


@pytest.mark.slow  # renders drives
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


def test_grad_clip_bites_only_when_the_gradient_is_larger(tmp_path, tiny_data):
    """A clip far above the gradients' norm changes nothing (bit-identical weights); a tiny one
    changes the run; a bad value is a config error."""
    tr, va, _ = tiny_data

    def weights(name, **kw):
        train(tiny_cfg(tmp_path / name, epochs=1, out=str(tmp_path / name), **kw), log=lambda s: None, data=(tr, va))
        from safetensors.torch import load_file

        return load_file(str(tmp_path / name / "last.safetensors"))

    plain, loose, tight = weights("plain"), weights("loose", grad_clip=1e9), weights("tight", grad_clip=1e-4)
    assert all(torch.equal(plain[k], loose[k]) for k in plain)
    assert any(not torch.equal(plain[k], tight[k]) for k in plain if plain[k].is_floating_point())
    for bad in (0, -1.0, float("nan"), True):
        with pytest.raises(ConfigError, match="grad_clip"):
            tiny_cfg(tmp_path, grad_clip=bad)


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
    rc = bev_train(argv + ["--out", str(tmp_path / "r"), "--no-progress"])
    err = capsys.readouterr().err
    assert rc != 0
    assert "error:" in err
    assert not (tmp_path / "r" / "last.json").exists()


def test_cli_resume_without_checkpoint_is_an_error(capsys, tmp_path):
    rc = bev_train(["--out", str(tmp_path / "none"), "--resume", "--no-progress"])
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


@pytest.mark.slow  # training runs and a freshly rendered drive
def test_training_on_a_bag_with_gt(tmp_path, capsys):
    pytest.importorskip("rosbags")
    from bags.cli.main import main as bag_main

    bag = tmp_path / "bag"
    g = [str(v) for v in TINY_GRID]
    assert bag_main(["synth", str(bag), "--rig", RIG, "--frames", "3", "--grid-x-min", g[0], "--grid-x-max", g[1],
                     "--grid-y-min", g[2], "--grid-y-max", g[3], "--grid-res", g[4]]) == 0
    from bags.io.train_data import bag_frameset, bag_rig_grid

    rig, grid = bag_rig_grid(bag)
    assert rig.names == preset_rig(RIG).names and grid == BevGrid(*TINY_GRID)
    fs = bag_frameset([bag], ("drivable", "vehicle"), rig, grid)
    assert len(fs) == 3 and fs.target.shape == (3, 2, 16, 32) and fs.labels.shape[1] == 4 and fs.mask.any()
    out = tmp_path / "run"
    rc = bev_train(["--bag", str(bag), "--val-bag", str(bag), "--rig", RIG, "--classes", "drivable,vehicle", "--epochs", "1",
                   "--batch", "2", "--input-width", "48", "--gv-hidden", "16", "--threads", "1", "--out", str(out),
                   "--no-progress"])
    assert rc == 0 and (out / "best.safetensors").is_file()
    with pytest.raises(ConfigError):  # a class the bag has no GT topic for
        bag_frameset([bag], ("road",), rig, grid)


# ----------------------------------------------------------------- plug-in interface
from dataclasses import dataclass, fields  # noqa: E402

from safetensors import safe_open  # noqa: E402
from safetensors.torch import save_file  # noqa: E402

from bev_mapper_core.geometry.rig import PRESETS  # noqa: E402
from bev_mapper_core.labels.classes import BEV_CLASS_NAMES, NUM_LABELS  # noqa: E402
from bev_mapper_core.mapper import INPUT_KINDS  # noqa: E402
from bev_mapper_core.methods.bimapper.config import (  # noqa: E402
    FUSIONS,
    STREAMS,
    BiMapperConfig,  # noqa: E402
)
from bev_mapper_core.methods.bimapper.losses import MUTUAL_MODES  # noqa: E402
from bev_mapper_core.methods.bimapper.train import BiMapperMethod, BiMapperTraining  # noqa: E402
from bev_mapper_core.nn.losses import masked_bce  # noqa: E402
from bev_mapper_core.training import method as method_mod  # noqa: E402
from bev_mapper_core.training.class_weights import POS_WEIGHTS  # noqa: E402
from bev_mapper_core.training.method import CliFlag, TrainMethod, method_class, register_train_method, train_methods  # noqa: E402
from bev_mapper_core.training.sources import DataNeeds, InMemorySource, SynthSource  # noqa: E402


@dataclass(frozen=True)
class ToyConfig:
    """Toy architecture: camera label one-hots pooled onto the grid, two convs."""

    input_kind: str = "labels"
    classes: tuple[str, ...] = ("road",)
    channels: int = 4

    def __post_init__(self) -> None:
        object.__setattr__(self, "classes", tuple(self.classes))

    def to_dict(self) -> dict:
        return {"input_kind": self.input_kind, "classes": list(self.classes), "channels": self.channels}


@dataclass(frozen=True)
class ToyLoss:
    pos_weight: float = 1.0


class ToyNet(torch.nn.Module):
    def __init__(self, cfg: ToyConfig, cameras: int, grid: BevGrid) -> None:
        super().__init__()
        self.hw = grid.shape
        self.net = torch.nn.Sequential(torch.nn.Conv2d(cameras * NUM_LABELS, cfg.channels, 3, padding=1),
                                       torch.nn.ReLU(), torch.nn.Conv2d(cfg.channels, len(cfg.classes), 1))

    def forward(self, images: torch.Tensor) -> torch.Tensor:
        B, N, h, w = images.shape
        x = torch.nn.functional.one_hot(images.long().clamp(max=NUM_LABELS - 1), NUM_LABELS)  # (B, N, h, w, L)
        x = x.permute(0, 1, 4, 2, 3).reshape(B, N * NUM_LABELS, h, w).float()  # -> (B, N*L, h, w)
        return self.net(torch.nn.functional.adaptive_avg_pool2d(x, self.hw))  # (B, K, H, W)


class ToyMethod(TrainMethod):
    """A second method, only through the plug-in interface (records its per-step hook calls)."""

    name = "toy"
    model_config_type = ToyConfig
    loss_config_type = ToyLoss
    cli_flags = (CliFlag("--toy-channels", "channels", min_value=1),)
    steps: list = []

    def build_model(self):
        return ToyNet(self.cfg.model, len(self.rig.names), self.grid)

    def loss(self, batch, epoch, step):
        logits = self.model(batch["images"].to(self.device))
        pw = torch.full((logits.shape[1],), self.cfg.loss.pos_weight)
        loss = masked_bce(logits, batch["target"], batch["mask"][:, None], pw)
        return loss, {"bce": float(loss.detach()), "total": float(loss.detach())}

    def after_step(self, step):
        ToyMethod.steps.append(step)

    def predict(self, batch):
        probs = torch.sigmoid(self.model(batch["images"].to(self.device))).numpy()
        return probs, np.ones((len(probs), *self.grid.shape), bool)

    def save(self, path):
        save_file({k: v.contiguous() for k, v in self.model.state_dict().items()}, str(path))

    def load(self, path):
        with safe_open(str(path), framework="pt") as f:
            self.model.load_state_dict({k: f.get_tensor(k) for k in f.keys()})


@pytest.fixture
def toy_method():
    register_train_method("toy", f"{__name__}:ToyMethod")  # lazily imported like a real plug-in
    ToyMethod.steps = []
    yield ToyMethod
    method_mod._REGISTRY.pop("toy")


def toy_dict(tmp_path, cache, **kw) -> dict:
    d = dict(method="toy", rig=RIG, classes="cam2bev", out=str(tmp_path / "toy"), epochs=3, batch=2, lr=1e-2, seed=3,
             train_drives=1, val_drives=1, frames_per_drive=3, stride=2, cache=str(cache), threads=1,
             grid=list(TINY_GRID), progress=False, channels=3)
    d.update(kw)
    return d


def test_a_second_method_trains_through_the_same_loop(tmp_path, tiny_data, toy_method):
    tr, va, cache = tiny_data
    assert "toy" in train_methods() and method_class("toy") is ToyMethod
    cfg = TrainConfig.from_dict(toy_dict(tmp_path, cache))
    assert cfg.model == ToyConfig("labels", ("road", "vehicle", "static"), 3) and cfg.loss == ToyLoss()
    logs = []
    doc = train(cfg, log=logs.append, data=(tr, va))
    assert ToyMethod.steps == [1, 2, 3, 4, 5, 6]  # after_step once per optimizer step
    losses = [h["loss_total"] for h in doc["history"]]
    assert len(losses) == 3 and losses[-1] < losses[0] and all("loss_bce" in h and "val_miou" in h for h in doc["history"])
    assert any("epoch 3/3: loss" in s and "(bce " in s for s in logs)
    out = tmp_path / "toy"
    for name in ("last.safetensors", "last.json", "last_optim.safetensors", "best.safetensors", "metrics.jsonl"):
        assert (out / name).is_file(), name
    saved = json.loads((out / "last.json").read_text())
    assert saved["config"]["method"] == "toy" and saved["config"]["model"]["channels"] == 3
    assert TrainConfig.from_dict(saved["config"]) == cfg
    # the generic checkpoint / resume works for it too
    part = train(TrainConfig.from_dict(toy_dict(tmp_path, cache, out=str(tmp_path / "p"), epochs=2)), log=lambda s: None,
                 data=(tr, va))
    resumed = train(TrainConfig.from_dict(toy_dict(tmp_path, cache, out=str(tmp_path / "p"), resume=True)),
                    log=lambda s: None, data=(tr, va))
    assert part["step"] == 4 and resumed["step"] == doc["step"] == 6
    assert [h["loss_total"] for h in resumed["history"]] == pytest.approx(losses, abs=1e-6)


def test_a_second_method_through_bev_train(tmp_path, tiny_data, toy_method, capsys):
    """bev-train offers the method's own flags (and not Bi-Mapper's), taking the method from the YAML."""
    _, _, cache = tiny_data
    assert "--toy-channels" in train_parser("toy").format_help()
    assert "--streams" not in train_parser("toy").format_help()
    import yaml

    cfg_file = tmp_path / "toy.yaml"
    cfg_file.write_text(yaml.safe_dump(toy_dict(tmp_path, cache, epochs=1)))
    assert bev_train(["--config", str(cfg_file), "--toy-channels", "2", "--out", str(tmp_path / "c")]) == 0
    saved = json.loads((tmp_path / "c" / "last.json").read_text())["config"]
    assert saved["method"] == "toy" and saved["model"]["channels"] == 2
    assert bev_train(["--config", str(cfg_file), "--streams", "gv", "--out", str(tmp_path / "d")]) == 2
    assert "unrecognized arguments: --streams" in capsys.readouterr().err


def test_data_sources_refuse_needs_they_cannot_honour(tiny_data):
    from bags.io.train_data import BagSource

    tr, va, _ = tiny_data
    untimed = [FrameSet(f.labels, f.target, f.mask) for f in (tr, va)]  # frames without poses
    for src in (BagSource(), InMemorySource(*untimed)):
        with pytest.raises(ConfigError, match=r"\['poses', 'sequences'\]"):
            src.check(DataNeeds(sequence_length=2, poses=True))
        src.check(DataNeeds(image_size=(8, 16)))  # labeled single frames: fine
    for src in (SynthSource(), InMemorySource(tr, va)):  # synthetic drives carry their poses
        src.check(DataNeeds(sequence_length=2, poses=True))
    with pytest.raises(ConfigError, match="unlabeled"):  # no unlabeled frames given
        InMemorySource(tr, va).check(DataNeeds(unlabeled=True))
    SynthSource().check(DataNeeds(unlabeled=True))  # from unlabeled_drives (tests/bev_mapper_core/methods/s2g2/test_s2g2.py)
    with pytest.raises(ConfigError, match="bag data source"):
        SynthSource().rig_grid(TrainConfig(bag=("some.bag",)))


def _choices(parser) -> dict:
    return {a.option_strings[0]: a.choices for a in parser._actions if a.option_strings and a.choices is not None}


def test_cli_choices_and_defaults_come_from_the_owning_constants():
    p = train_parser()
    assert _choices(p) == {"--method": list(train_methods()), "--rig": [*sorted(PRESETS), RANDOM_RIGS],
                           "--input": list(INPUT_KINDS),
                           "--streams": list(STREAMS), "--fusion": list(FUSIONS), "--mutual": list(MUTUAL_MODES),
                           "--pos-weight": list(POS_WEIGHTS), "--style": STYLE_CHOICES,
                           "--unlabeled-style": STYLE_CHOICES}
    assert TrainConfig().style == SynthConfig.style
    assert vars(p.parse_args([])) == {}  # no flag has a default of its own: the dataclasses have them
    assert "--rig" not in _choices(eval_parser())  # a preset or random-<seed>, checked by its type
    assert eval_parser().parse_args(["--rig", "random-950000044"]).rig == "random-950000044"
    e, d = eval_parser().parse_args([]), TrainConfig()
    assert (e.rig, e.val_drives, e.frames_per_drive, e.stride, e.cache, e.device, e.threads) == \
        (d.rig, d.val_drives, d.frames_per_drive, d.stride, d.cache, d.device, d.threads)
    for name in train_methods():  # every method flag lands on a field of the method's configs
        cls = method_class(name)
        own = {f.name for f in fields(cls.model_config_type)} | {f.name for f in fields(cls.loss_config_type)}
        assert {f.dest for f in cls.cli_flags} <= own, name


def test_bimapper_flags_land_on_its_config_objects():
    a = vars(train_parser().parse_args(
        ["--rig", "front1", "--input", "rgb", "--streams", "gv", "--fusion", "concat", "--no-asl", "--lv-full-res",
         "--ipm-skip", "--mutual", "sync", "--mutual-start-epoch", "2", "--pos-weight", "none", "--input-width", "64",
         "--gv-hidden", "32"]))
    cfg = TrainConfig.from_dict(a)
    assert cfg.model == BiMapperConfig(input_kind="rgb", classes=BEV_CLASS_NAMES, input_width=64, gv_hidden=32,
                                       streams="gv", fusion="concat", lv_full_res=True, ipm_skip=True)
    assert cfg.loss == BiMapperTraining(asl=False, mutual="sync", mutual_start_epoch=2, pos_weight="none")
    assert TrainConfig.from_dict(json.loads(json.dumps(cfg.to_dict()))) == cfg  # the saved form reads back
    d = TrainConfig()  # defaults: the plug-in's model (auto classes of the rig) and loss settings
    assert d.model == BiMapperMethod.default_model_config(BEV_CLASS_NAMES) and d.loss == BiMapperTraining()
    assert TrainConfig(rig="cam2bev4").class_names == ("road", "vehicle", "static")
    assert isinstance(d.grid, BevGrid) and d.grid == BevGrid()


def test_config_reads_old_flat_and_new_nested_forms(tmp_path):
    p = tmp_path / "old.yaml"
    p.write_text("rig: front1\ninput: labels\nclasses: standard\ngrid: [-8, 8, -4, 4, 0.5]\nipm_skip: true\n"
                 "asl: false\nmutual: none\nmutual_start_epoch: 3\npos_weight: none\ngv_hidden: 16\n")
    cfg = TrainConfig.from_yaml(p)
    assert cfg.grid == BevGrid(*TINY_GRID) and cfg.model.ipm_skip and cfg.model.gv_hidden == 16
    assert cfg.loss == BiMapperTraining(asl=False, mutual="none", mutual_start_epoch=3, pos_weight="none")
    p.write_text("rig: front1\ngrid: {x_min: -8, x_max: 8, y_min: -4, y_max: 4, resolution: 0.5}\n"
                 "model: {streams: lv, neck_channels: 16}\nloss: {asl: false}\n")
    cfg = TrainConfig.from_yaml(p, streams="gv")  # flat keys (flags) override the sub-mappings
    assert cfg.grid == BevGrid(*TINY_GRID) and cfg.model.streams == "gv" and cfg.model.neck_channels == 16
    assert cfg.model.gv_hidden == BiMapperMethod.default_model_config(BEV_CLASS_NAMES).gv_hidden
    assert not cfg.loss.asl
    for bad in ("model: {what: 1}\n", "loss: {asl: 3}\n", "grid: [1, 2]\n", "gv_hidden: 0\n", "input_width: two\n"):
        p.write_text(bad)
        with pytest.raises(ConfigError):
            TrainConfig.from_yaml(p)


def old_flat_config(out: str, epochs: int, cache: str, **kw) -> dict:
    """``config`` of a last.json as c383ad8 (before the plug-in split) wrote it for tiny_cfg."""
    d = {"method": "bimapper", "rig": RIG, "input": "labels", "classes": "cam2bev", "out": out, "epochs": epochs,
         "frames_per_epoch": None, "batch": 2, "lr": 0.001, "lr_gamma": 0.1, "lr_step_epoch": None,
         "mutual_start_epoch": None, "seed": 3, "train_drives": 1, "val_drives": 1, "val_seeds": None,
         "frames_per_drive": 3, "stride": 2, "val_frames": None, "cache": cache, "device": "cpu", "threads": 1,
         "resume": False, "streams": "both", "fusion": "sum", "lv_full_res": False, "ipm_skip": False, "asl": True,
         "mutual": "async", "input_width": 48, "gv_hidden": 16, "time_budget_min": None, "bag": None,
         "val_bag": None, "progress": False, "grid": list(TINY_GRID), "pos_weight": "auto"}
    d.update(kw)
    return d


def test_resume_of_a_run_written_before_the_plugin_split(tmp_path, tiny_data):
    tr, va, _ = tiny_data
    a, b = tmp_path / "a", tmp_path / "b"
    train(tiny_cfg(a, out=str(a)), log=lambda s: None, data=(tr, va))
    train(tiny_cfg(b, epochs=1, out=str(b)), log=lambda s: None, data=(tr, va))
    doc = json.loads((b / "last.json").read_text())
    doc["config"] = old_flat_config(str(b), 1, str(b / "cache"))
    (b / "last.json").write_text(json.dumps(doc))
    assert TrainConfig.from_dict(doc["config"]) == tiny_cfg(b, epochs=1, out=str(b))
    # a different model setting in the old file is still refused, naming the field
    (b / "last.json").write_text(json.dumps({**doc, "config": old_flat_config(str(b), 1, str(b / "cache"), streams="gv")}))
    from bev_mapper_core.training.trainer import TrainingError

    with pytest.raises(TrainingError, match=r"\['model\.streams'\]"):
        train(tiny_cfg(b, out=str(b), resume=True), log=lambda s: None, data=(tr, va))
    (b / "last.json").write_text(json.dumps(doc))
    logs = []
    resumed = train(tiny_cfg(b, out=str(b), resume=True), log=logs.append, data=(tr, va))
    assert any("resumed" in s for s in logs) and resumed["epoch"] == 1 and resumed["step"] == 4
    rig, cfg = preset_rig(RIG), tiny_cfg(tmp_path)
    ma, mb = (BiMapper(cfg.model, rig, cfg.grid) for _ in range(2))
    load_state(ma, a / "last.safetensors")
    load_state(mb, b / "last.safetensors")
    for (ka, va_), (kb, vb) in zip(ma.state_dict().items(), mb.state_dict().items()):
        assert ka == kb and torch.allclose(va_, vb, atol=1e-6), ka


def test_visibility_only_fine_tuning_keeps_the_class_outputs(tmp_path, tiny_data):
    """``--init-weights`` from a head-less run + ``--visibility-only``: the head learns (its BCE
    falls), every other tensor (BatchNorm statistics included) stays the initial file's."""
    from safetensors.torch import load_file

    tr, va, _ = tiny_data
    train(tiny_cfg(tmp_path, epochs=1, out=str(tmp_path / "base")), log=lambda s: None, data=(tr, va))
    base = str(tmp_path / "base" / "last.safetensors")
    cfg = tiny_cfg(tmp_path, epochs=4, lr=1e-2, out=str(tmp_path / "vis"), visibility_head=True,
                   init_weights=base, visibility_only=True, visibility_weight=1.0)
    doc = train(cfg, log=lambda s: None, data=(tr, va))
    vis = [h["loss_visibility"] for h in doc["history"]]
    assert vis[-1] < vis[0]
    old, new = load_file(base), load_file(str(tmp_path / "vis" / "last.safetensors"))
    assert set(new) - set(old) and all(k.startswith("decoder.vis_head.") for k in set(new) - set(old))
    for k, t in old.items():
        assert torch.equal(t, new[k]), k


def test_rgb_drives_cache_and_match_the_models_resize(tmp_path):
    """RGB in the drive cache: stored at the requested size with the models' own resize, read
    back identically, and a label-only cache of the same drive keeps its key."""
    from bev_mapper_core.synth import SynthConfig
    from bev_mapper_core.synth.drive import DriveRenderer
    from bev_mapper_core.synth.world import build_world
    from bev_mapper_core.training.data import resize_rgb

    rig = preset_rig("front1").scaled(0.25)
    grid = BevGrid(*TINY_GRID)
    w, h = rig.cameras[0].model.image_size
    size = (h // 2, w // 2)
    a = synth_frameset(rig, grid, ("drivable",), [21], 2, 2, tmp_path, rgb=size)
    b = synth_frameset(rig, grid, ("drivable",), [21], 2, 2, tmp_path, rgb=size)  # from the cache
    assert a.rgb.shape == (2, 1, *size, 3) and a.rgb.dtype == np.uint8
    np.testing.assert_array_equal(a.rgb, b.rgb)
    f = DriveRenderer(build_world(SynthConfig(frames=3, seed=21)), rig, grid).frame(2)
    np.testing.assert_array_equal(a.rgb[1, 0], resize_rgb(f.cameras[rig.names[0]].rgb, size))
    assert drive_spec(rig, grid, ("drivable",), 2, 2).key() != drive_spec(rig, grid, ("drivable",), 2, 2, size).key()
    assert "rgb" not in synth_frameset(rig, grid, ("drivable",), [21], 2, 2, tmp_path).batch(np.arange(1))


@pytest.mark.slow
def test_segmenter_and_rgb_bimapper_train_through_the_trainer(tmp_path):
    """`bev-train --method segmenter` and an RGB Bi-Mapper on tiny data: the loss falls, the
    checkpoints load back, and the segmenter's held-out score is segipm's."""
    cfg = TrainConfig.from_dict(dict(method="segmenter", rig="front1", classes="standard", out=str(tmp_path / "seg"),
                                     epochs=3, batch=2, lr=3e-3, seed=3, train_drives=1, val_drives=1,
                                     frames_per_drive=3, stride=2, cache=str(tmp_path / "cache"), threads=1,
                                     input_width=32, grid=TINY_GRID, progress=False))
    state = train(cfg, log=lambda m: None)
    lines = [json.loads(x) for x in (tmp_path / "seg" / "metrics.jsonl").read_text().splitlines()]
    assert lines[-1]["loss_ce"] < lines[0]["loss_ce"]
    assert 0.0 <= state["best_val_miou"] <= 1.0
    from bev_mapper_core.methods.segmenter.weights import load_segmenter
    assert load_segmenter(tmp_path / "seg" / "last.safetensors").config.input_width == 32
    rgb_cfg = tiny_cfg(tmp_path, input="rgb", out=str(tmp_path / "rgb"), epochs=2)
    train(rgb_cfg, log=lambda m: None)
    model = BiMapper(rgb_cfg.model, preset_rig(RIG), rgb_cfg.grid)
    load_state(model, tmp_path / "rgb" / "last.safetensors")
    assert model.config.input_kind == "rgb"
