"""CameraNode over a real rclpy context: bgr8 images with capture stamps, camera info, parameters, diagnostics."""
from __future__ import annotations

import itertools
import os
import signal
import subprocess
import sys
import threading

import cv2
import numpy as np
import pytest

pytest.importorskip("rclpy")
from rclpy.executors import SingleThreadedExecutor  # noqa: E402
from rclpy.node import Node  # noqa: E402
from rclpy.parameter import Parameter  # noqa: E402
from rclpy.qos import QoSProfile, ReliabilityPolicy  # noqa: E402

from touchroller_bringup import names  # noqa: E402
from touchroller_bringup.image_conversion import image_to_array, stamp_to_ns  # noqa: E402
from touchroller_bringup.nodes.camera_node import CameraNode  # noqa: E402
from touchroller_bringup.ros_diagnostics import status_values  # noqa: E402
from touchroller_driver.sources import Frame, SourceStats  # noqa: E402

pytestmark = pytest.mark.ros
IMAGE_TOPIC, CAMERA_INFO_TOPIC = names.topic(names.IMAGE), names.topic(names.CAMERA_INFO)   # /touchroller/...


class ListSource:
    """An external FrameSource that hands out given images (or raises for bad ones) once each."""

    def __init__(self, images, stamps=None):
        self.images = list(images)
        self.stamps = list(stamps or [1_700_000_000_000_000_000 + i * 33_000_000 for i in range(len(self.images))])
        self.index = 0
        self.stats = SourceStats()
        self.lock = threading.Lock()

    @property
    def info(self):
        return "list source"

    def open(self):
        self.stats.connected = True

    def read(self, timeout):
        with self.lock:
            if self.index >= len(self.images):
                self.stats.finished = True
                threading.Event().wait(min(timeout, 0.01))
                return None
            i = self.index
            self.index += 1
        self.stats.captured += 1
        return Frame(self.stamps[i], self.images[i], i)

    def close(self):
        self.stats.connected = False


class Listener:
    def __init__(self, context, qos=10):
        self.node = Node("listener", context=context)
        self.images, self.infos, self.diagnostics = [], [], []
        from diagnostic_msgs.msg import DiagnosticArray
        from sensor_msgs.msg import CameraInfo, Image

        self.node.create_subscription(Image, IMAGE_TOPIC, self.images.append, qos)
        self.node.create_subscription(CameraInfo, CAMERA_INFO_TOPIC, self.infos.append, qos)
        self.node.create_subscription(DiagnosticArray, "/diagnostics", self.diagnostics.append, 10)


def make_graph(context, **camera_kwargs):
    listener = Listener(context)
    camera = CameraNode(context=context, autostart=False, **camera_kwargs)
    executor = SingleThreadedExecutor(context=context)
    executor.add_node(listener.node)
    executor.add_node(camera)
    return listener, camera, executor


def wait_for_subscription(camera, spin_until, executor):
    assert spin_until(executor, lambda: camera.image_pub.get_subscription_count() > 0, timeout=20.0)


def test_external_source_frames_are_published_as_bgr8_with_capture_stamps(ros_context, spin_until):
    rng = np.random.default_rng(1)
    images = [rng.integers(0, 256, (48, 64, 3), dtype=np.uint8) for _ in range(3)]
    images.append(images[0][..., 0].copy())  # a grey frame: still published as bgr8
    source = ListSource(images)
    listener, camera, executor = make_graph(
        ros_context, source=source,
        parameter_overrides=[Parameter("camera.fx", value=612.5), Parameter("frame_id", value="cam_optical")])
    try:
        wait_for_subscription(camera, spin_until, executor)
        camera.start()
        assert spin_until(executor, lambda: len(listener.images) >= 4 and len(listener.infos) >= 4, timeout=20)
        for msg, image, stamp in zip(listener.images, images, source.stamps, strict=False):
            assert msg.encoding == "bgr8"
            assert msg.header.frame_id == "cam_optical"
            assert msg.header.stamp.sec * 10**9 + msg.header.stamp.nanosec == stamp
            expected = image if image.ndim == 3 else cv2.cvtColor(image, cv2.COLOR_GRAY2BGR)
            assert np.array_equal(image_to_array(msg), expected)
        info = listener.infos[0]
        assert info.k[0] == pytest.approx(612.5) and info.distortion_model == "plumb_bob"
        assert (info.width, info.height) == (640, 480)
        assert info.header.stamp == listener.images[0].header.stamp
        assert spin_until(executor, lambda: camera.finished, timeout=20)
    finally:
        executor.shutdown()
        camera.destroy_node()


