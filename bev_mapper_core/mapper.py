"""The one interface every BEV mapping method implements.

A :class:`Mapper` turns one synchronized set of camera images into per-class probability
layers on a :class:`~bev_mapper_core.geometry.grid.BevGrid`, plus a mask of the cells it knows about.
The ROS node and the bag tool only talk to this interface, so they never care which method
runs. Methods register a factory under a name; :func:`create_mapper` builds one.
"""

from __future__ import annotations

from abc import ABC, abstractmethod
from collections.abc import Callable, Mapping
from dataclasses import dataclass

import numpy as np

from .errors import ConfigError, InputError
from .geometry.grid import BevGrid
from .geometry.rig import Rig
from .labels.classes import BEV_CLASS_NAMES, resolve_classes
from .labels.label_maps import NATIVE, label_map
from .methods import mapper_targets
from .registry import resolve

INPUT_KINDS = ("labels", "rgb")
#: ``MapperConfig.backend`` choices (see :mod:`~bev_mapper_core.nn.backends`).
BACKENDS = ("torch", "onnxruntime", "openvino", "auto")
#: ``MapperConfig.segmenter_precision`` choices (see :mod:`~bev_mapper_core.methods.segmenter.int8`).
SEGMENTER_PRECISIONS = ("auto", "f32", "bf16", "int8")


@dataclass(frozen=True)
class MapperConfig:
    """Method-independent mapper settings (ROS parameters and CLI flags map onto these).

    Args:
        method: registered method name (``bimapper`` with the shipped weights by default,
            ``ipm``, ...).
        input_kind: ``labels`` (semantic label images, see ``label_map``) or ``rgb``.
        classes: BEV class names to produce, ``None`` = the method's/standard set.
        weights: path to a safetensors weights file (learned methods), ``None`` = shipped default.
        device: torch device for learned methods (``cpu``, ``cuda``).
        threads: CPU threads of learned methods' inference; 0 = the method's default.
        ipm_occlusion: occlusion reasoning on label images (see
            :mod:`~bev_mapper_core.methods.ipm.occlusion`). IPM: cells behind the near edge of an object
            seen in a camera are unknown to that camera instead of the object's flat-ground
            smear; False = the classical IPM. Learned methods on label input: cells farther than
            an object's full length behind its near edge in every camera are unknown; False =
            the frustum (and visibility head) only.
        unknown_below: Bi-Mapper with a visibility head only: cells whose predicted probability
            of being seen by some camera is below this are published as unknown
            (``known = frustum & p_visible >= unknown_below``; with ``ipm_occlusion`` on label
            input, a cell a camera's labels show as an object the model maps stays known: issue
            #39, see :class:`~bev_mapper_core.methods.bimapper.mapper.BiMapperMapper`); 0 = every
            in-frustum cell is known. 0.05 was chosen on both validation sets (seeds 900000000-05 and
            900000010-12, see docs/RESULTS.md "Honest maps"): the largest threshold tried (0.03-0.7)
            that keeps the visible mIoU within 1 point of the head-less model on both. Weights
            without the head ignore it.
        segmenter: the 2-D segmenter that turns RGB images into label images, for ``segipm``
            and for label-input models on RGB input (chained, e.g. the shipped label Bi-Mapper
            with ``input_kind`` ``rgb``): ``auto`` (the default shipped segmenter, ``camvid``;
            Bi-Mapper: only when no end-to-end RGB weights are given or shipped), ``camvid`` (from
            ImageNet, synthetic town and CamVid: non-commercial, the better on real frames),
            ``open`` (from ImageNet and the synthetic town only: commercial use allowed),
            ``none``, or a safetensors path.
            Label input ignores it.
        backend: inference runtime of learned methods: ``auto`` (the default: the fastest
            installed, OpenVINO, else onnxruntime, else torch), ``torch`` (the reference),
            ``onnxruntime`` or ``openvino`` (the model exported to ONNX once per weights and
            calibration, cached; optional extras); see
            :mod:`~bev_mapper_core.nn.backends`. Bi-Mapper, S2G2 and FocusBEV use it (FocusBEV
            for its image -> BEV feature part), and the segmenter stage of segipm and chained
            Bi-Mapper (``auto``: onnxruntime first there, its fastest in f32; OpenVINO first in int8).
        segmenter_precision: the segmenter stage's arithmetic on an exported backend (issue
            #41): ``auto`` (the default: ``bf16`` where OpenVINO is installed and the CPU
            computes in bf16, else ``f32``), ``f32``, ``bf16`` (OpenVINO's bf16 inference of the
            float export; CamVid test within 0.3 IoU of f32 per class, 2.3x faster here), or
            ``int8`` (its ONNX export quantized after training on a fixed synthetic calibration
            set, in the export cache: :mod:`~bev_mapper_core.methods.segmenter.int8`).
            ``backend`` torch runs f32 whatever this says (docs/SPEED.md, issue #41).
        label_map: how the ids of the label images (``input_kind`` labels) map onto this
            package's :class:`~bev_mapper_core.labels.classes.Label`: ``native`` (they are Label
            ids), a preset of another segmenter (``cityscapes_ids``, ``cityscapes_train_ids``,
            ``cam2bev``: rgb8 palette images) or the path of a YAML file; see
            :mod:`~bev_mapper_core.labels.label_maps`. The node and the bag tools apply it as they
            decode each image; the mapper itself always receives Label ids.
    """

    method: str = "bimapper"
    input_kind: str = "labels"
    classes: tuple[str, ...] | None = None
    weights: str | None = None
    device: str = "cpu"
    threads: int = 0
    ipm_occlusion: bool = True
    unknown_below: float = 0.05
    segmenter: str = "auto"
    label_map: str = NATIVE
    backend: str = "auto"
    segmenter_precision: str = "auto"

    def __post_init__(self) -> None:
        v = self.unknown_below
        if isinstance(v, bool) or not isinstance(v, (int, float)) or not 0.0 <= v <= 1.0:
            raise ConfigError(f"unknown_below must be a number in [0, 1], got {v!r}")
        if not isinstance(self.threads, int) or self.threads < 0:
            raise ConfigError(f"threads must be an integer >= 0 (0 = method default), got {self.threads!r}")
        if not isinstance(self.ipm_occlusion, bool):
            raise ConfigError(f"ipm_occlusion must be true or false, got {self.ipm_occlusion!r}")
        if not isinstance(self.segmenter, str) or not self.segmenter:
            raise ConfigError(f"segmenter must be 'auto', 'camvid', 'open', 'none' or a weights path, got "
                              f"{self.segmenter!r}")
        if self.method not in _REGISTRY:
            raise ConfigError(f"unknown method {self.method!r}; available: {list(available_methods())}")
        if self.backend not in BACKENDS:
            raise ConfigError(f"backend must be one of {BACKENDS}, got {self.backend!r}")
        if self.segmenter_precision not in SEGMENTER_PRECISIONS:
            raise ConfigError(f"segmenter_precision must be one of {SEGMENTER_PRECISIONS}, got "
                              f"{self.segmenter_precision!r}")
        if self.input_kind not in INPUT_KINDS:
            raise ConfigError(f"input_kind must be one of {INPUT_KINDS}, got {self.input_kind!r}")
        if self.classes is not None:
            object.__setattr__(self, "classes", tuple(self.classes))
            if not self.classes:
                raise ConfigError("classes must not be empty (use None for all classes)")
            resolve_classes(self.classes)  # raises ConfigError on unknown names
        label_map(self.label_map)  # raises ConfigError: no preset, or a bad YAML file
        if self.label_map != NATIVE and self.input_kind != "labels":
            raise ConfigError(f"label_map {self.label_map!r} applies to label images (input_kind 'labels'), "
                              f"not to input_kind {self.input_kind!r}")


