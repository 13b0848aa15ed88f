"""The segmenter stage (bev_mapper_core/methods/segmenter/stage.py): the shipped segmenters by
name, and the exported backends giving torch's labels.
"""

from __future__ import annotations

import importlib.util

import numpy as np
import pytest

from bev_mapper_core.errors import ConfigError
from bev_mapper_core.mapper import MapperConfig
from bev_mapper_core.methods import WEIGHTS_DIR
from bev_mapper_core.methods.segmenter.stage import (
    DEFAULT_SEGMENTER,
    SHIPPED_SEGMENTERS,
    SegmenterStage,
    segmenter_path,
    stage_backend,
)
from bev_mapper_core.methods.segmenter.weights import load_segmenter


def test_shipped_segmenters_by_name():
    assert segmenter_path(MapperConfig(segmenter="auto"), "surround6") == WEIGHTS_DIR / SHIPPED_SEGMENTERS[DEFAULT_SEGMENTER]
    assert segmenter_path(MapperConfig(segmenter="open"), "front1").name == "segmenter_open.safetensors"
    assert segmenter_path(MapperConfig(segmenter="camvid"), "").name == "segmenter.safetensors"
    for name in SHIPPED_SEGMENTERS:  # both are ImageNet-started Lite0 networks at 480 px
        cfg = load_segmenter(segmenter_path(MapperConfig(segmenter=name), "")).config
        assert (cfg.encoder, cfg.input_width) == ("lite", 480)
    with pytest.raises(ConfigError, match="'none'"):
        segmenter_path(MapperConfig(segmenter="none"), "")


@pytest.mark.slow
def test_exported_stage_gives_torchs_labels(tmp_path, monkeypatch):
    """Each installed runtime labels as torch does, from one cache: the exported files are the
    runtimes' common ONNX (the first runtime exports, the second loads the same files)."""
    backends = [b for b in ("onnxruntime", "openvino") if importlib.util.find_spec(b) is not None]
    if not backends:
        pytest.skip("neither onnxruntime nor openvino is installed")
    monkeypatch.setenv("BEV_MAPPER_CACHE", str(tmp_path))
    rng = np.random.default_rng(5)
    # smooth colour blobs of two camera sizes (one batch of two, one single), a real-world-ish input
    base = rng.integers(0, 255, (2, 18, 32, 3), dtype=np.uint8)
    images = {f"c{i}": np.ascontiguousarray(np.repeat(np.repeat(base[i], 12, 0), 12, 1)) for i in range(2)}
    images["odd"] = np.ascontiguousarray(np.repeat(np.repeat(base[0, :15, :20], 9, 0), 9, 1))  # 135 x 180
    path = WEIGHTS_DIR / SHIPPED_SEGMENTERS[DEFAULT_SEGMENTER]
    ref = SegmenterStage(path, backend="torch", threads=1).segment(images)
    # the same model input at another label size (a 160x90 camera is upsampled to the input of a
    # 400x225 one): its own export, its own size (they once shared a cached file)
    small = {"s": np.ascontiguousarray(np.repeat(np.repeat(base[0, :9, :16], 5, 0), 5, 1))}  # 80 x 45
    def files() -> set:
        return set(tmp_path.rglob("*.onnx"))

    for k, backend in enumerate(backends):
        got = SegmenterStage(path, backend=backend, threads=1).segment(images)
        for name, labels in ref.items():
            assert got[name].shape == labels.shape and got[name].dtype == np.uint8, backend
            assert (got[name] == labels).mean() > 0.999, (backend, name)  # argmax ties aside, the same labels
        if k == 0:
            assert len(files()) == 2  # one export per image size, not per batch
        SegmenterStage(path, backend=backend, threads=1).segment({"c0": images["c0"]})  # a set missing c1
        if k == 0:
            assert len(files()) == 2
        assert SegmenterStage(path, backend=backend, threads=1).segment(small)["s"].shape == (45, 80)
        if k == 0:
            exported = files()
            assert len(exported) == 3
        assert files() == exported  # the second runtime exports nothing: it loads the same three files
    assert SegmenterStage(path, backend="torch").segment(small)["s"].shape == (45, 80)


def test_stage_backend_auto_prefers_the_measured_fastest():
    from bev_mapper_core.nn.backends import installed_backends

    have = installed_backends()
    want = "onnxruntime" if "onnxruntime" in have else "openvino" if "openvino" in have else "torch"
    assert stage_backend("auto") == want
    assert stage_backend("torch") == "torch"


@pytest.mark.slow
def test_segipm_exports_in_the_background_and_maps_meanwhile(tmp_path, monkeypatch):
    """The node's start-up (issue #41) reaches the segmenter stage: the first frame is mapped by
    torch while the export runs, then the stage switches; close() stops an export under way."""
    if importlib.util.find_spec("onnxruntime") is None:
        pytest.skip("onnxruntime not installed")
    from bev_mapper_core.geometry.grid import BevGrid
    from bev_mapper_core.geometry.rig import preset_rig
    from bev_mapper_core.mapper import create_mapper

    monkeypatch.setenv("BEV_MAPPER_CACHE", str(tmp_path))
    rig = preset_rig("front1")
    mapper = create_mapper(rig, BevGrid(0.0, 16.0, -8.0, 8.0, 0.5),
                           MapperConfig(method="segipm", input_kind="rgb", backend="onnxruntime", threads=1))
    mapper.export_in_background()
    w, h = rig.cameras[0].model.image_size
    frame = {rig.names[0]: np.full((h, w, 3), 90, np.uint8)}
    first = mapper.map(frame)
    assert mapper.backend_state.startswith("torch (until the onnxruntime")
    (runner,) = mapper.stage._runners.values()
    assert runner.wait_ready(120)
    second = mapper.map(frame)
    assert mapper.backend_state == "onnxruntime"
    np.testing.assert_array_equal(first.known, second.known)
    mapper.close()


def test_exported_stage_preprocesses_as_torch_does():
    """Issue #41: an exported backend's stage resizes with OpenCV (float32 bilinear) where the
    model input is no smaller than the image; within 1e-5 of Segmenter.preprocess; larger images
    keep torch's antialiased path (the same tensor)."""
    import cv2
    import torch

    if importlib.util.find_spec("onnxruntime") is None:
        pytest.skip("onnxruntime not installed")
    path = WEIGHTS_DIR / SHIPPED_SEGMENTERS[DEFAULT_SEGMENTER]
    stage = SegmenterStage(path, backend="onnxruntime", threads=1)
    rng = np.random.default_rng(3)
    for h, w in ((225, 400), (270, 480), (360, 480), (900, 1600)):
        noise = rng.integers(0, 256, (2 * h, w, 3), dtype=np.uint8)
        batch = list(cv2.GaussianBlur(noise, (5, 5), 1.5).reshape(2, h, w, 3))
        ref = stage.model.preprocess(torch.from_numpy(np.stack(batch)))
        got = stage._preprocess(batch)
        assert got.shape == ref.shape and got.dtype == torch.float32
        np.testing.assert_allclose(got.numpy(), ref.numpy(), rtol=0, atol=1e-5)
