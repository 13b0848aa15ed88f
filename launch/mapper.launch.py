"""Launch the BEV mapper node with a rig's parameter file.

    ros2 launch bev_mapper_ros mapper.launch.py rig:=surround6 [method:=ipm] [params_file:=...]
"""

import os

from ament_index_python.packages import get_package_share_directory
from launch.actions import DeclareLaunchArgument, OpaqueFunction
from launch.substitutions import LaunchConfiguration
from launch_ros.actions import Node

from launch import LaunchDescription


def _node(context):
    rig = LaunchConfiguration("rig").perform(context)
    params_file = LaunchConfiguration("params_file").perform(context)
    if not params_file:
        share = get_package_share_directory("bev_mapper_ros")
        params_file = os.path.join(share, "config", f"{rig}.yaml")
    overrides = {}
    method = LaunchConfiguration("method").perform(context)
    if method:
        overrides["method"] = method
    return [
        Node(
            package="bev_mapper_ros",
            executable="mapper_node",
            name="mapper_node",
            output="screen",
            parameters=[params_file, overrides],
        )
    ]


def generate_launch_description():
    return LaunchDescription(
        [
            DeclareLaunchArgument("rig", default_value="surround6", description="preset rig name"),
            DeclareLaunchArgument("params_file", default_value="", description="parameter file"),
            DeclareLaunchArgument("method", default_value="", description="override the method"),
            OpaqueFunction(function=_node),
        ]
    )