@dataclass(frozen=True)
class BevPrediction:
    """Output of a mapper for one frame.

    Attributes:
        classes: layer names, in layer order.
        probs: ``(C, H, W)`` float32 probabilities in [0, 1].
        known: ``(H, W)`` bool, cells the method has evidence for (False = unknown).
        frames: frames a temporal method fused into this one (1: this frame alone).
        note: why a temporal method mapped without (some of) its memory ('' = nothing to say):
            no ego pose, a reset; for logs and ``/diagnostics``.
    """

    classes: tuple[str, ...]
    probs: np.ndarray
    known: np.ndarray
    frames: int = 1
    note: str = ""

    def layer(self, name: str) -> np.ndarray:
        """The ``(H, W)`` probability layer of class ``name``."""
        try:
            return self.probs[self.classes.index(name)]
        except ValueError:
            raise KeyError(f"no layer {name!r}; layers: {list(self.classes)}") from None


class Mapper(ABC):
    """Base class of BEV mapping methods.

    Subclasses set :attr:`name` and implement :meth:`map`. Calibration-dependent state is
    (re)built in :meth:`set_rig`, which the caller invokes only when calibration changes.

    Temporal methods set :attr:`uses_ego_pose`: callers then pass every frame's stamp and ego
    pose to :meth:`map` (single-frame methods may ignore both), and the method keeps its own
    memory, which :meth:`reset` drops.
    """

    name: str = ""
    #: the method reads ``ego_pose`` and ``stamp_ns`` (callers look poses up for it)
    uses_ego_pose: bool = False
    #: what the caller should tell the user once about how the method was set up (e.g. which
    #: weights it chose and why); the node logs them, ``bev-bag replay`` prints them as notes
    notes: tuple[str, ...] = ()
    #: :meth:`set_rig` only rebuilds cheap tables (no model export), so a rig placed per set at
    #: its cameras' times is affordable (:mod:`~bev_mapper_core.placement`); False: the method
    #: keeps its calibrated rig for every set
    per_set_rig: bool = False

    def __init__(self, rig: Rig, grid: BevGrid, config: MapperConfig) -> None:
        self.grid = grid
        self.config = config
        self.classes = resolve_classes(config.classes)
        self.class_names = tuple(c.name for c in self.classes)
        self.rig = rig
        self.set_rig(rig)

    @classmethod
    def preflight(cls, config: MapperConfig, rig_name: str, grid: BevGrid | None = None,
                  cameras: tuple[str, ...] | None = None) -> None:
        """Check what can be checked before any calibration is known (weights, input kind,
        and, when given, the grid and camera names the weights were trained for).

        Lets a node fail at start-up with a clear error instead of at its first frame.

        Raises:
            ConfigError: the configuration cannot work for this method.
        """

    @classmethod
    def output_classes(cls, config: MapperConfig, rig_name: str) -> tuple[str, ...]:
        """The names of the layers this method will produce, in order, known before any
        calibration (a node creates its output topics from them at start-up).

        Default: ``config.classes``, or every standard class when None.
        """
        return tuple(c.name for c in resolve_classes(config.classes))

    def set_rig(self, rig: Rig) -> None:
        """Adopt a new calibration; subclasses precompute lookup tables here."""
        self.rig = rig

    def reset(self) -> None:
        """Forget temporal state (memory banks); called on time jumps. No-op by default."""

    # a learned mapper's runner of its exported part (``nn.backends.BackendRunner``), if it has one
    _runner = None

    def export_in_background(self) -> None:
        """From now on, a learned mapper on an exported backend maps with torch until its model
        is exported (in a child process) and loaded, then switches (issue #41: a node maps from
        its first frame). Others: nothing changes.
        """
        for runner in self._backend_parts():
            runner.background = True

    @property
    def backend_state(self) -> str:
        """What runs the model now (``openvino``, ``torch (until the openvino model is ready)``,
        ...); ``""`` for methods without an inference backend (IPM).
        """
        parts = self._backend_parts()
        if len(parts) == 2:  # chained: the label model, and the segmenter stage in front of it
            return f"{parts[0].state}; segmenter {parts[1].state}"
        return parts[0].state if parts else ""

    def close(self) -> None:
        """Stop background work (an export under way: its process and partial file go)."""
        for runner in self._backend_parts():
            runner.close()

    def _backend_parts(self) -> list:
        """The parts run by an inference backend: the method's own runner, and a segmenter stage
        in front of it (``stage``: segipm, chained Bi-Mapper), each with ``background``,
        ``state`` and ``close()``.
        """
        parts = [self._runner] if self._runner is not None else []
        stage = getattr(self, "stage", None)
        return parts + ([stage] if stage is not None else [])

    @abstractmethod
    def map(
        self,
        images: Mapping[str, np.ndarray],
        ego_pose: np.ndarray | None = None,
        stamp_ns: int | None = None,
    ) -> BevPrediction:
        """Map one synchronized set of images (camera name -> image) to BEV layers.

        Cameras missing from ``images`` are treated as unseen. ``ego_pose`` is
        ``world_from_ego`` (4x4, ``odom_from_base``) and ``stamp_ns`` the images' stamp, for
        methods with temporal fusion (:attr:`uses_ego_pose`); ``None`` when unknown: such a
        method then maps the frame alone and says so in :attr:`BevPrediction.note`.
        """

    # ------------------------------------------------------------ helpers
    def check_images(self, images: Mapping[str, np.ndarray]) -> dict[str, np.ndarray]:
        """Validate the images against the rig and input kind; returns those of known cameras.

        Raises:
            InputError: unknown camera, wrong size, dtype or channel count, or no image at all.
        """
        sizes = self._image_sizes()
        out = {}
        for name, img in images.items():
            if name not in sizes:
                raise InputError(f"image from unknown camera {name!r}; rig cameras: {list(self.rig.names)}")
            img = np.asarray(img)
            w, h = sizes[name]
            if self.config.input_kind == "labels":
                if img.ndim != 2 or img.dtype != np.uint8:
                    raise InputError(
                        f"camera {name!r}: label image must be (H, W) uint8, got {img.shape} {img.dtype}"
                    )
            elif img.ndim != 3 or img.shape[2] != 3 or img.dtype != np.uint8:
                raise InputError(f"camera {name!r}: RGB image must be (H, W, 3) uint8, got {img.shape} {img.dtype}")
            if img.shape[:2] != (h, w):
                raise InputError(
                    f"camera {name!r}: image is {img.shape[1]}x{img.shape[0]}, calibration says {w}x{h}"
                )
            out[name] = img
        if not out:
            raise InputError("no camera image to map")
        return self.mask_ego(out) if self.config.input_kind == "labels" else out

    def mask_ego(self, labels: Mapping[str, np.ndarray]) -> dict[str, np.ndarray]:
        """Label images ``(H, W)`` with the pixels of their camera's ego mask set to ``UNLABELED``
        (copies; images of cameras without a mask are passed through).

        :meth:`check_images` applies it to label input; methods that segment RGB images apply it
        to the segmenter's labels.
        """
        masks = self._ego_pixels()
        if not masks:
            return dict(labels)
        out = {}
        for name, img in labels.items():
            m = masks.get(name)
            if m is not None and img.shape[:2] == m.shape:
                img = img.copy()
                img[m] = 0  # Label.UNLABELED
            out[name] = img
        return out

    def _ego_pixels(self) -> dict[str, np.ndarray]:
        """Camera name -> its ego mask ``(H, W)`` bool at its image size, kept per calibration."""
        cached = getattr(self, "_ego_cache", None)
        if cached is None or cached[0] is not self.rig:
            sizes = self._image_sizes()
            cached = self._ego_cache = (self.rig, {c.name: c.ego_mask.at(*sizes[c.name])
                                                   for c in self.rig.cameras if c.ego_mask is not None})
        return cached[1]

    def _image_sizes(self) -> dict[str, tuple[int, int]]:
        """Camera name -> ``(width, height)`` of its images, kept per calibration (a camera
        model's ``image_size`` builds its effective model each time).
        """
        cached = getattr(self, "_sizes", None)
        if cached is None or cached[0] is not self.rig:
            cached = self._sizes = (self.rig, {c.name: c.model.image_size for c in self.rig.cameras})
        return cached[1]

    def empty_prediction(self) -> BevPrediction:
        """A prediction with every cell unknown."""
        C = len(self.classes)
        return BevPrediction(
            self.class_names,
            np.zeros((C, *self.grid.shape), np.float32),
            np.zeros(self.grid.shape, bool),
        )


