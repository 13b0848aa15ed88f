"""The segmenter as a stage in front of label models: which file (``MapperConfig.segmenter``)
and :class:`SegmenterStage`, RGB camera images -> label images of the same size. ``segipm`` puts
IPM behind it; Bi-Mapper's label weights run on RGB cameras behind it (chained input).

Two segmenters ship (issue #37), named in :data:`SHIPPED_SEGMENTERS`:

* ``camvid`` (``segmenter.safetensors``, the default: ``auto``): EfficientNet-Lite0 from ImageNet,
  trained on the synthetic town and CamVid, which makes it **non-commercial** (CamVid is
  CC BY-NC 4.0); much the better on real frames (docs/RESULTS.md, "Pretrained trunk");
* ``open`` (``segmenter_open.safetensors``): the same network from the same ImageNet checkpoint
  (Apache-2.0), trained on the synthetic town only: every input allows commercial use.

``segmenter_w320.safetensors``, the segmenter shipped before, stays as the trunk that S2G2,
FocusBEV and Bi-Mapper's RGB encoders start from (``encoder_init auto``; their shipped weights
were trained from it, and their encoders have its sizes): :data:`TRUNK_SEGMENTER`.

The stage runs the network with the configured backend (:data:`STAGE_AUTO_ORDER` for ``auto``:
onnxruntime first, the fastest on the segmenter in f32, bench/bench_segmenter.py) through the
package's :class:`~bev_mapper_core.nn.backends.BackendRunner`; the labels equal torch's (tested).
``MapperConfig.segmenter_precision`` (issue #41, :func:`stage_precision`): ``auto`` runs OpenVINO
in bf16 where the CPU computes in it (2.3x onnxruntime's f32 here, CamVid test within 0.3 IoU per
class), else f32; ``int8`` runs the export quantized by :mod:`.int8`.
"""

from __future__ import annotations

import functools
from collections.abc import Mapping
from pathlib import Path

import cv2
import numpy as np
import torch
from torch.nn import functional as F

from bev_mapper_core.errors import ConfigError
from bev_mapper_core.mapper import SEGMENTER_PRECISIONS, MapperConfig
from bev_mapper_core.nn.backends import BackendRunner, installed_backends
from bev_mapper_core.nn.runtime import inference_threads

from .. import METHODS, WEIGHTS_DIR
from .int8 import Int8Export, recipe_tensor
from .model import DECISION_WIDTH_FACTOR, Segmenter
from .weights import load_segmenter

#: The shipped segmenters by name (``MapperConfig.segmenter``, ``--segmenter``): file in WEIGHTS_DIR.
SHIPPED_SEGMENTERS: dict[str, str] = {"camvid": METHODS["segmenter"].weights[0],
                                      "open": METHODS["segmenter"].weights[1]}
#: What ``auto`` means: the shipped segmenter that scores best on real frames (CamVid test 69.9
#: against 33.5 mean IoU of the five common classes, docs/RESULTS.md); non-commercial.
DEFAULT_SEGMENTER = "camvid"
#: The shipped segmenter used for rigs without their own (a segmenter works per camera image).
GENERAL_SEGMENTER = SHIPPED_SEGMENTERS[DEFAULT_SEGMENTER]
#: The segmenter whose trunk the other RGB methods start from (``encoder_init auto``).
TRUNK_SEGMENTER = "segmenter_w320.safetensors"
#: ``backend: auto`` for the segmenter stage: the fastest that gives torch's labels, measured
#: on the shipped segmenter at 480x360, 1 thread (bench/bench_segmenter.py, docs/SPEED.md):
#: onnxruntime 36.5 ms, OpenVINO 40.8 ms, torch 86.6 ms.
STAGE_AUTO_ORDER = ("onnxruntime", "openvino")
#: ``backend: auto`` for the int8 segmenter stage (``segmenter_precision`` int8): OpenVINO runs
#: the quantized file's convolutions in int8, faster than onnxruntime here (docs/SPEED.md, #41).
STAGE_AUTO_ORDER_INT8 = ("openvino", "onnxruntime")


