"""The segmenter as a stage in front of label models: which file (``MapperConfig.segmenter``:
``auto`` = the shipped file, or a path) and :class:`SegmenterStage`, RGB camera images -> label
images of the same size. ``segipm`` puts IPM behind it; Bi-Mapper's label weights run on RGB
cameras behind it (chained input); S2G2 starts its encoder from the shipped file.
"""

from __future__ import annotations

from collections.abc import Mapping
from pathlib import Path

import cv2
import numpy as np
import torch

from bev_mapper_core.errors import ConfigError
from bev_mapper_core.mapper import MapperConfig

from .. import METHODS, WEIGHTS_DIR
from .model import DECISION_WIDTH_FACTOR, Segmenter
from .weights import load_segmenter

#: The shipped segmenter used for rigs without their own (a segmenter works per camera image).
GENERAL_SEGMENTER = METHODS["segmenter"].weights[0]


def shipped_segmenter(rig_name: str) -> Path | None:
    """The shipped segmenter for a rig: ``segmenter_<rig>.safetensors``, else the general one."""
    for name in (f"segmenter_{rig_name}.safetensors", GENERAL_SEGMENTER):
        if (WEIGHTS_DIR / name).is_file():
            return WEIGHTS_DIR / name
    return None


def segmenter_path(config: MapperConfig, rig_name: str) -> Path:
    """The segmenter file ``config.segmenter`` names for this rig.

    Raises:
        ConfigError: ``none``, or ``auto`` with no shipped segmenter.
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
    return Path(spec)


class SegmenterStage:
    """RGB camera images -> label images of the same size, with a segmenter file.

    Raises (constructor):
        WeightsError: the file is not valid segmenter weights.
    """

    def __init__(self, path: Path, device: torch.device | str = "cpu") -> None:
        self.device = torch.device(device)
        self.path = path
        self.model: Segmenter = load_segmenter(path, self.device)

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
            x = torch.from_numpy(np.stack(batch)).to(self.device)  # (B, H/k, W/k, 3)
            labels = self.model.segment(x, size=(H, W)).cpu().numpy()  # (B, H, W)
            out.update({n: np.ascontiguousarray(labels[i]) for i, n in enumerate(names)})
        return out


__all__ = ["GENERAL_SEGMENTER", "SegmenterStage", "segmenter_path", "shipped_segmenter"]
