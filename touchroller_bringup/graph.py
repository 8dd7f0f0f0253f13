"""The ONE definition of the TouchRoller node graph: nodes, parameters, remappings, launch arguments.

Three consumers read it and nothing else:
- `launch/{scan,calibrate,replay}.launch.py` declare `LAUNCH_ARGUMENTS[<launch>]` and turn
  `build_graph(<launch>, values)` into `SetEnvironmentVariable` actions (`Graph.environment`, e.g. the
  Fast DDS profile) followed by launch_ros `Node` actions (`NodeSpec.launch_kwargs`);
- `touchroller scan` instantiates the same `NodeSpec`s in one process (`NodeSpec.node_kwargs`,
  `NodeSpec.load_class`), passing params files exactly as launch_ros would (`--params-file`, then
  the graph's own parameters, then the user's `name:=value` overrides, later ones winning);
- the tests compare the two.

Parameter files always start with the package defaults (`config/touchroller.yaml`, `config/scan.yaml`),
then `params_file`, then `calibration_file`, so a calibration overrides the defaults. Arguments left
empty (`""`) leave the value to the params files. No rclpy or launch import here.
"""
from __future__ import annotations

import importlib
import math
import os
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from touchroller_bringup import names
from touchroller_driver.paths import config_path

PACKAGE = "touchroller_bringup"
DEFAULT_PARAMS_FILES = ("touchroller.yaml", "scan.yaml")  # under config/
# fastdds_profile:=<name> -> config/<file>
FASTDDS_PROFILES = {"shm_udp": "fastdds_shm_udp.xml", "shm": "fastdds_shm.xml"}
# fastdds_profile:=auto (the default): shm_udp unless the environment already names a profile
AUTO_PROFILE = "shm_udp"
# Fast DDS 3 (Kilted on) reads FASTDDS_..., Fast DDS 2 (Humble, Iron, Jazzy) only FASTRTPS_... (which
# Fast DDS 3's RMW still reads but warns about), so the second is set only for those distributions.
FASTDDS_ENVIRONMENT = ("FASTDDS_DEFAULT_PROFILES_FILE", "FASTRTPS_DEFAULT_PROFILES_FILE")
FAST_DDS_2_DISTROS = ("humble", "iron", "jazzy")


class GraphError(ValueError):
    """A launch argument or graph description is invalid (reported as one line)."""


@dataclass(frozen=True)
class LaunchArgument:
    name: str
    default: str | None  # None: required
    description: str
    choices: tuple[str, ...] | None = None


@dataclass(frozen=True)
class NodeSpec:
    """One node of the graph: what launch_ros needs, and what an in-process runner needs."""

    key: str          # short role name: camera, perception, sweep, calibration
    executable: str   # console script in setup.py
    name: str         # ROS node name
    target: str       # "module:Class" of the rclpy Node subclass (takes **node_kwargs)
    parameters: Mapping[str, Any] = field(default_factory=dict)  # on top of the params files
    remappings: tuple[tuple[str, str], ...] = ()
    params_files: tuple[str, ...] = ()
    package: str = PACKAGE
    namespace: str = names.DEFAULT_NAMESPACE   # without slashes; "" is the root

    @property
    def full_name(self) -> str:
        """The node's fully qualified name: /touchroller/sweep."""
        return names.topic(self.name, self.namespace)

    def launch_kwargs(self) -> dict[str, Any]:
        """Keyword arguments for `launch_ros.actions.Node`."""
        return {
            "package": self.package,
            "executable": self.executable,
            "name": self.name,
            "namespace": f"/{self.namespace}",
            "parameters": [*self.params_files, dict(self.parameters)],
            "remappings": list(self.remappings),
            "output": "screen",
        }

    def node_kwargs(self, overrides: Mapping[str, Any] | None = None) -> dict[str, Any]:
        """`rclpy.node.Node` keyword arguments with the same effect as `launch_kwargs` in a launch."""
        from rclpy.parameter import Parameter

        cli_args = ["--ros-args", "-r", f"__node:={self.name}", "-r", f"__ns:=/{self.namespace}"]
        for path in self.params_files:
            cli_args += ["--params-file", str(path)]
        for source, target in self.remappings:
            cli_args += ["-r", f"{source}:={target}"]
        values = {**self.parameters, **(overrides or {})}
        return {"cli_args": cli_args,
                "parameter_overrides": [Parameter(name, value=value) for name, value in values.items()]}

    def load_class(self) -> type:
        """The node class; GraphError (one line) if its module has not landed or fails to import."""
        module_name, _, class_name = self.target.partition(":")
        try:
            module = importlib.import_module(module_name)
        except (ImportError, SyntaxError) as exc:  # not landed, or broken mid-edit: one line either way
            raise GraphError(f"the {self.key} node ({self.target}) is not available: "
                             f"{type(exc).__name__}: {exc}") from exc
        try:
            return getattr(module, class_name)
        except AttributeError:
            raise GraphError(f"the {self.key} node class {self.target} does not exist") from None