# --------------------------------------------------------------- registry
# name -> "module:Class", imported lazily so that IPM users never import torch; filled from the one
# table of methods (:data:`bev_mapper_core.methods.METHODS`).
_REGISTRY: dict[str, str | Callable[..., Mapper]] = dict(mapper_targets())


def register_method(name: str, target: str | Callable[..., Mapper]) -> None:
    """Register a method under ``name`` (a ``"module:Class"`` string or a factory)."""
    _REGISTRY[name] = target


def available_methods() -> tuple[str, ...]:
    """Names of the registered methods."""
    return tuple(sorted(_REGISTRY))


def mapper_class(method: str) -> type[Mapper]:
    """The class registered for ``method`` (imported on first use).

    Raises:
        ConfigError: unknown method.
    """
    try:
        target = _REGISTRY[method]
    except KeyError:
        raise ConfigError(f"unknown method {method!r}; available: {list(available_methods())}") from None
    return resolve(target)


def preflight(config: MapperConfig, rig_name: str, grid: BevGrid | None = None,
              cameras: tuple[str, ...] | None = None) -> None:
    """Run the method's start-up checks (see :meth:`Mapper.preflight`)."""
    cls = mapper_class(config.method)
    check = getattr(cls, "preflight", None)
    if check is not None:
        check(config, rig_name, grid, cameras)


def output_classes(config: MapperConfig, rig_name: str) -> tuple[str, ...]:
    """The layer names ``config.method`` will produce for this rig (see :meth:`Mapper.output_classes`)."""
    return mapper_class(config.method).output_classes(config, rig_name)


def create_mapper(rig: Rig, grid: BevGrid, config: MapperConfig) -> Mapper:
    """Build the mapper ``config.method`` for a rig and grid.

    Raises:
        ConfigError: unknown method, or a method that cannot serve this configuration.
    """
    return mapper_class(config.method)(rig, grid, config)


__all__ = [
    "BACKENDS",
    "SEGMENTER_PRECISIONS",
    "BEV_CLASS_NAMES",
    "BevPrediction",
    "Mapper",
    "MapperConfig",
    "available_methods",
    "create_mapper",
    "mapper_class",
    "output_classes",
    "preflight",
    "register_method",
]