def recorded_logs(node) -> list[tuple[str, str]]:
    """(severity, message) of everything the node logs from now on."""
    logs: list[tuple[str, str]] = []
    logger = node.get_logger()
    for severity in ("info", "warning", "error"):
        setattr(logger, severity, lambda message, *_, s=severity, **__: logs.append((s, str(message))))
    return logs


def test_a_device_that_cannot_be_opened_is_logged_as_such_never_as_streaming(ros_context, spin_until, tmp_path):
    device = str(tmp_path / "video9")   # no such device
    camera = CameraNode(context=ros_context, autostart=False, parameter_overrides=[
        Parameter("source", value="v4l2"), Parameter("device", value=device)])
    logs = recorded_logs(camera)
    try:
        camera.start()
        assert spin_until(camera, lambda: any(s == "warning" for s, _ in logs), timeout=20.0), logs
        spin_until(camera, lambda: False, timeout=0.5)   # a few back-off retries
    finally:
        camera.destroy_node()
    assert ("info", f"opening v4l2 {device} 640x480@30") in logs
    failures = [m for s, m in logs if s == "warning"]
    assert failures == ["cannot open the camera (open failed: device not available); retrying with back-off"]
    assert not any("streaming" in m for _, m in logs)


def test_streaming_is_logged_once_the_first_frame_is_out(ros_context, spin_until):
    listener, camera, executor = make_graph(ros_context, source=ListSource([np.zeros((4, 4, 3), np.uint8)] * 3))
    logs = recorded_logs(camera)
    try:
        wait_for_subscription(camera, spin_until, executor)
        camera.start()
        assert spin_until(executor, lambda: len(listener.images) >= 3, timeout=20)
    finally:
        executor.shutdown()
        camera.destroy_node()
        listener.node.destroy_node()
    messages = [m for _, m in logs]
    assert messages.index("opening list source") < messages.index("streaming from list source")
    assert messages.count("streaming from list source") == 1


def test_malformed_frames_are_logged_and_skipped_and_the_node_keeps_publishing(ros_context, spin_until):
    good = np.full((8, 8, 3), 9, np.uint8)
    images = [good, np.zeros((8, 8, 3), np.float32), np.zeros((8, 8, 2), np.uint8), good]
    listener, camera, executor = make_graph(ros_context, source=ListSource(images))
    try:
        wait_for_subscription(camera, spin_until, executor)
        camera.start()
        # The camera thread counts a frame after publishing it, and the listener may get the image first:
        # wait for the source to run dry (every frame handled and counted), then for the images.
        assert spin_until(executor, lambda: camera.finished, timeout=20)
        assert spin_until(executor, lambda: len(listener.images) >= 2, timeout=20)
        assert camera.malformed == 2 and camera.published == 2
        stamps = [m.header.stamp.nanosec for m in listener.images]
        assert len(set(stamps)) == 2  # the first and the last frame, nothing else
    finally:
        executor.shutdown()
        camera.destroy_node()


