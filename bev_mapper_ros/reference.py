"""The node's reference tables for README.md, generated from the code that defines them.

* parameters: one row per entry of :data:`~bev_mapper_ros.params.PARAMETERS` (the declarations
  of :data:`~bev_mapper_ros.config.PARAM_FIELDS`, defaults from the dataclass fields they set),
  the same table ``mapper_node --help`` prints;
* diagnostics keys: the key/values of :func:`~bev_mapper_ros.stats.diagnostic_values`, with the
  text of :data:`DIAGNOSTIC_KEYS` (a key the node publishes that has no text here is an error).

README.md holds each table between ``<!-- NAME:begin -->`` and ``<!-- NAME:end -->``
(``params``, ``diagnostics``); ``tests/test_readme.py`` checks that they equal what this module
renders, and ``--write`` puts them there::

    .venv/bin/python -m bev_mapper_ros.reference              # print both tables
    .venv/bin/python -m bev_mapper_ros.reference --write      # ... and write them into README.md
"""

from __future__ import annotations

import argparse
import pathlib
import sys

from .config import PARAM_FIELDS, NodeConfig
from .odometry import FAR_AHEAD_S
from .params import _EXTRINSICS_TEXT, _TYPE_NAMES, PARAMETERS, _shown
from .stats import NodeStats, diagnostic_values
from .tf_source import TF_ERROR_TEXTS

README = pathlib.Path(__file__).resolve().parents[1] / "README.md"

#: ``/diagnostics`` key -> what it says (the node's ``DiagnosticStatus`` values, in order).
DIAGNOSTIC_KEYS: dict[str, str] = {
    "mapped_sets": "synchronized sets mapped and published since start-up",
    "dropped_sets": "sets dropped since start-up (a newer set replaced it in the one-slot mailbox, or the synchronizer gave it up)",
    "bad_input": "messages refused since start-up (wrong encoding, size mismatch, truncated data, uncalibrated CameraInfo, ...)",
    "errors": "failures of the mapping step since start-up (logged; the node keeps running)",
    "sets_with_missing_cameras": "sets mapped without every camera (timed out after `sync_timeout_s`)",
    "missing_by_camera": "per camera, the mapped sets that lacked it (`camera:count`, comma-separated)",
    "split_sets": "frames whose cameras spread wider than the synchronizer's window, so that they were mapped as two "
                  "partial sets (widen `sync_slop_s`)",
    "sync_window_ms": "the stamp spread a set may have now: `sync_slop_s`, at most half the cameras' measured frame "
                      "period",
    "cameras_missing": "cameras missing from the last mapped set, comma-separated",
    "waiting_for": "cameras still without CameraInfo or extrinsics, comma-separated",
    "last_error": "the last bad input or error message",
    "backend": "what runs a learned model now: the exported backend (`openvino`, `onnxruntime`), `torch`, or "
               "`torch (until the openvino model is ready)` while its export runs in the background at start-up, "
               "`torch (openvino failed: ...)` after a failed export; empty for IPM",
    "rate_hz": "sets mapped per second over the last `diagnostics_window_s`",
    "processing_ms": "mean time to decode, map and publish a set over the window",
    "clock_offset_s": "node clock minus the stamp of the last image",
    "latency_ms": "mean of (node clock once the set is published - image stamp) over the window; `clock mismatch` when "
                  "the offset exceeds `clock_mismatch_s` (`use_sim_time`?)",
    "dropped_in_window": "sets dropped over the window",
    "drop_ratio": "dropped / (dropped + mapped) over the window; WARN above `drop_warn_ratio`",
    "temporal_frames": "frames fused into the last published set (only with `temporal_window` > 1 or a method "
                       "with a memory, e.g. FocusBEV)",
    "temporal_note": "why the last set was mapped without its history ('' = it was not); same condition",
}
#: Keys the node adds to :func:`~bev_mapper_ros.stats.diagnostic_values`'s (``mapper_node``).
#: What each odometry problem kind (``bev_mapper_core.temporal.ODOMETRY_PROBLEMS``) means.
ODOMETRY_TEXTS = {
    "no_pose": "no pose at the set's stamp: mapped alone",
    "bad_pose": "not a finite rigid transform: mapped alone",
    "stamp_back": "an odometry stamp went back",
    "duplicate_stamp": "an odometry stamp repeated",
    "far_stamp": f"stamped more than {FAR_AHEAD_S:g} s ahead of the newest image: skipped",
    "frame_change": "the odometry's frame ids changed: memory reset",
    "jump": "a motion no vehicle makes (a velocity change over `max_accel_mps2` or a jump over "
            "`max_jump_m`): memory reset",
    "bad_covariance": "a NaN or infinite covariance (the pose is used)",
}
NODE_DIAGNOSTIC_KEYS: dict[str, str] = {
    "use_sim_time": "the node's `use_sim_time` (`true` / `false`)",
    "tf": "`tf2_ros` (TF is read), `not importable` (extrinsics from parameters, poses from `odom_topic`) or `off` "
          "(`use_tf` false)",
    "extrinsics_source": "per camera, where its extrinsic comes from: `tf` or `parameter` (`camera:source`, "
                         "comma-separated)",
    "pose_source": "where the last frame's ego pose came from: `odom` or `tf` ('' = no pose needed)",
    **{f"tf_errors_{kind}": f"TF problems of kind `{kind}` since start-up ({text}); none stops the node or reaches a map"
       for kind, text in TF_ERROR_TEXTS.items()},
    "tf_last_error": "the last TF problem",
    "clock_jumps_back": "times the node's clock went back since start-up (a bag looping with `/clock`): that set's "
                        "latency is not measured, never negative",
    "temporal_resets": "temporal memory resets (the fusion's or the method's own) since start-up: a pose jump, a "
                       "stamp going back, a gap (only with temporal fusion or FocusBEV)",
    "frames_without_pose": "sets mapped without their history since start-up: no usable ego pose",
    **{f"odometry_{kind}": f"odometry problems of kind `{kind}` since start-up ({text})"
       for kind, text in ODOMETRY_TEXTS.items()},
    "time_placement": "the `time_placement` parameter: `auto` (each camera placed with the ego pose of its own "
                      "stamp) or `off`",
    "placement_sets_placed": "sets whose cameras were placed at their own times since start-up",
    "placement_sets_static": "sets with ego poses whose every correction was under half the rounding step "
                             "(`time_placement_step_cells`): mapped with the calibrated rig",
    "placement_sets_without_pose": "sets without an ego pose at their stamp: every camera as calibrated",
    "placement_sets_warped": "of the placed sets, those of a method whose model holds the calibration "
                             "(Bi-Mapper, S2G2, FocusBEV): the moved cameras' images warped to their calibrated "
                             "pose by the ground plane instead",
    "placement_cameras_without_pose": "cameras without an ego pose at their own stamp: mapped as calibrated",
    "placement_stamp_jumps": "cameras stamped more than `time_placement_max_offset_s` from their set's stamp: "
                             "mapped as calibrated",
    "placement_rebuilds": "times the mapper's tables were rebuilt for a new rounded placement (IPM: only the "
                          "cameras that moved), or a camera's warp maps computed (learned methods)",
    "placement_max_offset_m": "the largest displacement a camera's correction gave a grid corner or the camera "
                              "since start-up (m)",
}


