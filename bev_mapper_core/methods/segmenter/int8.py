"""The segmenter in INT8 (issue #41): its exported ONNX model quantized after training by
onnxruntime's static quantizer, for ``MapperConfig.segmenter_precision`` ``int8``.

* **Format**: QDQ (QuantizeLinear / DequantizeLinear pairs around each quantized operator),
  weights int8 per output channel, activations uint8 per tensor, MinMax calibration. The last
  part of the graph (the bilinear upsampling of the class scores to the camera's size, the
  argmax, the cast to labels) stays float: every node after the classifier's convolution is
  left out; so do the first :data:`FLOAT_LEADING_CONVS` convolutions (accuracy). OpenVINO reads
  the QDQ file and runs its convolutions in int8
  (:data:`~.stage.STAGE_AUTO_ORDER_INT8`); onnxruntime runs it too, slower here.
* **Calibration**: :data:`CALIBRATION_SEEDS` synthetic-town drives (training seeds of run seed
  77, below the validation seeds: never a held-out or test drive), :data:`CALIBRATION_FRAMES`
  frames each, every surround6 camera, resized to the model's input: deterministic, needs no
  dataset, and the same on every machine. No CamVid image is read, so building the file at a
  node's first start needs nothing but the package.
* **Where it is built**: in the export cache, as part of the export (:meth:`Int8Export.after_export`
  runs right after the float export, in the export's child process when the node exports in the
  background), so the int8 file is verified, refused and rebuilt like any export
  (:mod:`~bev_mapper_core.nn.export_cache`); its key differs from the float export's by the
  module's ``int8_recipe`` buffer (:func:`recipe_tensor`: the recipe, the calibration set and the
  quantizer's version). Measured cost and accuracy: docs/SPEED.md ("Issue #41: surround6 RGB at
  camera rate").
"""

from __future__ import annotations

import hashlib
import logging
import shutil
import tempfile
import time
from pathlib import Path

import cv2
import numpy as np
import torch

from bev_mapper_core.errors import ConfigError

#: Version of the recipe below (bump when anything in it changes: the cache key follows).
RECIPE_VERSION = 2
#: The first convolutions (in graph order: the stem and the trunk's stride-2 and -4 blocks of
#: EfficientNet-Lite0) stay float: quantized, they cost CamVid test 1.5 IoU of pedestrian; left
#: float, 0.4 (docs/SPEED.md, issue #41).
FLOAT_LEADING_CONVS = 14
#: Synthetic drives of the calibration set: training seeds of run seed 77 (``train_seeds(77, n)``).
CALIBRATION_SEEDS: tuple[int, ...] = tuple(77 * 100_000 + i for i in range(4))
#: Frames per calibration drive (every 15th frame of the drive; all six cameras each).
CALIBRATION_FRAMES = 2
CALIBRATION_STRIDE = 15

log = logging.getLogger("bev_mapper.export_cache")


def quantizer_version() -> str:
    """The version of the quantizer (onnxruntime); ``""`` when it is not installed."""
    try:
        import onnxruntime  # noqa: PLC0415

        return str(onnxruntime.__version__)
    except ImportError:
        return ""


def recipe_tensor() -> torch.Tensor:
    """What the int8 file depends on besides the float model, as an int64 tensor (a buffer of
    the exported module: the export cache's key hashes it).
    """
    text = f"{RECIPE_VERSION}|{FLOAT_LEADING_CONVS}|{CALIBRATION_SEEDS}|{CALIBRATION_FRAMES}|{CALIBRATION_STRIDE}|{quantizer_version()}"
    digest = hashlib.sha256(text.encode()).digest()[:16]
    return torch.tensor(np.frombuffer(digest, dtype=np.int64).copy())


def calibration_images() -> list[np.ndarray]:
    """The calibration set's camera images ``(225, 400, 3)`` uint8, in a fixed order
    (:data:`CALIBRATION_SEEDS` x :data:`CALIBRATION_FRAMES` x the six surround6 cameras).
    """
    from bev_mapper_core.geometry.grid import BevGrid  # noqa: PLC0415
    from bev_mapper_core.geometry.rig import preset_rig  # noqa: PLC0415
    from bev_mapper_core.labels.classes import BEV_CLASS_NAMES  # noqa: PLC0415
    from bev_mapper_core.training.data import render_drive  # noqa: PLC0415

    rig, grid = preset_rig("surround6"), BevGrid()
    out = []
    for seed in CALIBRATION_SEEDS:
        d = render_drive(rig, grid, BEV_CLASS_NAMES, seed, CALIBRATION_FRAMES, CALIBRATION_STRIDE, rgb=(225, 400))
        out += [np.ascontiguousarray(d["rgb"][k, i]) for k in range(CALIBRATION_FRAMES) for i in range(len(rig.names))]
    return out


