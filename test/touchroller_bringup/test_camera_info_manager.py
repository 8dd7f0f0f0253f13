"""camera_info_manager's conventions on the camera node over a real rclpy context: camera_info_url round trip,
~/set_camera_info, the optical frame, one-line errors for a bad URL."""
from __future__ import annotations

import numpy as np
import pytest

pytest.importorskip("rclpy")
from rclpy.executors import SingleThreadedExecutor  # noqa: E402
from rclpy.node import Node  # noqa: E402
from rclpy.parameter import Parameter  # noqa: E402

from touchroller_bringup import names  # noqa: E402
from touchroller_bringup.camera_info_files import (  # noqa: E402
    CameraCalibration,
    read_camera_info,
    write_camera_info,
)
from touchroller_bringup.errors import UserError  # noqa: E402
from touchroller_bringup.nodes.camera_node import CameraNode  # noqa: E402
from touchroller_driver.sources import Frame, SourceStats  # noqa: E402

pytestmark = pytest.mark.ros

# a calibration as ROS's cameracalibrator commits it: P is not [K | 0]
CALIBRATION = CameraCalibration("roller_left", 320, 240, (301.5, 0.0, 161.25, 0.0, 302.75, 119.5, 0.0, 0.0, 1.0),
                                "plumb_bob", (-0.21, 0.047, 0.0012, -0.0007, 0.0031),
                                p=(290.0, 0.0, 160.0, 0.0, 0.0, 291.0, 120.0, 0.0, 0.0, 0.0, 1.0, 0.0))


class FrameList:
    """An external FrameSource: `count` grey frames, then finished."""

    def __init__(self, count: int = 200) -> None:
        self.count, self.index, self.stats = count, 0, SourceStats()

    info = "frame list"

    def open(self) -> None:
        self.stats.connected = True

    def read(self, timeout: float):
        if self.index >= self.count:
            self.stats.finished = True
            return None
        self.index += 1
        import time

        time.sleep(0.01)
        return Frame(1_700_000_000_000_000_000 + self.index * 10_000_000, np.zeros((240, 320, 3), np.uint8), self.index)

    def close(self) -> None:
        self.stats.connected = False


def camera_info_of(msg) -> CameraCalibration:
    return CameraCalibration(CALIBRATION.camera_name, msg.width, msg.height, tuple(msg.k), msg.distortion_model,
                             tuple(msg.d), tuple(msg.r), tuple(msg.p))


