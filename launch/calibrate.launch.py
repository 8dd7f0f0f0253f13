"""The calibration graph: camera, perception and the calibration node.
`ros2 launch touchroller_bringup calibrate.launch.py output_file:=my_roller.yaml`

Nodes, parameters and remappings come from `touchroller_bringup.graph` (the one definition,
shared with `touchroller scan`); this file only declares its arguments and builds launch_ros Nodes.
"""
from launch import LaunchDescription
from launch.actions import DeclareLaunchArgument, OpaqueFunction
from launch.substitutions import LaunchConfiguration
from launch_ros.actions import Node

from touchroller_bringup import graph

LAUNCH = "calibrate"


def _nodes(context, *args, **kwargs):
    values = {arg.name: LaunchConfiguration(arg.name).perform(context) for arg in graph.LAUNCH_ARGUMENTS[LAUNCH]}
    return [Node(**spec.launch_kwargs()) for spec in graph.build_graph(LAUNCH, values).nodes]


def generate_launch_description():
    arguments = []
    for arg in graph.LAUNCH_ARGUMENTS[LAUNCH]:
        options = {"description": arg.description}
        if arg.default is not None:
            options["default_value"] = arg.default
        if arg.choices is not None:
            options["choices"] = list(arg.choices)
        arguments.append(DeclareLaunchArgument(arg.name, **options))
    return LaunchDescription([*arguments, OpaqueFunction(function=_nodes)])
