"""``segipm``: the two-stage RGB baseline, a 2-D segmenter per camera followed by IPM.

Register as ``"segipm": "bev_mapper_core.methods.segipm.mapper:SegIpmMapper"``. Each RGB camera
image goes through the segmenter (:class:`~.segmenter.Segmenter`, weights from
``MapperConfig.segmenter``: ``auto`` = the shipped file, or a path); its label image, at the
camera's own size, goes through :class:`~bev_mapper_core.methods.ipm.mapper.IpmMapper` with the same config
(occlusion reasoning included). Works for any rig and grid, as IPM does.

:class:`~bev_mapper_core.methods.segmenter.stage.SegmenterStage` is the first stage.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import replace

import numpy as np

from bev_mapper_core.errors import ConfigError
from bev_mapper_core.geometry.grid import BevGrid
from bev_mapper_core.geometry.rig import Rig
from bev_mapper_core.mapper import BevPrediction, Mapper, MapperConfig
from bev_mapper_core.nn.runtime import inference_device

from .. import alternatives
from ..ipm.mapper import IpmMapper
from ..segmenter.stage import SegmenterStage, segmenter_path
from ..segmenter.weights import load_segmenter


class SegIpmMapper(Mapper):
    """Segmenter + IPM on RGB images (see the module docstring)."""

    name = "segipm"
    per_set_rig = True  # set_rig rebuilds IPM's tables only; the segmenter holds no calibration

    @classmethod
    def preflight(cls, config: MapperConfig, rig_name: str, grid: BevGrid | None = None,
                  cameras: tuple[str, ...] | None = None) -> None:
        """RGB input and a segmenter file whose every tensor fits (a node never starts with one it cannot run)."""
        if config.input_kind != "rgb":
            raise ConfigError(f"segipm maps RGB images (input_kind 'rgb'), not {config.input_kind!r}; "
                              f"{alternatives('segipm', config.input_kind, rig_name)}")
        load_segmenter(segmenter_path(config, rig_name))  # every tensor checked (cached for the constructor)

    def __init__(self, rig: Rig, grid: BevGrid, config: MapperConfig) -> None:
        self.preflight(config, rig.name)
        self.stage = SegmenterStage(segmenter_path(config, rig.name), inference_device(config), config.backend,
                                    config.threads, config.segmenter_precision)
        self.ipm = IpmMapper(rig, grid, replace(config, method="ipm", input_kind="labels"))
        super().__init__(rig, grid, config)

    def set_rig(self, rig: Rig) -> None:
        """New calibration: IPM's tables (the segmenter does not depend on it)."""
        super().set_rig(rig)
        self.ipm.set_rig(rig)

    def map(self, images: Mapping[str, np.ndarray], ego_pose=None, stamp_ns=None) -> BevPrediction:
        """Segment each camera image, then IPM."""
        return self.ipm.map(self.stage.segment(self.check_images(images)))


__all__ = ["SegIpmMapper"]
