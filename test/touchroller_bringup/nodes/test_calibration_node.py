"""The calibration node on a real rclpy context: capture simulated presses, solve, and check that the
perception node, the YAML files and the camera node (through set_camera_info) all receive the calibration."""
from __future__ import annotations

import math

import numpy as np
import pytest

pytest.importorskip("rclpy")
pytestmark = pytest.mark.ros

from rclpy.executors import SingleThreadedExecutor  # noqa: E402
from rclpy.parameter import Parameter  # noqa: E402

sim = pytest.importorskip("touchroller_driver.sim")


@pytest.fixture(scope="module")
def presses():
    sensor = sim.SimulatedSensor(sim.load_scene("calibration_hemispheres", **{"motion.presses": 4}), seed=2)
    frames = list(sensor.frames())
    references = [f for f in frames if f.truth.get("phase") == "reference"][:3]
    pressed = [f for f in frames if f.truth.get("phase") == "press"]
    return sensor.camera, references, pressed


@pytest.fixture
def graph(ros_context, presses, tmp_path):
    from rclpy.node import Node
    from sensor_msgs.msg import Image

    from touchroller_bringup import names
    from touchroller_bringup.nodes.calibration_node import CalibrationNode
    from touchroller_bringup.nodes.camera_node import CameraNode
    from touchroller_bringup.nodes.perception_node import PerceptionNode

    truth = presses[0]
    start = truth.replace(theta=0.0, d=0.0)
    geometry = [Parameter(n, value=v) for n, v in start.to_params().items()]
    perception = PerceptionNode(context=ros_context,
                                parameter_overrides=[*geometry, Parameter("map.publish_rate", value=0.0)])
    node = CalibrationNode(context=ros_context, parameter_overrides=[
        *geometry, Parameter("output_path", value=str(tmp_path / "cal.yaml"))])
    # the camera node that owns camera_info: no frames of its own here (the helper publishes them), its
    # camera_info_url a file the calibration's set_camera_info writes
    camera = CameraNode(context=ros_context, autostart=False, source=_NoFrames(), parameter_overrides=[
        Parameter("camera_info_url", value=f"file://{tmp_path}/camera_info.yaml")])
    helper = Node("calibration_test_helper", context=ros_context)
    image_pub = helper.create_publisher(Image, names.topic(names.IMAGE), 10)
    executor = SingleThreadedExecutor(context=ros_context)
    for n in (perception, node, helper, camera):
        executor.add_node(n)
    yield node, perception, helper, executor, image_pub, camera
    executor.shutdown()
    for n in (perception, node, helper, camera):
        n.destroy_node()


class _NoFrames:
    """An external frame source that never delivers (the camera node only serves set_camera_info here)."""

    info = "no frames"

    def open(self) -> None:
        pass

    def read(self, timeout: float) -> None:
        return None

    def close(self) -> None:
        pass


def call(executor, spin_until, helper, name: str) -> object:
    from std_srvs.srv import Trigger

    from touchroller_bringup import names

    client = helper.create_client(Trigger, names.service(names.CALIBRATION_NODE, name))
    assert spin_until(executor, client.service_is_ready, timeout=20)
    future = client.call_async(Trigger.Request())
    assert spin_until(executor, future.done, timeout=30.0)
    helper.destroy_client(client)
    return future.result()


def show(executor, spin_until, node, image_pub, frame) -> None:
    from touchroller_bringup.image_conversion import array_to_image

    assert spin_until(executor, lambda: image_pub.get_subscription_count() > 0, timeout=20)
    image_pub.publish(array_to_image(frame.image, frame.stamp_ns))
    assert spin_until(executor, lambda: node.latest is not None and node.latest[0] == frame.stamp_ns, timeout=20)

def capture_all(executor, spin_until, node, image_pub, helper, target: str, frames) -> None:
    """Shows each frame to the calibration node with `target` set and captures it; every capture succeeds."""
    node.set_parameters([Parameter("target", value=target)])
    for frame in frames:
        show(executor, spin_until, node, image_pub, frame)
        assert call(executor, spin_until, helper, "capture").success


