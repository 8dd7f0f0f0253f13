"""The calibration graph: camera, perception and the calibration node.
`ros2 launch touchroller_bringup calibrate.launch.py output_file:=my_roller.yaml`

Nodes, parameters and remappings come from `touchroller_bringup.graph` (the one definition,
shared with `touchroller scan`); this file only declares its arguments and builds launch_ros Nodes
(after the environment the graph asks for: `fastdds_profile:=shm` selects the shared-memory Fast DDS profile).
"""
from launch import LaunchDescription
from launch.actions import DeclareLaunchArgument, OpaqueFunction, SetEnvironmentVariable
from launch.substitutions import LaunchConfiguration
from launch_ros.actions import Node

from touchroller_bringup import graph

LAUNCH = "calibrate"


def _nodes(context, *args, **kwargs):
    values = {arg.name: LaunchConfiguration(arg.name).perform(context) for arg in graph.LAUNCH_ARGUMENTS[LAUNCH]}
    built = graph.build_graph(LAUNCH, values)
    # the environment first (e.g. fastdds_profile:=shm), so every node's process starts with it
    environment = [SetEnvironmentVariable(name, value) for name, value in built.environment.items()]
    return [*environment, *(Node(**spec.launch_kwargs()) for spec in built.nodes)]


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
