"""ROS parameter declarations of the mapper node, with descriptors and validation.

Every parameter maps onto a field of :class:`bev_mapper_ros.config.NodeConfig` (or the core
dataclasses inside it, see :data:`bev_mapper_ros.config.PARAM_FIELDS`), whose default it
declares; :func:`declare_parameters` declares them on a node and
:func:`read_parameters` reads them back as the flat dict that
:func:`bev_mapper_ros.config.node_config_from_params` takes.
"""

from __future__ import annotations

from rcl_interfaces.msg import FloatingPointRange, ParameterDescriptor, ParameterType
from rclpy.exceptions import ParameterUninitializedException
from rclpy.node import Node
from rclpy.parameter import Parameter

from bev_mapper_core.mapper import INPUT_KINDS, available_methods

from .config import PARAM_FIELDS, NodeConfigError, parameter_defaults

_T = ParameterType
# name -> (type, read_only, description); the default comes from the dataclass field the
# parameter sets (config.PARAM_FIELDS), never from here.
_DECLARATIONS: dict[str, tuple] = {
    "rig": (_T.PARAMETER_STRING, True, "rig name (selects shipped default weights)"),
    "cameras": (_T.PARAMETER_STRING_ARRAY, True, "camera names, in rig order"),
    "input_kind": (_T.PARAMETER_STRING, True, f"one of {list(INPUT_KINDS)}"),
    "image_topic": (_T.PARAMETER_STRING, True,
                    "image topic pattern with {camera}; '' = /cameras/{camera}/labels or /image_raw"),
    "camera_info_topic": (_T.PARAMETER_STRING, True, "CameraInfo topic pattern with {camera}"),
    "compressed": (_T.PARAMETER_BOOL, True, "subscribe to <image_topic>/compressed"),
    "method": (_T.PARAMETER_STRING, True,
               f"mapping method, one of {list(available_methods())} (bimapper: shipped weights per rig)"),
    "weights": (_T.PARAMETER_STRING, True, "safetensors weights ('' = shipped default)"),
    "device": (_T.PARAMETER_STRING, True, "torch device of learned methods"),
    "threads": (_T.PARAMETER_INTEGER, True,
                "CPU threads of learned methods; 0 = all CPUs but one (left to the callbacks)"),
    "classes": (_T.PARAMETER_STRING_ARRAY, True, "classes to publish ([] = all)"),
    "grid.x_min": (_T.PARAMETER_DOUBLE, True, "grid extent along x (m)"),
    "grid.x_max": (_T.PARAMETER_DOUBLE, True, "grid extent along x (m)"),
    "grid.y_min": (_T.PARAMETER_DOUBLE, True, "grid extent along y (m)"),
    "grid.y_max": (_T.PARAMETER_DOUBLE, True, "grid extent along y (m)"),
    "grid.resolution": (_T.PARAMETER_DOUBLE, True, "cell size (m)"),
    "base_frame": (_T.PARAMETER_STRING, True, "frame of the output grids"),
    "sync_slop_s": (_T.PARAMETER_DOUBLE, True, "max stamp spread in a synchronized set (s)"),
    "sync_timeout_s": (_T.PARAMETER_DOUBLE, True, "wait for missing cameras this long (s)"),
    "use_tf": (_T.PARAMETER_BOOL, True, "look extrinsics up in TF when tf2_ros is importable"),
    "output_prefix": (_T.PARAMETER_STRING, True, "output topics: <prefix>/<class>, <prefix>/image"),
    "diagnostics_period_s": (_T.PARAMETER_DOUBLE, True, "period of /diagnostics (s)"),
}
_DEFAULTS = parameter_defaults()
# name -> (default, type, read_only, description), in PARAM_FIELDS order
PARAMETERS: dict[str, tuple] = {name: (_DEFAULTS[name], *_DECLARATIONS[name]) for name in PARAM_FIELDS}
_RANGES = {
    "sync_slop_s": (0.0, 10.0),
    "sync_timeout_s": (0.001, 60.0),
    "diagnostics_period_s": (0.05, 60.0),
    "grid.resolution": (0.01, 10.0),
}


def declare_parameters(node: Node) -> None:
    """Declare every node parameter, then ``extrinsics.<camera>`` for each configured camera."""
    for name, (default, ptype, read_only, text) in PARAMETERS.items():
        desc = ParameterDescriptor(name=name, type=ptype, read_only=read_only, description=text)
        if name in _RANGES:
            lo, hi = _RANGES[name]
            desc.floating_point_range = [FloatingPointRange(from_value=lo, to_value=hi, step=0.0)]
        if name == "method":
            desc.additional_constraints = f"one of {list(available_methods())}"
        node.declare_parameter(name, default, desc)
    cams = cameras_of(node)
    if len(set(cams)) != len(cams):
        raise NodeConfigError(f"cameras must be distinct, got {cams}")
    for cam in cams:
        node.declare_parameter(
            f"extrinsics.{cam}",
            Parameter.Type.DOUBLE_ARRAY,  # typed, no value unless the params file gives one
            ParameterDescriptor(
                name=f"extrinsics.{cam}",
                type=_T.PARAMETER_DOUBLE_ARRAY,
                read_only=True,
                description="ego_from_cam [x, y, z, qx, qy, qz, qw], used when TF has none",
            ),
        )


def cameras_of(node: Node) -> list[str]:
    """The ``cameras`` parameter without empty entries."""
    return [c for c in node.get_parameter("cameras").value if c]


def read_parameters(node: Node) -> dict:
    """Flat dict ``name -> value`` of the declared parameters (placeholders become empty)."""
    out = {name: node.get_parameter(name).value for name in PARAMETERS}
    out["cameras"] = cameras_of(node)
    out["classes"] = [c for c in out["classes"] if c]
    for cam in out["cameras"]:
        try:
            out[f"extrinsics.{cam}"] = list(node.get_parameter(f"extrinsics.{cam}").value)
        except ParameterUninitializedException:
            out[f"extrinsics.{cam}"] = []
    return out