def test_bad_parameter_values_are_rejected_and_good_ones_reopen_the_source(ros_context, spin_until, tmp_path):
    video = tmp_path / "clip.avi"
    writer = cv2.VideoWriter(str(video), cv2.VideoWriter.fourcc(*"MJPG"), 30.0, (32, 24))
    for i in range(5):
        writer.write(np.full((24, 32, 3), 50 * i, np.uint8))
    writer.release()
    listener, camera, executor = make_graph(
        ros_context, parameter_overrides=[Parameter("source", value="video"),
                                          Parameter("video_path", value=str(video)),
                                          Parameter("rate", value=0.0), Parameter("wait_for_subscribers", value=1)])
    try:
        camera.start()
        # #28: a file that does not exist is refused (at start-up, see test_reliability; here on a change)
        results = camera.set_parameters([Parameter("video_path", value=str(tmp_path / "missing.avi"))])
        assert not results[0].successful and "does not exist" in results[0].reason
        results = camera.set_parameters([Parameter("source", value="usb")])
        assert not results[0].successful and "one of" in results[0].reason
        results = camera.set_parameters([Parameter("width", value=-5)])
        assert not results[0].successful
        results = camera.set_parameters([Parameter("extrinsics.d", value=0.2)])  # outside the 5 cm tube
        assert not results[0].successful
        assert camera.get_parameter("source").value == "video"
        wait_for_subscription(camera, spin_until, executor)
        assert spin_until(executor, lambda: len(listener.images) >= 5, timeout=20)
        assert [listener.images[i].encoding for i in range(5)] == ["bgr8"] * 5
        assert camera.source is not None and "clip.avi" in camera.source.info
    finally:
        executor.shutdown()
        camera.destroy_node()


def test_diagnostics_report_rate_lag_and_drops(ros_context, spin_until):
    counter = itertools.count()

    class Endless(ListSource):
        def read(self, timeout):
            threading.Event().wait(0.01)
            i = next(counter)
            self.stats.captured += 1
            self.stats.dropped = i // 2  # pretend every other frame was dropped at capture
            return Frame(camera.get_clock().now().nanoseconds, np.zeros((4, 4, 3), np.uint8), i)

    listener, camera, executor = make_graph(ros_context, source=Endless([]))
    try:
        camera.start()

        def streaming():
            """Statuses once frames flow and drops are counted: an early status (a slow first frame on a
            loaded machine) may report 1 frame, none dropped and no rate yet."""
            return [s for array in listener.diagnostics for s in array.status
                    if int(status_values(s).get("dropped", "0")) > 0
                    and float(status_values(s).get("frame_rate_hz", "0")) > 0]

        assert spin_until(executor, lambda: bool(streaming()), timeout=20)
        status = streaming()[-1]
        values = status_values(status)
        assert int(values["published"]) > 0
        assert float(values["lag_median_ms"]) >= 0
        assert values["source"] == "list source"
        assert status.level == b"\x00" and status.message == "streaming"
    finally:
        executor.shutdown()
        camera.destroy_node()


def test_image_publisher_is_reliable_and_qos_can_be_overridden(ros_context, spin_until):
    source = ListSource([np.zeros((4, 4, 3), np.uint8)])
    camera = CameraNode(context=ros_context, source=source, autostart=False)
    try:
        info = camera.get_publishers_info_by_topic(IMAGE_TOPIC)
        assert info and info[0].qos_profile.reliability == ReliabilityPolicy.RELIABLE
    finally:
        camera.destroy_node()
    override = "qos_overrides." + IMAGE_TOPIC + ".publisher.reliability"
    camera = CameraNode(context=ros_context, source=ListSource([]), autostart=False,
                        parameter_overrides=[Parameter(override, value="best_effort")])
    try:
        info = camera.get_publishers_info_by_topic(IMAGE_TOPIC)
        assert info[0].qos_profile.reliability == ReliabilityPolicy.BEST_EFFORT
        # a best-effort subscriber still connects, as the perception node does
        listener = Node("be_listener", context=ros_context)
        from sensor_msgs.msg import Image

        listener.create_subscription(Image, IMAGE_TOPIC, lambda m: None,
                                     QoSProfile(depth=1, reliability=ReliabilityPolicy.BEST_EFFORT))
        assert spin_until(camera, lambda: camera.image_pub.get_subscription_count() == 1, timeout=20)
        listener.destroy_node()
    finally:
        camera.destroy_node()
    # the override applied to that node only: the next one is reliable again
    camera = CameraNode(context=ros_context, source=ListSource([]), autostart=False)
    try:
        info = camera.get_publishers_info_by_topic(IMAGE_TOPIC)
        assert info[0].qos_profile.reliability == ReliabilityPolicy.RELIABLE
    finally:
        camera.destroy_node()


