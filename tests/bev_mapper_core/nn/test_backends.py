"""Inference backends (issue #15): the ONNX export run by onnxruntime / OpenVINO maps as torch
does, ``auto`` picks an installed runtime and falls back to torch, and a missing runtime asked
for by name is a clear error."""

from __future__ import annotations

import importlib.util

import numpy as np
import pytest
from model_helpers import memory_focusbev

from bev_mapper_core.errors import ConfigError
from bev_mapper_core.geometry.grid import BevGrid
from bev_mapper_core.geometry.rig import preset_rig
from bev_mapper_core.mapper import BACKENDS, MapperConfig, create_mapper, preflight
from bev_mapper_core.nn import backends
from bev_mapper_core.synth import SynthConfig, generate_drive


def _hide(monkeypatch, *modules):
    real = importlib.util.find_spec
    monkeypatch.setattr(importlib.util, "find_spec", lambda name, *a: None if name in modules else real(name, *a))


def test_auto_falls_back_to_torch_and_a_missing_runtime_is_a_clear_error(monkeypatch):
    _hide(monkeypatch, "openvino", "onnxruntime")
    assert backends.installed_backends() == ("torch",)
    assert backends.resolve_backend("auto") == "torch"
    with pytest.raises(ConfigError, match="backend 'openvino' is not installed: pip install openvino"):
        backends.resolve_backend("openvino")
    with pytest.raises(ConfigError, match="not installed"):  # refused at start-up (preflight) and construction
        preflight(MapperConfig(backend="onnxruntime"), "surround6")
    with pytest.raises(ConfigError, match="not installed"):
        create_mapper(preset_rig("surround6"), BevGrid(), MapperConfig(backend="onnxruntime"))
    _hide(monkeypatch, "openvino")
    if importlib.util.find_spec("onnxruntime") is not None:
        assert backends.resolve_backend("auto") == "onnxruntime"
    with pytest.raises(ConfigError, match="backend must be one of"):
        MapperConfig(backend="tensorrt")
    assert BACKENDS == ("torch", "onnxruntime", "openvino", "auto")


@pytest.mark.slow
@pytest.mark.parametrize("backend", ["onnxruntime", "openvino"])
def test_exported_bimapper_maps_as_torch_does(backend, tmp_path_factory, monkeypatch):
    """The shipped surround6 Bi-Mapper through the backend, on real frames (one with a camera
    missing): probabilities within ``backends.TOLERANCE`` of torch's, the same known cells; the
    export is cached and reused."""
    if importlib.util.find_spec(backend) is None:
        pytest.skip(f"{backend} is not installed (the 'fast' extra)")
    cache = tmp_path_factory.getbasetemp() / "onnx_cache"  # shared by both backends: one export
    monkeypatch.setenv(backends.CACHE_ENV, str(cache))
    rig, grid = preset_rig("surround6"), BevGrid()
    ref = create_mapper(rig, grid, MapperConfig(backend="torch", threads=1))
    fast = create_mapper(rig, grid, MapperConfig(threads=1, backend=backend))
    assert fast.backend == backend
    frames = list(generate_drive(rig, grid, SynthConfig(frames=2, seed=950_000_018)))
    sets = [{n: c.labels for n, c in f.cameras.items()} for f in frames]
    sets.append({n: v for n, v in sets[0].items() if n != "back"})
    for images in sets:
        a, b = fast.map(images), ref.map(images)
        assert np.abs(a.probs - b.probs).max() <= backends.TOLERANCE
        np.testing.assert_array_equal(a.known, b.known)
    assert len(list((cache / "onnx").glob("*.onnx"))) == 1


def _pose(x: float) -> np.ndarray:
    T = np.eye(4)
    T[0, 3] = x
    return T


@pytest.mark.slow
@pytest.mark.parametrize("backend", ["onnxruntime", "openvino"])
@pytest.mark.parametrize("method", ["s2g2", "focusbev", "focusbev_memory"])
def test_exported_monocular_methods_map_as_torch_does(method, backend, tmp_path_factory, monkeypatch):
    """The shipped front1 RGB weights of S2G2 and FocusBEV (both with segipm's prior, single frame)
    and a FocusBEV file with a memory bank (``focusbev_memory``, window 2) through the backend, on
    a real drive in order with its stamps and poses (the bank fuses the kept features): within
    ``backends.TOLERANCE`` of torch, the same known cells and frames; the same rig rebuilt does
    not export again.
    """
    if importlib.util.find_spec(backend) is None:
        pytest.skip(f"{backend} is not installed (the 'fast' extra)")
    from bev_mapper_core.geometry.grid import grid_preset

    tmp_path = tmp_path_factory.getbasetemp() / f"onnx_cache_{method}"  # shared by both backends: one export
    monkeypatch.setenv(backends.CACHE_ENV, str(tmp_path))
    rig, grid = preset_rig("front1"), grid_preset("ahead")
    # f32: S2G2's prior runs the segmenter stage, whose OpenVINO default may be bf16 (other labels)
    tmp_path.mkdir(parents=True, exist_ok=True)
    weights = memory_focusbev(tmp_path / "focusbev_w2.safetensors") if method == "focusbev_memory" else None
    cfg = MapperConfig(backend="torch", method=method.removesuffix("_memory"), input_kind="rgb", threads=1,
                       segmenter_precision="f32", weights=weights)
    ref, fast = create_mapper(rig, grid, cfg), create_mapper(rig, grid, MapperConfig(**{**cfg.__dict__, "backend": backend}))
    frames = list(generate_drive(rig, grid, SynthConfig(frames=3, seed=950_000_011)))
    for k, f in enumerate(frames):
        images = {n: c.rgb for n, c in f.cameras.items()}
        pose, stamp = _pose(2.0 * k), 10**9 + k * 300_000_000  # one memory interval apart
        a, b = fast.map(images, pose, stamp), ref.map(images, pose, stamp)
        assert np.abs(a.probs - b.probs).max() <= backends.TOLERANCE, (k, np.abs(a.probs - b.probs).max())
        np.testing.assert_array_equal(a.known, b.known)
        assert a.frames == b.frames
    if method == "focusbev_memory":
        assert a.frames == 2  # the bank was used: the exported features are what it keeps
    # the shipped weights map with segipm's prior (issue #39): its segmenter stage exports too
    exported = 1 if method == "focusbev_memory" else 2
    assert len(list((tmp_path / "onnx").glob("*.onnx"))) == exported
    moved = rig.scaled(1.0)  # the same rig, rebuilt: no new export
    fast.set_rig(moved)
    fast.map({n: c.rgb for n, c in frames[0].cameras.items()})
    assert len(list((tmp_path / "onnx").glob("*.onnx"))) == exported
