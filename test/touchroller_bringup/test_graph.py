"""The graph module: arguments, nodes, parameter precedence, and in-process instantiation."""
from __future__ import annotations

import ast
import re
from pathlib import Path

import numpy as np
import pytest

from touchroller_bringup import graph
from touchroller_bringup.graph import GraphError, NodeSpec, build_graph, replay_perception, resolve_arguments

ROOT = Path(__file__).resolve().parents[2]


def console_scripts() -> dict[str, str]:
    """name -> 'module:function' from setup.py's entry points (parsed, not executed)."""
    tree = ast.parse((ROOT / "setup.py").read_text())
    scripts = {}
    for node in ast.walk(tree):
        if isinstance(node, ast.Constant) and isinstance(node.value, str):
            match = re.fullmatch(r"\s*(\w+)\s*=\s*([\w.]+:\w+)\s*", node.value)
            if match:
                scripts[match.group(1)] = match.group(2)
    return scripts


def all_graphs(tmp_path: Path) -> list[graph.Graph]:
    return [build_graph("scan"), build_graph("scan", {"use_sim": "false"}), build_graph("calibrate"),
            build_graph("replay", {"bag": str(tmp_path)})]


def test_every_node_has_a_console_script_that_runs_its_module(tmp_path):
    """The console scripts are ros_main's entries (its Ctrl-C handling is up before the node's module
    loads), each running the main() of the node's own module."""
    from touchroller_bringup import ros_main

    scripts = console_scripts()
    for g in all_graphs(tmp_path):
        names = [spec.name for spec in g.nodes]
        assert len(set(names)) == len(names), names
        for spec in g.nodes:
            assert spec.package == "touchroller_bringup"
            module, function = scripts[spec.executable].split(":")
            assert module == "touchroller_bringup.ros_main"
            assert getattr(ros_main, function).module == spec.target.split(":")[0]


def test_scan_graph_defaults_are_simulated():
    g = build_graph("scan")
    assert g.keys == ("camera", "perception", "sweep")
    # the simulated camera is on the sweep node's simulated arm: TF and one simulated clock (use_sim_time)
    assert g.node("camera").parameters == {"source": "sim", "scene": "surface_mapping", "sim.motion": "arm",
                                           "use_sim_time": True}
    assert g.node("sweep").parameters == {"use_sim": True, "use_sim_time": True}
    assert g.node("perception").parameters == {**replay_perception("touchroller"), "use_sim_time": True}   # every frame
    assert build_graph("calibrate").node("camera").parameters["sim.motion"] == "scene"
    assert "use_sim_time" not in build_graph("scan", {"use_sim": "false"}).node("sweep").parameters
    files = g.node("sweep").params_files
    assert [Path(f).name for f in files] == ["touchroller.yaml", "scan.yaml"]


def test_scan_graph_with_hardware_arguments():
    g = build_graph("scan", {"use_sim": "False", "camera_device": "/dev/v4l/by-id/cam", "robot_ip": "10.0.0.2",
                             "sweep_speed": "0.02", "sweep_length": "0.05"})
    assert g.node("camera").parameters == {"source": "v4l2", "device": "/dev/v4l/by-id/cam"}
    assert g.node("sweep").parameters == {"use_sim": False, "robot_ip": "10.0.0.2", "sweep.speed": 0.02,
                                          "sweep.length": 0.05, "arm.backend": "ur_rtde"}
    driver = build_graph("scan", {"use_sim": "false", "arm_backend": "ur_driver"})
    assert driver.node("sweep").parameters["arm.backend"] == "ur_driver"
    with pytest.raises(GraphError, match="arm_backend"):
        build_graph("scan", {"use_sim": "false", "arm_backend": "ur_rtd"})


def test_scan_map_file_becomes_the_perception_save_path(tmp_path):
    assert "map.save_path" not in build_graph("scan").node("perception").parameters
    g = build_graph("scan", {"map_file": str(tmp_path / "roll.png")})
    assert g.node("perception").parameters["map.save_path"] == str(tmp_path / "roll.png")


def test_user_files_follow_the_defaults(tmp_path):
    params, calibration = tmp_path / "p.yaml", tmp_path / "c.yaml"
    params.write_text("/**:\n  ros__parameters: {}\n")
    calibration.write_text("/**:\n  ros__parameters: {}\n")
    g = build_graph("calibrate", {"params_file": str(params), "calibration_file": str(calibration)})
    for spec in g.nodes:
        assert spec.params_files[-2:] == (str(params.resolve()), str(calibration.resolve()))