def test_sim_source_by_parameters_publishes_rendered_frames(ros_context, spin_until):
    pytest.importorskip("touchroller_driver.sim")
    listener, camera, executor = make_graph(
        ros_context, parameter_overrides=[Parameter("source", value="sim"),
                                          Parameter("scene", value="surface_mapping"),
                                          Parameter("rate", value=0.0)])
    try:
        wait_for_subscription(camera, spin_until, executor)
        camera.start()
        assert spin_until(executor, lambda: len(listener.images) >= 2, timeout=30)
        msg = listener.images[0]
        assert (msg.encoding, msg.height, msg.width) == ("bgr8", 480, 640)
        assert image_to_array(msg).std() > 0
        assert "sim" in camera.source.info
    finally:
        executor.shutdown()
        camera.destroy_node()


def test_wait_for_subscribers_holds_the_source_until_a_subscriber_matches(ros_context, spin_until):
    """Replay: a recording's first frames (perception's reference) must not go out before anyone listens."""
    rng = np.random.default_rng(2)
    source = ListSource([rng.integers(0, 256, (48, 64, 3), dtype=np.uint8) for _ in range(3)])
    camera = CameraNode(context=ros_context, source=source,
                        parameter_overrides=[Parameter("wait_for_subscribers", value=1)])
    executor = SingleThreadedExecutor(context=ros_context)
    executor.add_node(camera)
    listener = None
    try:
        spin_until(executor, lambda: False, timeout=0.5)
        assert source.index == 0 and camera.published == 0          # nobody listens: nothing read
        listener = Listener(ros_context)
        executor.add_node(listener.node)
        assert spin_until(executor, lambda: len(listener.images) == 3, timeout=10.0)
        assert [m.header.stamp.sec * 10**9 + m.header.stamp.nanosec for m in listener.images] == source.stamps
    finally:
        executor.shutdown()
        camera.destroy_node()
        if listener is not None:
            listener.node.destroy_node()


