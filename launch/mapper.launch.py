"""Launch the BEV mapper node with a rig's parameter file.

    ros2 launch bev_mapper_ros mapper.launch.py rig:=surround6 [use_sim_time:=true]
        [params_file:=FILE] [namespace:=NS] [method:=ipm] [input_kind:=labels|rgb]

``params_file`` '' = the installed ``config/<rig>.yaml``; ``method`` / ``input_kind`` '' = the
file's. Topics are remapped as with any launch_ros Node: include this file and add
``SetRemap`` actions, or run the node with ``--ros-args -r from:=to``. A launch that cannot
start says why in one line (``[ERROR] [launch]: ...``).
"""

import os

from launch.actions import DeclareLaunchArgument, OpaqueFunction
from launch.substitutions import LaunchConfiguration

from launch import LaunchDescription

try:
    from launch_ros.actions import Node
except ImportError as exc:  # e.g. composition_interfaces missing: launch_ros cannot load
    raise RuntimeError(f"launch_ros is not usable here ({exc}); scripts/setup_venv.sh builds "
                       "composition_interfaces into .venv, or source a ROS 2 distribution") from None

ARGUMENTS = (
    ("rig", "surround6", "preset rig: surround6, cam2bev4 or front1 (selects config/<rig>.yaml)"),
    ("params_file", "", "parameter file ('' = the installed config/<rig>.yaml)"),
    ("use_sim_time", "false", "true: follow /clock (a bag played with --clock)"),
    ("namespace", "", "namespace of the node (and of its relative topic names)"),
    ("method", "", "mapping method ('' = the parameter file's)"),
    ("input_kind", "", "labels or rgb ('' = the parameter file's)"),
)


def _node(context):
    def arg(name):
        return LaunchConfiguration(name).perform(context).strip()

    rig, params_file = arg("rig"), arg("params_file")
    if not params_file:
        from ament_index_python.packages import get_package_share_directory

        params_file = os.path.join(get_package_share_directory("bev_mapper_ros"), "config", f"{rig}.yaml")
        if not os.path.isfile(params_file):
            shipped = sorted(f[:-5] for f in os.listdir(os.path.dirname(params_file)) if f.endswith(".yaml"))
            raise RuntimeError(f"rig {rig!r} has no installed parameter file {params_file}; "
                               f"choose one of {shipped} or give params_file:=FILE")
    elif not os.path.isfile(params_file):
        raise RuntimeError(f"params_file {params_file!r} does not exist")
    sim = arg("use_sim_time").lower()
    if sim not in ("true", "false"):
        raise RuntimeError(f"use_sim_time must be true or false, got {sim!r}")
    overrides = {"use_sim_time": sim == "true"}
    for name in ("method", "input_kind"):
        if arg(name):
            overrides[name] = arg(name)
    return [
        Node(
            package="bev_mapper_ros",
            executable="mapper_node",
            name="mapper_node",
            namespace=arg("namespace"),
            output="screen",
            parameters=[params_file, overrides],
        )
    ]


def generate_launch_description():
    return LaunchDescription(
        [DeclareLaunchArgument(name, default_value=default, description=text) for name, default, text in ARGUMENTS]
        + [OpaqueFunction(function=_node)]
    )