def test_capture_solve_and_hand_over(graph, presses, spin_until, tmp_path):
    from touchroller_perception.geometry import CameraModel

    node, perception, helper, executor, image_pub, camera = graph
    truth, references, pressed = presses

    failed = call(executor, spin_until, helper, "solve")
    assert not failed.success and "nothing captured" in failed.message
    assert not call(executor, spin_until, helper, "capture").success     # no image yet

    capture_all(executor, spin_until, node, image_pub, helper, "reference", references)
    again = call(executor, spin_until, helper, "capture")
    assert not again.success and "no new image" in again.message

    node.set_parameters([Parameter("target", value="hemispheres")])
    show(executor, spin_until, node, image_pub, sim.Frame(references[0].stamp_ns + 1, references[0].image))
    empty = call(executor, spin_until, helper, "capture")      # checked at capture: nothing pressed
    assert not empty.success and "no imprints" in empty.message
    for frame in pressed:
        show(executor, spin_until, node, image_pub, frame)
        assert call(executor, spin_until, helper, "capture").success
    assert len(node.captures["hemispheres"]) == 4 and len(node.captures["reference"]) == 3
    # a lights-off frame (here: black, as if the gel had no background of its own) goes to the row balance
    node.set_parameters([Parameter("target", value="dark")])
    show(executor, spin_until, node, image_pub, sim.Frame(pressed[-1].stamp_ns + 1, 0 * references[0].image))
    assert call(executor, spin_until, helper, "capture").success
    assert len(node.captures["dark"]) == 1

    solved = call(executor, spin_until, helper, "solve")
    assert solved.success, solved.message
    assert "extrinsics from 4/4 images" in solved.message
    assert spin_until(executor, lambda: node.remote_result is not None, timeout=20)
    assert node.remote_result.successful
    model = perception.geometry.model
    assert abs(math.degrees(model.theta - truth.theta)) < 0.15
    assert abs(model.d - truth.d) < 0.05e-3
    written = CameraModel.from_yaml(tmp_path / "cal.yaml")
    assert written.theta == pytest.approx(model.theta) and written.d == pytest.approx(model.d)
    assert node.geometry.model.theta == pytest.approx(model.theta)
    # theta and d only: camera_info (intrinsics) stays the camera node's, untouched; no camera-info YAML
    assert node.camera_result is None and not (tmp_path / "cal.camera_info.yaml").exists()

    assert call(executor, spin_until, helper, "reset").success
    assert not any(node.captures.values())


def test_rejects_an_unknown_target(graph):
    node = graph[0]
    result = node.set_parameters([Parameter("target", value="teapot")])[0]
    assert not result.successful and "target must be one of" in result.reason
    for name in ("intrinsics.distortion", "intrinsics.corners", "imprints.centre", "imprints.strength"):
        result = node.set_parameters([Parameter(name, value="teapot")])[0]
        assert not result.successful and f"{name} must be one of" in result.reason


def test_the_corner_path_is_a_parameter(graph):
    node = graph[0]
    assert node._intrinsics_config().corners == "fronto_parallel"
    assert node.set_parameters([Parameter("intrinsics.corners", value="image")])[0].successful
    assert node._intrinsics_config().corners == "image"


def test_the_imprint_strength_is_a_parameter(graph):
    node = graph[0]
    assert node._extrinsics_config().detector.strength == "auto"
    assert node.set_parameters([Parameter("imprints.strength", value="relative")])[0].successful
    assert node._extrinsics_config().detector.strength == "relative"


def test_coverage_is_published_on_diagnostics(graph, spin_until):
    from diagnostic_msgs.msg import DiagnosticArray

    node, _, helper, executor, _, _ = graph
    arrays: list = []
    helper.create_subscription(DiagnosticArray, "/diagnostics", arrays.append, 10)
    node.board_corners = [np.array([(200.0 + 20 * i, 180.0 + 20 * j) for j in range(7) for i in range(7)])]
    assert spin_until(executor, lambda: any(s.name.endswith("chessboard coverage") for a in arrays
                                            for s in a.status), timeout=20)
    status = next(s for a in arrays for s in a.status if s.name.endswith("chessboard coverage"))
    assert status.level == b"\x01" and "image corners not covered" in status.message
    assert {kv.key for kv in status.values} >= {"views", "X", "Y", "size", "skew", "image_corners_seen", "reach"}


def test_missing_perception_node_is_reported(graph, presses, spin_until):
    node, _, helper, executor, image_pub, _ = graph
    truth, references, pressed = presses
    node.set_parameters([Parameter("target", value="chessboard")])
    show(executor, spin_until, node, image_pub, pressed[0])
    no_board = call(executor, spin_until, helper, "capture")
    assert not no_board.success and "no 7x7 chessboard found" in no_board.message
    node.set_parameters([Parameter("target", value="hemispheres"),
                         Parameter("perception_node", value="nobody_here")])
    for frame in pressed[1:4]:
        show(executor, spin_until, node, image_pub, frame)
        assert call(executor, spin_until, helper, "capture").success
    solved = call(executor, spin_until, helper, "solve")
    assert solved.success and "/nobody_here/set_parameters_atomically is not available" in solved.message


