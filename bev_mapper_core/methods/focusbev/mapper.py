"""FocusBEV behind the core :class:`~bev_mapper_core.mapper.Mapper` interface, with its memory bank.

Registered as ``"focusbev"``. Built from ``MapperConfig(method="focusbev", weights=path, ...)``
for a rig of one camera; without ``weights`` the shipped
``weights/focusbev_<rig>_<input>.safetensors`` (``focusbev_front1_rgb``, trained on the
``ahead`` grid: the node's ``config/front1_focusbev.yaml`` sets it).

**Memory bank.** Weights with a temporal window ``W`` > 1 keep, per frame, the view
transformation's BEV feature with its stamp and ego pose (``odom_from_base``). A frame is
fused with the ``W - 1`` kept features closest to ``k x memory_interval_s`` before it
(``k = 1 .. W-1``; the spacing of the training windows, from the weights), each taken only
within half an interval of its target; a slot with no such feature gets the reference feature,
as at the start of a drive. So the history spacing is what the model was trained on whatever
the camera rate (at 10 Hz and 0.3 s the bank holds the last 3-4 frames). The bank is dropped
(:meth:`FocusBEVMapper.reset`, and the prediction's ``note`` says why) when a frame's stamp is
not after the last one (a bag loop), on a gap longer than ``max_gap_s`` or an ego jump larger
than ``max_jump_m`` (:class:`~bev_mapper_core.temporal.TemporalConfig`'s defaults, the same
rules as the method-independent fusion), and when a frame comes without a valid pose or stamp:
it is then mapped alone, and the next frame with a pose starts a new bank.

**segipm's prior** (weights with ``prior_skip``, issue #39): each frame also runs segipm on the
image (:class:`~bev_mapper_core.methods.segipm.prior.SegIpmPrior`, the segmenter of
``MapperConfig.segmenter``) and hands its map to the head. The prior is the current frame's
only: the bank keeps BEV features, which the fusion warps, and the prior enters after the fusion.
"""

from __future__ import annotations

from collections import deque
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from bev_mapper_core.geometry.grid import BevGrid
from bev_mapper_core.geometry.rig import Rig
from bev_mapper_core.mapper import BevPrediction, MapperConfig
from bev_mapper_core.nn.backends import backend_runner
from bev_mapper_core.nn.mono_mapper import MonocularMapper
from bev_mapper_core.nn.runtime import inference_device
from bev_mapper_core.temporal import TemporalConfig, drop_reason, pose_problem

from .. import shipped_weights
from ..segipm.prior import SegIpmPrior
from .model import FocusBEV
from .weights import load_focusbev, read_focusbev_metadata, validate_focusbev


def shipped_focusbev(rig_name: str, input_kind: str) -> Path:
    """Where the shipped FocusBEV weights of a rig and input kind live (the file may not exist)."""
    return shipped_weights("focusbev", rig_name, input_kind)


@dataclass
class _Kept:
    stamp_ns: int
    odom_from_base: np.ndarray  # (4, 4) float64
    feature: torch.Tensor  # (1, C, hb, wb)


