"""The contract every registered method keeps (bev_mapper_core/methods/__init__.py is the one table).

Over the table, not a hand-kept list, so a new method gets these checks by being registered:
its training plug-in builds on a stand-in grid, saves and loads its weights bit for bit; the
weights map a real synthetic frame through ``create_mapper`` (probabilities in [0, 1] on the
grid); where the method exports, every installed inference backend maps as torch does.
"""

from __future__ import annotations

import importlib.util
import pathlib

import numpy as np
import pytest
import yaml
from augment_helpers import RUNS as TINY_RUNS

from bev_mapper_core.geometry.grid import BevGrid
from bev_mapper_core.geometry.rig import preset_rig
from bev_mapper_core.mapper import MapperConfig, available_methods, create_mapper, mapper_class
from bev_mapper_core.methods import METHODS, WEIGHTS_DIR, method_presets
from bev_mapper_core.synth import SynthConfig, generate_drive
from bev_mapper_core.training.method import method_class, train_methods

REPO = pathlib.Path(__file__).resolve().parents[3]
CORE = REPO / "bev_mapper_core"
GRID = BevGrid(0.0, 16.0, -8.0, 8.0, 0.5)  # 32 x 32 cells ahead of the car
#: the rig each trainable method is built for here (monocular methods: one camera)
RIGS = {"bimapper": "cam2bev4", "segmenter": "front1", "s2g2": "front1", "focusbev": "front1"}
#: the mapper that runs a trainer's weights, and the MapperConfig field that names the file
RUNS_AS = {"segmenter": ("segipm", "segmenter")}
BACKENDS = [b for b in ("onnxruntime", "openvino") if importlib.util.find_spec(b) is not None]
#: small sizes of the stand-in models (the exporter's time grows with the layers; the shipped sizes
#: go through every backend in tests/bev_mapper_core/nn/test_backends.py)
SIZES = {name: {k: v for k, v in keys.items() if k not in ("method", "rig", "input", "input_width")}
         for name, (keys, _, _) in TINY_RUNS.items()}


def test_the_table_is_both_registries_and_names_every_shipped_file():
    assert set(available_methods()) == {n for n, s in METHODS.items() if s.mapper}
    assert set(train_methods()) == {n for n, s in METHODS.items() if s.trainer}
    assert set(RIGS) == set(train_methods()), "a new trainable method needs a stand-in rig here"
    shipped = {p.name for p in WEIGHTS_DIR.glob("*.safetensors")}
    assert shipped == {w for s in METHODS.values() for w in s.weights}
    for name, over in method_presets().items():
        params = yaml.safe_load((REPO / "config" / f"{name}.yaml").read_text())["/**"]["ros__parameters"]
        assert params["method"] == over["method"] and params["rig"] == over["rig"], name
    for name in available_methods():
        assert mapper_class(name).name == name


def test_no_module_outside_the_method_packages_is_named_after_a_method():
    offenders = []
    for f in CORE.rglob("*.py"):
        rel = f.relative_to(CORE)
        if rel.parts[0] == "methods":
            continue
        if any(m in part for part in rel.with_suffix("").parts for m in METHODS if m != "ipm"):
            offenders.append(str(rel))
    assert not offenders


@pytest.mark.slow
@pytest.mark.parametrize("name", sorted(RIGS))
def test_each_trainable_method_builds_round_trips_its_weights_and_maps(name, tmp_path, monkeypatch):
    import torch

    from bev_mapper_core.nn import backends
    from bev_mapper_core.training.config import TrainConfig

    monkeypatch.setenv(backends.CACHE_ENV, str(tmp_path / "cache"))
    rig = preset_rig(RIGS[name])
    cfg = TrainConfig.from_dict(dict(method=name, rig=rig.name, out=str(tmp_path / "run"), threads=1, progress=False, input_width=64,
                                     cache=None, grid=(GRID.x_min, GRID.x_max, GRID.y_min, GRID.y_max, GRID.resolution),
                                     **SIZES.get(name, {})))
    torch.manual_seed(0)
    trained = method_class(name)(cfg, rig, cfg.grid)
    path = trained.save(tmp_path / "w.safetensors") or tmp_path / "w.safetensors"
    torch.manual_seed(1)
    other = method_class(name)(cfg, rig, cfg.grid)
    a, b = trained.model.state_dict(), other.model.state_dict()
    assert any(not torch.equal(a[k], b[k]) for k in a if a[k].is_floating_point())  # two different inits
    other.load(path)
    b = other.model.state_dict()
    assert a.keys() == b.keys() and all(torch.equal(a[k], b[k]) for k in a)

    method, field = RUNS_AS.get(name, (name, "weights"))
    kind = cfg.model.input_kind
    mc = MapperConfig(backend="torch", method=method, input_kind=kind, threads=1, **{field: str(path)})
    mapper = create_mapper(rig, GRID, mc)
    frame = next(iter(generate_drive(rig, GRID, SynthConfig(frames=1, seed=950_000_011))))
    images = {n: (c.rgb if kind == "rgb" else c.labels) for n, c in frame.cameras.items()}
    pred = mapper.map(images, np.eye(4), 10**9)
    assert pred.probs.shape == (len(pred.classes), *GRID.shape) and pred.known.shape == GRID.shape
    assert np.isfinite(pred.probs).all() and pred.probs.min() >= 0.0 and pred.probs.max() <= 1.0
    if method not in ("bimapper", "s2g2", "focusbev"):  # the methods with an exported network
        return
    for backend in BACKENDS:
        fast = create_mapper(rig, GRID, MapperConfig(**{**mc.__dict__, "backend": backend}))
        got = fast.map(images, np.eye(4), 10**9)
        assert np.abs(got.probs - pred.probs).max() <= backends.TOLERANCE, backend
        np.testing.assert_array_equal(got.known, pred.known)


#: the input of the training-free mappers that do not read label images
INPUT = {"segipm": "rgb"}


@pytest.mark.parametrize("name", sorted(n for n, s in METHODS.items() if s.mapper and not s.trainer))
def test_each_training_free_method_maps_a_frame(name):
    rig = preset_rig("front1")
    frame = next(iter(generate_drive(rig, GRID, SynthConfig(frames=1, seed=950_000_011))))
    kind = INPUT.get(name, "labels")
    images = {n: (c.rgb if kind == "rgb" else c.labels) for n, c in frame.cameras.items()}
    pred = create_mapper(rig, GRID, MapperConfig(backend="torch", method=name, input_kind=kind, threads=1)).map(images)
    assert pred.probs.shape == (len(pred.classes), *GRID.shape) and pred.known.any()