@pytest.mark.timeout(120)
@pytest.mark.parametrize("processes", [1, 2], ids=["one_process", "two_processes"])
def test_sim_camera_is_on_the_sweep_nodes_arm_through_tf_and_one_clock(processes, ros_context, spin_until):
    """Scan graph as separate nodes (as ros2 launch runs them; with 2, the sweep node is its own process):
    only TF and the simulated clock (/clock) couple the sweep node's simulated arm and the simulated
    camera; the frames roll with the arm and stitch into a map of the commanded length."""
    from geometry_msgs.msg import PoseStamped
    from std_msgs.msg import Float32
    from std_srvs.srv import Trigger

    from touchroller_bringup.graph import build_graph
    from touchroller_bringup.nodes.sweep_node import SweepNode
    from touchroller_driver.sim.clock import first_frame_at_or_after, frame_time_ns
    from touchroller_perception.stitching import stitch

    length, speed = 0.01, 0.01                      # 1 cm in 1 s: ~30 frames, ~3 px of roll per frame
    graph = build_graph("scan", {"sweep_length": str(length), "sweep_speed": str(speed)})
    camera = CameraNode(context=ros_context, **graph.node("camera").node_kwargs())
    sweep = SweepNode(context=ros_context, **graph.node("sweep").node_kwargs()) if processes == 1 else None
    sweep_process = (start_node_process("touchroller_bringup.nodes.sweep_node", graph.node("sweep"))
                     if sweep is None else None)
    listener = Listener(ros_context, qos=QoSProfile(depth=200, reliability=ReliabilityPolicy.RELIABLE))
    poses: list = []
    progress: list = []
    listener.node.create_subscription(PoseStamped, names.topic(names.TCP_POSE), poses.append, 200)
    listener.node.create_subscription(Float32, names.topic(names.SWEEP_PROGRESS),
                                      lambda m: progress.append(m.data), 200)
    executor = SingleThreadedExecutor(context=ros_context)
    nodes = [n for n in (camera, sweep, listener.node) if n is not None]
    for node in nodes:
        executor.add_node(node)
    start, clearance = [0.4, 0.0, 0.2], 0.002     # config/scan.yaml's sweep.start_pose and sweep.clearance
    try:
        assert camera.get_parameter("sim.motion").value == "arm" and camera.tf_listener is not None
        assert camera.get_parameter("use_sim_time").value
        # the roller rests at (or above) the surface, unpressed: frames arrive once poses do, barely changing
        assert spin_until(executor, lambda: len(listener.images) >= 5, timeout=30.0)
        resting = [coarse(image_to_array(m)) for m in listener.images[-3:]]
        rest_change = np.mean(np.abs(resting[-1] - resting[-2]))
        latest_pose_ns = camera.tf_listener.buffer.time_range("tool0")[1]
        assert camera.source.state_at(latest_pose_ns).depth == pytest.approx(-clearance, abs=1e-9)
        # frames are on the simulated clock's frame grid: stamps are whole multiples of 1/30 s
        stamps = [m.header.stamp.sec * 10**9 + m.header.stamp.nanosec for m in listener.images]
        assert all(stamp == frame_time_ns(first_frame_at_or_after(stamp, 30.0), 30.0) for stamp in stamps)

        client = listener.node.create_client(Trigger, names.service(names.SWEEP_NODE, names.START))
        assert spin_until(executor, client.service_is_ready, timeout=10.0)
        future = client.call_async(Trigger.Request())
        assert spin_until(executor, future.done, timeout=10.0) and future.result().success

        def lifted_at_the_end() -> bool:
            last = poses[-1].pose.position if poses else None
            return bool(progress) and progress[-1] == 1.0 and last is not None and \
                last.x == pytest.approx(start[0] + length) and last.z == pytest.approx(start[2] + clearance)

        assert spin_until(executor, lifted_at_the_end, timeout=30.0)
        if sweep is not None:
            assert spin_until(executor, sweep.finished.is_set, timeout=20.0)
            assert sweep.status.phase.value == "done"
        spin_until(executor, lambda: False, timeout=0.3)   # the last frames
    finally:
        executor.shutdown()
        for node in nodes:
            node.destroy_node()
        sweep_exit = stop_node_process(sweep_process) if sweep_process is not None else None
    if sweep_exit is not None:
        assert_clean_exit(*sweep_exit)

    frames = [(stamp_to_ns(m.header.stamp), image_to_array(m))
              for m in listener.images]
    # the frames of the roll: while the arm's poses are on the rolling segment (pressed, moving along x)
    rolling_stamps = [stamp_to_ns(p.header.stamp) for p in poses
                      if start[0] + 1e-3 < p.pose.position.x < start[0] + length - 1e-3]
    rolling = [(stamp, image) for stamp, image in frames
               if rolling_stamps and rolling_stamps[0] <= stamp <= rolling_stamps[-1]]
    assert len(rolling) >= 15, len(rolling)     # ~0.8 s of roll at 30 Hz
    # over the roll the surface under the band has moved on by ~80 px: far more than frame noise
    roll_change = np.mean(np.abs(coarse(rolling[-1][1]) - coarse(rolling[0][1])))
    assert roll_change > 3 * rest_change, (roll_change, rest_change)   # measured 4-5x

    tactile_map, _ = stitch([image for _, image in frames], stamps=[stamp for stamp, _ in frames],
                            camera=camera.geometry.model)
    rolled_px = length / (camera.geometry.model.radius / camera.geometry.model.fy)
    # one band (the stitcher's 70 rows) + the roll (100 px at r / fy = 0.1 mm per pixel). A camera that does
    # not follow the arm gives one band (~70 rows), far outside this bound.
    assert abs(tactile_map.shape[0] - (70 + rolled_px)) <= 0.1 * rolled_px, (tactile_map.shape, rolled_px)


def start_node_process(module: str, spec) -> subprocess.Popen:
    """The node as its own process, with the graph's name, params files and parameters (as launch_ros
    would start it); it inherits the test's ROS_DOMAIN_ID."""
    arguments = list(spec.node_kwargs()["cli_args"])
    for name, value in spec.parameters.items():
        arguments += ["-p", f"{name}:={str(value).lower() if isinstance(value, bool) else value}"]
    return subprocess.Popen([sys.executable, "-c", f"from {module} import main; main()", *arguments],
                            env=dict(os.environ, PYTHONUNBUFFERED="1"), stdout=subprocess.PIPE,
                            stderr=subprocess.STDOUT, text=True)


