"""ROS parameter declarations of the mapper node, with descriptors, validation and ``--help``.

Every parameter maps onto a field of :class:`bev_mapper_ros.config.NodeConfig` (or the core
dataclasses inside it, see :data:`bev_mapper_ros.config.PARAM_FIELDS`), whose default it
declares; :func:`declare_parameters` declares them on a node and
:func:`read_parameters` reads them back as the flat dict that
:func:`bev_mapper_ros.config.node_config_from_params` takes. :func:`parameter_help` prints
the same table for ``mapper_node --help``.

Unknown parameters (typos) are found by comparing the names the command line and params files
set for this node (rclpy keeps them as ``Node._parameter_overrides``; there is no public
accessor, and ``automatically_declare_parameters_from_overrides`` fails on an empty list in a
params file) with the declared ones.

Empty arrays: ROS infers a parameter's type from its value and cannot from ``[]``, so an array
parameter without a value (``classes``, or ``cameras`` without a preset rig) is declared typed
and writable, set to ``[]`` of its type, then given its read-only descriptor: ``ros2 param get``
shows ``[]`` and ``ros2 param dump`` works (an unset parameter empties a whole dump).
"""

from __future__ import annotations

import textwrap

from rcl_interfaces.msg import FloatingPointRange, ParameterDescriptor, ParameterType
from rclpy.exceptions import ParameterUninitializedException
from rclpy.node import Node
from rclpy.parameter import Parameter

from bev_mapper_core.geometry.rig import PRESETS
from bev_mapper_core.geometry.time_placement import PLACEMENT_MODES
from bev_mapper_core.labels.classes import BEV_CLASS_NAMES
from bev_mapper_core.labels.label_maps import PRESET_NAMES
from bev_mapper_core.mapper import BACKENDS, INPUT_KINDS, SEGMENTER_PRECISIONS, available_methods

from .config import (
    PARAM_FIELDS,
    POSE_SOURCES,
    RELIABILITY_CHOICES,
    RUNTIME_PARAMETERS,
    NodeConfigError,
    parameter_defaults,
    preset_parameters,
    unknown_parameter_messages,
)

