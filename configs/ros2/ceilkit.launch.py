"""Launch ceilkit's ROS 2 node with the parameter file beside this one.

    ros2 launch ceilkit.launch.py device:=/dev/video0 rig:=rig.yaml site:=site.yaml \
        serial:=/dev/ttyUSB0 params:=my.params.yaml

``device``, ``rig``, ``site``, ``serial`` and ``method`` become ``ceilkit-ros2`` options
(empty: not given); ``params`` replaces the packaged ``ceilkit.params.yaml``; every
other ``ceilrun`` option goes in ``extra`` (``extra:="--start-pose 1,2,0 --status"``).
Needs a ROS 2 installation (``launch``, ``launch_ros``); ceilkit itself from pip.
"""

from pathlib import Path

from launch import LaunchDescription
from launch.actions import DeclareLaunchArgument, OpaqueFunction
from launch.substitutions import LaunchConfiguration
from launch_ros.actions import Node

PARAMS = str(Path(__file__).resolve().parent / "ceilkit.params.yaml")
OPTIONS = ("device", "rig", "site", "serial", "method")


def _node(context):
    args = []
    for name in OPTIONS:
        value = LaunchConfiguration(name).perform(context)
        if value:
            args += [f"--{name}", value]
    args += LaunchConfiguration("extra").perform(context).split()
    return [Node(executable="ceilkit-ros2", name="ceilkit", output="screen",
                 arguments=args,
                 parameters=[LaunchConfiguration("params").perform(context)])]


def generate_launch_description():
    return LaunchDescription(
        [DeclareLaunchArgument(name, default_value="") for name in OPTIONS]
        + [DeclareLaunchArgument("extra", default_value=""),
           DeclareLaunchArgument("params", default_value=PARAMS),
           OpaqueFunction(function=_node)])