@pytest.mark.parametrize(("launch", "values", "message"), [
    ("scan", {"use_sim": "maybe"}, "use_sim"),
    ("scan", {"sweep_speed": "-0.1"}, "sweep_speed"),
    ("scan", {"sweep_length": "fast"}, "not a number"),
    ("scan", {"sweep_speed": "nan"}, "sweep_speed"),
    ("scan", {"robot": "1.2.3.4"}, "unknown scan argument"),
    ("scan", {"params_file": "/nonexistent/p.yaml"}, "params_file /nonexistent/p.yaml does not exist"),
    ("replay", {}, "bag is required"),
    ("replay", {"bag": "b", "rate": "-1"}, "rate"),
    ("nope", {}, "unknown launch"),
])
def test_bad_arguments_are_one_clear_error(launch, values, message):
    with pytest.raises(GraphError, match=message) as info:
        build_graph(launch, values)
    assert "\n" not in str(info.value)


def test_resolve_arguments_fills_defaults():
    args = resolve_arguments("replay", {"bag": "x"})
    assert args == {"bag": "x", "rate": "1.0", "loop": "false", "params_file": "", "calibration_file": "",
                    "fastdds_profile": "auto", "namespace": "touchroller"}


@pytest.mark.parametrize(("distro", "variables"), [
    ("kilted", {"FASTDDS_DEFAULT_PROFILES_FILE"}),            # Fast DDS 3: FASTRTPS_ only draws a warning
    ("", {"FASTDDS_DEFAULT_PROFILES_FILE"}),                  # our pip wheels (Kilted), no ROS_DISTRO
    ("jazzy", {"FASTDDS_DEFAULT_PROFILES_FILE", "FASTRTPS_DEFAULT_PROFILES_FILE"}),   # Fast DDS 2
    ("humble", {"FASTDDS_DEFAULT_PROFILES_FILE", "FASTRTPS_DEFAULT_PROFILES_FILE"}),
])
def test_fastdds_profile_sets_the_environment_of_every_launch(tmp_path, monkeypatch, distro, variables):
    monkeypatch.setenv("ROS_DISTRO", distro)
    for name in ("FASTDDS_DEFAULT_PROFILES_FILE", "FASTRTPS_DEFAULT_PROFILES_FILE"):
        monkeypatch.delenv(name, raising=False)
    shipped = Path(__file__).resolve().parents[2] / "config" / "fastdds_shm.xml"
    assert shipped.is_file()
    for launch, required in (("scan", {}), ("calibrate", {}), ("replay", {"bag": "b"})):
        # the default: shared memory for this host and UDP for others, unless the user set a profile
        default = build_graph(launch, required).environment
        assert set(default) == variables and {Path(p).name for p in default.values()} == {"fastdds_shm_udp.xml"}
        assert all(Path(p).is_file() for p in default.values())
        with monkeypatch.context() as env:
            env.setenv("FASTDDS_DEFAULT_PROFILES_FILE", str(tmp_path / "theirs.xml"))
            assert build_graph(launch, required).environment == {}
        assert build_graph(launch, {**required, "fastdds_profile": ""}).environment == {}   # the environment's
        environment = build_graph(launch, {**required, "fastdds_profile": "shm"}).environment
        assert set(environment) == variables
        assert {Path(p).name for p in environment.values()} == {"fastdds_shm.xml"}
        assert all(Path(p).is_file() for p in environment.values())
    mine = tmp_path / "my_profile.xml"
    mine.write_text("<dds/>")
    assert set(build_graph("scan", {"fastdds_profile": str(mine)}).environment.values()) == {str(mine)}
    with pytest.raises(GraphError, match="fastdds_profile"):
        build_graph("scan", {"fastdds_profile": str(tmp_path / "missing.xml")})


def test_missing_node_module_is_a_clear_error():
    spec = NodeSpec("ghost", "ghost_node", "ghost", "touchroller_perception.no_such_node:Ghost")
    with pytest.raises(GraphError, match="ghost node"):
        spec.load_class()
    spec = NodeSpec("ghost", "ghost_node", "ghost", "touchroller_driver.arm:NoSuchClass")
    with pytest.raises(GraphError, match="does not exist"):
        spec.load_class()