_T = ParameterType
# name -> (type, description); the default comes from the dataclass field the parameter sets
# (config.PARAM_FIELDS), read-only-ness from config.RUNTIME_PARAMETERS, never from here.
_DECLARATIONS: dict[str, tuple] = {
    "rig": (_T.PARAMETER_STRING,
            f"rig name; a preset ({', '.join(PRESETS)}) gives the cameras and their extrinsics unless "
            "cameras / extrinsics.<camera> are set, and selects the shipped weights"),
    "cameras": (_T.PARAMETER_STRING_ARRAY, "camera names, in rig order ([] = the preset rig's)"),
    "input_kind": (_T.PARAMETER_STRING, f"one of {list(INPUT_KINDS)}"),
    "label_map": (_T.PARAMETER_STRING,
                  f"what the label images hold: one of {list(PRESET_NAMES)} (native: this package's ids; "
                  "cam2bev: rgb8 palette images) or the path of a YAML file of upstream id (or colour) -> "
                  "label name (README, 'Label images from other segmenters')"),
    "image_topic": (_T.PARAMETER_STRING,
                    "image topic pattern with {camera}; '' = /cameras/{camera}/labels or /image_raw"),
    "camera_info_topic": (_T.PARAMETER_STRING, "CameraInfo topic pattern with {camera}"),
    "compressed": (_T.PARAMETER_BOOL, "subscribe to <image_topic>/compressed"),
    "image_reliability": (_T.PARAMETER_STRING,
                          f"QoS of the image and camera_info subscriptions, one of {list(RELIABILITY_CHOICES)}: "
                          "auto = what the publishers offer (reliable ones: no image of a burst lost)"),
    "method": (_T.PARAMETER_STRING,
               f"mapping method, one of {list(available_methods())} (bimapper: shipped weights per rig)"),
    "weights": (_T.PARAMETER_STRING, "safetensors weights ('' = shipped default)"),
    "device": (_T.PARAMETER_STRING, "torch device of learned methods"),
    "threads": (_T.PARAMETER_INTEGER, "CPU threads of learned methods; 0 = all CPUs but one (left to the callbacks)"),
    "backend": (_T.PARAMETER_STRING, f"inference runtime of learned methods, one of {list(BACKENDS)}: torch, or the model "
                "exported to ONNX (cached) for onnxruntime / openvino (the 'fast' extra); auto = the fastest installed"),
    "ipm_occlusion": (_T.PARAMETER_BOOL, "occlusion reasoning on label images: cells hidden behind an object a "
                      "camera sees are unknown to it (IPM: not the flat-ground smear; learned "
                      "methods: beyond the object's full length)"),
    "unknown_below": (_T.PARAMETER_DOUBLE, "Bi-Mapper with a visibility head: cells predicted seen with "
                      "probability below this are unknown, but for those a camera's labels show as a mapped "
                      "object (ipm_occlusion) (0 = all in-frustum cells known)"),
    "segmenter": (_T.PARAMETER_STRING, "RGB input: 2-D segmenter of segipm and of label weights run on RGB "
                  "(auto = camvid, the default; camvid: trained with CamVid, non-commercial; open: commercial use "
                  "allowed; none; or a safetensors file)"),
    "segmenter_precision": (_T.PARAMETER_STRING, f"RGB input: arithmetic of the segmenter on an exported backend, one "
                            f"of {list(SEGMENTER_PRECISIONS)}: auto = bf16 on OpenVINO where the CPU computes in bf16, else f32; "
                            "int8: its ONNX export quantized once, cached (docs/SPEED.md, issue #41)"),
    "classes": (_T.PARAMETER_STRING_ARRAY,
                f"classes to publish, of {list(BEV_CLASS_NAMES)} or the weights' ([] = all)"),
    "grid.x_min": (_T.PARAMETER_DOUBLE, "grid extent along x (m)"),
    "grid.x_max": (_T.PARAMETER_DOUBLE, "grid extent along x (m)"),
    "grid.y_min": (_T.PARAMETER_DOUBLE, "grid extent along y (m)"),
    "grid.y_max": (_T.PARAMETER_DOUBLE, "grid extent along y (m)"),
    "grid.resolution": (_T.PARAMETER_DOUBLE, "cell size (m)"),
    "base_frame": (_T.PARAMETER_STRING, "frame of the output grids"),
    "sync_slop_s": (_T.PARAMETER_DOUBLE, "max stamp spread in a synchronized set (s)"),
    "sync_timeout_s": (_T.PARAMETER_DOUBLE, "wait for missing cameras this long (s)"),
    "use_tf": (_T.PARAMETER_BOOL, "read TF when tf2_ros is importable: camera extrinsics base_frame <- CameraInfo "
               "frame_id (extrinsics.<camera> the fallback) and, per pose_source, the ego pose"),
    "tf_extrinsic_jump_m": (_T.PARAMETER_DOUBLE, "a TF extrinsic moving a camera by more than this (m) is refused "
                            "(tf_errors_extrinsic_jump in /diagnostics)"),
    "pose_source": (_T.PARAMETER_STRING, f"ego pose for the temporal fusion and FocusBEV, one of {list(POSE_SOURCES)}: "
                    "odom = odom_topic, tf = TF odom_frame -> base_frame at the image stamp (interpolated), "
                    "auto = odometry once odom_topic delivers; before that TF, else odometry"),
    "odom_frame": (_T.PARAMETER_STRING, "fixed frame of the TF ego pose (pose_source tf / auto)"),
    "output_prefix": (_T.PARAMETER_STRING, "output topics: <prefix>/<class>, <prefix>/image"),
    "diagnostics_period_s": (_T.PARAMETER_DOUBLE, "period of /diagnostics (s)"),
    "diagnostics_window_s": (_T.PARAMETER_DOUBLE, "rate, latency and drop ratio in /diagnostics: over this window (s)"),
    "clock_mismatch_s": (_T.PARAMETER_DOUBLE,
                         "image stamps further than this from the node's clock: warning and WARN "
                         "(use_sim_time:=true missing?) (s)"),
    "drop_warn_ratio": (_T.PARAMETER_DOUBLE, "WARN when more than this fraction of the sets in the window is dropped"),
    "stale_error_s": (_T.PARAMETER_DOUBLE,
                      "ERROR when images arrive but nothing is mapped for this long, or images stop (s)"),
    "odom_topic": (_T.PARAMETER_STRING, "nav_msgs/Odometry of the ego: its pose at each image stamp aligns the "
                   "frames of the temporal fusion"),
    "temporal_window": (_T.PARAMETER_INTEGER, "fuse the flat layers over the last N frames, aligned by odometry "
                        "(log-odds; 1 = off)"),
    "time_placement": (_T.PARAMETER_STRING, f"one of {list(PLACEMENT_MODES)}: auto = place each camera with the ego "
                       "pose (pose_source) of its own stamp, in base_frame at the set's stamp (ipm, segipm: a placed "
                       "rig; learned methods: the moved cameras' images warped); off = every camera as calibrated"),
    "time_placement_step_cells": (_T.PARAMETER_DOUBLE, "round each camera's correction to this many grid cells "
                                  "(under half of it: skipped, counted as static; 0 = exact, tables rebuilt every set)"),
    "time_placement_max_offset_s": (_T.PARAMETER_DOUBLE, "a camera stamped farther than this from its set's stamp "
                                    "is mapped as calibrated (placement_stamp_jumps in /diagnostics) (s)"),
}
_DEFAULTS = parameter_defaults()
# name -> (default, type, read_only, description), in PARAM_FIELDS order; default None = an empty
# string array (declared typed, then set to [], see the module docstring)
PARAMETERS: dict[str, tuple] = {
    name: (_DEFAULTS[name], _DECLARATIONS[name][0], name not in RUNTIME_PARAMETERS, _DECLARATIONS[name][1])
    for name in PARAM_FIELDS
}
# ROS-side ranges (shown by ros2 param describe); NodeConfig validates every value again, and
# alone the thresholds (its error message is the reason a rejected `ros2 param set` gives).
_RANGES = {
    "sync_slop_s": (0.0, 10.0),
    "sync_timeout_s": (0.001, 60.0),
    "diagnostics_period_s": (0.05, 60.0),
    "grid.resolution": (0.01, 10.0),
}
_TYPE_NAMES = {
    _T.PARAMETER_STRING: "string", _T.PARAMETER_BOOL: "bool", _T.PARAMETER_INTEGER: "integer",
    _T.PARAMETER_DOUBLE: "double", _T.PARAMETER_STRING_ARRAY: "string array", _T.PARAMETER_DOUBLE_ARRAY: "double array",
}
_EXTRINSICS_TEXT = "ego_from_cam [x, y, z, qx, qy, qz, qw], used when TF has none (default: the preset rig's)"
_EGO_MASK_TEXT = ("PNG of the camera's image size: nonzero pixels are the ego vehicle itself (hood, trunk), "
                  "ignored by every method ('' = none; bev-bag propose-mask proposes one from a drive). A "
                  "missing, non-binary or wrong-size mask leaves the camera out (counted, logged)")


