"""``segipm``: the two-stage RGB baseline, a 2-D segmenter per camera followed by IPM.

Register as ``"segipm": "bev_mapper_core.methods.segipm.mapper:SegIpmMapper"``. Each RGB camera
image goes through the segmenter (:class:`~.segmenter.Segmenter`, weights from
``MapperConfig.segmenter``: ``auto`` = the shipped file, or a path); its label image, at the
camera's own size, goes through :class:`~bev_mapper_core.methods.ipm.mapper.IpmMapper` with the same config
(occlusion reasoning included). Works for any rig and grid, as IPM does.

:class:`SegmenterStage` is the first stage on its own; Bi-Mapper uses it to run label weights on
RGB cameras (chained input).
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import replace
from pathlib import Path

import numpy as np
import torch

from bev_mapper_core.errors import ConfigError
from bev_mapper_core.geometry.grid import BevGrid
from bev_mapper_core.geometry.rig import Rig
from bev_mapper_core.mapper import BevPrediction, Mapper, MapperConfig
from bev_mapper_core.nn.runtime import inference_device

from .. import WEIGHTS_DIR
from ..ipm.mapper import IpmMapper
from ..segmenter.model import Segmenter
from ..segmenter.weights import load_segmenter

#: The shipped segmenter used for rigs without their own (a segmenter works per camera image).
GENERAL_SEGMENTER = "segmenter.safetensors"


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
        size are segmented as one batch.
        """
        out: dict[str, np.ndarray] = {}
        by_size: dict[tuple, list[str]] = {}
        for name, img in images.items():
            by_size.setdefault(img.shape, []).append(name)
        for names in by_size.values():
            x = torch.from_numpy(np.stack([images[n] for n in names])).to(self.device)  # (B, H, W, 3)
            labels = self.model.segment(x).cpu().numpy()  # (B, H, W)
            out.update({n: np.ascontiguousarray(labels[i]) for i, n in enumerate(names)})
        return out


class SegIpmMapper(Mapper):
    """Segmenter + IPM on RGB images (see the module docstring)."""

    name = "segipm"

    @classmethod
    def preflight(cls, config: MapperConfig, rig_name: str, grid: BevGrid | None = None,
                  cameras: tuple[str, ...] | None = None) -> None:
        """RGB input and a segmenter file whose every tensor fits (a node never starts with one it cannot run)."""
        if config.input_kind != "rgb":
            raise ConfigError("segipm maps RGB images (input_kind 'rgb'); for label images use method 'ipm'")
        load_segmenter(segmenter_path(config, rig_name))  # every tensor checked (cached for the constructor)

    def __init__(self, rig: Rig, grid: BevGrid, config: MapperConfig) -> None:
        self.preflight(config, rig.name)
        self.stage = SegmenterStage(segmenter_path(config, rig.name), inference_device(config))
        self.ipm = IpmMapper(rig, grid, replace(config, method="ipm", input_kind="labels"))
        super().__init__(rig, grid, config)

    def set_rig(self, rig: Rig) -> None:
        """New calibration: IPM's tables (the segmenter does not depend on it)."""
        super().set_rig(rig)
        self.ipm.set_rig(rig)

    def map(self, images: Mapping[str, np.ndarray], ego_pose=None, stamp_ns=None) -> BevPrediction:
        """Segment each camera image, then IPM."""
        return self.ipm.map(self.stage.segment(self.check_images(images)))


__all__ = ["SegIpmMapper", "SegmenterStage", "segmenter_path", "shipped_segmenter"]