def calibration_inputs(preprocess, shape: tuple[int, ...]) -> list[np.ndarray]:
    """The calibration images as model inputs of ``shape`` = ``(1, 3, h, w)``: each resized to
    ``w x h`` (area or bilinear) and normalised by ``preprocess`` (the segmenter's).
    """
    _, _, h, w = shape
    xs = []
    for img in calibration_images():
        interp = cv2.INTER_AREA if img.shape[1] > w else cv2.INTER_LINEAR
        img = cv2.resize(img, (w, h), interpolation=interp)
        with torch.inference_mode():
            xs.append(preprocess(torch.from_numpy(img)[None]).numpy().astype(np.float32))
    return xs


def float_nodes(path: Path) -> list[str]:
    """Names of the nodes left float: the first :data:`FLOAT_LEADING_CONVS` convolutions and
    every node after the last convolution (upsampling, argmax, cast).
    """
    import onnx  # noqa: PLC0415

    nodes = onnx.load(str(path), load_external_data=False).graph.node
    convs = [i for i, n in enumerate(nodes) if n.op_type == "Conv"]
    return [nodes[i].name for i in convs[:FLOAT_LEADING_CONVS]] + [n.name for n in nodes[convs[-1] + 1:]]


def quantize_onnx(src: Path, dst: Path, inputs: list[np.ndarray]) -> Path:
    """Quantize the float ONNX model ``src`` into ``dst`` (QDQ, per-channel int8 weights,
    uint8 activations, MinMax calibration on ``inputs``: arrays for its single input).

    Raises:
        ConfigError: onnxruntime's quantizer is not installed.
    """
    try:
        import onnxruntime as ort  # noqa: PLC0415
        from onnxruntime.quantization import (  # noqa: PLC0415
            CalibrationDataReader,
            CalibrationMethod,
            QuantFormat,
            QuantType,
            quantize_static,
        )
        from onnxruntime.quantization.shape_inference import quant_pre_process  # noqa: PLC0415
    except ImportError:
        raise ConfigError("segmenter_precision int8 needs onnxruntime (its quantizer): pip install onnxruntime, "
                          "or use segmenter_precision f32") from None
    name = ort.InferenceSession(str(src), providers=["CPUExecutionProvider"]).get_inputs()[0].name

    class _Reader(CalibrationDataReader):
        def __init__(self) -> None:
            self._it = iter(inputs)

        def get_next(self):
            x = next(self._it, None)
            return None if x is None else {name: x}

    started = time.perf_counter()
    with tempfile.TemporaryDirectory(prefix="bev_int8_") as tmp:  # the system's: nothing left in the cache
        pre, out = Path(tmp) / "pre.onnx", Path(tmp) / "int8.onnx"
        quant_pre_process(str(src), str(pre), skip_symbolic_shape=True)
        quantize_static(str(pre), str(out), _Reader(), quant_format=QuantFormat.QDQ, per_channel=True,
                        activation_type=QuantType.QUInt8, weight_type=QuantType.QInt8,
                        nodes_to_exclude=float_nodes(pre), calibrate_method=CalibrationMethod.MinMax)
        shutil.copyfile(out, dst)
    log.warning("export cache: quantized to int8 on %d calibration images in %.1f s", len(inputs),
                time.perf_counter() - started)
    return dst


class Int8Export:
    """Mixin of an exported module whose ONNX file is quantized right after the export
    (:func:`~bev_mapper_core.nn.backends.export_onnx` calls :meth:`after_export`). The module
    must register :func:`recipe_tensor` as a buffer and have a ``preprocess`` for the calibration
    images.
    """

    def after_export(self, path: Path, inputs) -> None:
        """Replace the float model at ``path`` by its int8 quantization."""
        xs = calibration_inputs(self.calibration_preprocess, tuple(inputs[0].shape))
        with tempfile.TemporaryDirectory(prefix="bev_int8_") as tmp:
            f32 = Path(tmp) / "f32.onnx"
            shutil.copyfile(path, f32)
            quantize_onnx(f32, path, xs)


__all__ = ["CALIBRATION_FRAMES", "CALIBRATION_SEEDS", "CALIBRATION_STRIDE", "FLOAT_LEADING_CONVS", "Int8Export",
           "RECIPE_VERSION", "calibration_images", "calibration_inputs", "float_nodes", "quantize_onnx",
           "quantizer_version", "recipe_tensor"]