def _cell(text: str) -> str:
    """``text`` for a markdown table cell: ``|`` escaped, ``<`` / ``>`` as entities (not HTML tags)."""
    return text.replace("|", "\\|").replace("<", "&lt;").replace(">", "&gt;")


def parameter_table() -> str:
    """Markdown table of the node's parameters: name, type, default, run-time changeable, description."""
    lines = ["| parameter | type | default | runtime | description |", "|---|---|---|---|---|"]
    for name, (default, ptype, read_only, text) in PARAMETERS.items():
        owner = PARAM_FIELDS[name]
        lines.append(f"| `{name}` | {_TYPE_NAMES[ptype]} | `{_cell(_shown(name, default))}` | "
                     f"{'' if read_only else 'yes'} | {_cell(text)} (`{owner.owner.__name__}.{owner.field}`) |")
    lines.append(f"| `extrinsics.<camera>` | double array | the preset rig's | | {_cell(_EXTRINSICS_TEXT)} |")
    return "\n".join(lines)


def diagnostic_keys() -> list[str]:
    """Every key the node's ``/diagnostics`` status can carry, in the order it publishes them."""
    temporal = PARAM_FIELDS["temporal_window"].owner(window=2)
    cfg = NodeConfig(cameras=("front",), temporal=temporal)
    _, _, values = diagnostic_values(NodeStats(), 0.0, cfg, 0)
    return [*values, *NODE_DIAGNOSTIC_KEYS]


def diagnostics_table() -> str:
    """Markdown table of the ``/diagnostics`` keys and what each says."""
    keys = diagnostic_keys()
    texts = {**DIAGNOSTIC_KEYS, **NODE_DIAGNOSTIC_KEYS}
    missing = [k for k in keys if k not in texts]
    if missing:
        raise KeyError(f"diagnostics keys without a description in DIAGNOSTIC_KEYS: {missing}")
    lines = ["| key | value |", "|---|---|"]
    lines += [f"| `{k}` | {_cell(texts[k])} |" for k in keys]
    return "\n".join(lines)


#: README block name -> the function that renders it
TABLES = {"params": parameter_table, "diagnostics": diagnostics_table}


def markers(name: str) -> tuple[str, str]:
    """The README's begin and end markers of block ``name``."""
    return f"<!-- {name}:begin (generated: python -m bev_mapper_ros.reference --write) -->", f"<!-- {name}:end -->"


def readme_block(text: str, name: str) -> str | None:
    """The text between the markers of block ``name`` (None when the markers are missing)."""
    begin, end = markers(name)
    if begin not in text or end not in text:
        return None
    return text.split(begin, 1)[1].split(end, 1)[0].strip("\n")


def write_readme(path: pathlib.Path = README) -> None:
    """Replace every generated block of ``path`` with the table rendered now."""
    text = path.read_text()
    for name, render in TABLES.items():
        begin, end = markers(name)
        if readme_block(text, name) is None:
            raise SystemExit(f"error: {path} has no {begin} ... {end} block")
        head, rest = text.split(begin, 1)
        _, tail = rest.split(end, 1)
        text = f"{head}{begin}\n{render()}\n{end}{tail}"
    path.write_text(text)


def main(argv: list[str] | None = None) -> int:
    """Print the tables; ``--write``: also write them into README.md."""
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--write", action="store_true", help="write the tables into README.md between their markers")
    args = ap.parse_args(argv)
    for name, render in TABLES.items():
        print(f"{name}:\n{render()}\n")
    if args.write:
        write_readme()
    return 0


if __name__ == "__main__":
    sys.exit(main())