def shipped_segmenter(rig_name: str) -> Path | None:
    """The shipped segmenter for a rig: ``segmenter_<rig>.safetensors``, else the default one."""
    for name in (f"segmenter_{rig_name}.safetensors", GENERAL_SEGMENTER):
        if (WEIGHTS_DIR / name).is_file():
            return WEIGHTS_DIR / name
    return None


def segmenter_path(config: MapperConfig, rig_name: str) -> Path:
    """The segmenter file ``config.segmenter`` names for this rig: ``auto`` (the rig's own or the
    default, :data:`DEFAULT_SEGMENTER`), a name of :data:`SHIPPED_SEGMENTERS`, or a path.

    Raises:
        ConfigError: ``none``, or ``auto`` / a name with no shipped file.
    """
    spec = config.segmenter
    if spec == "none":
        raise ConfigError("RGB input needs a segmenter here, but segmenter is 'none'")
    if spec == "auto":
        path = shipped_segmenter(rig_name)
        if path is None:
            raise ConfigError("no segmenter shipped; train one (bev-train --method segmenter) and pass "
                              "segmenter=<file>")
        return path
    if spec in SHIPPED_SEGMENTERS:
        path = WEIGHTS_DIR / SHIPPED_SEGMENTERS[spec]
        if not path.is_file():
            raise ConfigError(f"the shipped segmenter {spec!r} ({path.name}) is missing from this installation")
        return path
    return Path(spec)


@functools.cache
def cpu_has_bf16() -> bool:
    """True when OpenVINO is installed and says this CPU computes in bf16 (AVX512-BF16 / AMX)."""
    if "openvino" not in installed_backends():
        return False
    try:
        import openvino as ov  # noqa: PLC0415

        return "BF16" in ov.Core().get_property("CPU", "OPTIMIZATION_CAPABILITIES")
    except Exception:  # noqa: BLE001 - no CPU plugin, an old runtime: no bf16
        return False


def stage_precision(backend: str, precision: str, device: str = "cpu") -> str:
    """The precision the segmenter stage runs for ``MapperConfig.backend`` ``backend`` and
    ``MapperConfig.segmenter_precision`` ``precision``: ``auto`` is ``bf16`` where ``backend`` is
    ``auto`` or ``openvino`` and :func:`cpu_has_bf16`, else ``f32``; torch (or a GPU) runs f32.

    Raises:
        ConfigError: an unknown precision, or ``bf16`` asked of onnxruntime (OpenVINO runs it).
    """
    if precision not in SEGMENTER_PRECISIONS:
        raise ConfigError(f"segmenter_precision must be one of {SEGMENTER_PRECISIONS}, got {precision!r}")
    if backend == "torch" or torch.device(device).type != "cpu":
        return "f32"
    if precision == "auto":
        return "bf16" if backend in ("auto", "openvino") and cpu_has_bf16() else "f32"
    if precision == "bf16" and backend == "onnxruntime":
        raise ConfigError("segmenter_precision bf16 runs on OpenVINO: use backend 'openvino' or 'auto'")
    return precision


def stage_backend(name: str, precision: str = "f32") -> str:
    """The backend the segmenter stage runs for ``MapperConfig.backend`` ``name`` (``auto``:
    the first installed of :data:`STAGE_AUTO_ORDER`; for ``precision`` (resolved:
    :func:`stage_precision`) int8 of :data:`STAGE_AUTO_ORDER_INT8`, for bf16 OpenVINO; else torch).
    """
    if name != "auto":
        return name
    have = installed_backends()
    order = {"int8": STAGE_AUTO_ORDER_INT8, "bf16": ("openvino",)}.get(precision, STAGE_AUTO_ORDER)
    return next((b for b in order if b in have), "torch")