def test_intrinsics_then_extrinsics_reach_the_perception_node(graph, presses, spin_until, tmp_path):
    """Chessboard views and presses in one session: one solve sets intrinsics (incl. the distortion
    array and the integer image size) and theta, d on the perception node in one atomic call."""
    node, perception, helper, executor, image_pub, camera = graph
    truth, references, pressed = presses
    boards = sim.SimulatedSensor(sim.load_scene("calibration_chessboard", **{"motion.views": 8}), seed=5)
    node.set_parameters([Parameter("target", value="chessboard")])
    replies = []
    for frame in boards.frames():     # a later session: stamps after the presses' ones
        show(executor, spin_until, node, image_pub, sim.Frame(frame.stamp_ns + 10**12, frame.image))
        replies.append(call(executor, spin_until, helper, "capture"))
        assert replies[-1].success
    # every capture says what the views cover so far, as camera_calibration's bars do
    assert all("coverage: X " in r.message and "image corners" in r.message for r in replies)
    status = node._coverage_status()
    assert status.values["views"] == 8 and set(status.values) >= {"X", "Y", "size", "skew", "image_corners_seen"}
    assert (status.level == 1) == bool(node.coverage().warnings())
    node.set_parameters([Parameter("target", value="reference")])
    show(executor, spin_until, node, image_pub, references[0])
    assert call(executor, spin_until, helper, "capture").success
    capture_all(executor, spin_until, node, image_pub, helper, "hemispheres", pressed)
    solved = call(executor, spin_until, helper, "solve")
    assert solved.success, solved.message
    assert "intrinsics from 8/8 views" in solved.message and "setting 9 parameters" in solved.message
    assert "coverage: X " in solved.message          # the result says what the views covered
    assert spin_until(executor, lambda: node.remote_result is not None, timeout=20)
    assert node.remote_result.successful, node.remote_result.reason
    model = perception.geometry.model
    assert abs(model.fx - truth.fx) < 2.0 and abs(model.cy - truth.cy) < 3.0
    assert model.distortion[0] == pytest.approx(truth.distortion[0], abs=0.02)
    assert abs(math.degrees(model.theta - truth.theta)) < 0.5
    # the intrinsics reach the camera node (the graph's one camera_info publisher) through set_camera_info,
    # which writes its camera_info_url; the calibration writes the same camera_calibration_parsers YAML
    from touchroller_bringup.camera_info_files import read_camera_info

    assert spin_until(executor, lambda: node.camera_result is not None, timeout=20)
    assert node.camera_result[0], node.camera_result[1]
    assert camera.get_parameter("camera.fx").value == pytest.approx(model.fx)
    assert camera.camera_info.calibration.k[0] == pytest.approx(model.fx)
    written = read_camera_info(tmp_path / "cal.camera_info.yaml")
    assert written == read_camera_info(tmp_path / "camera_info.yaml")
    assert written.matches(node.geometry.model) and "cal.camera_info.yaml" in solved.message


@pytest.mark.parametrize("name, value, message", [
    ("target", "boards", "target must be one of"),
    ("image_topic", "bad topic!", "not a valid ROS name"),
    ("perception_node", "bad node!", "not a valid ROS name"),
    ("board.square", float("nan"), "finite"),
    ("frame.pitch_x", "abc", "must be a number"),
    ("output_path", "/", "not a regular file"),
])
def test_start_up_values_it_cannot_use_stop_the_node_in_one_line(ros_context, name, value, message):
    """#28: the calibration node started on a bad parameter and failed at ~/solve, or never."""
    from touchroller_bringup.errors import UserError
    from touchroller_bringup.nodes.calibration_node import CalibrationNode

    with pytest.raises(UserError, match=message):
        CalibrationNode(context=ros_context, parameter_overrides=[Parameter(name, value=value)])


