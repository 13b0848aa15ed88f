"""Node configuration: one frozen dataclass, filled from ROS parameters (or YAML / CLI).

The node's parameters map one to one onto fields of :class:`NodeConfig` and the core's own
dataclasses (:class:`~bev_mapper_core.mapper.MapperConfig`,
:class:`~bev_mapper_core.geometry.grid.BevGrid`); :data:`PARAM_FIELDS` says which. Their defaults are
those fields' defaults (:func:`parameter_defaults`): no default is written twice. This module
imports no rclpy, so the mapping is unit-testable without a ROS graph.
"""

from __future__ import annotations

import difflib
import math
from dataclasses import MISSING, dataclass, field, fields, replace

import numpy as np

from bev_mapper_core.errors import BevMapperError, ConfigError
from bev_mapper_core.geometry.grid import BevGrid
from bev_mapper_core.geometry.rig import PRESETS, preset_rig
from bev_mapper_core.geometry.time_placement import TimePlacementConfig
from bev_mapper_core.geometry.transforms import make_transform, quat_to_rot
from bev_mapper_core.mapper import MapperConfig
from bev_mapper_core.temporal import TemporalConfig
from msg_adapters.sync import SyncConfig

from .rig_params import rig_parameters

#: Values of ``image_reliability`` (:mod:`.input_qos` says what each means).
RELIABILITY_CHOICES = ("auto", "reliable", "best_effort")
#: Values of ``pose_source``: where the ego pose at an image stamp comes from (``auto``: odometry
#: once ``odom_topic`` has delivered some; before that TF, else odometry).
POSE_SOURCES = ("auto", "tf", "odom")
DEFAULT_TOPICS = {"labels": "/cameras/{camera}/labels", "rgb": "/cameras/{camera}/image_raw"}


class NodeConfigError(ConfigError):
    """A node parameter is missing, malformed or out of range."""


def _ns_to_s(ns: int) -> float:
    return ns / 1e9