def descriptor(name: str) -> ParameterDescriptor:
    """The descriptor of one of the node's parameters (type, read-only, text, range)."""
    _, ptype, read_only, text = PARAMETERS[name]
    desc = ParameterDescriptor(name=name, type=ptype, read_only=read_only, description=text)
    if name in _RANGES:
        lo, hi = _RANGES[name]
        desc.floating_point_range = [FloatingPointRange(from_value=lo, to_value=hi, step=0.0)]
    if name == "method":
        desc.additional_constraints = f"one of {list(available_methods())}"
    elif name == "input_kind":
        desc.additional_constraints = f"one of {list(INPUT_KINDS)}"
    elif name == "label_map":
        desc.additional_constraints = f"one of {list(PRESET_NAMES)}, or a label-map YAML file"
    elif name == "pose_source":
        desc.additional_constraints = f"one of {list(POSE_SOURCES)}"
    elif name == "rig":
        desc.additional_constraints = f"a preset ({', '.join(PRESETS)}), or any name with cameras set"
    return desc


def _declare(node: Node, name: str, value, desc: ParameterDescriptor) -> None:
    """Declare ``name`` with ``desc``; a given value (override) wins over ``value``.

    ``value`` None (an array): declared typed, ``[]`` unless given (see the module docstring).
    """
    if value is not None:
        node.declare_parameter(name, value, desc)
        return
    ptype = Parameter.Type(desc.type)
    node.declare_parameter(name, ptype, ParameterDescriptor(name=name, type=desc.type, description=desc.description))
    try:
        node.get_parameter(name)
    except ParameterUninitializedException:
        result = node.set_parameters([Parameter(name, ptype, [])])[0]
        if not result.successful:
            raise NodeConfigError(f"{name}: {result.reason}") from None
    node.set_descriptor(name, desc)