@pytest.mark.ros
def test_node_kwargs_apply_name_files_and_overrides_like_launch(ros_context, tmp_path):
    from rclpy.node import Node

    first, second = tmp_path / "a.yaml", tmp_path / "b.yaml"
    first.write_text("/**:\n  ros__parameters:\n    alpha: 1.0\n    beta: 'one'\n    gamma: 1\n")
    second.write_text("/**:\n  ros__parameters:\n    alpha: 2.0\n")
    spec = NodeSpec("probe", "probe_node", "renamed_probe", "x:Y", parameters={"beta": "graph"},
                    remappings=(("/in", "/remapped_in"),), params_files=(str(first), str(second)))

    class Probe(Node):
        def __init__(self, **node_kwargs):
            super().__init__("probe", **node_kwargs)
            for name, default in (("alpha", 0.0), ("beta", ""), ("gamma", 0)):
                self.declare_parameter(name, default)

    node = Probe(context=ros_context, **spec.node_kwargs({"gamma": 3}))
    try:
        assert node.get_name() == "renamed_probe"
        assert node.get_parameter("alpha").value == 2.0     # later file wins
        assert node.get_parameter("beta").value == "graph"  # graph parameters over files
        assert node.get_parameter("gamma").value == 3       # user overrides over everything
        assert node.resolve_topic_name("/in") == "/remapped_in"
    finally:
        node.destroy_node()


@pytest.mark.ros
def test_sweep_node_from_the_graph_reads_the_scan_defaults(ros_context):
    spec = build_graph("scan", {"sweep_speed": "0.02"}).node("sweep")
    node = spec.load_class()(context=ros_context, **spec.node_kwargs())
    try:
        assert node.get_fully_qualified_name() == "/touchroller/sweep"
        assert node.get_parameter("sweep.speed").value == pytest.approx(0.02)   # argument
        assert node.get_parameter("sweep.length").value == pytest.approx(0.11)  # config/scan.yaml
        assert node.get_parameter("mount.xyz").value == pytest.approx([0.0, 0.0, 0.1])  # config/touchroller.yaml
    finally:
        node.destroy_node()


@pytest.mark.ros
@pytest.mark.parametrize(("launch", "values"), [
    ("scan", {"use_sim": "false", "camera_device": "/nonexistent/video9", "robot_ip": "127.0.0.213",
              "sweep_speed": "0.02", "sweep_length": "0.05"}),
    ("replay", {"bag": "made by the test", "rate": "2.0", "loop": "true"}),
    ("calibrate", {"use_sim": "false", "output_file": "/tmp/never_written.yaml"}),
])
def test_every_graph_parameter_is_declared_by_its_node(ros_context, bag_factory, launch, values):
    """The graph's parameter names and types agree with the nodes that exist (missing ones are skipped)."""
    if launch == "replay":   # a bag that does not exist is refused at start-up (a device may come back, a file not)
        values = {**values, "bag": str(bag_factory([(k, np.zeros((8, 8, 3), np.uint8)) for k in range(3)]))}
    checked = 0
    for spec in build_graph(launch, values).nodes:
        try:
            cls = spec.load_class()
        except GraphError:
            continue  # that node has not landed yet
        node = cls(context=ros_context, **spec.node_kwargs())
        try:
            assert node.get_name() == spec.name
            for name, value in spec.parameters.items():
                assert node.has_parameter(name), f"{spec.name} does not declare {name}"
                assert node.get_parameter(name).value == value
                checked += 1
        finally:
            node.destroy_node()
    assert checked > 0


