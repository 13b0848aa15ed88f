"""The segmenter stage's precision (issue #41, ``MapperConfig.segmenter_precision``): which
precision and backend run, the int8 export (quantized in the export cache: its labels against
f32's on synthetic camera images, a damaged file rebuilt to the same bytes), and bf16 on OpenVINO.
"""

from __future__ import annotations

import importlib.util
import logging

import numpy as np
import pytest

from bev_mapper_core.errors import ConfigError
from bev_mapper_core.mapper import MapperConfig
from bev_mapper_core.methods import WEIGHTS_DIR
from bev_mapper_core.methods.segmenter.stage import (
    DEFAULT_SEGMENTER,
    SHIPPED_SEGMENTERS,
    SegmenterStage,
    cpu_has_bf16,
    stage_backend,
    stage_precision,
)
from bev_mapper_core.nn.export_cache import file_sha256

PATH = WEIGHTS_DIR / SHIPPED_SEGMENTERS[DEFAULT_SEGMENTER]
#: Least share of pixels whose int8 / bf16 label equals f32's on the synthetic images (measured:
#: 0.997 int8, on three surround6 frames of a held-out drive; CamVid test within 0.5 IoU per class
#: of interest, docs/SPEED.md).
AGREEMENT = 0.99


def test_precision_resolution():
    assert stage_precision("torch", "int8") == "f32"  # torch is the f32 reference
    assert stage_precision("onnxruntime", "auto") == "f32"
    assert stage_precision("onnxruntime", "int8") == "int8"
    assert stage_precision("auto", "auto") == ("bf16" if cpu_has_bf16() else "f32")
    assert stage_precision("openvino", "int8", "cuda") == "f32"
    with pytest.raises(ConfigError, match="bf16 runs on OpenVINO"):
        stage_precision("onnxruntime", "bf16")
    with pytest.raises(ConfigError, match="segmenter_precision must be one of"):
        stage_precision("auto", "fp16")
    with pytest.raises(ConfigError, match="segmenter_precision must be one of"):
        MapperConfig(segmenter_precision="int4")
    assert stage_backend("auto", "bf16") in ("openvino", "torch")
    if importlib.util.find_spec("openvino") is not None:
        assert stage_backend("auto", "int8") == "openvino"  # the faster int8 runtime here


@pytest.fixture(scope="module")
def frames():
    """Six surround6 camera images (400x225) of two frames of a held-out drive."""
    from bev_mapper_core.geometry.grid import BevGrid
    from bev_mapper_core.geometry.rig import preset_rig
    from bev_mapper_core.labels.classes import BEV_CLASS_NAMES
    from bev_mapper_core.training.data import render_drive

    rig = preset_rig("surround6")
    d = render_drive(rig, BevGrid(), BEV_CLASS_NAMES, 950000011, 2, 7, rgb=(225, 400))
    return [{n: np.ascontiguousarray(d["rgb"][k, i]) for i, n in enumerate(rig.names)} for k in range(2)]


def _agreement(a: dict, b: dict) -> float:
    return float(np.mean([np.mean(a[n] == b[n]) for n in a]))


@pytest.mark.slow
def test_int8_export_agrees_with_f32_and_a_damaged_file_is_rebuilt(frames, tmp_path, monkeypatch, caplog):
    """The node's start-up (issue #41): segipm in int8 maps with torch while the export process
    exports and quantizes, then switches to the int8 model; that one file serves both runtimes,
    agrees with f32, and a damaged copy is rebuilt to the same bytes (two quantizations in all)."""
    if importlib.util.find_spec("onnxruntime") is None:
        pytest.skip("onnxruntime not installed (its quantizer builds the int8 file)")
    import onnx

    from bev_mapper_core.geometry.grid import BevGrid
    from bev_mapper_core.geometry.rig import preset_rig
    from bev_mapper_core.mapper import create_mapper

    monkeypatch.setenv("BEV_MAPPER_CACHE", str(tmp_path))
    mapper = create_mapper(preset_rig("surround6"), BevGrid(),
                           MapperConfig(method="segipm", input_kind="rgb", backend="onnxruntime",
                                        segmenter_precision="int8", threads=1))
    try:
        mapper.export_in_background()
        mapper.map(frames[0])
        assert mapper.backend_state == "torch (until the onnxruntime model is ready)"
        (runner,) = mapper.stage._runners.values()
        assert runner.wait_ready(300)
        mapper.map(frames[1])
        assert mapper.backend_state == "onnxruntime int8"
    finally:
        mapper.close()
    (model,) = tmp_path.rglob("*.onnx")  # one file for both runtimes, quantized, its tail float
    ops = {n.op_type for n in onnx.load(str(model)).graph.node}
    assert {"QuantizeLinear", "DequantizeLinear", "ArgMax"} <= ops

    backends = [b for b in ("onnxruntime", "openvino") if importlib.util.find_spec(b) is not None]
    ref = SegmenterStage(PATH, backend="torch", threads=1)
    want = [ref.segment(f) for f in frames]
    caplog.set_level(logging.WARNING, "bev_mapper.export_cache")
    for backend in backends:
        stage = SegmenterStage(PATH, backend=backend, threads=1, precision="int8")
        got = [stage.segment(f) for f in frames]
        assert stage.state == f"{backend} int8"
        for g, w in zip(got, want):
            assert all(g[n].shape == w[n].shape and g[n].dtype == np.uint8 for n in w)
            assert _agreement(g, w) > AGREEMENT, backend
            assert _agreement(g, w) < 1.0  # it is another model: not f32's labels to the pixel
    assert list(tmp_path.rglob("*.onnx")) == [model]  # the runtimes loaded the background export's file
    sha = file_sha256(model)
    # the f32 export of the same weights and size is another file (the recipe is in the key)
    SegmenterStage(PATH, backend="onnxruntime", threads=1).segment(frames[0])
    assert len(list(tmp_path.rglob("*.onnx"))) == 2

    data = bytearray(model.read_bytes())  # a flipped byte: refused, rebuilt, the same file again
    data[len(data) // 2] ^= 0xFF
    model.write_bytes(bytes(data))
    caplog.clear()
    stage = SegmenterStage(PATH, backend=backends[0], threads=1, precision="int8")
    assert _agreement(stage.segment(frames[1]), want[1]) > AGREEMENT
    assert "is not used: its contents differ from its record" in caplog.text
    assert "quantized to int8" in caplog.text
    assert file_sha256(model) == sha  # the calibration and the quantizer are deterministic
    # (a missing file is exported again like any other: tests/bev_mapper_core/nn/test_export_cache.py;
    # a third 20-45 s quantization here would test nothing more)


@pytest.mark.slow
def test_bf16_runs_on_openvino_and_agrees_with_f32(frames, tmp_path, monkeypatch):
    if not cpu_has_bf16():
        pytest.skip("OpenVINO not installed or this CPU has no bf16")
    monkeypatch.setenv("BEV_MAPPER_CACHE", str(tmp_path))
    ref = SegmenterStage(PATH, backend="torch", threads=1)
    stage = SegmenterStage(PATH, backend="auto", threads=1, precision="auto")
    assert (stage.backend, stage.precision) == ("openvino", "bf16")
    for f in frames:
        assert _agreement(stage.segment(f), ref.segment(f)) > AGREEMENT
    assert stage.state == "openvino bf16"