def _value(node: Node, name: str, empty):
    """The parameter's value; ``empty`` when it is declared without one."""
    try:
        value = node.get_parameter(name).value
    except ParameterUninitializedException:
        return empty
    return empty if value is None else value


def declare_parameters(node: Node) -> list[str]:
    """Declare every node parameter, then ``extrinsics.<camera>`` and ``ego_mask.<camera>`` for
    each configured camera.

    ``rig`` comes first: a preset rig gives the defaults of ``cameras`` and
    ``extrinsics.<camera>`` (:func:`~bev_mapper_ros.config.preset_parameters`), so
    ``ros2 param get`` shows the values in use. Returns one warning per given parameter that
    is not the node's (a typo).
    """
    given = set(getattr(node, "_parameter_overrides", {}))  # see the module docstring
    preset: dict = {}
    for name, (default, _ptype, _ro, _text) in PARAMETERS.items():
        _declare(node, name, preset.get(name, default), descriptor(name))
        if name == "rig":
            preset = preset_parameters(node.get_parameter("rig").value)
    cams = cameras_of(node)
    if len(set(cams)) != len(cams):
        raise NodeConfigError(f"cameras must be distinct, got {cams}")
    for cam in cams:
        name = f"extrinsics.{cam}"
        _declare(node, name, preset.get(name), ParameterDescriptor(
            name=name, type=_T.PARAMETER_DOUBLE_ARRAY, read_only=True, description=_EXTRINSICS_TEXT))
        name = f"ego_mask.{cam}"
        _declare(node, name, "", ParameterDescriptor(
            name=name, type=_T.PARAMETER_STRING, read_only=True, description=_EGO_MASK_TEXT))
    return unknown_parameter_messages(given, cams)


def cameras_of(node: Node) -> list[str]:
    """The ``cameras`` parameter ([] when not set)."""
    return [c for c in _value(node, "cameras", []) if c]


def read_parameters(node: Node) -> dict:
    """Flat dict ``name -> value`` of the declared parameters (not set -> empty)."""
    out = {name: _value(node, name, []) for name in PARAMETERS}
    out["cameras"] = cameras_of(node)
    for cam in out["cameras"]:
        out[f"extrinsics.{cam}"] = list(_value(node, f"extrinsics.{cam}", []))
        out[f"ego_mask.{cam}"] = str(_value(node, f"ego_mask.{cam}", "") or "")
    return out


def _shown(name: str, default) -> str:
    if default is None:
        return "[]"
    if isinstance(default, bool):
        return str(default).lower()
    return repr(default) if isinstance(default, str) else str(default)


def parameter_help(prog: str = "mapper_node") -> str:
    """``--help`` text: usage, how to choose a rig, and every parameter (name, type, default,
    whether it can change at run time, description), from the same table the node declares.
    """
    presets = "|".join(PRESETS)
    lines = [
        f"usage: {prog} [-h] --ros-args [--params-file FILE] [-p NAME:=VALUE ...]",
        "",
        "BEV mapper node: synchronized camera images in, one nav_msgs/OccupancyGrid per class out",
        "(<output_prefix>/<class>, <output_prefix>/image, /diagnostics).",
        "",
        "Choose a rig: -p rig:=<" + presets + "> (a preset's cameras, topics and extrinsics), or",
        "--params-file <share>/config/<rig>.yaml (ros2 pkg prefix --share bev_mapper_ros), or",
        "cameras:=[...] with extrinsics.<camera> (or TF). Explicit values override the preset.",
        "A bag played with --clock needs -p use_sim_time:=true.",
        "",
        "parameters (name: type = default; [runtime] = may change with ros2 param set):",
    ]
    for name, (default, ptype, read_only, text) in PARAMETERS.items():
        flag = "" if read_only else " [runtime]"
        lines.append(f"  {name}: {_TYPE_NAMES[ptype]} = {_shown(name, default)}{flag}")
        lines.extend(textwrap.wrap(text, 96, initial_indent=" " * 6, subsequent_indent=" " * 6))
    lines.append("  extrinsics.<camera>: double array = []")
    lines.extend(textwrap.wrap(_EXTRINSICS_TEXT, 96, initial_indent=" " * 6, subsequent_indent=" " * 6))
    lines.append("  ego_mask.<camera>: string = ''")
    lines.extend(textwrap.wrap(_EGO_MASK_TEXT, 96, initial_indent=" " * 6, subsequent_indent=" " * 6))
    return "\n".join(lines) + "\n"