@pytest.mark.ros
@pytest.mark.timeout(90)
def test_replay_graph_gives_the_contacts_of_touchroller_contacts(ros_context, spin_until, bag_factory, tmp_path):
    """What replay.launch.py runs (camera node on the bag -> perception node), in one context: the
    contacts equal `touchroller contacts` on the same bag with the same geometry."""
    import csv

    import numpy as np
    from geometry_msgs.msg import PointStamped
    from rclpy.executors import SingleThreadedExecutor
    from rclpy.node import Node

    from touchroller_bringup.cli import main
    from touchroller_driver.paths import config_path
    from touchroller_driver.sim.taps import TapRenderer
    from touchroller_perception.geometry import CameraModel

    camera_model = CameraModel.from_yaml(config_path("touchroller.yaml"))
    renderer = TapRenderer(camera_model, seed=3)
    rng = np.random.default_rng(3)
    taps = [[]] * 5 + [[(200.0 + 20 * k, 180.0 + 8 * k)] for k in range(8)]   # 5 reference frames, 8 taps
    bag = bag_factory([(1_700_000_000_000_000_000 + 33_000_000 * i, renderer.render(pixels, rng))
                       for i, pixels in enumerate(taps)])
    csv_path = tmp_path / "contacts.csv"
    assert main(["contacts", str(bag), "--params", str(config_path("touchroller.yaml")), "--out", str(csv_path)]) == 0
    with open(csv_path, newline="") as stream:
        expected = [(int(r["stamp_ns"]), float(r["x"]), float(r["y"]), float(r["z"])) for r in csv.DictReader(stream)]
    assert len(expected) == 8

    g = build_graph("replay", {"bag": str(bag)})   # perception: reliable deep queue; camera waits for it
    classes = {spec.key: spec.load_class() for spec in g.nodes}
    nodes = [classes[spec.key](context=ros_context, **spec.node_kwargs()) for spec in g.nodes]
    probe = Node("replay_probe", context=ros_context)
    received: list = []
    probe.create_subscription(PointStamped, "/touchroller/contacts", received.append, 100)
    executor = SingleThreadedExecutor(context=ros_context)
    for node in (*nodes, probe):
        executor.add_node(node)
    try:
        camera, perception = nodes
        assert spin_until(executor, lambda: camera.finished and perception.received == len(taps), timeout=30.0)
        assert spin_until(executor, lambda: len(received) >= len(expected), timeout=20)
    finally:
        executor.shutdown()
        for node in (*nodes, probe):
            node.destroy_node()
    got = [(m.header.stamp.sec * 1_000_000_000 + m.header.stamp.nanosec, m.point.x, m.point.y, m.point.z)
           for m in received]
    assert [s for s, *_ in got] == [s for s, *_ in expected]           # the recorded stamps, frame by frame
    np.testing.assert_allclose([p for _, *p in got], [p for _, *p in expected], atol=1e-6)


def test_the_simulated_calibration_scenes_hold_each_view_for_captures_by_hand():
    sim = pytest.importorskip("touchroller_driver.sim")
    default = build_graph("calibrate").node("camera").parameters
    assert default["loop"] is True and default["scene"] == "calibration_hemispheres:by_hand"
    hemispheres = sim.load_scene(default["scene"])
    assert hemispheres.motion["hold_frames"] / hemispheres.fps >= 1.0     # a press stays a second or more
    assert hemispheres.motion["gap_frames"] < hemispheres.motion["hold_frames"]
    assert 1.0 / sim.load_scene("calibration_chessboard:by_hand").fps >= 1.0


@pytest.mark.ros
@pytest.mark.timeout(180)
def test_calibrate_graph_in_simulation_can_be_followed_by_hand(ros_context, spin_until, tmp_path):
    """docs/calibration.md's steps on `calibrate.launch.py use_sim:=true`: ~/capture called at a human pace
    (once a second, here at twice the speed with rate 2) keeps finding presses after the scene's first pass
    has ended (it loops), and ~/solve then calibrates. The scene is the shipped one with 3 presses."""
    import time

    import yaml
    from rclpy.executors import SingleThreadedExecutor
    from rclpy.node import Node
    from std_srvs.srv import Trigger

    from touchroller_bringup import names
    from touchroller_driver.paths import config_path

    scene = yaml.safe_load(config_path("scenes", "calibration_hemispheres.yaml").read_text())
    scene["motion"]["presses"] = 3
    scene_path = tmp_path / "hemispheres.yaml"
    scene_path.write_text(yaml.safe_dump(scene))
    built = build_graph("calibrate", {"scene": f"{scene_path}:by_hand", "output_file": str(tmp_path / "cal.yaml")})
    overrides = {"camera": {"rate": 2.0}, "perception": {"map.publish_rate": 0.0}, "calibration": {}}
    nodes = [spec.load_class()(context=ros_context, **spec.node_kwargs(overrides[spec.key])) for spec in built.nodes]
    camera = nodes[0]
    probe = Node("calibration_user", context=ros_context)
    executor = SingleThreadedExecutor(context=ros_context)
    for node in (*nodes, probe):
        executor.add_node(node)

    def call(service: str) -> Trigger.Response:
        client = probe.create_client(Trigger, names.service(names.CALIBRATION_NODE, service))
        assert spin_until(executor, client.service_is_ready, timeout=20.0)
        future = client.call_async(Trigger.Request())
        assert spin_until(executor, future.done, timeout=20.0)
        return future.result()

    one_pass = 5 + 3 * (45 + 15)   # frames of the scene: reference, then 3 presses held 45 and lifted 15
    answers = []
    try:
        assert spin_until(executor, lambda: camera.published > 0, timeout=30.0)
        while camera.published < 2 * one_pass and len(answers) < 60:   # into the second pass
            answers.append(call(names.CAPTURE))
            deadline = time.monotonic() + 0.5
            spin_until(executor, lambda d=deadline: time.monotonic() > d, timeout=1.0)
        solved = call(names.SOLVE)
    finally:
        executor.shutdown()
        for node in (*nodes, probe):
            node.destroy_node()
    assert camera.published >= 2 * one_pass, "the scene loops"
    captured = [a for a in answers if a.success]
    assert len(captured) >= 4, [a.message for a in answers]
    assert all(a.message.startswith(("not captured: no imprints", "no new image")) for a in answers if not a.success)
    assert solved.success, solved.message
    assert (tmp_path / "cal.yaml").is_file()


