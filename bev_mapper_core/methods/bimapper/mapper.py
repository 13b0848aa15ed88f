"""Bi-Mapper behind the core :class:`~bev_mapper_core.mapper.Mapper` interface.

Register as ``"bimapper": "bev_mapper_core.methods.bimapper.mapper:BiMapperMapper"``. Built from
``MapperConfig(method="bimapper", weights=path, device=...)``; with ``weights=None`` it looks for
the shipped file ``bev_mapper_core/weights/bimapper_<rig>_<input_kind>.safetensors`` (on RGB
input without shipped RGB weights: the label weights behind the segmenter, see
:meth:`BiMapperMapper.plan`). With
``classes=None`` the weights' classes are used; otherwise they must be among the weights'
classes (a subset, in any order: only those layers are returned).
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import replace
from pathlib import Path

import numpy as np
import torch

from bev_mapper_core.errors import ConfigError
from bev_mapper_core.geometry.grid import BevGrid
from bev_mapper_core.geometry.rig import Rig, scaled_camera
from bev_mapper_core.labels.classes import resolve_classes
from bev_mapper_core.mapper import BevPrediction, Mapper, MapperConfig
from bev_mapper_core.nn.backends import backend_runner, resolve_backend
from bev_mapper_core.nn.runtime import inference_device, inference_threads
from bev_mapper_core.nn.weights import WeightsError

from .. import WEIGHTS_DIR, alternatives, shipped_weights
from ..ipm.mapper import LineOfSight
from ..ipm.occlusion import OcclusionModel, learned_footprints
from ..segipm.prior import SegIpmPrior
from ..segmenter.stage import SegmenterStage, segmenter_path
from ..segmenter.weights import load_segmenter
from .model import BiMapper
from .weights import ANY_RIG, WeightsFile


def default_weights_path(rig_name: str, input_kind: str) -> Path:
    """Where the shipped weights of a rig and input kind live."""
    return shipped_weights("bimapper", rig_name, input_kind)


class BiMapperMapper(Mapper):
    """Learned Bi-Mapper inference: batch 1, ``torch.inference_mode``, sigmoid probabilities.

    ``known`` = ground cells inside the image of at least one camera present in the frame; with
    a visibility head, only those it predicts seen with probability >= ``unknown_below``; on
    label input with ``ipm_occlusion``, only those some camera's ray reaches: a cell farther than
    an object's largest depth (:func:`~bev_mapper_core.methods.ipm.occlusion.learned_footprints`)
    beyond the near edge of an object in that camera's labels is hidden from it
    (:class:`~bev_mapper_core.methods.ipm.mapper.LineOfSight`). There the head does not
    withhold the cells a camera sees as an object the model maps (vehicle, pedestrian): its
    pixel shows the object and the cell lies within IPM's face-width depth of its near edge
    (:meth:`~bev_mapper_core.methods.ipm.mapper.LineOfSight.seen_objects`), so
    ``known = frustum & line of sight & (p_visible >= unknown_below | seen object)``
    (issue #39: the head called the far parts of seen cars unseen).
    Class probabilities are ``sigmoid(logit / T_k)`` with the weights' per-class temperature.
    Cameras missing from a frame are zeroed and masked out of both streams. ``prior_skip``
    weights (issue #39) also run segipm on the present cameras' RGB images
    (:class:`~bev_mapper_core.methods.segipm.prior.SegIpmPrior`, the segmenter of
    ``MapperConfig.segmenter``) and hand its map to the model.

    Raises (constructor):
        ConfigError: no weights file given and none shipped, or a bad device.
        WeightsError: the weights do not fit this rig, grid, input kind or classes.
    """

    name = "bimapper"

    @classmethod
    def weights_path(cls, config: MapperConfig, rig_name: str) -> Path:
        """The weights file to use: ``config.weights``, or the shipped one for the rig and input
        kind; on RGB input without shipped RGB weights and with a segmenter, the shipped label
        weights (chained input, :meth:`plan`); for a rig without weights of its own, the same
        lookup for the rig-free weights ``bimapper_any_<input>.safetensors`` (:data:`ANY_RIG`).

        Raises:
            ConfigError: none given and none shipped for this rig and input kind.
        """
        if config.weights:
            return Path(config.weights)
        chain = config.input_kind == "rgb" and config.segmenter != "none"  # RGB may run label weights behind the segmenter
        candidates = [default_weights_path(rig_name, config.input_kind)]
        if chain:
            candidates.append(default_weights_path(rig_name, "labels"))
        # the rig-free weights (trained on random rigs) map any rig without weights of its own
        candidates += [default_weights_path(ANY_RIG, config.input_kind)] + (
            [default_weights_path(ANY_RIG, "labels")] if chain else [])
        for path in candidates:
            if path.is_file():
                return path
        shipped = sorted(p.name for p in WEIGHTS_DIR.glob("bimapper_*.safetensors"))
        hint = ""
        if config.input_kind == "rgb" and any(default_weights_path(r, "labels").is_file() for r in (rig_name, ANY_RIG)):
            hint = (f"; segmenter 'auto' (not {config.segmenter!r}) runs shipped label weights on RGB, "
                    "the segmenter in front")
        raise ConfigError(
            f"no Bi-Mapper weights given and none shipped for rig {rig_name!r} / input "
            f"{config.input_kind!r} (shipped: {', '.join(shipped) or 'none'}){hint}; "
            f"{alternatives('bimapper', config.input_kind, rig_name)}"
        )

    @classmethod
    def fitting_default(cls, config: MapperConfig, rig_name: str, cameras: tuple[str, ...] | None = None,
                        rig: Rig | None = None) -> tuple[MapperConfig, str]:
        """``(config, note)``: ``config`` itself, unless it names no weights and the shipped
        default for ``rig_name`` was trained for other cameras (names, in order) or another
        model input size (another image aspect ratio; needs ``rig``) than this rig's: then the
        config with the shipped weights for any rig (:data:`ANY_RIG`), and the note that says so.
        A rig called ``surround6`` whose cameras are not nuScenes' still maps.
        """
        if config.weights:
            return config, ""
        try:
            path = cls.weights_path(config, rig_name)
            wf = WeightsFile.open(path)
        except (ConfigError, WeightsError):
            return config, ""  # preflight says what is wrong
        if wf.rig_name == ANY_RIG:
            return config, ""
        why = ""
        if cameras is not None and list(cameras) != list(wf.cameras):
            why = f"its cameras {list(wf.cameras)} are not this rig's {list(cameras)}"
        elif rig is not None:
            sizes = {scaled_camera(c, wf.config.input_width).model.image_size for c in rig.cameras}
            h, w = wf.meta["input_size"]
            if sizes != {(w, h)}:
                why = (f"its model input {w}x{h} (the trained image aspect) is not this rig's "
                       f"{', '.join(f'{a}x{b}' for a, b in sorted(sizes))}")
        anyrig = [default_weights_path(ANY_RIG, k) for k in (config.input_kind, "labels")]
        anyrig = [p for p in anyrig if p.is_file() and (p.name.endswith("_labels.safetensors") or
                                                          config.input_kind == "rgb")]
        if not why or not anyrig:
            return config, ""
        if config.input_kind == "rgb" and anyrig[0].name.endswith("_labels.safetensors") and config.segmenter == "none":
            return config, ""
        return (replace(config, weights=str(anyrig[0])),
                f"bimapper: the shipped weights of rig {rig_name!r} ({path.name}) do not fit: {why}; "
                f"mapping with the weights for any rig ({anyrig[0].name})")

    @classmethod
    def plan(cls, config: MapperConfig, rig_name: str) -> tuple[Path, str, Path | None]:
        """``(weights file, the model's input kind, segmenter file or None)``.

        RGB input with label weights runs chained: the segmenter (``config.segmenter``) turns
        each RGB image into a label image first. End-to-end RGB weights take no segmenter, except
        ``prior_skip`` weights, whose prior is segipm's map: their segmenter file is returned.

        Raises:
            ConfigError: label weights, or ``prior_skip`` weights, on RGB input with ``segmenter``
                ``none``; an explicit segmenter with other RGB weights; or no weights (see
                :meth:`weights_path`).
            WeightsError: the weights file cannot be read.
        """
        path = cls.weights_path(config, rig_name)
        if config.input_kind == "labels":
            return path, "labels", None  # preflight refuses RGB weights
        weights = WeightsFile.open(path)
        if weights.input_kind == "rgb":
            if weights.config.prior_skip:  # segipm's map is the model's second input
                return path, "rgb", segmenter_path(config, rig_name)
            if config.segmenter not in ("auto", "none"):
                raise ConfigError(f"{path} maps RGB end to end; it takes no segmenter (got {config.segmenter!r})")
            return path, "rgb", None
        return path, "labels", segmenter_path(config, rig_name)

    @classmethod
    def preflight(cls, config: MapperConfig, rig_name: str, grid: BevGrid | None = None,
                  cameras: tuple[str, ...] | None = None) -> None:
        """The weights file exists and is a Bi-Mapper safetensors file for this input kind, rig,
        classes and (when given) grid and camera names (in rig order), and every tensor fits the
        stored architecture (:meth:`WeightsFile.validate`): a node never starts with weights it
        cannot run. Chained RGB input (:meth:`plan`) also needs a readable segmenter file, and a
        ``backend`` named explicitly an installed runtime.

        Reads the file once (:meth:`WeightsFile.open` caches the header and the checked tensors
        for the constructor).
        """
        resolve_backend(config.backend)  # an inference runtime asked for by name must be installed
        config, _ = cls.fitting_default(config, rig_name, cameras)
        path, kind, seg = cls.plan(config, rig_name)
        weights = WeightsFile.open(path)
        weights.check(rig_name=rig_name, cameras=cameras, grid=grid, input_kind=kind,
                      hint=alternatives("bimapper", config.input_kind, rig_name, None if cameras is None else len(cameras)),
                      classes=config.classes)
        weights.validate()
        if seg is not None:
            load_segmenter(seg)  # every tensor checked (cached for the constructor)

    @classmethod
    def output_classes(cls, config: MapperConfig, rig_name: str) -> tuple[str, ...]:
        """``config.classes``, or the classes the weights were trained for (header only)."""
        if config.classes is not None:
            return tuple(config.classes)
        return tuple(WeightsFile.open(cls.weights_path(config, rig_name)).classes)

    def __init__(self, rig: Rig, grid: BevGrid, config: MapperConfig) -> None:
        config, note = self.fitting_default(config, rig.name, rig.names, rig)
        self.notes = (note,) if note else ()
        self.preflight(config, rig.name, grid, rig.names)  # the clear errors first (file, rig, grid, cameras)
        path, self.model_input, seg = self.plan(config, rig.name)
        self._weights = WeightsFile.open(path)  # the header preflight just read (cached)
        prior_skip = self._weights.config.prior_skip
        weight_classes = self._weights.classes
        if config.classes is None:
            config = replace(config, classes=weight_classes)
        #: output layers of the model to return, in the configured order (a subset is allowed)
        self._layers = [weight_classes.index(c) for c in config.classes]
        self._weight_classes = weight_classes
        self.device = inference_device(config)
        #: runs the model by ``MapperConfig.backend`` (``auto``: the fastest installed)
        self._runner = backend_runner(config, self.device)
        #: the inference runtime (``MapperConfig.backend`` resolved)
        self.backend = self._runner.backend
        self.weights_path = path
        #: the chained first stage (RGB -> labels), None when the model reads the input itself
        self.stage = None
        if seg is not None and not prior_skip:
            self.stage = SegmenterStage(seg, self.device, config.backend, config.threads, config.segmenter_precision)
        #: segipm's map of the images, the second input of ``prior_skip`` weights (None otherwise)
        self.prior: SegIpmPrior | None = None
        if prior_skip:
            self.prior = SegIpmPrior(rig, grid, weight_classes, replace(config, segmenter=str(seg)))
        self.model: BiMapper | None = None
        super().__init__(rig, grid, config)

    def set_rig(self, rig: Rig) -> None:
        """Load the model for this rig on first use (the tensors are read once, here);
        afterwards rebuild its calibration tables.
        """
        super().set_rig(rig)
        self.sight = self.faces = None
        if self.config.ipm_occlusion and self.model_input == "labels":
            # the classes the model maps (the weights', not the layers asked for: the unknown
            # cells do not depend on which layers are published)
            model_classes = resolve_classes(self._weight_classes)
            mapped = {label for c in model_classes for label in c.labels}
            self.sight = LineOfSight(rig, self.grid, OcclusionModel(footprints=learned_footprints(mapped)))
            #: labels of the object classes the model maps (vehicle, pedestrian): where a camera
            #: sees one, the visibility head does not withhold the cell (:meth:`map`)
            self.object_labels = sorted({label for c in model_classes if not c.flat for label in c.labels})
            if self.object_labels and self._weights.config.visibility_head:  # IPM's priors, the same tables and rays
                self.faces = LineOfSight(rig, self.grid, OcclusionModel(), tables=self.sight.tables,
                                         rasters=self.sight.rays)
        if getattr(self, "prior", None) is not None:
            self.prior.set_rig(rig)
        if self.model is None:
            self.model = self._weights.build_model(rig, self.grid, input_kind=self.model_input,
                                                   classes=self._weight_classes, device=self.device)
        else:
            self.model.set_rig(rig)
        self._runner.reset(_Exportable(self.model))  # tables changed: export again on the next frame

    def _run_exported(self, raw: torch.Tensor, cam_mask: torch.Tensor,
                      prior: torch.Tensor | None) -> dict[str, torch.Tensor] | None:
        """The model's calibrated logits (and visibility logits) from the ONNX backend, or None
        when the backend is torch or the model runs on a GPU.
        """
        if self._runner.eager:
            return None
        args = (raw, cam_mask) if prior is None else (raw, cam_mask, prior)
        outs = self._runner(self.model.preprocess(raw), *args)
        res = {"logits": outs[0]}
        if len(outs) > 1:
            res["visibility_logits"] = outs[1]
        return res

    def map(self, images: Mapping[str, np.ndarray], ego_pose=None, stamp_ns=None) -> BevPrediction:
        """Map one synchronized set of images; cameras absent from ``images`` are unseen."""
        images = self.check_images(images)
        if self.stage is not None:  # chained: RGB -> labels first
            images = self.mask_ego(self.stage.segment(images))
        present = [name in images for name in self.rig.names]
        prior = None
        if self.prior is not None:  # segipm's map of the present cameras' images
            prior = torch.from_numpy(self.prior.frame(images))[None].to(self.device)  # (1, K + 1, H, W)
        raws = []
        for name in self.rig.names:
            img = images.get(name)
            if img is None:
                w, h = self.rig[name].model.image_size
                img = np.zeros((h, w) if self.model_input == "labels" else (h, w, 3), np.uint8)
            raws.append(np.ascontiguousarray(img))
        with torch.inference_mode():
            cam_mask = torch.tensor([present], dtype=torch.bool, device=self.device)  # (1, N)
            if len({r.shape for r in raws}) == 1:
                raw = torch.from_numpy(np.stack(raws))[None].to(self.device)  # (1, N, H, W[, 3])
                out = self._run_exported(raw, cam_mask, prior)
                if out is None:
                    out = self.model(raw, cam_mask, prior)
                    out = {**out, "logits": self.model.calibrated(out["logits"])}
            else:  # cameras of different sizes (the model refuses lv_full_res then; torch only)
                xs = [self.model.preprocess(torch.from_numpy(r)[None, None].to(self.device)) for r in raws]  # (1, 1, C_in, h, w) each
                if self.model.config.ipm_skip:  # each camera's own image
                    prior = self.model.ipm_prior([torch.from_numpy(r)[None].to(self.device) for r in raws], cam_mask)
                out = self.model.forward_preprocessed(torch.cat(xs, dim=1), cam_mask, None, prior)  # input (1, N, C_in, h, w)
                out = {**out, "logits": self.model.calibrated(out["logits"])}
            logits = out["logits"]  # per-class temperature applied (1 if uncalibrated)
            probs = torch.sigmoid(logits[0, self._layers]).float().cpu().numpy()  # (K_wanted, H, W)
            known = self.model.known(cam_mask)[0].cpu().numpy()  # (H, W)
            vis = out.get("visibility_logits")
            head = None
            if vis is not None and self.config.unknown_below > 0:
                head = (torch.sigmoid(vis[0, 0]) >= self.config.unknown_below).cpu().numpy()  # (H, W)
        if self.sight is not None:
            known = known & self.sight.known(images)
        if head is not None:
            if self.faces is not None:  # a camera sees an object there: the head does not overrule it
                head = head | self.faces.seen_objects(images, self.object_labels)
            known = known & head
        return BevPrediction(self.class_names, np.ascontiguousarray(probs, dtype=np.float32), known.astype(bool))


class _Exportable(torch.nn.Module):
    """The part of :meth:`BiMapperMapper.map` an ONNX backend runs: the resized model input ``x``
    ``(1, N, C_in, h, w)`` (:meth:`BiMapper.preprocess`, run in torch: OpenVINO's antialiased
    resize differs from torch's), the raw images ``(1, N, H, W[, 3])`` (for the full-resolution
    streams), the camera mask ``(1, N)`` and, for ``prior_skip`` weights, segipm's prior
    ``(1, K + 1, H, W)`` -> calibrated logits (and visibility logits when the weights have the head).
    """

    def __init__(self, model: BiMapper) -> None:
        super().__init__()
        self.model = model

    def forward(self, x: torch.Tensor, raw: torch.Tensor, cam_mask: torch.Tensor, prior: torch.Tensor | None = None):
        m = self.model
        x_lv = m.preprocess(raw, resize=False) if m.config.lv_full_res and m.use_lv else None  # (1, N, C_in, H, W)
        if m.config.ipm_skip:
            prior = m.ipm_prior(raw, cam_mask)
        out = m.forward_preprocessed(x, cam_mask, x_lv, prior)
        logits = m.calibrated(out["logits"])
        vis = out.get("visibility_logits")
        return (logits,) if vis is None else (logits, vis)


__all__ = ["BiMapperMapper", "WeightsError", "default_weights_path", "inference_device", "inference_threads"]