@dataclass(frozen=True)
class NodeConfig:
    """Everything the mapper node is configured with.

    Attributes:
        cameras: camera names, in rig order; ``{camera}`` in topic patterns expands to them.
            Given none, a preset ``rig`` supplies them (see :func:`preset_parameters`).
        rig: rig name: a preset (:data:`~bev_mapper_core.geometry.rig.PRESETS`) supplies the cameras and
            their extrinsics unless those are given; selects the shipped default weights and
            names the live rig ('' = none).
        image_topic: image topic pattern ('' = the default for ``mapper.input_kind``).
        camera_info_topic: CameraInfo topic pattern.
        compressed: subscribe to ``sensor_msgs/CompressedImage`` on ``<image_topic>/compressed``.
        image_reliability: QoS reliability of the image and CameraInfo subscriptions: ``auto``
            (what the publishers offer, as ``ros2 bag record``), ``reliable`` or
            ``best_effort`` (see :mod:`.input_qos`).
        mapper: method settings (core dataclass).
        grid: output grid (core dataclass).
        base_frame: frame of the output grids (the ego frame).
        sync_slop_s: max stamp spread within one synchronized set (default:
            :class:`~msg_adapters.sync.SyncConfig`'s ``slop_ns``).
        sync_timeout_s: wait this long for missing cameras before emitting a partial set
            (default: ``SyncConfig.timeout_ns``).
        extrinsics: camera name -> ``ego_from_cam`` 4x4 from parameters (used without TF).
        ego_masks: camera name -> path of its ego-body mask PNG (``ego_mask.<camera>``
            parameters; nonzero = the ego vehicle's own pixels, ignored by every method; see
            :mod:`bev_mapper_core.geometry.ego_mask`).
        use_tf: read TF (tf2_ros, when importable): camera extrinsics ``base_frame <- camera
            frame`` (the parameters are the fallback) and, per ``pose_source``, the ego pose.
        tf_extrinsic_jump_m: a TF extrinsic that moves a camera by more than this from the one
            in use is refused (counted as ``tf_errors_extrinsic_jump``).
        pose_source: where the ego pose at each image stamp comes from, for the temporal fusion
            and methods with a memory (FocusBEV): ``odom`` (``odom_topic``), ``tf``
            (``odom_frame -> base_frame`` at the image stamp, tf2's interpolation) or ``auto``
            (odometry once ``odom_topic`` has delivered some; before that TF, else odometry).
        odom_frame: the fixed frame of the TF ego pose.
        output_prefix: output topics are ``<output_prefix>/<class>`` and ``<output_prefix>/image``.
        diagnostics_period_s: period of ``/diagnostics`` messages.
        diagnostics_window_s: rate, latency and drop ratio in ``/diagnostics`` are over the
            last this many seconds.
        clock_mismatch_s: image stamps further than this from the node's clock (either way)
            are a clock mismatch (typically a bag played with ``--clock`` into a node without
            ``use_sim_time``): a warning, WARN in ``/diagnostics``, no latency figure.
        drop_warn_ratio: ``/diagnostics`` WARNs when more than this fraction of the
            synchronized sets in the window were dropped (mapping slower than the cameras).
        stale_error_s: ``/diagnostics`` reports ERROR when images arrive but nothing was
            mapped for this long, or when no image arrived for this long after some did.
        odom_topic: ``nav_msgs/Odometry`` of the ego (``frame_id`` a fixed frame,
            ``child_frame_id`` the base frame); its pose at each image stamp aligns the frames
            of the temporal fusion.
        temporal: method-independent temporal fusion (core dataclass; ``window`` 1 = off).
        time_placement: each camera placed with the ego pose (``pose_source``) of its own stamp,
            in ``base_frame`` at the set's stamp (core dataclass; IPM and segipm; learned
            methods keep their calibration, counted; :mod:`bev_mapper_core.placement`).
    """

    cameras: tuple[str, ...]
    rig: str = ""
    image_topic: str = ""
    camera_info_topic: str = "/cameras/{camera}/camera_info"
    compressed: bool = False
    image_reliability: str = "auto"
    mapper: MapperConfig = field(default_factory=MapperConfig)
    grid: BevGrid = field(default_factory=BevGrid)
    base_frame: str = "base_link"
    sync_slop_s: float = _ns_to_s(SyncConfig.slop_ns)
    sync_timeout_s: float = _ns_to_s(SyncConfig.timeout_ns)
    extrinsics: tuple = ()
    ego_masks: tuple = ()
    use_tf: bool = True
    tf_extrinsic_jump_m: float = 0.5
    pose_source: str = "auto"
    odom_frame: str = "odom"
    output_prefix: str = "bev"
    diagnostics_period_s: float = 1.0
    diagnostics_window_s: float = 5.0
    clock_mismatch_s: float = 10.0
    drop_warn_ratio: float = 0.2
    stale_error_s: float = 5.0
    odom_topic: str = "/odom"
    temporal: TemporalConfig = field(default_factory=TemporalConfig)
    time_placement: TimePlacementConfig = field(default_factory=TimePlacementConfig)

    def __post_init__(self) -> None:
        cams = tuple(self.cameras)
        object.__setattr__(self, "cameras", cams)
        if not cams:
            raise NodeConfigError(no_cameras_message(self.rig))
        if any(not c or "/" in c for c in cams) or len(set(cams)) != len(cams):
            raise NodeConfigError(f"cameras must be distinct non-empty names without '/', got {list(cams)}")
        for name in ("sync_slop_s", "sync_timeout_s", "diagnostics_period_s", "diagnostics_window_s",
                     "clock_mismatch_s", "stale_error_s"):
            v = getattr(self, name)
            if not isinstance(v, (int, float)) or not math.isfinite(v) or v <= 0:
                raise NodeConfigError(f"{name} must be > 0, got {v}")
        if not (isinstance(self.drop_warn_ratio, (int, float)) and 0.0 <= self.drop_warn_ratio <= 1.0):
            raise NodeConfigError(f"drop_warn_ratio must be in [0, 1], got {self.drop_warn_ratio}")
        if self.sync_timeout_s < self.sync_slop_s:
            raise NodeConfigError("sync_timeout_s must be >= sync_slop_s")
        for pat in (self.image_topic, self.camera_info_topic):
            if pat and "{camera}" not in pat:
                raise NodeConfigError(f"topic pattern {pat!r} must contain '{{camera}}'")
        if not self.base_frame:
            raise NodeConfigError("base_frame must not be empty")
        if self.pose_source not in POSE_SOURCES:
            raise NodeConfigError(f"pose_source must be one of {list(POSE_SOURCES)}, got {self.pose_source!r}")
        if self.pose_source == "tf" and not self.use_tf:
            raise NodeConfigError("pose_source tf needs use_tf true")
        if not self.odom_frame or self.odom_frame.lstrip("/") == self.base_frame.lstrip("/"):
            raise NodeConfigError(f"odom_frame must be a frame other than base_frame, got {self.odom_frame!r}")
        if not (isinstance(self.tf_extrinsic_jump_m, (int, float)) and math.isfinite(self.tf_extrinsic_jump_m)
                and self.tf_extrinsic_jump_m > 0):
            raise NodeConfigError(f"tf_extrinsic_jump_m must be > 0, got {self.tf_extrinsic_jump_m}")
        if self.image_reliability not in RELIABILITY_CHOICES:
            raise NodeConfigError(f"image_reliability must be one of {list(RELIABILITY_CHOICES)}, "
                                  f"got {self.image_reliability!r}")
        ext = dict(self.extrinsics)
        unknown = sorted(set(ext) - set(cams))
        if unknown:
            raise NodeConfigError(f"extrinsics given for unknown cameras {unknown}")
        object.__setattr__(self, "extrinsics", tuple(sorted(ext.items())))
        masks = {cam: str(path) for cam, path in dict(self.ego_masks).items() if path}
        unknown = sorted(set(masks) - set(cams))
        if unknown:
            raise NodeConfigError(f"ego masks given for unknown cameras {unknown}")
        object.__setattr__(self, "ego_masks", tuple(sorted(masks.items())))

    def sync_config(self) -> SyncConfig:
        """The synchronizer settings: slop and timeout from here, the rest SyncConfig's defaults."""
        return SyncConfig(slop_ns=round(self.sync_slop_s * 1e9), timeout_ns=round(self.sync_timeout_s * 1e9))

    def image_topic_for(self, camera: str) -> str:
        """The image topic of one camera."""
        pattern = self.image_topic or DEFAULT_TOPICS[self.mapper.input_kind]
        topic = pattern.format(camera=camera)
        return f"{topic}/compressed" if self.compressed else topic

    def camera_info_topic_for(self, camera: str) -> str:
        """The CameraInfo topic of one camera."""
        return self.camera_info_topic.format(camera=camera)

    def extrinsic(self, camera: str) -> np.ndarray | None:
        """``ego_from_cam`` given by parameters for ``camera``, or None."""
        return dict(self.extrinsics).get(camera)


