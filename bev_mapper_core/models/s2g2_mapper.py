"""S2G2 behind the core :class:`~bev_mapper_core.mapper.Mapper` interface.

Registered as ``"s2g2": "bev_mapper_core.models.s2g2_mapper:S2G2Mapper"``. Built from
``MapperConfig(method="s2g2", weights=path, input_kind=..., device=...)`` for a rig of one
camera. Without ``weights`` the shipped file of the rig and input kind is used,
``weights/s2g2_<rig>_<input>.safetensors`` (``s2g2_front1_rgb``, trained on the ``ahead`` grid:
the node's ``config/front1_s2g2.yaml`` sets that grid). The weights' metadata names the branch
that maps (``inference_branch``: ``active`` or ``passive``). With ``classes=None`` the weights' classes are used; otherwise they
must be among them (a subset, any order).
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import replace
from pathlib import Path

import numpy as np
import torch

from ..errors import ConfigError
from ..grid import BevGrid
from ..mapper import BevPrediction, Mapper, MapperConfig
from ..rig import Rig
from .runtime import inference_device
from .s2g2 import S2G2, check_monocular
from .s2g2_weights import WeightsError, load_s2g2, read_s2g2_metadata, validate_s2g2

WEIGHTS_DIR = Path(__file__).resolve().parent.parent / "weights"


def shipped_s2g2(rig_name: str, input_kind: str) -> Path:
    """Where the shipped S2G2 weights of a rig and input kind live (the file may not exist)."""
    return WEIGHTS_DIR / f"s2g2_{rig_name}_{input_kind}.safetensors"


class S2G2Mapper(Mapper):
    """Learned S2G2 inference: batch 1, ``torch.inference_mode``, sigmoid probabilities of the
    weights' ``inference_branch``; ``known`` = ground cells inside the camera's image.

    Raises (constructor):
        ConfigError: no weights file given and none shipped, a rig of more than one camera, or a
            bad device.
        WeightsError: the weights do not fit this rig, grid, input kind or classes.
    """

    name = "s2g2"

    @classmethod
    def weights_path(cls, config: MapperConfig, rig_name: str) -> Path:
        """``config.weights``, or the shipped file of the rig and input kind.

        Raises:
            ConfigError: none given and none shipped for this rig and input kind.
        """
        if config.weights:
            return Path(config.weights)
        path = shipped_s2g2(rig_name, config.input_kind)
        if not path.is_file():
            shipped = sorted(p.name for p in WEIGHTS_DIR.glob("s2g2_*.safetensors"))
            raise ConfigError(f"no S2G2 weights given and none shipped for rig {rig_name!r} / input "
                              f"{config.input_kind!r} (shipped: {', '.join(shipped) or 'none'}): train them "
                              "(bev-train --method s2g2 --rig front1 --grid ahead --unlabeled-drives N ...) and pass "
                              "weights=<file>, or use method 'ipm'")
        return path

    @classmethod
    def preflight(cls, config: MapperConfig, rig_name: str, grid: BevGrid | None = None,
                  cameras: tuple[str, ...] | None = None) -> None:
        """One camera (when the camera names are given), and a weights file that is S2G2
        safetensors for this input kind, rig, classes, camera and (when given) grid, every tensor
        of which fits the stored architecture: a node never starts with weights it cannot run.

        Raises:
            ConfigError: more than one camera; no weights given.
            WeightsError: the first mismatch.
        """
        if cameras is not None and len(cameras) != 1:
            raise ConfigError(f"S2G2 is monocular: rig {rig_name!r} has {len(cameras)} cameras {list(cameras)}; "
                              "use a one-camera rig (e.g. front1), or method bimapper / ipm")
        path = cls.weights_path(config, rig_name)
        meta = read_s2g2_metadata(path)
        if meta["input_kind"] != config.input_kind:
            raise WeightsError(f"{path} is for input {meta['input_kind']!r}, configured input is {config.input_kind!r}")
        if rig_name and meta["rig"] != rig_name:
            raise WeightsError(f"{path} was trained for rig {meta['rig']!r}, not {rig_name!r}")
        unknown = [c for c in config.classes or () if c not in meta["classes"]]
        if unknown:
            raise WeightsError(f"{path}: classes {unknown} are not among the weights' classes {meta['classes']}")
        if cameras is not None and list(cameras) != list(meta["cameras"]):
            raise WeightsError(f"{path}: weights were trained for camera {meta['cameras']}, but {list(cameras)} "
                               "is configured")
        stored = BevGrid.from_dict(meta["grid"])
        if grid is not None and not grid.isclose(stored):
            raise WeightsError(f"{path}: weights were trained for grid {stored.describe()}, but {grid.describe()} "
                               "is configured; use weights trained for this grid, or method 'ipm'")
        validate_s2g2(path)

    @classmethod
    def output_classes(cls, config: MapperConfig, rig_name: str) -> tuple[str, ...]:
        """``config.classes``, or the classes the weights were trained for (header only)."""
        if config.classes is not None:
            return tuple(config.classes)
        return tuple(read_s2g2_metadata(cls.weights_path(config, rig_name))["classes"])

    def __init__(self, rig: Rig, grid: BevGrid, config: MapperConfig) -> None:
        check_monocular(rig)
        self.preflight(config, rig.name, grid, rig.names)
        self.weights_file = self.weights_path(config, rig.name)
        meta = read_s2g2_metadata(self.weights_file)
        weight_classes = tuple(meta["classes"])
        if config.classes is None:
            config = replace(config, classes=weight_classes)
        #: output layers of the model to return, in the configured order (a subset is allowed)
        self._layers = [weight_classes.index(c) for c in config.classes]
        #: the branch that maps (the weights' ``inference_branch``)
        self.branch = meta["inference_branch"]
        self.device = inference_device(config)
        self.model: S2G2 | None = None
        super().__init__(rig, grid, config)

    def set_rig(self, rig: Rig) -> None:
        """Load the model on first use; afterwards rebuild its frustum for the new calibration."""
        check_monocular(rig)
        super().set_rig(rig)
        if self.model is None:
            self.model, _ = load_s2g2(self.weights_file, rig, self.grid, self.device)
        else:
            self.model.set_rig(rig)

    def map(self, images: Mapping[str, np.ndarray], ego_pose=None, stamp_ns=None) -> BevPrediction:
        """Map the camera's image (the only camera, so always present)."""
        images = self.check_images(images)
        img = np.ascontiguousarray(images[self.rig.names[0]])
        with torch.inference_mode():
            raw = torch.from_numpy(img)[None, None].to(self.device)  # (1, 1, H, W[, 3])
            logits = self.model.logits(self.model.preprocess(raw), self.branch)  # (1, K, H, W)
            probs = torch.sigmoid(logits[0, self._layers]).float().cpu().numpy()  # (K_wanted, H, W)
            known = self.model.known().cpu().numpy()
        return BevPrediction(self.class_names, np.ascontiguousarray(probs, dtype=np.float32), known.astype(bool))


__all__ = ["S2G2Mapper", "shipped_s2g2"]