def test_camera_info_url_round_trip(ros_context, spin_until, tmp_path):
    """Write the YAML, load it through the URL, publish it, set_camera_info writes it back, a reload equals."""
    from sensor_msgs.msg import CameraInfo
    from sensor_msgs.srv import SetCameraInfo

    path = tmp_path / "cams" / "roller_left.yaml"
    write_camera_info(path, CALIBRATION)
    url = f"file://{tmp_path}/cams/${{NAME}}.yaml"
    camera = CameraNode(context=ros_context, autostart=False, source=FrameList(), parameter_overrides=[
        Parameter("camera_name", value="roller_left"), Parameter("camera_info_url", value=url)])
    helper = Node("camera_info_helper", context=ros_context)
    infos: list = []
    helper.create_subscription(CameraInfo, names.topic(names.CAMERA_INFO), infos.append, 10)
    executor = SingleThreadedExecutor(context=ros_context)
    for node in (camera, helper):
        executor.add_node(node)
    try:
        # loaded: the node's camera.* parameters are the file's intrinsics
        assert camera.get_parameter("camera.fx").value == 301.5
        assert list(camera.get_parameter("camera.distortion").value) == list(CALIBRATION.d)
        assert (camera.get_parameter("camera.width").value, camera.get_parameter("camera.height").value) == (320, 240)
        assert spin_until(executor, lambda: camera.info_pub.get_subscription_count() > 0, timeout=20)
        camera.start()
        assert spin_until(executor, lambda: len(infos) >= 1, timeout=20)
        assert camera_info_of(infos[0]) == CALIBRATION        # published as the file has it, its own P
        assert infos[0].header.frame_id == names.CAMERA_OPTICAL_FRAME

        # set_camera_info: stored on the node, written back to the URL's file
        client = helper.create_client(SetCameraInfo, names.service(names.CAMERA_NODE, names.SET_CAMERA_INFO))
        assert spin_until(executor, client.service_is_ready, timeout=20)
        request = SetCameraInfo.Request()
        new = CameraCalibration("whatever", 320, 240, (310.0, 0.0, 158.0, 0.0, 311.0, 121.0, 0.0, 0.0, 1.0),
                                "plumb_bob", (0.01, -0.002, 0.0, 0.0, 0.0))
        for field in ("width", "height", "distortion_model"):
            setattr(request.camera_info, field, getattr(new, field))
        request.camera_info.k, request.camera_info.d = list(new.k), list(new.d)
        request.camera_info.r, request.camera_info.p = list(new.r), list(new.p)
        future = client.call_async(request)
        assert spin_until(executor, future.done, timeout=20)
        assert future.result().success, future.result().status_message
        assert str(path) in future.result().status_message
        assert camera.get_parameter("camera.fx").value == 310.0
        expected = CameraCalibration("roller_left", *[getattr(new, f) for f in ("width", "height", "k",
                                                                                 "distortion_model", "d", "r", "p")])
        assert read_camera_info(path) == expected             # written with the node's camera_name
        count = len(infos)
        assert spin_until(executor, lambda: len(infos) > count and infos[-1].k[0] == 310.0, timeout=20)

        # a camera info the camera model cannot hold is refused, and nothing changes
        request.camera_info.distortion_model = "equidistant"
        request.camera_info.d = [0.1, 0.0, 0.0, 0.0]
        future = client.call_async(request)
        assert spin_until(executor, future.done, timeout=20)
        assert not future.result().success and "'equidistant' is not supported" in future.result().status_message
        assert read_camera_info(path) == expected
    finally:
        executor.shutdown()
        camera.destroy_node()
        helper.destroy_node()
    again = CameraNode(context=ros_context, autostart=False, source=FrameList(), parameter_overrides=[
        Parameter("camera_name", value="roller_left"), Parameter("camera_info_url", value=url)])
    try:
        assert again.camera_info.calibration == expected          # reload equals what was set
        assert again.get_parameter("camera.fx").value == 310.0
    finally:
        again.destroy_node()


def test_without_a_url_set_camera_info_sets_the_node_and_says_it_saved_nothing(ros_context):
    from sensor_msgs.msg import CameraInfo

    camera = CameraNode(context=ros_context, autostart=False, source=FrameList())
    try:
        info = CameraInfo()
        info.width, info.height, info.distortion_model = 320, 240, "plumb_bob"
        info.k = [400.0, 0.0, 160.0, 0.0, 400.0, 120.0, 0.0, 0.0, 1.0]
        info.d = [0.0] * 5
        info.r = list(CALIBRATION.r)
        info.p = [400.0, 0.0, 160.0, 0.0, 0.0, 400.0, 120.0, 0.0, 0.0, 0.0, 1.0, 0.0]
        ok, message = camera.camera_info.store(info)
        assert ok and "not saved to a file: camera_info_url is empty" in message
        assert camera.get_parameter("camera.fx").value == 400.0
        # a camera.* parameter set by hand is published from then on (P = [K | 0])
        camera.set_parameters([Parameter("camera.fx", value=420.0)])
        assert camera.camera_info.calibration.k[0] == 420.0 and camera.camera_info.calibration.p[0] == 420.0
    finally:
        camera.destroy_node()


def test_a_file_that_does_not_exist_yet_is_created_by_the_first_set_camera_info(ros_context, tmp_path):
    from sensor_msgs.msg import CameraInfo

    url = f"file://{tmp_path}/new/cam.yaml"
    camera = CameraNode(context=ros_context, autostart=False, source=FrameList(),
                        parameter_overrides=[Parameter("camera_info_url", value=url)])
    try:
        assert camera.get_parameter("camera.fx").value == 500.0        # the defaults until then
        info = CameraInfo()
        info.width, info.height, info.distortion_model = 640, 480, "plumb_bob"
        info.k = [505.0, 0.0, 320.0, 0.0, 506.0, 240.0, 0.0, 0.0, 1.0]
        info.d, info.r = [0.0] * 5, list(CALIBRATION.r)
        info.p = [505.0, 0.0, 320.0, 0.0, 0.0, 506.0, 240.0, 0.0, 0.0, 0.0, 1.0, 0.0]
        ok, message = camera.camera_info.store(info)
        assert ok, message
        assert read_camera_info(tmp_path / "new" / "cam.yaml").k[0] == 505.0
    finally:
        camera.destroy_node()


