"""Bad weights never start a node: the preflight check reads every tensor, and a damaged or
hostile metadata document is refused before anything is allocated (issue: hardening)."""

from __future__ import annotations

import json
import tracemalloc

import pytest
import torch
from safetensors import safe_open
from safetensors.torch import save_file

from bev_mapper_core.geometry.grid import BevGrid
from bev_mapper_core.geometry.rig import preset_rig
from bev_mapper_core.mapper import MapperConfig, create_mapper, preflight
from bev_mapper_core.methods.bimapper.mapper import default_weights_path
from bev_mapper_core.methods.bimapper.weights import WeightsFile
from bev_mapper_core.nn.weights import META_KEY, WeightsError

SHIPPED = default_weights_path("front1", "labels")


def _load():
    with safe_open(str(SHIPPED), framework="pt") as f:
        return {k: f.get_tensor(k) for k in f.keys()}, json.loads(f.metadata()[META_KEY])


def _write(path, tensors, meta, raw_meta=None):
    save_file(tensors, str(path), metadata={META_KEY: raw_meta if raw_meta is not None else json.dumps(meta)})
    return path


def _first_float(tensors):
    return next(k for k, t in tensors.items() if t.is_floating_point() and t.numel() > 1)


def _tensor_damage():
    """name -> function(tensors) that damages a copy of the shipped tensors."""
    def shape(t):
        k = _first_float(t)
        t[k] = torch.zeros(t[k].numel() + 1)
    def dtype(t):
        k = _first_float(t)
        t[k] = t[k].double()
    def missing(t):
        t.pop(_first_float(t))
    def extra(t):
        t["surprise.weight"] = torch.zeros(3)
    def nan(t):
        k = _first_float(t)
        t[k] = t[k].clone()
        t[k].view(-1)[0] = float("nan")
    return {"shape": shape, "dtype": dtype, "missing": missing, "extra": extra, "nan": nan}


def _preflight(path):
    WeightsFile.clear_cache()
    preflight(MapperConfig(weights=str(path)), "front1", BevGrid(), ("front",))


@pytest.mark.parametrize("damage", sorted(_tensor_damage()))
def test_damaged_tensors_fail_the_preflight(tmp_path, damage):
    tensors, meta = _load()
    _tensor_damage()[damage](tensors)
    path = _write(tmp_path / "bad.safetensors", tensors, meta)
    with pytest.raises(WeightsError, match="tensor|tensors"):
        _preflight(path)


@pytest.mark.parametrize("edit, match", [
    (lambda m: m.update(classes=["drivable", "lava"]), "unknown class"),
    (lambda m: m["config"].update(neck_channels=1_000_000), "neck_channels"),
    (lambda m: m["config"].update(plane_shape=[100_000, 100_000]), "plane_shape"),
    (lambda m: m["config"].update(input_width=float("nan")), "input_width"),
    (lambda m: m["config"].update(width_mult=1e9), "multipliers"),
    (lambda m: m.update(grid={"x_min": -30000.0, "x_max": 30000.0, "y_min": -30000.0, "y_max": 30000.0,
                              "resolution": 1.0}), "cells"),
    (lambda m: m.update(input_size=[10**9, 112]), "input_size"),
    (lambda m: m.update(cameras="front"), "cameras"),
], ids=["unknown-class", "neck-1e6", "plane-1e5", "width-nan", "width-mult", "grid-huge", "input-size", "cameras"])
def test_hostile_metadata_is_refused_before_allocating(tmp_path, edit, match):
    tensors, meta = _load()
    edit(meta)
    path = _write(tmp_path / "bad.safetensors", tensors, meta)
    tracemalloc.start()
    try:
        with pytest.raises(WeightsError, match=match):
            _preflight(path)
        _, peak = tracemalloc.get_traced_memory()
    finally:
        tracemalloc.stop()
    assert peak < 64 * 2**20, f"refusing the file allocated {peak / 2**20:.0f} MiB"


def test_good_weights_pass_and_the_model_reuses_the_checked_tensors(monkeypatch):
    """The shipped file passes; after the preflight the mapper reads no tensor file again."""
    import bev_mapper_core.nn.weights as W

    WeightsFile.clear_cache()
    _preflight(SHIPPED)
    opened = []
    real = W.safe_open
    monkeypatch.setattr(W, "safe_open", lambda *a, **k: opened.append(a) or real(*a, **k))
    mapper = create_mapper(preset_rig("front1"), BevGrid(), MapperConfig())
    assert opened == []
    ref, _ = _load()
    got = mapper.model.state_dict()
    assert all(torch.equal(got[k], ref[k]) for k in ref)