class _Labels(torch.nn.Module):
    """The exported part: normalised input ``(B, 3, h, w)`` -> ``(B, H, W)`` uint8 labels decided
    at ``size`` = ``(H, W)``.
    """

    def __init__(self, model: Segmenter, size: tuple[int, int]) -> None:
        super().__init__()
        self.model, self.size = model, tuple(size)
        # the label size is baked into the exported graph: as a buffer it is part of the export
        # cache's key (which hashes parameters and buffers), so two sizes never share a file
        self.register_buffer("label_size", torch.tensor(self.size, dtype=torch.int64), persistent=False)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.model(x, size=self.size).argmax(dim=1).to(torch.uint8)


class _Int8Labels(Int8Export, _Labels):
    """:class:`_Labels` whose export is quantized to int8 (:mod:`.int8`); its ``int8_recipe``
    buffer (the calibration set's and the quantizer's identity) gives it a cache key of its own.
    """

    def __init__(self, model: Segmenter, size: tuple[int, int]) -> None:
        super().__init__(model, size)
        self.register_buffer("int8_recipe", recipe_tensor(), persistent=False)

    def calibration_preprocess(self, images: torch.Tensor) -> torch.Tensor:
        """``(1, h, w, 3)`` uint8 already at the model's input size -> its normalised input."""
        return self.model.preprocess(images)


