"""The one launch helper: a graph of `touchroller_bringup.graph` as a `launch` LaunchDescription.

Every launch file is `generate_launch_description = lambda: launch_description(LAUNCH)` in effect: it
declares `graph.LAUNCH_ARGUMENTS[LAUNCH]` (name, default, description, choices) and, once the arguments
are known, turns `graph.build_graph(LAUNCH, values)` into `SetEnvironmentVariable` actions (the graph's
environment, e.g. the Fast DDS profile, so every node's process starts with it) followed by launch_ros
`Node` actions (`NodeSpec.launch_kwargs`: package, executable, name, namespace, parameters, remappings).

`launch` and `launch_ros` are imported when a description is built, so this module imports without them.
"""
from __future__ import annotations

from typing import Any

from touchroller_bringup import graph


def launch_description(launch: str) -> Any:
    """The LaunchDescription of graph `launch` ("scan", "calibrate", "replay")."""
    from launch import LaunchDescription
    from launch.actions import DeclareLaunchArgument, OpaqueFunction

    arguments = []
    for arg in graph.LAUNCH_ARGUMENTS[launch]:
        options: dict[str, Any] = {"description": arg.description}
        if arg.default is not None:
            options["default_value"] = arg.default
        if arg.choices is not None:
            options["choices"] = list(arg.choices)
        arguments.append(DeclareLaunchArgument(arg.name, **options))
    return LaunchDescription([*arguments, OpaqueFunction(function=_actions, args=[launch])])


def _actions(context: Any, launch: str) -> list[Any]:
    """The environment and the nodes of graph `launch` for the launch arguments' values in `context`."""
    from launch.actions import SetEnvironmentVariable
    from launch.substitutions import LaunchConfiguration
    from launch_ros.actions import Node

    values = {arg.name: LaunchConfiguration(arg.name).perform(context) for arg in graph.LAUNCH_ARGUMENTS[launch]}
    built = graph.build_graph(launch, values)
    environment = [SetEnvironmentVariable(name, value) for name, value in built.environment.items()]
    return [*environment, *(Node(**spec.launch_kwargs()) for spec in built.nodes)]