def test_the_simulated_calibrate_graph_starts_from_the_simulated_cameras_intrinsics(tmp_path):
    """Out of the box, calibrate.launch.py's nodes assume the camera the scene renders (fx 380 px), not
    the defaults' 500 px (with which the presses gave d = 18.4 mm); a user's calibration file wins."""
    sim = pytest.importorskip("touchroller_driver.sim")
    built = build_graph("calibrate")
    truth = sim.load_scene(built.node("camera").parameters["scene"]).camera
    for key in ("camera", "perception", "calibration"):   # the camera node publishes camera_info from them
        params = built.node(key).parameters
        assert params["camera.fx"] == truth.fx and params["camera.cy"] == truth.cy
        assert params["camera.distortion"] == list(truth.distortion)
        assert "extrinsics.d" not in params and "extrinsics.theta" not in params
    calibration = tmp_path / "c.yaml"
    calibration.write_text("/**:\n  ros__parameters: {}\n")
    mine = build_graph("calibrate", {"calibration_file": str(calibration)})
    assert "camera.fx" not in mine.node("calibration").parameters
    assert "camera.fx" not in build_graph("calibrate", {"use_sim": "false"}).node("calibration").parameters


@pytest.mark.ros
@pytest.mark.parametrize("launch", ["calibrate", "scan"])
def test_one_publisher_of_camera_info_per_graph(ros_context, spin_until, launch):
    """camera_info has one owner, the camera node (camera_info_manager's convention); the calibration node
    hands solved intrinsics to it through set_camera_info instead of publishing a second camera_info."""
    from rclpy.executors import SingleThreadedExecutor
    from rclpy.node import Node

    from touchroller_bringup import names

    built = build_graph(launch)
    nodes = [spec.load_class()(context=ros_context, **spec.node_kwargs()) for spec in built.nodes]
    probe = Node("camera_info_census", context=ros_context)
    executor = SingleThreadedExecutor(context=ros_context)
    for node in (*nodes, probe):
        executor.add_node(node)
    topic = names.topic(names.CAMERA_INFO)
    try:
        camera = nodes[built.keys.index("camera")]
        assert spin_until(executor, lambda: bool(probe.get_publishers_info_by_topic(topic)), timeout=20.0)
        spin_until(executor, lambda: False, timeout=1.0)    # time for a second publisher to be discovered
        publishers = probe.get_publishers_info_by_topic(topic)
        assert [(p.node_namespace, p.node_name) for p in publishers] == [("/touchroller", names.CAMERA_NODE)]
        services = dict(probe.get_service_names_and_types())
        assert services[names.service(names.CAMERA_NODE, names.SET_CAMERA_INFO)] == ["sensor_msgs/srv/SetCameraInfo"]
        assert camera.frame_id == names.CAMERA_OPTICAL_FRAME
    finally:
        executor.shutdown()
        for node in (*nodes, probe):
            node.destroy_node()


def test_a_simulated_arm_in_a_namespace_gets_its_own_flange_beside_the_shared_base():
    """Two simulated scans on one domain: their arms must not both publish base -> tool0."""
    left = build_graph("scan", {"namespace": "left"}).node("sweep").parameters
    assert left["arm.tool_frame"] == "left/tool0" and "arm.base_frame" not in left
    assert "arm.tool_frame" not in build_graph("scan", {}).node("sweep").parameters
    hardware = build_graph("scan", {"namespace": "left", "use_sim": "false"}).node("sweep").parameters
    assert "arm.tool_frame" not in hardware   # a real robot's flange is its driver's name, set by the user


def test_inspect_switches_the_perception_nodes_live_findings():
    def findings(value):
        return graph.build_graph("scan", {"inspect": value}).node("perception").parameters.get("findings.enabled")

    assert findings("false") is False and findings("true") is True and findings("auto") is None
    with pytest.raises(graph.GraphError, match="inspect"):
        graph.build_graph("scan", {"inspect": "maybe"})