@dataclass(frozen=True)
class Graph:
    launch: str
    nodes: tuple[NodeSpec, ...]
    arguments: Mapping[str, str]
    environment: Mapping[str, str] = field(default_factory=dict)  # set for every node's process
    rviz_config: str | None = None   # rviz:=true: the RViz 2 config to open beside the graph

    def node(self, key: str) -> NodeSpec:
        for spec in self.nodes:
            if spec.key == key:
                return spec
        raise KeyError(key)

    @property
    def keys(self) -> tuple[str, ...]:
        return tuple(spec.key for spec in self.nodes)

    @property
    def namespace(self) -> str:
        """The namespace of every node (without slashes; "" is the root)."""
        return names.check_namespace(self.arguments["namespace"])


_BOOL = ("true", "false")
_COMMON = (
    LaunchArgument("namespace", names.DEFAULT_NAMESPACE, "ROS namespace of every node, topic and service "
                   "(e.g. left: /left/image_raw, /left/sweep/start); frame ids take the prefix left/ "
                   "(none in the default namespace)"),
    LaunchArgument("params_file", "", "Extra ROS 2 params YAML (/**: ros__parameters:) applied to every "
                   "node after the package defaults (config/touchroller.yaml, config/scan.yaml)"),
    LaunchArgument("calibration_file", "", "Calibration YAML (camera.*, extrinsics.*) applied after "
                   "params_file; empty: the geometry in the params files"),
    LaunchArgument("fastdds_profile", "auto", "Fast DDS XML profile for every node (sets FASTDDS_DEFAULT_"
                   "PROFILES_FILE, and FASTRTPS_... on Humble/Jazzy): 'shm_udp' = config/fastdds_shm_udp.xml (shared "
                   "memory sized for whole images on this host, UDP to others), 'shm' = config/fastdds_shm.xml (this "
                   "host only), a path, or empty for the environment's; 'auto': shm_udp unless the environment "
                   "already sets a profile"),
)
LAUNCH_ARGUMENTS: dict[str, tuple[LaunchArgument, ...]] = {
    "scan": (
        LaunchArgument("use_sim", "true", "Simulated sensor and arm (true) or a V4L2 camera and a UR5 (false)",
                       _BOOL),
        LaunchArgument("camera_device", "", "V4L2 device when use_sim is false: an index or a stable "
                       "/dev/v4l/by-id/... path; empty: the params files (default 0)"),
        LaunchArgument("robot_ip", "", "UR controller IP (ur_rtde) when use_sim is false; empty: the params files"),
        LaunchArgument("arm_backend", "ur_rtde", "The arm when use_sim is false: ur_rtde (ur_rtde's own control "
                       "script, robot_ip) or ur_driver (URScript through a running ur_robot_driver, docs/ur5.md)",
                       ("ur_rtde", "ur_driver")),
        *_COMMON,
        LaunchArgument("sweep_speed", "", "Roll speed in m/s; empty: the params files (0.011, the paper's 10 s)"),
        LaunchArgument("sweep_length", "", "Roll length in m; empty: the params files (0.11)"),
        LaunchArgument("area", "", "Rectangle to cover, 'x,y,length,width' in m in the robot's base frame "
                       "(corner, length along sweep.direction, width along the roller's axis): a raster of "
                       "passes; empty: the params files (one roll of sweep_length)"),
        LaunchArgument("scene", "surface_mapping", "Simulator scene when use_sim is true"),
        LaunchArgument("map_file", "", "PNG the perception node writes the finished map to when the roll "
                       "ends (perception map.save_path); empty: not saved (touchroller scan writes map.png anyway)"),
        LaunchArgument("rviz", "false", "Open RViz 2 with config/rviz/touchroller.rviz (robot TF, contacts, the "
                       "tactile image and map) where RViz 2 is installed", _BOOL),
        LaunchArgument("inspect", "auto", "Defects in the world map (docs/inspection.md): the perception node's live "
                       "`findings` markers (findings.enabled) and, with touchroller scan, findings.csv + findings.png "
                       "beside map.png when the sweep ends; auto: live markers on, the files for a raster (area)",
                       ("auto", "true", "false")),
    ),
    "calibrate": (
        LaunchArgument("use_sim", "true", "Simulated calibration scene (true) or a V4L2 camera (false)", _BOOL),
        LaunchArgument("camera_device", "", "V4L2 device when use_sim is false; empty: the params files"),
        *_COMMON,
        LaunchArgument("output_file", "touchroller_calibration.yaml",
                       "Where the calibration node writes the solved calibration YAML"),
        LaunchArgument("scene", "calibration_hemispheres:by_hand", "Simulator scene (NAME or NAME:VARIANT) when "
                       "use_sim is true, played on a loop; the by_hand variants hold each press (chessboard view) "
                       "long enough to call ~/capture by hand"),
    ),
    "replay": (
        LaunchArgument("bag", None, "rosbag2 folder (sqlite3 or MCAP) with {names.topic(names.IMAGE)}"),
        LaunchArgument("rate", "1.0", "Playback rate: 1 real time, 0 as fast as possible"),
        LaunchArgument("loop", "false", "Restart the recording at its end", _BOOL),
        *_COMMON,
    ),
}