@pytest.mark.parametrize("url, message", [
    ("/tmp/cam.yaml", "is not a file:///path.yaml or package://PACKAGE/path.yaml URL"),
    ("package://no_such_package_here/cam.yaml", "package 'no_such_package_here' of the camera_info_url is not found"),
    ("file:///BAD", "camera_matrix is missing"),
])
def test_a_bad_url_stops_the_node_in_one_line_and_is_refused_at_run_time(ros_context, tmp_path, url, message):
    if url == "file:///BAD":
        (tmp_path / "bad.yaml").write_text("image_width: 640\nimage_height: 480\n")
        url = f"file://{tmp_path}/bad.yaml"
    with pytest.raises(UserError, match=message) as info:
        CameraNode(context=ros_context, autostart=False, source=FrameList(),
                   parameter_overrides=[Parameter("camera_info_url", value=url)])
    assert "\n" not in str(info.value)
    camera = CameraNode(context=ros_context, autostart=False, source=FrameList())
    try:
        result = camera.set_parameters([Parameter("camera_info_url", value=url)])[0]
        assert not result.successful and message.split(" of ")[0] in result.reason and "\n" not in result.reason
        bad_name = camera.set_parameters([Parameter("camera_name", value="left-cam")])[0]
        assert not bad_name.successful and "letters, digits and _" in bad_name.reason
    finally:
        camera.destroy_node()


def test_a_url_set_at_run_time_loads_its_file(ros_context, tmp_path):
    write_camera_info(tmp_path / "cam.yaml", CALIBRATION)
    camera = CameraNode(context=ros_context, autostart=False, source=FrameList())
    try:
        assert camera.set_parameters([Parameter("camera_info_url", value=f"file://{tmp_path}/cam.yaml")])[0].successful
        assert camera.camera_info.calibration.p == CALIBRATION.p      # loaded by the time the set returns
        assert camera.get_parameter("camera.fx").value == 301.5
    finally:
        camera.destroy_node()


def test_the_optical_frame_is_on_tf_static_under_touchroller_camera(ros_context, spin_until):
    from touchroller_bringup.tf import TransformListener

    camera = CameraNode(context=ros_context, autostart=False, source=FrameList(), namespace="left")
    helper = Node("tf_helper", context=ros_context)
    listener = TransformListener(helper)
    executor = SingleThreadedExecutor(context=ros_context)
    for node in (camera, helper):
        executor.add_node(node)
    try:
        assert camera.frame_id == "left/touchroller_camera_optical_frame"
        assert spin_until(executor, lambda: listener.received > 0, timeout=20)
        with listener.lock:
            transform = listener.buffer.lookup("left/touchroller_camera", "left/touchroller_camera_optical_frame", 0)
        assert np.allclose(transform.matrix(), np.eye(4))   # touchroller_camera has the optical axes already
        # and it is the image's frame: points of the membrane carried by TF (cylinder -> camera from theta and d,
        # as the perception node publishes it, then this transform) into the optical frame project through the
        # camera_info's K onto the pixels the camera model puts them at (x along u, y along v, z the view)
        from touchroller_bringup.tf import camera_in_cylinder
        from touchroller_perception.geometry import CameraModel

        model = CameraModel.from_params({**camera.geometry.model.to_params(), "extrinsics.theta": 0.3,
                                         "extrinsics.d": 0.012})
        pixels = np.array([[100.0, 80.0], [320.0, 240.0], [600.0, 400.0], [500.0, 90.0]])
        points, valid = model.back_project(pixels)
        assert valid.all()
        optical = (camera_in_cylinder(model) @ transform).inverse().apply(points)
        k = np.array(camera.camera_info.calibration.k).reshape(3, 3)
        assert (optical[:, 2] > 0).all()
        projected = (k @ (optical / optical[:, 2:]).T).T[:, :2]
        np.testing.assert_allclose(projected, pixels, atol=1e-6)
    finally:
        executor.shutdown()
        camera.destroy_node()
        helper.destroy_node()
