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
    return [*environment, *(Node(**spec.launch_kwargs()) for spec in built.nodes), *_viewers(built)]


def _viewers(built: graph.Graph) -> list[Any]:
    """RViz 2 with the graph's config when rviz:=true and RViz 2 is installed; else a line saying so."""
    if built.rviz_config is None:
        return []
    from ament_index_python.packages import PackageNotFoundError, get_package_share_directory
    from launch.actions import LogInfo
    from launch_ros.actions import Node

    try:
        get_package_share_directory("rviz2")
    except (PackageNotFoundError, OSError):   # OSError: no ament index at all (AMENT_PREFIX_PATH unset)
        return [LogInfo(msg=f"rviz:=true, but RViz 2 (package rviz2) is not installed here; on a machine that has "
                            f"it: rviz2 -d {built.rviz_config}")]
    return [Node(package="rviz2", executable="rviz2", name="rviz2", arguments=["-d", built.rviz_config],
                 output="screen")]
