"""Node configuration: one frozen dataclass, filled from ROS parameters (or YAML / CLI).

The node's parameters map one to one onto fields of :class:`NodeConfig` and the core's own
dataclasses (:class:`~bev_mapper_core.mapper.MapperConfig`,
:class:`~bev_mapper_core.grid.BevGrid`); :data:`PARAM_FIELDS` says which. Their defaults are
those fields' defaults (:func:`parameter_defaults`): no default is written twice. This module
imports no rclpy, so the mapping is unit-testable without a ROS graph.
"""

from __future__ import annotations

import math
import os
from dataclasses import MISSING, dataclass, field, fields

import numpy as np

from bev_mapper_core.errors import BevMapperError, ConfigError
from bev_mapper_core.grid import BevGrid
from bev_mapper_core.mapper import MapperConfig
from bev_mapper_core.transforms import make_transform, quat_to_rot
from msg_adapters.sync import SyncConfig

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
        rig: rig name: selects the shipped default weights and names the live rig ('' = none).
        image_topic: image topic pattern ('' = the default for ``mapper.input_kind``).
        camera_info_topic: CameraInfo topic pattern.
        compressed: subscribe to ``sensor_msgs/CompressedImage`` on ``<image_topic>/compressed``.
        mapper: method settings (core dataclass).
        grid: output grid (core dataclass).
        base_frame: frame of the output grids (the ego frame).
        sync_slop_s: max stamp spread within one synchronized set (default:
            :class:`~msg_adapters.sync.SyncConfig`'s ``slop_ns``).
        sync_timeout_s: wait this long for missing cameras before emitting a partial set
            (default: ``SyncConfig.timeout_ns``).
        extrinsics: camera name -> ``ego_from_cam`` 4x4 from parameters (used without TF).
        use_tf: look extrinsics up in TF (tf2_ros) when it is importable.
        output_prefix: output topics are ``<output_prefix>/<class>`` and ``<output_prefix>/image``.
        diagnostics_period_s: period of ``/diagnostics`` messages.
    """

    cameras: tuple[str, ...]
    rig: str = ""
    image_topic: str = ""
    camera_info_topic: str = "/cameras/{camera}/camera_info"
    compressed: bool = False
    mapper: MapperConfig = field(default_factory=MapperConfig)
    grid: BevGrid = field(default_factory=BevGrid)
    base_frame: str = "base_link"
    sync_slop_s: float = _ns_to_s(SyncConfig.slop_ns)
    sync_timeout_s: float = _ns_to_s(SyncConfig.timeout_ns)
    extrinsics: tuple = ()
    use_tf: bool = True
    output_prefix: str = "bev"
    diagnostics_period_s: float = 1.0

    def __post_init__(self) -> None:
        cams = tuple(self.cameras)
        object.__setattr__(self, "cameras", cams)
        if not cams or any(not c or "/" in c for c in cams) or len(set(cams)) != len(cams):
            raise NodeConfigError(f"cameras must be distinct non-empty names without '/', got {list(cams)}")
        for name in ("sync_slop_s", "sync_timeout_s", "diagnostics_period_s"):
            v = getattr(self, name)
            if not math.isfinite(v) or v <= 0:
                raise NodeConfigError(f"{name} must be > 0, got {v}")
        if self.sync_timeout_s < self.sync_slop_s:
            raise NodeConfigError("sync_timeout_s must be >= sync_slop_s")
        for pat in (self.image_topic, self.camera_info_topic):
            if pat and "{camera}" not in pat:
                raise NodeConfigError(f"topic pattern {pat!r} must contain '{{camera}}'")
        if not self.base_frame:
            raise NodeConfigError("base_frame must not be empty")
        ext = dict(self.extrinsics)
        unknown = sorted(set(ext) - set(cams))
        if unknown:
            raise NodeConfigError(f"extrinsics given for unknown cameras {unknown}")
        object.__setattr__(self, "extrinsics", tuple(sorted(ext.items())))

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


def node_default_threads() -> int:
    """Inference threads in the node: every CPU but one, which stays free for the executor.

    With torch on every core the subscription callbacks starve, the images of one set arrive
    further apart than the sync timeout and sets are split into partial ones (measured with
    ``bench/bench_node_rate.py``).
    """
    try:
        cpus = len(os.sched_getaffinity(0))
    except AttributeError:  # not Linux
        cpus = os.cpu_count() or 1
    return max(1, cpus - 1)


#: A ROS string array cannot be declared empty with a type; this placeholder stands for
#: "none" (cameras: required, classes: all) and is dropped when the parameters are read.
STRING_ARRAY_PLACEHOLDER = ("",)


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
        """The default as the node declares it: ``None`` -> ``''``, tuples -> lists, an empty
        or required string array -> :data:`STRING_ARRAY_PLACEHOLDER`."""
        value = self.default()
        if self.string_array:
            return list(value) if value is not MISSING and value else list(STRING_ARRAY_PLACEHOLDER)
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


#: Node parameter name -> the dataclass field it sets, in declaration order. ``extrinsics.<cam>``
#: parameters are declared per camera on top of these.
PARAM_FIELDS: dict[str, ParamField] = {
    "rig": ParamField(NodeConfig, "rig"),
    "cameras": ParamField(NodeConfig, "cameras", string_array=True),
    "input_kind": ParamField(MapperConfig, "input_kind"),
    "image_topic": ParamField(NodeConfig, "image_topic"),
    "camera_info_topic": ParamField(NodeConfig, "camera_info_topic"),
    "compressed": ParamField(NodeConfig, "compressed"),
    "method": ParamField(MapperConfig, "method"),
    "weights": ParamField(MapperConfig, "weights"),
    "device": ParamField(MapperConfig, "device"),
    "threads": ParamField(MapperConfig, "threads"),
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
    "output_prefix": ParamField(NodeConfig, "output_prefix"),
    "diagnostics_period_s": ParamField(NodeConfig, "diagnostics_period_s"),
}


def parameter_defaults() -> dict:
    """Parameter name -> the default the node declares (see :meth:`ParamField.declared_default`)."""
    return {name: pf.declared_default() for name, pf in PARAM_FIELDS.items()}


def node_config_from_params(p: dict) -> NodeConfig:
    """Build a :class:`NodeConfig` from a flat parameter dict (names as the node declares them).

    Missing parameters take the dataclass defaults; ``threads`` 0 becomes
    :func:`node_default_threads`.

    Raises:
        NodeConfigError / ConfigError / GridError: with a message naming the bad parameter.
    """
    kwargs: dict[type, dict] = {NodeConfig: {}, MapperConfig: {}, BevGrid: {}}
    for name, pf in PARAM_FIELDS.items():
        if name in p:
            kwargs[pf.owner][pf.field] = pf.from_param(p[name])
    mapper_kw = kwargs[MapperConfig]
    mapper_kw["threads"] = mapper_kw.get("threads") or node_default_threads()
    mapper = MapperConfig(**mapper_kw)
    grid = BevGrid(**kwargs[BevGrid])
    node_kw = kwargs[NodeConfig]
    cameras = node_kw.pop("cameras", ())
    ext = {}
    for cam in cameras:
        T = extrinsic_from_list(cam, p.get(f"extrinsics.{cam}"))
        if T is not None:
            ext[cam] = T
    return NodeConfig(cameras=cameras, mapper=mapper, grid=grid, extrinsics=tuple(ext.items()), **node_kw)