def test_ball_presses_solve_the_photometric_model(graph, spin_until, tmp_path):
    from touchroller_perception.height import PhotometricModel

    node, _perception, helper, executor, image_pub, _camera = graph
    sensor = sim.SimulatedSensor(sim.load_scene("ball_presses", **{"motion.presses": 6}), seed=4)
    frames = list(sensor.frames())
    refs = [f for f in frames if f.truth.get("phase") == "reference"][:2]
    balls = [f for f in frames if f.truth.get("phase") == "press"]
    node.set_parameters([Parameter("photometric.output_path", value=str(tmp_path / "p.npz")),
                         Parameter("photometric.ball_radius", value=0.004), Parameter("target", value="ball")])
    show(executor, spin_until, node, image_pub, balls[0])
    early = call(executor, spin_until, helper, "capture")
    assert not early.success and "reference first" in early.message
    nothing = call(executor, spin_until, helper, "solve_photometric")
    assert not nothing.success and "nothing to solve" in nothing.message
    capture_all(executor, spin_until, node, image_pub, helper, "reference", refs)
    capture_all(executor, spin_until, node, image_pub, helper, "ball", balls)
    solved = call(executor, spin_until, helper, "solve_photometric")
    assert solved.success, solved.message
    assert "6 presses" in solved.message and (tmp_path / "p.npz").is_file()
    assert PhotometricModel.load(tmp_path / "p.npz").width == 640


def test_an_implausible_result_is_refused_and_never_set_on_perception(graph, presses, spin_until, tmp_path):
    """The calibrate graph's old defaults: the nodes assume fx = 500 px for a camera of 380 px. The
    presses then solve to a d many mm off; ~/solve refuses it with the reason, writes nothing and sets
    nothing on the perception node."""
    node, perception, helper, executor, image_pub, _camera = graph
    truth, references, pressed = presses
    node.set_parameters([Parameter("camera.fx", value=500.0), Parameter("camera.fy", value=500.0),
                         Parameter("target", value="reference")])
    for frame in references:
        show(executor, spin_until, node, image_pub, frame)
        assert call(executor, spin_until, helper, "capture").success
    capture_all(executor, spin_until, node, image_pub, helper, "hemispheres", pressed)
    solved = call(executor, spin_until, helper, "solve")
    assert not solved.success
    assert "implausible result, not applied: d = " in solved.message and "intrinsics" in solved.message
    assert node.remote_result is None and perception.geometry.model.d == 0.0
    assert not (tmp_path / "cal.yaml").exists()


def test_a_board_change_reaches_its_config_and_detects_the_captured_views_again(ros_context):
    """board.* and frame.* are bound to cal.Chessboard and cal.HemisphereFrame (ros_params.ConfigParameters):
    a board change re-detects the captured chessboards, a frame change does not."""
    from touchroller_bringup.nodes.calibration_node import CalibrationNode
    from touchroller_perception import calibration as cal

    node = CalibrationNode(context=ros_context)
    try:
        detected: list = []
        node._redetect_boards = lambda: detected.append(node.board_parameters.config)
        assert node.set_parameters_atomically([Parameter("board.columns", value=9),
                                               Parameter("board.square", value=0.02)]).successful
        assert detected == [cal.Chessboard(columns=9, square=0.02)]
        assert node.set_parameters([Parameter("frame.rows", value=3)])[0].successful
        assert node.frame_parameters.config == cal.HemisphereFrame(rows=3) and len(detected) == 1
        refused = node.set_parameters([Parameter("board.rows", value=1)])[0]
        assert not refused.successful and node.board_parameters.config.rows == 7
    finally:
        node.destroy_node()


def test_a_perception_node_that_never_answers_is_reported_after_the_deadline(ros_context, other_participant, spin_until,
                                                                            monkeypatch, tmp_path):
    """The solved calibration's set_parameters_atomically to a node that takes no requests (here a node
    nobody spins: discovered, never answering) ends in a failed result naming the service and the wait,
    instead of waiting for ever."""
    from rclpy.node import Node

    from touchroller_bringup.nodes import calibration_node
    from touchroller_bringup.nodes.calibration_node import CalibrationNode

    monkeypatch.setattr(calibration_node, "REMOTE_TIMEOUT_S", 1.0)
    ghost = Node("ghost_perception", namespace="/touchroller", context=other_participant)   # never spun
    node = CalibrationNode(context=ros_context, parameter_overrides=[
        Parameter("perception_node", value="/touchroller/ghost_perception"),
        Parameter("output_path", value=str(tmp_path / "cal.yaml"))])
    executor = SingleThreadedExecutor(context=ros_context)
    executor.add_node(node)
    try:
        said = ""
        for _ in range(100):   # until discovery shows the ghost's service
            said = node._send(node.geometry.model, with_intrinsics=False)
            if "setting" in said:
                break
            spin_until(executor, lambda: False, timeout=0.2)
        assert said.startswith("setting"), said
        assert spin_until(executor, lambda: node.remote_result is not None, timeout=20.0)
        assert not node.remote_result.successful
        assert node.remote_result.reason == \
            "no answer from /touchroller/ghost_perception/set_parameters_atomically within 1 s"
    finally:
        executor.shutdown()
        node.destroy_node()
        ghost.destroy_node()
