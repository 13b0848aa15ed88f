"""Node configuration: one frozen dataclass, filled from ROS parameters (or YAML / CLI).

The node's parameters map one to one onto :class:`NodeConfig` and the core's own dataclasses
(:class:`~bev_mapper_core.mapper.MapperConfig`, :class:`~bev_mapper_core.grid.BevGrid`). This
module imports no rclpy, so the mapping is unit-testable without a ROS graph.
"""

from __future__ import annotations

import math
import os
from dataclasses import dataclass, field

import numpy as np

from bev_mapper_core.errors import BevMapperError, ConfigError
from bev_mapper_core.grid import BevGrid
from bev_mapper_core.mapper import MapperConfig
from bev_mapper_core.transforms import make_transform, quat_to_rot

DEFAULT_TOPICS = {"labels": "/cameras/{camera}/labels", "rgb": "/cameras/{camera}/image_raw"}


class NodeConfigError(ConfigError):
    """A node parameter is missing, malformed or out of range."""


@dataclass(frozen=True)
class NodeConfig:
    """Everything the mapper node is configured with.

    Attributes:
        cameras: camera names, in rig order; ``{camera}`` in topic patterns expands to them.
        image_topic: image topic pattern ('' = the default for ``mapper.input_kind``).
        camera_info_topic: CameraInfo topic pattern.
        compressed: subscribe to ``sensor_msgs/CompressedImage`` on ``<image_topic>/compressed``.
        mapper: method settings (core dataclass).
        grid: output grid (core dataclass).
        base_frame: frame of the output grids (the ego frame).
        sync_slop_s: max stamp spread within one synchronized set.
        sync_timeout_s: wait this long for missing cameras before emitting a partial set.
        extrinsics: camera name -> ``ego_from_cam`` 4x4 from parameters (used without TF).
        use_tf: look extrinsics up in TF (tf2_ros) when it is importable.
        output_prefix: output topics are ``<output_prefix>/<class>`` and ``<output_prefix>/image``.
        diagnostics_period_s: period of ``/diagnostics`` messages.
    """

    cameras: tuple[str, ...]
    image_topic: str = ""
    camera_info_topic: str = "/cameras/{camera}/camera_info"
    compressed: bool = False
    mapper: MapperConfig = field(default_factory=MapperConfig)
    grid: BevGrid = field(default_factory=BevGrid)
    base_frame: str = "base_link"
    sync_slop_s: float = 0.02
    sync_timeout_s: float = 0.2
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


def node_config_from_params(p: dict) -> NodeConfig:
    """Build a :class:`NodeConfig` from a flat parameter dict (names as the node declares them).

    Raises:
        NodeConfigError / ConfigError / GridError: with a message naming the bad parameter.
    """
    cameras = tuple(p.get("cameras") or ())
    classes = tuple(p.get("classes") or ()) or None
    mapper = MapperConfig(
        method=p.get("method", MapperConfig.method),
        input_kind=p.get("input_kind", "labels"),
        classes=classes,
        weights=p.get("weights") or None,
        device=p.get("device", "cpu"),
        threads=int(p.get("threads", 0)) or node_default_threads(),
    )
    grid = BevGrid(
        x_min=float(p.get("grid.x_min", -30.0)),
        x_max=float(p.get("grid.x_max", 30.0)),
        y_min=float(p.get("grid.y_min", -15.0)),
        y_max=float(p.get("grid.y_max", 15.0)),
        resolution=float(p.get("grid.resolution", 0.15)),
    )
    ext = {}
    for cam in cameras:
        T = extrinsic_from_list(cam, p.get(f"extrinsics.{cam}"))
        if T is not None:
            ext[cam] = T
    return NodeConfig(
        cameras=cameras,
        image_topic=p.get("image_topic", ""),
        camera_info_topic=p.get("camera_info_topic", "/cameras/{camera}/camera_info"),
        compressed=bool(p.get("compressed", False)),
        mapper=mapper,
        grid=grid,
        base_frame=p.get("base_frame", "base_link"),
        sync_slop_s=float(p.get("sync_slop_s", 0.02)),
        sync_timeout_s=float(p.get("sync_timeout_s", 0.2)),
        extrinsics=tuple(ext.items()),
        use_tf=bool(p.get("use_tf", True)),
        output_prefix=p.get("output_prefix", "bev"),
        diagnostics_period_s=float(p.get("diagnostics_period_s", 1.0)),
    )