def extrinsic_from_list(camera: str, values) -> np.ndarray | None:
    """Parameter ``[x, y, z, qx, qy, qz, qw]`` -> ``ego_from_cam``; empty list -> None."""
    values = list(values or [])
    if not values:
        return None
    if len(values) != 7 or not all(math.isfinite(float(v)) for v in values):
        raise NodeConfigError(
            f"extrinsics.{camera} must be 7 finite numbers [x, y, z, qx, qy, qz, qw], got {values}"
        )
    x, y, z, qx, qy, qz, qw = (float(v) for v in values)
    try:
        return make_transform(quat_to_rot(qx, qy, qz, qw), (x, y, z))
    except BevMapperError as exc:
        raise NodeConfigError(f"extrinsics.{camera}: {exc}") from None


@dataclass(frozen=True)
class ParamField:
    """Where a node parameter's value lives: ``owner.field`` (the owner holds its default).

    ``string_array``: a ``tuple[str, ...]`` field, declared as a ROS string array.
    """

    owner: type
    field: str
    string_array: bool = False

    def default(self):
        """The field's default (``dataclasses.MISSING`` for a required field)."""
        f = next(f for f in fields(self.owner) if f.name == self.field)
        if f.default is not MISSING:
            return f.default
        if f.default_factory is not MISSING:
            return f.default_factory()
        return MISSING

    def declared_default(self):
        """The default as the node declares it: ``None`` -> ``''``, tuples -> lists; ``None``
        for an empty, optional or required string array: ROS cannot infer the type of ``[]``,
        so the node declares it typed and then sets it to ``[]`` (see ``params.py``).
        """
        value = self.default()
        if self.string_array:
            return list(value) if value is not MISSING and value else None
        if value is MISSING:
            raise TypeError(f"{self.owner.__name__}.{self.field} has no default to declare")
        return "" if value is None else value

    def from_param(self, value):
        """A parameter value (as declared, or a YAML/CLI value) -> the field's value."""
        default = self.default()
        if self.string_array:
            values = tuple(value or ())
            return values if values or default is not None else None
        if default is None:  # optional string ('' = None)
            return value or None
        for kind in (bool, int, float):  # bool first: a bool is an int
            if isinstance(default, kind):
                return kind(value)
        return value


