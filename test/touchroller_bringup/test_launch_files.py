"""The launch files agree with the graph module.

Each launch file is (1) parsed with `ast` (it hands its LAUNCH to `touchroller_bringup.launching`, and
spells no node by hand) and (2) imported with stub `launch`/`launch_ros` modules injected into
sys.modules only inside the test, then its arguments and the Nodes it builds are compared with
`touchroller_bringup.graph`. Where the real `launch` imports (a ROS 2 machine, or the venv with
ros-extras installed), the description is also built and its actions inspected.
"""
from __future__ import annotations

import ast
import importlib.util
import sys
import types
from pathlib import Path

import pytest

from touchroller_bringup import graph

LAUNCH_DIR = Path(__file__).resolve().parents[2] / "launch"
LAUNCH_FILES = sorted(LAUNCH_DIR.glob("*.launch.py"))


def test_one_launch_file_per_graph_launch():
    assert {p.name.removesuffix(".launch.py") for p in LAUNCH_FILES} == set(graph.LAUNCH_ARGUMENTS)


@pytest.mark.parametrize("path", LAUNCH_FILES, ids=lambda p: p.name)
def test_launch_file_reads_everything_from_the_graph(path):
    tree = ast.parse(path.read_text())
    constants = {node.targets[0].id: node.value.value for node in tree.body
                 if isinstance(node, ast.Assign) and isinstance(node.value, ast.Constant)}
    assert constants.get("LAUNCH") == path.name.removesuffix(".launch.py")
    imported = {(n.module, alias.name) for n in ast.walk(tree) if isinstance(n, ast.ImportFrom) for alias in n.names}
    assert imported == {("touchroller_bringup.launching", "launch_description")}
    generate = next(n for n in tree.body if isinstance(n, ast.FunctionDef) and n.name == "generate_launch_description")
    assert ast.unparse(generate.body[-1]) == "return launch_description(LAUNCH)"
    # No node is spelled out by hand: no executable/package string literals in the launch file.
    literals = {n.value for n in ast.walk(tree) if isinstance(n, ast.Constant) and isinstance(n.value, str)}
    executables = {role[0] for role in (graph.CAMERA, graph.PERCEPTION, graph.SWEEP, graph.CALIBRATION)}
    assert not literals & executables


# -- stub launch/launch_ros ----------------------------------------------------------------------

class _Recorder:
    def __init__(self, *args, **kwargs) -> None:
        self.args, self.kwargs = args, kwargs


class FakeContext:
    def __init__(self, values: dict[str, str]) -> None:
        self.values = values


def _stub_modules(monkeypatch):
    class LaunchConfiguration(_Recorder):
        def perform(self, context: FakeContext) -> str:
            return context.values[self.args[0]]

    modules = {
        "launch": types.ModuleType("launch"),
        "launch.actions": types.ModuleType("launch.actions"),
        "launch.substitutions": types.ModuleType("launch.substitutions"),
        "launch_ros": types.ModuleType("launch_ros"),
        "launch_ros.actions": types.ModuleType("launch_ros.actions"),
    }
    modules["launch"].LaunchDescription = type("LaunchDescription", (_Recorder,), {})
    modules["launch.actions"].DeclareLaunchArgument = type("DeclareLaunchArgument", (_Recorder,), {})
    modules["launch.actions"].OpaqueFunction = type("OpaqueFunction", (_Recorder,), {})
    modules["launch.actions"].SetEnvironmentVariable = type("SetEnvironmentVariable", (_Recorder,), {})
    modules["launch.actions"].LogInfo = type("LogInfo", (_Recorder,), {})
    modules["launch.substitutions"].LaunchConfiguration = LaunchConfiguration
    modules["launch_ros.actions"].Node = type("Node", (_Recorder,), {})
    for name, module in modules.items():
        monkeypatch.setitem(sys.modules, name, module)


def _load(path: Path, monkeypatch):
    _stub_modules(monkeypatch)
    spec = importlib.util.spec_from_file_location(f"_launch_{path.stem.replace('.', '_')}", path)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def _example_values(launch: str, tmp_path: Path) -> dict[str, str]:
    """Non-default values for every argument, so each one visibly reaches the nodes."""
    params = tmp_path / "extra.yaml"
    params.write_text("/**:\n  ros__parameters:\n    sweep.depth: 0.002\n")
    calibration = tmp_path / "cal.yaml"
    calibration.write_text("/**:\n  ros__parameters:\n    extrinsics.theta: 0.01\n")
    values = {"params_file": str(params), "calibration_file": str(calibration), "fastdds_profile": "shm",
              "namespace": "left"}
    if launch == "scan":
        values |= {"use_sim": "false", "camera_device": "/dev/v4l/by-id/usb-cam", "robot_ip": "127.0.0.1",
                   "arm_backend": "ur_driver",
                   "sweep_speed": "0.02", "sweep_length": "0.08", "area": "0.4,0.0,0.1,0.08",
                   "scene": "surface_mapping", "map_file": str(tmp_path / "roll.png"), "rviz": "true",
                   "inspect": "false"}
    elif launch == "calibrate":
        values |= {"use_sim": "true", "camera_device": "", "output_file": str(tmp_path / "out.yaml"),
                   "scene": "calibration_hemispheres"}
    else:
        values |= {"bag": str(tmp_path / "bag"), "rate": "2.0", "loop": "true"}
    return values