def replay_perception(namespace: str) -> dict[str, Any]:
    """Replaying is offline work: perception takes every frame of the recording (a reliable queue instead
    of the live graph's "newest frame only"), so it finds what `touchroller contacts` finds in the bag."""
    return {names.qos_override(names.IMAGE, namespace, "subscription", "reliability"): "reliable",
            names.qos_override(names.IMAGE, namespace, "subscription", "depth"): 100}


CAMERA = ("camera_node", names.CAMERA_NODE, "touchroller_bringup.nodes.camera_node:CameraNode")
PERCEPTION = ("perception_node", names.PERCEPTION_NODE, "touchroller_bringup.nodes.perception_node:PerceptionNode")
SWEEP = ("sweep_node", names.SWEEP_NODE, "touchroller_bringup.nodes.sweep_node:SweepNode")
CALIBRATION = ("calibration_node", names.CALIBRATION_NODE, "touchroller_bringup.nodes.calibration_node:CalibrationNode")


def resolve_arguments(launch: str, values: Mapping[str, str] | None = None) -> dict[str, str]:
    """All of `launch`'s arguments as strings: given values over defaults; GraphError on unknown,
    missing or out-of-choice values."""
    if launch not in LAUNCH_ARGUMENTS:
        raise GraphError(f"unknown launch {launch!r}; expected one of {', '.join(LAUNCH_ARGUMENTS)}")
    declared = {arg.name: arg for arg in LAUNCH_ARGUMENTS[launch]}
    values = dict(values or {})
    unknown = sorted(set(values) - set(declared))
    if unknown:
        raise GraphError(f"unknown {launch} argument(s) {', '.join(unknown)}; "
                         f"expected one of {', '.join(declared)}")
    resolved = {}
    for name, arg in declared.items():
        value = str(values.get(name, arg.default if arg.default is not None else "")).strip()
        if arg.default is None and not value:
            raise GraphError(f"{launch}: argument {name} is required ({arg.description})")
        if arg.choices is not None and value.lower() not in arg.choices:
            raise GraphError(f"{launch}: {name}:={value} must be one of {', '.join(arg.choices)}")
        resolved[name] = value.lower() if arg.choices is not None else value
    return resolved