#: Node parameter name -> the dataclass field it sets, in declaration order (``rig`` first: a
#: preset rig gives the defaults of ``cameras`` and ``extrinsics.<cam>``). ``extrinsics.<cam>``
#: parameters are declared per camera on top of these.
PARAM_FIELDS: dict[str, ParamField] = {
    "rig": ParamField(NodeConfig, "rig"),
    "cameras": ParamField(NodeConfig, "cameras", string_array=True),
    "input_kind": ParamField(MapperConfig, "input_kind"),
    "label_map": ParamField(MapperConfig, "label_map"),
    "image_topic": ParamField(NodeConfig, "image_topic"),
    "camera_info_topic": ParamField(NodeConfig, "camera_info_topic"),
    "compressed": ParamField(NodeConfig, "compressed"),
    "image_reliability": ParamField(NodeConfig, "image_reliability"),
    "method": ParamField(MapperConfig, "method"),
    "weights": ParamField(MapperConfig, "weights"),
    "device": ParamField(MapperConfig, "device"),
    "threads": ParamField(MapperConfig, "threads"),
    "backend": ParamField(MapperConfig, "backend"),
    "ipm_occlusion": ParamField(MapperConfig, "ipm_occlusion"),
    "unknown_below": ParamField(MapperConfig, "unknown_below"),
    "segmenter": ParamField(MapperConfig, "segmenter"),
    "segmenter_precision": ParamField(MapperConfig, "segmenter_precision"),
    "classes": ParamField(MapperConfig, "classes", string_array=True),
    "grid.x_min": ParamField(BevGrid, "x_min"),
    "grid.x_max": ParamField(BevGrid, "x_max"),
    "grid.y_min": ParamField(BevGrid, "y_min"),
    "grid.y_max": ParamField(BevGrid, "y_max"),
    "grid.resolution": ParamField(BevGrid, "resolution"),
    "base_frame": ParamField(NodeConfig, "base_frame"),
    "sync_slop_s": ParamField(NodeConfig, "sync_slop_s"),
    "sync_timeout_s": ParamField(NodeConfig, "sync_timeout_s"),
    "use_tf": ParamField(NodeConfig, "use_tf"),
    "tf_extrinsic_jump_m": ParamField(NodeConfig, "tf_extrinsic_jump_m"),
    "pose_source": ParamField(NodeConfig, "pose_source"),
    "odom_frame": ParamField(NodeConfig, "odom_frame"),
    "output_prefix": ParamField(NodeConfig, "output_prefix"),
    "diagnostics_period_s": ParamField(NodeConfig, "diagnostics_period_s"),
    "diagnostics_window_s": ParamField(NodeConfig, "diagnostics_window_s"),
    "clock_mismatch_s": ParamField(NodeConfig, "clock_mismatch_s"),
    "drop_warn_ratio": ParamField(NodeConfig, "drop_warn_ratio"),
    "stale_error_s": ParamField(NodeConfig, "stale_error_s"),
    "odom_topic": ParamField(NodeConfig, "odom_topic"),
    "temporal_window": ParamField(TemporalConfig, "window"),
    "time_placement": ParamField(TimePlacementConfig, "mode"),
    "time_placement_step_cells": ParamField(TimePlacementConfig, "step_cells"),
    "time_placement_max_offset_s": ParamField(TimePlacementConfig, "max_offset_s"),
}

#: Parameters that may change while the node runs (``ros2 param set``): the diagnostics'
#: period, window and thresholds. The others are read-only (they shape subscriptions, the
#: mapper or its lookup tables). All are :class:`NodeConfig` fields.
RUNTIME_PARAMETERS: tuple[str, ...] = (
    "diagnostics_period_s", "diagnostics_window_s", "clock_mismatch_s", "drop_warn_ratio", "stale_error_s",
)

#: Per-camera parameter prefixes, declared for each of the configured cameras on top of
#: :data:`PARAM_FIELDS`: ``extrinsics.<cam>`` (``[x, y, z, qx, qy, qz, qw]``, default the preset
#: rig's) and ``ego_mask.<cam>`` (a mask PNG's path, '' = none).
PER_CAMERA: tuple[str, ...] = ("extrinsics", "ego_mask")

#: Parameters every rclpy node has (``use_sim_time``, ...): known, never reported as unknown.
ROS_PARAMETERS: tuple[str, ...] = ("use_sim_time", "start_type_description_service")


def parameter_defaults() -> dict:
    """Parameter name -> the default the node declares (see :meth:`ParamField.declared_default`)."""
    return {name: pf.declared_default() for name, pf in PARAM_FIELDS.items()}


def preset_parameters(rig: str) -> dict:
    """What a preset rig sets when the parameters do not: ``cameras`` and ``extrinsics.<cam>``.

    The same values as the shipped ``config/<rig>.yaml`` (both come from
    :func:`bev_mapper_ros.rig_params.rig_parameters`); ``{}`` for a name that is no preset.
    """
    if rig not in PRESETS:
        return {}
    params = rig_parameters(preset_rig(rig))
    out = {"cameras": list(params["cameras"])}
    out.update({f"extrinsics.{cam}": list(v) for cam, v in params["extrinsics"].items()})
    return out