class SegmenterStage:
    """RGB camera images -> label images of the same size, with a segmenter file, run by
    ``backend`` (``torch``, ``onnxruntime``, ``openvino`` or ``auto``: :func:`stage_backend`)
    with ``threads`` intra-op threads (0: :func:`~bev_mapper_core.nn.runtime.inference_threads`),
    in ``precision`` ``f32``, ``bf16`` (OpenVINO), ``int8`` (:mod:`.int8`) or ``auto``
    (:func:`stage_precision`; exported backends only, torch runs f32).

    Raises (constructor):
        WeightsError: the file is not valid segmenter weights.
        ConfigError: a backend that is not installed.
    """

    def __init__(self, path: Path, device: torch.device | str = "cpu", backend: str = "torch",
                 threads: int = 0, precision: str = "f32") -> None:
        self.device = torch.device(device)
        self.path = path
        self.model: Segmenter = load_segmenter(path, self.device)
        precision = stage_precision(backend, precision, self.device.type)
        self.backend = stage_backend(backend, precision)
        if self.backend not in installed_backends():
            raise ConfigError(f"backend {self.backend!r} is not installed (installed: {installed_backends()})")
        self.precision = precision if self.backend != "torch" and self.device.type == "cpu" else "f32"
        self.threads = threads or inference_threads()
        self._runners: dict[tuple, BackendRunner] = {}  # (input shape, label size) -> its exported part
        self._background = False

    @property
    def background(self) -> bool:
        """Export in the background, mapping with torch meanwhile (the node: issue #41; see
        :class:`~bev_mapper_core.nn.backends.BackendRunner`); applies to every input size.
        """
        return self._background

    @background.setter
    def background(self, on: bool) -> None:
        self._background = bool(on)
        for runner in self._runners.values():
            runner.background = self._background

    @property
    def state(self) -> str:
        """What runs the network now (each input size's runner; the backend before the first
        frame), ``int8`` appended where it runs the quantized model.
        """
        states = sorted({r.state for r in self._runners.values()}) or [self.backend]
        if self.precision != "f32":
            states = [f"{s} {self.precision}" if s == self.backend or s.startswith(f"{self.backend} ") else s for s in states]
        return "; ".join(states)

    def close(self) -> None:
        """Stop background exports (their processes and partial files go)."""
        for runner in self._runners.values():
            runner.close()

    def _labels(self, x: torch.Tensor, size: tuple[int, int]) -> torch.Tensor:
        """Normalised input ``(B, 3, h, w)`` -> ``(B, *size)`` uint8 labels, by the backend.

        An exported model has a fixed batch, so it runs one image at a time: one export per
        image size, whatever number of cameras a set brings (a set missing cameras would
        otherwise export again for its smaller batch).
        """
        key = (tuple(x.shape[1:]), tuple(size))
        runner = self._runners.get(key)
        if runner is None:
            runner = self._runners[key] = BackendRunner(self.backend, self.device, self.threads,
                                                        background=self._background,
                                                        precision="bf16" if self.precision == "bf16" else "f32")
            runner.reset((_Int8Labels if self.precision == "int8" else _Labels)(self.model, size))
        with torch.inference_mode():
            if runner.eager:
                return runner(x)[0]
            return torch.cat([runner(x[i:i + 1])[0] for i in range(len(x))])  # B x (1, H, W) -> (B, H, W)

    def _preprocess(self, batch: list[np.ndarray]) -> torch.Tensor:
        """``B x (H, W, 3)`` uint8 -> ``(B, 3, h, w)`` normalised model input. Torch runs
        :meth:`Segmenter.preprocess` (the reference); an exported backend, where the input is
        no smaller than the image (antialiasing changes nothing then), resizes each image with
        OpenCV's bilinear on float32 (the same half-pixel sampling; within 1e-5 of torch's) and
        normalises it in place: 2.7x faster for six 400x225 cameras (issue #41).
        """
        H, W = batch[0].shape[:2]
        h, w = self.model.config.input_size((W, H))
        if self.backend == "torch" or self.device.type != "cpu" or h < H or w < W:
            return self.model.preprocess(torch.from_numpy(np.stack(batch)).to(self.device))  # (B, H, W, 3) in
        std = self.model.rgb_std.reshape(3).numpy()
        scale = (1.0 / (255.0 * std)).astype(np.float32)
        shift = (-self.model.rgb_mean.reshape(3).numpy() / std).astype(np.float32)
        out = np.empty((len(batch), 3, h, w), np.float32)
        for i, img in enumerate(batch):
            r = img.astype(np.float32) if (h, w) == (H, W) else cv2.resize(img.astype(np.float32), (w, h),
                                                                           interpolation=cv2.INTER_LINEAR)
            out[i] = (r * scale + shift).transpose(2, 0, 1)  # (h, w, 3) -> (3, h, w)
        return torch.from_numpy(out)

    def segment(self, images: Mapping[str, np.ndarray]) -> dict[str, np.ndarray]:
        """``{camera: (H, W, 3) uint8}`` -> ``{camera: (H, W) uint8 label ids}``; cameras of one
        size are segmented as one batch. An image ``k`` >= 2 times wider than the labels are
        decided at (:meth:`Segmenter.decision_size`) is first reduced by a ``k x k`` box mean
        (OpenCV's area resampling on the uint8 image), then resized to the model's input as any
        other; the labels come back at the image's size.
        """
        out: dict[str, np.ndarray] = {}
        by_size: dict[tuple, list[str]] = {}
        for name, img in images.items():
            by_size.setdefault(img.shape, []).append(name)
        for names in by_size.values():
            H, W = images[names[0]].shape[:2]
            k = max(1, W // (DECISION_WIDTH_FACTOR * self.model.config.input_width))
            batch = [images[n] if k == 1 else cv2.resize(images[n], (W // k, H // k), interpolation=cv2.INTER_AREA)
                     for n in names]  # a full-resolution camera: a k x k box mean first, cheap on uint8
            h, w = self.model.decision_size((H, W))
            with torch.inference_mode():
                labels = self._labels(self._preprocess(batch), (h, w))  # (B, h, w), as Segmenter.segment
            if (h, w) != (H, W):
                labels = F.interpolate(labels[:, None], size=(H, W), mode="nearest")[:, 0]  # (B, 1, H, W) -> (B, H, W)
            labels = labels.cpu().numpy()
            out.update({n: np.ascontiguousarray(labels[i]) for i, n in enumerate(names)})
        return out


__all__ = ["DEFAULT_SEGMENTER", "GENERAL_SEGMENTER", "SHIPPED_SEGMENTERS", "STAGE_AUTO_ORDER", "STAGE_AUTO_ORDER_INT8",
           "TRUNK_SEGMENTER",
           "SegmenterStage", "cpu_has_bf16", "segmenter_path", "shipped_segmenter", "stage_backend",
           "stage_precision"]