@pytest.mark.parametrize("launch", sorted(graph.LAUNCH_ARGUMENTS))
def test_the_examples_cover_every_argument(launch, tmp_path):
    assert set(_example_values(launch, tmp_path)) == {arg.name for arg in graph.LAUNCH_ARGUMENTS[launch]}


@pytest.mark.parametrize("path", LAUNCH_FILES, ids=lambda p: p.name)
def test_stubbed_launch_matches_the_graph(path, monkeypatch, tmp_path):
    launch = path.name.removesuffix(".launch.py")
    module = _load(path, monkeypatch)
    description = module.generate_launch_description()
    actions = description.args[0]
    declared = [a for a in actions if type(a).__name__ == "DeclareLaunchArgument"]
    assert [a.args[0] for a in declared] == [arg.name for arg in graph.LAUNCH_ARGUMENTS[launch]]
    for action, arg in zip(declared, graph.LAUNCH_ARGUMENTS[launch], strict=True):
        assert action.kwargs["description"] == arg.description and arg.description
        assert action.kwargs.get("default_value") == arg.default
        assert action.kwargs.get("choices") == (list(arg.choices) if arg.choices else None)

    opaque = [a for a in actions if type(a).__name__ == "OpaqueFunction"]
    assert len(opaque) == 1
    values = _example_values(launch, tmp_path)
    built = opaque[0].kwargs["function"](FakeContext(values), *opaque[0].kwargs.get("args", ()))
    expected = graph.build_graph(launch, values)
    # the environment (the Fast DDS profile) is set before any node starts
    environment = [a for a in built if type(a).__name__ == "SetEnvironmentVariable"]
    assert built[:len(environment)] == environment
    assert {a.args[0]: a.args[1] for a in environment} == expected.environment
    assert "FASTDDS_DEFAULT_PROFILES_FILE" in expected.environment
    nodes = built[len(environment):len(environment) + len(expected.nodes)]
    assert [n.kwargs for n in nodes] == [spec.launch_kwargs() for spec in expected.nodes]
    viewers = built[len(environment) + len(expected.nodes):]
    assert [type(a).__name__ for a in viewers] == (["LogInfo"] if launch == "scan" else [])   # no RViz 2 here
    assert {n.kwargs["namespace"] for n in nodes} == {"/left"}
    for node in nodes:  # the user's files come after the defaults, in order
        assert node.kwargs["parameters"][-3:-1] == [str(Path(values["params_file"]).resolve()),
                                                    str(Path(values["calibration_file"]).resolve())]


@pytest.mark.parametrize("path", LAUNCH_FILES, ids=lambda p: p.name)
def test_with_real_launch(path, ros_tools):
    from launch import LaunchContext  # noqa: I001 (ruff takes launch/ for first-party)
    from launch.actions import DeclareLaunchArgument, OpaqueFunction

    spec = importlib.util.spec_from_file_location(f"_real_{path.stem.replace('.', '_')}", path)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    launch = path.name.removesuffix(".launch.py")
    description = module.generate_launch_description()
    names = [a.name for a in description.entities if isinstance(a, DeclareLaunchArgument)]
    assert names == [arg.name for arg in graph.LAUNCH_ARGUMENTS[launch]]
    context = LaunchContext()
    for arg in graph.LAUNCH_ARGUMENTS[launch]:
        context.launch_configurations[arg.name] = arg.default if arg.default is not None else "/tmp/bag"
    opaque = next(a for a in description.entities if isinstance(a, OpaqueFunction))
    from launch_ros.actions import Node

    nodes = [a for a in opaque.execute(context) if isinstance(a, Node)]
    assert len(nodes) == len(graph.build_graph(launch, dict(context.launch_configurations)).nodes)


@pytest.mark.parametrize("installed", [True, False])
def test_rviz_true_opens_the_shipped_config_where_rviz_is_installed(monkeypatch, tmp_path, installed):
    import ament_index_python.packages as packages

    path = LAUNCH_DIR / "scan.launch.py"
    module = _load(path, monkeypatch)
    if installed:
        real = packages.get_package_share_directory
        monkeypatch.setattr(packages, "get_package_share_directory",
                            lambda name, *a: str(tmp_path) if name == "rviz2" else real(name, *a))
    opaque = next(a for a in module.generate_launch_description().args[0] if type(a).__name__ == "OpaqueFunction")
    values = {arg.name: arg.default for arg in graph.LAUNCH_ARGUMENTS["scan"]} | {"rviz": "true"}
    built = opaque.kwargs["function"](FakeContext(values), *opaque.kwargs.get("args", ()))
    config = graph.build_graph("scan", values).rviz_config
    assert config and Path(config).is_file()
    last = built[-1]
    if installed:
        assert last.kwargs["package"] == "rviz2" and last.kwargs["arguments"] == ["-d", config]
    else:
        assert type(last).__name__ == "LogInfo" and config in last.kwargs["msg"]
    values["rviz"] = "false"
    assert all(type(a).__name__ != "LogInfo" and a.kwargs.get("package") != "rviz2"
               for a in opaque.kwargs["function"](FakeContext(values), *opaque.kwargs.get("args", ())))