def no_cameras_message(rig: str) -> str:
    """The error for a node without cameras: how to choose a rig (and which ones exist)."""
    presets = "|".join(PRESETS)
    how = (f"choose a preset rig with -p rig:=<{presets}> (its cameras, topics and extrinsics), "
           f"or --params-file <share>/config/<rig>.yaml, or set cameras:=[...] with "
           f"extrinsics.<camera> (or TF); `mapper_node --help` lists the parameters")
    if rig:
        return f"rig {rig!r} is no preset ({', '.join(PRESETS)}) and no cameras are given: {how}"
    return f"no rig and no cameras configured: {how}"


def unknown_parameter_messages(given, cameras) -> list[str]:
    """One warning per given parameter the node does not know, naming the closest valid one.

    ``given``: names set by the command line / params files; ``cameras``: the configured
    cameras (``extrinsics.<cam>`` is known for those). ROS's own (:data:`ROS_PARAMETERS`,
    ``qos_overrides.*``) are known.
    """
    known = [*PARAM_FIELDS, *(f"{prefix}.{c}" for prefix in PER_CAMERA for c in cameras), *ROS_PARAMETERS]
    out = []
    for name in sorted(set(given) - set(known)):
        if name.startswith("qos_overrides."):
            continue
        if name.split(".", 1)[0] in PER_CAMERA:
            out.append(f"parameter {name!r} ignored: {name.split('.', 1)[1]!r} is not one of the "
                       f"cameras {list(cameras)}")
            continue
        close = difflib.get_close_matches(name, known, n=1, cutoff=0.6)
        hint = f"; did you mean {close[0]!r}?" if close else "; `mapper_node --help` lists the parameters"
        out.append(f"unknown parameter {name!r} ignored{hint}")
    return out


def node_config_from_params(p: dict) -> NodeConfig:
    """Build a :class:`NodeConfig` from a flat parameter dict (names as the node declares them).

    Missing parameters take the dataclass defaults; a preset ``rig`` gives the cameras and
    extrinsics that ``p`` leaves empty (:func:`preset_parameters`). ``threads`` 0 stays 0: the
    mapper then takes :func:`~bev_mapper_core.nn.runtime.inference_threads` (every CPU but
    one, the rule of replay and the benchmarks too).

    Raises:
        NodeConfigError / ConfigError / GridError: with a message naming the bad parameter.
    """
    p = {**preset_parameters(str(p.get("rig") or "")),
         **{k: v for k, v in p.items() if not (k == "cameras" or k.startswith("extrinsics.")) or list(v or ())}}
    kwargs: dict[type, dict] = {NodeConfig: {}, MapperConfig: {}, BevGrid: {}, TemporalConfig: {},
                                TimePlacementConfig: {}}
    for name, pf in PARAM_FIELDS.items():
        if name in p:
            kwargs[pf.owner][pf.field] = pf.from_param(p[name])
    mapper = MapperConfig(**kwargs[MapperConfig])
    grid = BevGrid(**kwargs[BevGrid])
    node_kw = kwargs[NodeConfig]
    cameras = node_kw.pop("cameras", ())
    ext = {}
    for cam in cameras:
        T = extrinsic_from_list(cam, p.get(f"extrinsics.{cam}"))
        if T is not None:
            ext[cam] = T
    masks = {cam: str(p.get(f"ego_mask.{cam}") or "") for cam in cameras}
    return NodeConfig(cameras=cameras, mapper=mapper, grid=grid, extrinsics=tuple(ext.items()),
                      ego_masks=tuple(masks.items()),
                      temporal=TemporalConfig(**kwargs[TemporalConfig]),
                      time_placement=TimePlacementConfig(**kwargs[TimePlacementConfig]), **node_kw)


def with_runtime_parameters(cfg: NodeConfig, changes: dict) -> NodeConfig:
    """``cfg`` with new values of :data:`RUNTIME_PARAMETERS` (name -> value), validated by
    :class:`NodeConfig` itself.

    Raises:
        NodeConfigError: a value out of range, or a parameter that cannot change at run time.
    """
    kwargs = {}
    for name, value in changes.items():
        if name not in RUNTIME_PARAMETERS:
            raise NodeConfigError(f"{name} cannot change while the node runs (restart it)")
        kwargs[PARAM_FIELDS[name].field] = PARAM_FIELDS[name].from_param(value)
    return replace(cfg, **kwargs)
