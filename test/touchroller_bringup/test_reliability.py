"""Reliability: truncated bags, bad parameter values, malformed images, a camera that vanishes.

Each case must give one clear log line or error, keep the node running, and lose nothing else.
"""
from __future__ import annotations

import itertools
import threading

import numpy as np
import pytest

pytest.importorskip("rclpy")
from rclpy.executors import SingleThreadedExecutor  # noqa: E402
from rclpy.node import Node  # noqa: E402
from rclpy.parameter import Parameter  # noqa: E402
from sensor_msgs.msg import Image  # noqa: E402

from touchroller_bringup.bags import read_images  # noqa: E402
from touchroller_bringup.cli import main  # noqa: E402
from touchroller_bringup.names import IMAGE_TOPIC  # noqa: E402
from touchroller_bringup.nodes.camera_node import CameraNode  # noqa: E402
from touchroller_driver.sources import Backoff, BagSource, V4L2Source  # noqa: E402

pytestmark = pytest.mark.ros


def truncate_storage(bag):
    storage = next(p for p in bag.iterdir() if p.suffix in (".db3", ".mcap"))
    with open(storage, "r+b") as stream:
        stream.truncate(storage.stat().st_size // 2)


def frames(n, shape=(24, 32, 3)):
    return [(1_000_000_000 + i * 10_000_000, np.full(shape, i, np.uint8)) for i in range(n)]


@pytest.mark.parametrize("storage", ["sqlite3", "mcap"])
def test_truncated_bag_is_one_line_for_replay_and_ends_a_bag_source_cleanly(
        ros_context, bag_factory, capsys, storage):
    bag = bag_factory(frames(40), storage=storage)
    truncate_storage(bag)
    assert main(["replay", str(bag), "--rate", "100"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and str(bag) in err[0] and "Traceback" not in err[0]

    source = BagSource(bag, rate=0.0, reader=read_images)
    source.open()
    assert source.read(timeout=0.5) is None  # no exception escapes
    assert source.stats.finished and source.stats.last_error


def test_camera_node_on_a_truncated_bag_reports_and_keeps_serving(ros_context, spin_until, bag_factory):
    bag = bag_factory(frames(20), storage="mcap")
    truncate_storage(bag)
    camera = CameraNode(context=ros_context, parameter_overrides=[
        Parameter("source", value="bag"), Parameter("bag_path", value=str(bag)), Parameter("rate", value=0.0)])
    try:
        assert spin_until(camera, lambda: camera.finished, timeout=20)
        status = camera._diagnostic_status()
        assert status.level == 2 and "source stopped" in status.message
        # still alive: parameters still answer, a new (good) source can be chosen
        good = bag_factory(frames(3))
        assert camera.set_parameters([Parameter("bag_path", value=str(good))])[0].successful
        assert spin_until(camera, lambda: camera.published == 3, timeout=20)
    finally:
        camera.destroy_node()


def test_bad_parameter_values_are_rejected_and_keep_the_old_values(ros_context):
    camera = CameraNode(context=ros_context, autostart=False)
    try:
        bad = [Parameter("exposure", value=float("nan")), Parameter("fps", value=float("inf")),
               Parameter("width", value="wide"), Parameter("rate", value=-1.0),
               Parameter("source", value="gige"), Parameter("frame_id", value=" "),
               Parameter("camera.fx", value=float("nan")), Parameter("extrinsics.d", value=0.05),
               Parameter("camera.distortion", value=[0.1, 0.2])]
        before = {p.name: camera.get_parameter(p.name).value for p in bad}
        for param in bad:
            result = camera.set_parameters([param])[0]
            assert not result.successful, param.name
            assert result.reason and "\n" not in result.reason
        assert {p.name: camera.get_parameter(p.name).value for p in bad} == before
        assert camera.geometry.model.fx == 500.0
    finally:
        camera.destroy_node()


class DyingCapture:
    """A capture that delivers 5 frames and then fails every grab, like an unplugged USB camera."""

    opened = 0

    def __init__(self, counter):
        DyingCapture.opened += 1
        self.counter, self.grabs = counter, 0

    def isOpened(self):  # noqa: N802
        return True

    def grab(self):
        threading.Event().wait(0.005)
        self.grabs += 1
        return self.grabs <= 5

    def retrieve(self):
        image = np.zeros((8, 8, 3), np.uint8)
        image[0, 0, :2] = divmod(next(self.counter), 256)  # the frame number, big-endian in two bytes
        return True, image

    def release(self):
        pass


def test_camera_that_vanishes_is_reconnected_and_publishing_resumes(ros_context, spin_until):
    counter = itertools.count()
    DyingCapture.opened = 0
    source = V4L2Source("/dev/v4l/by-id/usb-fake", open_capture=lambda: DyingCapture(counter),
                        backoff=Backoff(0.01, 2.0, 0.05))
    camera = CameraNode(context=ros_context, source=source)
    listener = Node("listener", context=ros_context)
    received = []
    listener.create_subscription(Image, IMAGE_TOPIC, received.append, 50)
    executor = SingleThreadedExecutor(context=ros_context)
    executor.add_node(camera)
    executor.add_node(listener)
    try:
        assert spin_until(executor, lambda: len(received) >= 12 and DyingCapture.opened >= 3, timeout=15)
        assert source.stats.reconnects >= 2
        values = [256 * m.data[0] + m.data[1] for m in received]
        assert values == sorted(values)  # in order, nothing duplicated
        assert camera._diagnostic_status().values["reconnects"] >= 2
    finally:
        executor.shutdown()
        camera.destroy_node()
        listener.destroy_node()


def malformed_images():
    good = np.zeros((48, 64, 3), np.uint8)
    cases = []
    for change in ({"step": 10}, {"height": 4800}, {"encoding": "yuv422_yuy2"}, {"encoding": "8UC7"},
                   {"width": 0}):
        msg = Image(height=48, width=64, encoding="bgr8", step=64 * 3, is_bigendian=0)
        msg.data = good.tobytes()
        for key, value in change.items():
            setattr(msg, key, value)
        cases.append(msg)
    short = Image(height=48, width=64, encoding="bgr8", step=64 * 3)
    short.data = good.tobytes()[:1000]
    cases.append(short)
    return cases


def test_perception_node_survives_malformed_images(ros_context, spin_until):
    perception_node = pytest.importorskip("touchroller_bringup.nodes.perception_node")
    node = perception_node.PerceptionNode(context=ros_context)
    talker = Node("talker", context=ros_context)
    publisher = talker.create_publisher(Image, IMAGE_TOPIC, 10)
    executor = SingleThreadedExecutor(context=ros_context)
    executor.add_node(node)
    executor.add_node(talker)
    try:
        assert spin_until(executor, lambda: publisher.get_subscription_count() > 0, timeout=20)
        for msg in malformed_images():
            publisher.publish(msg)
            executor.spin_once(timeout_sec=0.05)  # a callback that raised would propagate here
        spin_until(executor, lambda: False, timeout=0.3)
        assert node.get_parameter("camera.fx").value == 500.0  # still answering
        good = Image(height=48, width=64, encoding="bgr8", step=64 * 3)
        good.data = np.zeros((48, 64, 3), np.uint8).tobytes()
        publisher.publish(good)
        spin_until(executor, lambda: False, timeout=0.2)
    finally:
        executor.shutdown()
        node.destroy_node()
        talker.destroy_node()