def _positive_float(launch: str, name: str, text: str, *, allow_zero: bool = False) -> float:
    try:
        value = float(text)
    except ValueError:
        raise GraphError(f"{launch}: {name}:={text} is not a number") from None
    if not math.isfinite(value) or value < 0 or (value == 0 and not allow_zero):
        raise GraphError(f"{launch}: {name}:={text} must be a finite number {'>=' if allow_zero else '>'} 0")
    return value


def _params_files(args: Mapping[str, str], extra: Sequence[str | Path] = ()) -> tuple[str, ...]:
    files = [str(config_path(name)) for name in DEFAULT_PARAMS_FILES if config_path(name).is_file()]
    given = [("params file", p) for p in extra]
    given += [(key, args[key]) for key in ("params_file", "calibration_file") if args.get(key)]
    for what, name in given:
        path = Path(name).expanduser()
        if not path.is_file():
            raise GraphError(f"{what} {name} does not exist")
        files.append(str(path.resolve()))
    return tuple(files)


def _environment(args: Mapping[str, str]) -> dict[str, str]:
    choice = args.get("fastdds_profile", "")
    if choice == "auto":
        given = any(os.environ.get(name) for name in FASTDDS_ENVIRONMENT)
        choice = "" if given else AUTO_PROFILE
    if not choice:
        return {}
    path = config_path(FASTDDS_PROFILES[choice]) if choice in FASTDDS_PROFILES else Path(choice).expanduser()
    if not path.is_file():
        raise GraphError(f"fastdds_profile {choice}: {path} does not exist "
                         f"(give {' or '.join(FASTDDS_PROFILES)} or the path of a Fast DDS XML profile)")
    fast_dds_2 = os.environ.get("ROS_DISTRO", "").strip().lower() in FAST_DDS_2_DISTROS
    return dict.fromkeys(FASTDDS_ENVIRONMENT if fast_dds_2 else FASTDDS_ENVIRONMENT[:1], str(path.resolve()))


def _area(launch: str, text: str) -> list[float]:
    parts = [p for p in text.replace(" ", ",").split(",") if p]
    try:
        values = [float(p) for p in parts]
    except ValueError:
        values = []
    if len(values) != 4 or not all(math.isfinite(v) for v in values) or values[2] <= 0 or values[3] < 0:
        raise GraphError(f"{launch}: area:={text} must be 'x,y,length,width' in m (length > 0, width >= 0)")
    return values


def _scene_intrinsics(launch: str, scene: str) -> dict[str, Any]:
    """The simulated camera's intrinsics and cylinder (not theta and d: those are calibrated)."""
    from touchroller_driver.sim import load_scene  # lazy: only the simulated calibrate graph needs it

    try:
        params = load_scene(scene).camera.to_params()
    except (OSError, ValueError) as exc:
        raise GraphError(f"{launch}: scene {scene}: {exc}") from None
    return {k: v for k, v in params.items() if k.startswith(("camera.", "cylinder."))}