class FocusBEVMapper(MonocularMapper):
    """Learned FocusBEV inference with its memory bank (see the module docstring); ``known`` =
    ground cells inside the camera's image. A new calibration keeps the bank: the ego motion
    does not depend on the camera's calibration.

    Raises (constructor):
        ConfigError: no weights file given and none shipped, a rig of more than one camera, or a
            bad device.
        WeightsError: the weights do not fit this rig, grid, input kind or classes.
    """

    name = "focusbev"
    title = "FocusBEV"
    train_hint = "bev-train --method focusbev --rig front1 --grid ahead ..."
    uses_ego_pose = True
    read_metadata = staticmethod(read_focusbev_metadata)
    load = staticmethod(load_focusbev)
    validate = staticmethod(validate_focusbev)
    #: when the memory is dropped (gap, jump): the method-independent fusion's defaults
    rules = TemporalConfig()

    def __init__(self, rig: Rig, grid: BevGrid, config: MapperConfig) -> None:
        config, meta = self.open_weights(rig, grid, config)
        self.window = int(meta["config"]["window"])
        self.interval_ns = int(round(float(meta["memory_interval_s"]) * 1e9))
        self.device = inference_device(config)
        self.model: FocusBEV | None = None
        self._kept: deque[_Kept] = deque()
        #: runs image -> BEV feature by ``MapperConfig.backend`` (the fusion and head: torch)
        self._runner = backend_runner(config, self.device)
        #: segipm's map of the image, the head's second input of ``prior_skip`` weights (None otherwise)
        self.prior: SegIpmPrior | None = None
        if meta["config"].get("prior_skip"):
            self.prior = SegIpmPrior(rig, grid, meta["classes"], config)
        super().__init__(rig, grid, config)

    def set_rig(self, rig: Rig) -> None:
        """The model for this calibration (see :class:`MonocularMapper`); export again if exported."""
        super().set_rig(rig)
        if self.prior is not None:
            self.prior.set_rig(rig)
        self._runner.reset(_Features(self.model))

    def reset(self) -> None:
        """Drop the memory bank."""
        self._kept.clear()

    def _memory_state(self, ego_pose, stamp_ns) -> tuple[bool, str]:
        """``(usable, note)``: whether this frame can use (and join) the bank, and why not or why
        the bank was dropped ('' = nothing to say). Drops the bank when it cannot be used.
        """
        if stamp_ns is None:
            self.reset()
            return False, "no stamp for this frame: mapped without temporal fusion"
        problem = pose_problem(ego_pose)
        if problem:
            self.reset()
            return False, problem
        note = ""
        if self._kept:
            last = self._kept[-1]
            note = drop_reason(last.stamp_ns, last.odom_from_base, int(stamp_ns), ego_pose, self.rules)
            if note:
                self.reset()
        return True, note

    def _history(self, stamp_ns: int, pose: np.ndarray, reference: torch.Tensor) -> list:
        """The fusion's history (newest first): for each slot the kept feature nearest its
        target time within half an interval, else the reference (absent).
        """
        out = []
        for k in range(1, self.window):
            target = stamp_ns - k * self.interval_ns
            best = min(self._kept, key=lambda e: abs(e.stamp_ns - target), default=None)
            if best is not None and abs(best.stamp_ns - target) <= self.interval_ns // 2:
                prev_from_cur = torch.from_numpy(np.linalg.inv(best.odom_from_base) @ pose)[None]  # (1, 4, 4)
                out.append((best.feature, prev_from_cur, torch.ones(1, dtype=torch.bool)))
            else:
                out.append((reference, torch.eye(4, dtype=torch.float64)[None], torch.zeros(1, dtype=torch.bool)))
        return out

    def map(self, images: Mapping[str, np.ndarray], ego_pose=None, stamp_ns=None) -> BevPrediction:
        """Map the camera's image, fused with the memory bank when the frame has a stamp and pose."""
        images = self.check_images(images)
        img = np.ascontiguousarray(images[self.rig.names[0]])
        temporal = self.window > 1
        use_bank, note = self._memory_state(ego_pose, stamp_ns) if temporal else (False, "")
        frames = 1
        with torch.inference_mode():
            raw = torch.from_numpy(img)[None, None].to(self.device)  # (1, 1, H, W[, 3])
            bev = self._runner(self.model.preprocess(raw))[0]  # (1, C, hb, wb)
            fused = bev
            if temporal:
                hist = []
                if use_bank:
                    pose = np.asarray(ego_pose, dtype=np.float64)
                    hist = self._history(int(stamp_ns), pose, bev)
                    frames += sum(bool(h[2][0]) for h in hist)
                    self._kept.append(_Kept(int(stamp_ns), pose, bev))
                    horizon = int(stamp_ns) - (self.window - 1) * self.interval_ns - self.interval_ns // 2
                    while self._kept and self._kept[0].stamp_ns < horizon:
                        self._kept.popleft()
                fused = self.model.temporal(bev, hist)
            prior = None if self.prior is None else torch.from_numpy(self.prior.one(img))[None].to(self.device)
            logits = self.model.logits(fused, prior)  # (1, K, H, W); prior (1, K + 1, H, W)
            probs = torch.sigmoid(logits[0, self._layers]).float().cpu().numpy()  # (K_wanted, H, W)
            known = self.model.known().cpu().numpy()
        return BevPrediction(self.class_names, np.ascontiguousarray(probs, dtype=np.float32), known.astype(bool),
                             frames, note)


class _Features(torch.nn.Module):
    """What a backend runs: the model input ``(1, C_in, h, w)`` -> the frame's BEV feature (the
    preprocessing stays in torch: OpenVINO's antialiased resize differs from torch's).
    """

    def __init__(self, model: FocusBEV) -> None:
        super().__init__()
        self.model = model

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.model.bev_features(x)


__all__ = ["FocusBEVMapper", "shipped_focusbev"]