def stop_node_process(process: subprocess.Popen) -> tuple[int, str]:
    """Ctrl-C; (exit code, output). Checked by the caller once the test body passed (not in `finally`,
    where a failure here would hide the body's)."""
    process.send_signal(signal.SIGINT)
    try:
        output, _ = process.communicate(timeout=30)
    except subprocess.TimeoutExpired:
        process.kill()
        output, _ = process.communicate()
    return process.returncode, output


def assert_clean_exit(returncode: int, output: str) -> None:
    assert returncode == 0, output


def coarse(image: np.ndarray) -> np.ndarray:
    """Grey, 8x smaller: the sensor noise averages out, the image content stays."""
    grey = cv2.cvtColor(image, cv2.COLOR_BGR2GRAY).astype(np.float64)
    return cv2.resize(grey, (grey.shape[1] // 8, grey.shape[0] // 8), interpolation=cv2.INTER_AREA)


def test_a_bad_start_up_parameter_is_the_error_not_a_failing_cleanup(ros_context):
    """`touchroller scan extrinsics.theta:=10.0` said `'CameraNode' object has no attribute '_stop'`: the
    context destroys every node it tracks at shutdown, also one whose constructor raised part-way."""
    from rclpy.exceptions import InvalidParameterValueException

    with pytest.raises(InvalidParameterValueException, match="extrinsics.theta") as failure:
        CameraNode(context=ros_context, autostart=False,
                   parameter_overrides=[Parameter("extrinsics.theta", value=10.0)])
    ros_context.try_shutdown()   # destroys the half-built node, which the traceback keeps alive
    assert failure.value is not None and not ros_context.ok()


def test_failing_right_after_node_init_shuts_down_cleanly(ros_context, fail_after_node_init):
    failure = fail_after_node_init(CameraNode)
    with pytest.raises(failure) as raised:
        CameraNode(context=ros_context, autostart=False)
    ros_context.try_shutdown()
    assert raised.value is not None and not ros_context.ok()


def _tf_only_bag(tmp_path):
    from touchroller_bringup.bags import TransformRecord, write_scan

    path = tmp_path / "tf_only"
    write_scan(path, [TransformRecord("base", "tool0", k, (0.0, 0.0, 0.0), (0.0, 0.0, 0.0, 1.0), False)
                      for k in range(3)])
    return path


@pytest.mark.parametrize("overrides, message", [
    ({"source": "V4L2"}, "source must be one of"),                       # a case typo: never the simulator
    ({"source": "usb"}, "source must be one of"),
    ({"source": "video", "video_path": "missing.avi"}, "video_path missing.avi does not exist"),
    ({"source": "bag", "bag_path": "no_such_bag"}, "bag_path no_such_bag does not exist"),
    ({"source": "bag", "bag_path": "TF_ONLY"}, "has no images on /touchroller/image_raw"),
    ({"source": "bag", "bag_path": "TF_ONLY", "bag_topic": "/tf"}, "has type tf2_msgs/msg/TFMessage"),
    ({"source": "sim", "scene": "no_such_scene"}, "scene 'no_such_scene'"),
    ({"source": "sim", "sim.motion": "bogus"}, "sim.motion must be one of"),
    ({"source": "sim", "frame_id": ""}, "frame_id must not be empty"),
    ({"source": "sim", "frame_prefix": "a b/"}, "frame_prefix 'a b/' must be empty or a frame id"),
])
def test_a_source_that_cannot_be_and_will_not_appear_stops_the_node_at_start_up(ros_context, tmp_path, overrides,
                                                                               message):
    """#28: these logged an ERROR and kept running (an unknown source fell back to the simulator)."""
    from touchroller_bringup.errors import UserError

    if overrides.get("bag_path") == "TF_ONLY":
        overrides = {**overrides, "bag_path": str(_tf_only_bag(tmp_path))}
    with pytest.raises(UserError, match=message):
        CameraNode(context=ros_context, autostart=False,
                   parameter_overrides=[Parameter(k, value=v) for k, v in overrides.items()])


def test_a_device_that_may_come_back_is_not_refused_at_start_up(ros_context):
    camera = CameraNode(context=ros_context, autostart=False, parameter_overrides=[
        Parameter("source", value="v4l2"), Parameter("device", value="/dev/video_not_plugged_in")])
    camera.destroy_node()