def build_graph(launch: str, values: Mapping[str, str] | None = None,
                extra_params_files: Sequence[str | Path] = ()) -> Graph:
    """The nodes of `launch` ("scan", "calibrate", "replay") for these launch-argument values.

    `extra_params_files` (e.g. `touchroller scan a.yaml b.yaml`) come after the package defaults and
    before `params_file` and `calibration_file`.
    """
    args = resolve_arguments(launch, values)
    files = _params_files(args, extra_params_files)
    use_sim = args.get("use_sim") == "true"
    try:
        namespace = names.check_namespace(args["namespace"])
    except names.InvalidName as exc:
        raise GraphError(f"{launch}: {exc}") from None

    def spec(role: tuple[str, str, str], key: str, parameters: Mapping[str, Any],
             remappings: Sequence[tuple[str, str]] = ()) -> NodeSpec:
        executable, name, target = role
        return NodeSpec(key, executable, name, target, dict(parameters), tuple(remappings), files,
                        namespace=namespace)

    def camera_parameters(on_arm: bool = False) -> dict[str, Any]:
        if use_sim and on_arm:   # in scan, the simulated sensor is on the sweep node's simulated arm (TF, one clock)
            return {"source": "sim", "scene": args["scene"], "sim.motion": "arm"}
        if use_sim:   # calibrate: the scene's presses over and over, for captures by hand
            return {"source": "sim", "scene": args["scene"], "sim.motion": "scene", "loop": True}
        params: dict[str, Any] = {"source": "v4l2"}
        if args.get("camera_device"):
            params["device"] = args["camera_device"]   # an index or a path, as a string
        return params

    if launch == "scan":
        sweep: dict[str, Any] = {"use_sim": use_sim}
        if args["robot_ip"]:
            sweep["robot_ip"] = args["robot_ip"]
        if not use_sim:
            sweep["arm.backend"] = args["arm_backend"]
        if args["sweep_speed"]:
            sweep["sweep.speed"] = _positive_float(launch, "sweep_speed", args["sweep_speed"])
        if args["sweep_length"]:
            sweep["sweep.length"] = _positive_float(launch, "sweep_length", args["sweep_length"])
        if args["area"]:
            sweep["sweep.area"] = _area(launch, args["area"])
        perception: dict[str, Any] = {}
        if args["inspect"] != "auto":   # the live findings; auto: the params files' (on)
            perception["findings.enabled"] = args["inspect"] == "true"
        if args["map_file"]:
            perception["map.save_path"] = str(Path(args["map_file"]).expanduser())
        camera = camera_parameters(on_arm=True)
        prefix = names.frame_prefix(namespace)
        if use_sim and prefix:
            # the robot's frames are the driver's names (no prefix): here the driver is our simulated arm, and
            # a second one in another namespace needs a flange of its own beside the shared base
            sweep["arm.tool_frame"] = names.frame(names.TOOL_FRAME, prefix)
        if use_sim:
            # One simulated clock: the sweep node's simulated arm publishes it on /clock and every node
            # runs on it. Perception takes every frame (as in replay): the simulated scan is deterministic.
            perception.update(replay_perception(namespace))
            for params in (camera, perception, sweep):
                params["use_sim_time"] = True
        nodes = (spec(CAMERA, "camera", camera),
                 spec(PERCEPTION, "perception", perception),
                 spec(SWEEP, "sweep", sweep))
    elif launch == "calibrate":
        # simulated: the nodes start from the simulated camera's intrinsics, as they would from a real
        # camera's chessboard calibration (a user's calibration_file wins); the defaults' 500 px would put
        # the scale error into d
        intrinsics = _scene_intrinsics(launch, args["scene"]) if use_sim and not args.get("calibration_file") else {}
        # the camera node is the graph's one publisher of camera_info: it starts from the same intrinsics and
        # receives the solved ones through its ~/set_camera_info
        nodes = (spec(CAMERA, "camera", {**camera_parameters(), **intrinsics}),
                 spec(PERCEPTION, "perception", dict(intrinsics)),
                 spec(CALIBRATION, "calibration", {**intrinsics, "output_path": args["output_file"],
                                                   "perception_node": names.PERCEPTION_NODE,
                                                   "camera_node": names.CAMERA_NODE}))
    else:  # replay: a recording through the camera node into perception
        camera = {"source": "bag", "bag_path": args["bag"],
                  "rate": _positive_float(launch, "rate", args["rate"], allow_zero=True),
                  "loop": args["loop"] == "true",
                  "wait_for_subscribers": 1}   # perception: it must see the first (reference) frames
        nodes = (spec(CAMERA, "camera", camera), spec(PERCEPTION, "perception", replay_perception(namespace)))
    rviz = str(config_path("rviz", "touchroller.rviz")) if args.get("rviz") == "true" else None
    return Graph(launch, nodes, args, _environment(args), rviz)
