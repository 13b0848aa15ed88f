"""S2G2 behind the core :class:`~bev_mapper_core.mapper.Mapper` interface.

Registered as ``"s2g2": "bev_mapper_core.methods.s2g2.mapper:S2G2Mapper"``. Built from
``MapperConfig(method="s2g2", weights=path, input_kind=..., device=...)`` for a rig of one
camera. Without ``weights`` the shipped file of the rig and input kind is used,
``weights/s2g2_<rig>_<input>.safetensors`` (``s2g2_front1_rgb``, trained on the ``ahead`` grid:
the node's ``config/front1_s2g2.yaml`` sets that grid). The weights' metadata names the branch
that maps (``inference_branch``: ``active`` or ``passive``). With ``classes=None`` the weights' classes are used; otherwise they
must be among them (a subset, any order).

Weights with ``prior_skip`` (issue #39) also run segipm on the image (:class:`~bev_mapper_core.methods.segipm.prior.SegIpmPrior`,
the segmenter of ``MapperConfig.segmenter``) and hand its map to the network as a second input.
"""

from __future__ import annotations

from collections.abc import Mapping
from pathlib import Path

import numpy as np
import torch

from bev_mapper_core.geometry.grid import BevGrid
from bev_mapper_core.geometry.rig import Rig
from bev_mapper_core.mapper import BevPrediction, MapperConfig
from bev_mapper_core.nn.backends import backend_runner
from bev_mapper_core.nn.mono_mapper import MonocularMapper
from bev_mapper_core.nn.runtime import inference_device

from .. import shipped_weights
from ..segipm.prior import SegIpmPrior
from .model import S2G2
from .weights import load_s2g2, read_s2g2_metadata, validate_s2g2


def shipped_s2g2(rig_name: str, input_kind: str) -> Path:
    """Where the shipped S2G2 weights of a rig and input kind live (the file may not exist)."""
    return shipped_weights("s2g2", rig_name, input_kind)


class S2G2Mapper(MonocularMapper):
    """Learned S2G2 inference: batch 1, ``torch.inference_mode``, sigmoid probabilities of the
    weights' ``inference_branch``; ``known`` = ground cells inside the camera's image.

    Raises (constructor):
        ConfigError: no weights file given and none shipped, a rig of more than one camera, or a
            bad device.
        WeightsError: the weights do not fit this rig, grid, input kind or classes.
    """

    name = "s2g2"
    title = "S2G2"
    train_hint = "bev-train --method s2g2 --rig front1 --grid ahead --unlabeled-drives N ..."
    read_metadata = staticmethod(read_s2g2_metadata)
    load = staticmethod(load_s2g2)
    validate = staticmethod(validate_s2g2)

    def __init__(self, rig: Rig, grid: BevGrid, config: MapperConfig) -> None:
        config, meta = self.open_weights(rig, grid, config)
        #: the branch that maps (the weights' ``inference_branch``)
        self.branch = meta["inference_branch"]
        self.device = inference_device(config)
        self.model: S2G2 | None = None
        #: runs image -> logits by ``MapperConfig.backend``
        self._runner = backend_runner(config, self.device)
        #: segipm's map of the image, the second input of ``prior_skip`` weights (None otherwise)
        self.prior: SegIpmPrior | None = None
        if meta["config"].get("prior_skip"):
            self.prior = SegIpmPrior(rig, grid, meta["classes"], config)
        super().__init__(rig, grid, config)

    def set_rig(self, rig: Rig) -> None:
        """The model for this calibration (see :class:`MonocularMapper`); export again if exported."""
        super().set_rig(rig)
        if self.prior is not None:
            self.prior.set_rig(rig)
        self._runner.reset(_Logits(self.model, self.branch))

    def map(self, images: Mapping[str, np.ndarray], ego_pose=None, stamp_ns=None) -> BevPrediction:
        """Map the camera's image (the only camera, so always present)."""
        images = self.check_images(images)
        img = np.ascontiguousarray(images[self.rig.names[0]])
        with torch.inference_mode():
            raw = torch.from_numpy(img)[None, None].to(self.device)  # (1, 1, H, W[, 3])
            if self.prior is None:
                logits = self._runner(self.model.preprocess(raw))[0]  # (1, K, H, W)
            else:
                prior = torch.from_numpy(self.prior.one(img))[None].to(self.device)  # (1, K + 1, H, W)
                logits = self._runner(self.model.preprocess(raw), prior)[0]  # (1, K, H, W)
            probs = torch.sigmoid(logits[0, self._layers]).float().cpu().numpy()  # (K_wanted, H, W)
            known = self.model.known().cpu().numpy()
        return BevPrediction(self.class_names, np.ascontiguousarray(probs, dtype=np.float32), known.astype(bool))


class _Logits(torch.nn.Module):
    """What a backend runs: the model input ``(1, C_in, h, w)`` -> the branch's logits (the
    preprocessing stays in torch: OpenVINO's antialiased resize differs from torch's).
    """

    def __init__(self, model: S2G2, branch: str) -> None:
        super().__init__()
        self.model, self.branch = model, branch

    def forward(self, x: torch.Tensor, prior: torch.Tensor | None = None) -> torch.Tensor:
        return self.model.logits(x, self.branch, prior)


__all__ = ["S2G2Mapper", "shipped_s2g2"]
