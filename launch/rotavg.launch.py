"""Launch ``rotavg_node`` with the package's parameter file.

Usage: ``ros2 launch rotavg_ros rotavg.launch.py [params_file:=/path/to.yaml]
[namespace:=/robot]``. Needs ``launch`` and ``launch_ros`` (not on PyPI; no test uses this).
"""

from __future__ import annotations

import os

from ament_index_python.packages import get_package_share_directory
from launch.actions import DeclareLaunchArgument
from launch.substitutions import LaunchConfiguration
from launch_ros.actions import Node

from launch import LaunchDescription


def generate_launch_description() -> LaunchDescription:
    default_params = os.path.join(
        get_package_share_directory("rotavg_ros"), "config", "rotavg.yaml"
    )
    return LaunchDescription([
        DeclareLaunchArgument(
            "params_file", default_value=default_params,
            description="Parameter file for rotavg_node",
        ),
        DeclareLaunchArgument("namespace", default_value="", description="Node namespace"),
        Node(
            package="rotavg_ros",
            executable="rotavg_node",
            name="rotavg_node",
            namespace=LaunchConfiguration("namespace"),
            parameters=[LaunchConfiguration("params_file")],
            output="screen",
            emulate_tty=True,
        ),
    ])
