"""The perception node on a real rclpy context: synthetic frames in, PointStamped contacts out."""
from __future__ import annotations

import math
from types import SimpleNamespace

import numpy as np
import pytest

pytest.importorskip("rclpy")
pytestmark = pytest.mark.ros

from rclpy.executors import SingleThreadedExecutor  # noqa: E402
from rclpy.parameter import Parameter  # noqa: E402

from touchroller_bringup import names  # noqa: E402
from touchroller_driver.sim.taps import TapRenderer  # noqa: E402
from touchroller_perception.geometry import CameraModel  # noqa: E402

IMAGE_TOPIC = names.topic(names.IMAGE)   # /touchroller/image_raw
CAMERA = CameraModel(fx=200.0, fy=200.0, cx=159.5, cy=119.5, width=320, height=240)


@pytest.fixture
def graph(ros_context):
    from geometry_msgs.msg import PointStamped
    from sensor_msgs.msg import Image
    from std_srvs.srv import Trigger

    from touchroller_bringup.nodes.perception_node import PerceptionNode

    overrides = [Parameter(name, value=value) for name, value in CAMERA.to_params().items()]
    overrides += [Parameter("reference.frames", value=3), Parameter("map.publish_rate", value=0.0)]
    node = PerceptionNode(context=ros_context, parameter_overrides=overrides)
    helper = rclpy_node("perception_test_helper", ros_context)
    received: list = []
    helper.create_subscription(PointStamped, names.topic(names.CONTACTS), received.append, 10)
    image_pub = helper.create_publisher(Image, IMAGE_TOPIC, 10)
    recapture = helper.create_client(Trigger, names.service(names.PERCEPTION_NODE, names.RECAPTURE_REFERENCE))
    executor = SingleThreadedExecutor(context=ros_context)
    executor.add_node(node)
    executor.add_node(helper)
    yield node, executor, image_pub, recapture, received
    executor.shutdown()
    node.destroy_node()
    helper.destroy_node()


def rclpy_node(name, context):
    from rclpy.node import Node

    return Node(name, context=context)


def send(executor, spin_until, node, publisher, msg) -> None:
    """Publish one frame and spin until the node has taken it (the image QoS keeps only the newest)."""
    before = node.received
    assert spin_until(executor, lambda: publisher.get_subscription_count() > 0, timeout=10.0)
    publisher.publish(msg)
    assert spin_until(executor, lambda: node.received > before, timeout=10.0)


def test_contacts_are_published_with_stamp_frame_and_position(graph, spin_until):
    from touchroller_bringup.image_conversion import array_to_image

    node, executor, image_pub, recapture, received = graph
    renderer = TapRenderer(CAMERA, seed=1)
    rng = np.random.default_rng(0)
    for i in range(3):
        send(executor, spin_until, node, image_pub, array_to_image(renderer.render([], rng), 1_000 + i))
    assert node.detector.reference_ready and received == []

    truth = CAMERA.surface_point(0.012, 0.15)
    uv, _ = CAMERA.project(truth)
    frame = renderer.render([uv], rng)
    stamp_ns = 1_700_000_000_123_456_789
    send(executor, spin_until, node, image_pub, array_to_image(frame, stamp_ns))
    assert spin_until(executor, lambda: len(received) == 1, timeout=20.0)
    point = received[0]
    assert point.header.frame_id == "touchroller_cylinder"
    assert point.header.stamp.sec * 1_000_000_000 + point.header.stamp.nanosec == stamp_ns
    located = np.array([point.point.x, point.point.y, point.point.z])
    assert np.linalg.norm(located - truth) < 0.3e-3

    # the calibration node sets theta at run time: the same pixel now maps elsewhere
    theta = 0.05
    assert node.set_parameters([Parameter("extrinsics.theta", value=theta)])[0].successful
    assert node.camera.theta == theta
    send(executor, spin_until, node, image_pub, array_to_image(frame, stamp_ns + 1))
    assert spin_until(executor, lambda: len(received) == 2, timeout=20.0)
    moved = np.array([received[1].point.x, received[1].point.y, received[1].point.z])
    expected, _ = CAMERA.replace(theta=theta).back_project(uv)
    assert np.linalg.norm(moved - expected) < 0.3e-3
    assert np.linalg.norm(moved - located) == pytest.approx(CAMERA.radius * theta, rel=0.1)
    # an invalid combination is refused with a reason, the model stays as it was
    result = node.set_parameters([Parameter("extrinsics.d", value=0.2)])[0]
    assert not result.successful and node.camera.d == 0.0

    # a malformed image is logged and counted; the node keeps detecting
    bad = array_to_image(frame, stamp_ns + 2)
    bad.step = 7
    send(executor, spin_until, node, image_pub, bad)
    assert node.malformed == 1
    odd = array_to_image(frame, stamp_ns + 2)
    odd.encoding = "32FC1"
    send(executor, spin_until, node, image_pub, odd)
    short = array_to_image(frame[:10], stamp_ns + 2)
    short.height = CAMERA.height                     # claims more rows than its data holds
    send(executor, spin_until, node, image_pub, short)
    assert node.malformed == 3
    send(executor, spin_until, node, image_pub, array_to_image(frame, stamp_ns + 3))
    assert spin_until(executor, lambda: len(received) == 3, timeout=20.0)

    # diagnostics: counts of what happened, published on /diagnostics
    from diagnostic_msgs.msg import DiagnosticArray

    from touchroller_bringup.ros_diagnostics import WARN, status_values

    status = node._diagnostic_status()
    assert status.level == WARN and "3 malformed" in status.message   # bad input is never silent
    assert status.values["frames_malformed"] == 3 and status.values["contacts_total"] == 3
    assert status.values["frames_received"] == 3 + 6
    arrays: list = []
    helper = [n for n in executor.get_nodes() if n is not node][0]
    helper.create_subscription(DiagnosticArray, "/diagnostics", arrays.append, 10)
    assert spin_until(executor, lambda: any("perception" in s.name for a in arrays for s in a.status), timeout=20.0)
    mine = [s for a in arrays for s in a.status if "perception" in s.name][0]
    assert float(status_values(mine)["processing_ms_median"]) > 0

    # recapturing the reference: the next 3 frames are the new background
    assert spin_until(executor, recapture.service_is_ready, timeout=10.0)
    future = recapture.call_async(recapture.srv_type.Request())
    assert spin_until(executor, future.done, timeout=20.0)
    assert future.result().success and "3 frames" in future.result().message
    assert not node.detector.reference_ready


def test_detector_parameters_are_validated_and_applied(graph):
    node = graph[0]
    assert not node.set_parameters([Parameter("contacts.method", value="magic")])[0].successful
    assert node.set_parameters([Parameter("contacts.method", value="paper")])[0].successful
    assert node.detector.config.method == "paper"
    assert node.set_parameters([Parameter("contacts.threshold_sigma", value=4.0)])[0].successful
    assert math.isclose(node.detector.config.threshold_sigma, 4.0)
    assert node.set_parameters([Parameter("contacts.compensate_illumination", value=False)])[0].successful
    assert node.detector.config.compensate_illumination is False
    # out of the declared range: rclpy refuses it
    assert not node.set_parameters([Parameter("contacts.downscale", value=64)])[0].successful


def test_stitcher_parameters_are_validated_and_start_a_new_map(graph):
    node = graph[0]
    assert node.stitcher_config.method == "default"
    assert not node.set_parameters([Parameter("map.method", value="magic")])[0].successful
    node.stitcher = object()   # stands for a map in progress
    assert node.set_parameters([Parameter("map.method", value="paper"),
                                Parameter("map.band_rows", value=50)])[0].successful
    assert (node.stitcher_config.method, node.stitcher_config.band_rows) == ("paper", 50)
    assert node.stitcher is None   # the next frame starts a map stitched the new way
    # outside the declared range
    assert not node.set_parameters([Parameter("map.keyframe_overlap", value=1.5)])[0].successful


def test_tactile_map_is_published_latched(ros_context, spin_until):
    pytest.importorskip("touchroller_perception.stitching")
    from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy
    from sensor_msgs.msg import Image

    from touchroller_bringup.image_conversion import array_to_image, image_to_array
    from touchroller_bringup.nodes.perception_node import PerceptionNode

    overrides = [Parameter(name, value=value) for name, value in CAMERA.to_params().items()]
    overrides += [Parameter("reference.frames", value=2), Parameter("map.publish_rate", value=50.0)]
    node = PerceptionNode(context=ros_context, parameter_overrides=overrides)
    helper = rclpy_node("map_test_helper", ros_context)
    image_pub = helper.create_publisher(Image, IMAGE_TOPIC, 10)
    executor = SingleThreadedExecutor(context=ros_context)
    executor.add_node(node)
    executor.add_node(helper)
    try:
        rng = np.random.default_rng(0)
        texture = rng.integers(0, 255, (CAMERA.height * 3, CAMERA.width, 3), dtype=np.uint8)
        for k in range(6):   # the surface slides along v by 4 px a frame
            frame = np.ascontiguousarray(texture[4 * k:4 * k + CAMERA.height])
            send(executor, spin_until, node, image_pub, array_to_image(frame, 1_000_000 * (k + 1)))
        assert spin_until(executor, lambda: node.stitcher is not None and not node._map_dirty, timeout=20.0)
        # a subscriber that joins late still gets the last map (transient local)
        maps: list = []
        latched = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=1, reliability=ReliabilityPolicy.RELIABLE,
                             durability=DurabilityPolicy.TRANSIENT_LOCAL)
        helper.create_subscription(Image, names.topic(names.MAP), maps.append, latched)
        assert spin_until(executor, lambda: len(maps) >= 1, timeout=20.0)
        tactile_map = image_to_array(maps[0])
        assert tactile_map.size > 0 and maps[0].header.frame_id == "touchroller_cylinder"
        # 0 Hz disables the map
        assert node.set_parameters([Parameter("map.publish_rate", value=0.0)])[0].successful
        assert node._map_timer is None
    finally:
        executor.shutdown()
        node.destroy_node()
        helper.destroy_node()


def test_a_busy_node_skips_stale_frames_and_counts_them(graph, spin_until):
    from touchroller_bringup.image_conversion import array_to_image
    from touchroller_bringup.nodes.perception_node import _has_message_info

    node, executor, image_pub, _, _ = graph
    assert spin_until(executor, lambda: image_pub.get_subscription_count() > 0, timeout=10.0)
    frame = TapRenderer(CAMERA, seed=1).render([], np.random.default_rng(0))
    send(executor, spin_until, node, image_pub, array_to_image(frame, 999))   # the sequence baseline
    for k in range(8):           # published while the node is not spinning: only the newest is kept
        image_pub.publish(array_to_image(frame, 1000 + k))
    assert spin_until(executor, lambda: node.received >= 2, timeout=20.0)
    spin_until(executor, lambda: False, timeout=0.3)
    assert node.received < 1 + 8
    if _has_message_info():
        assert node.received + node.dropped == 1 + 8
    # Skipped on purpose (keep-last 1), not lost: DDS's message_lost count stays at zero.
    assert node.lost_in_transport == 0


def test_image_subscription_qos_defaults_and_overrides(ros_context, spin_until):
    from rclpy.qos import HistoryPolicy, ReliabilityPolicy

    from touchroller_bringup.nodes.perception_node import PerceptionNode

    prefix = f"qos_overrides.{IMAGE_TOPIC}.subscription"
    default = PerceptionNode("perception_default", context=ros_context,
                             parameter_overrides=[Parameter("map.publish_rate", value=0.0)])
    overridden = PerceptionNode("perception_overridden", context=ros_context, parameter_overrides=[
        Parameter("map.publish_rate", value=0.0), Parameter(f"{prefix}.depth", value=3),
        Parameter(f"{prefix}.reliability", value="reliable")])
    probe = rclpy_node("qos_probe", ros_context)
    try:
        assert (default.image_sub.qos_profile.depth, default.image_sub.qos_profile.reliability) == \
            (1, ReliabilityPolicy.BEST_EFFORT)
        assert default.get_parameter(f"{prefix}.depth").value == 1
        assert overridden.image_sub.qos_profile.depth == 3
        assert overridden.image_sub.qos_profile.reliability == ReliabilityPolicy.RELIABLE
        assert overridden.image_sub.qos_profile.history == HistoryPolicy.KEEP_LAST
        # what the middleware was given, as another node sees the graph
        def endpoints():
            return {info.node_name: info.qos_profile for info in probe.get_subscriptions_info_by_topic(IMAGE_TOPIC)}

        assert spin_until(probe, lambda: {"perception_default", "perception_overridden"} <= set(endpoints()),
                          timeout=10.0)
        seen = endpoints()
        assert seen["perception_overridden"].reliability == ReliabilityPolicy.RELIABLE
        assert seen["perception_default"].reliability == ReliabilityPolicy.BEST_EFFORT
        # read-only: fixed at start-up, as rclpy's QoS overrides are
        assert not overridden.set_parameters([Parameter(f"{prefix}.depth", value=5)])[0].successful
    finally:
        for node in (default, overridden, probe):
            node.destroy_node()


def test_map_follows_the_roll_and_is_saved_when_it_ends(ros_context, spin_until, tmp_path):
    pytest.importorskip("touchroller_perception.stitching")
    import cv2
    from sensor_msgs.msg import Image
    from std_msgs.msg import Float32

    from touchroller_bringup.image_conversion import array_to_image
    from touchroller_bringup.nodes.perception_node import PerceptionNode

    saved = tmp_path / "map.png"
    overrides = [Parameter(name, value=value) for name, value in CAMERA.to_params().items()]
    overrides += [Parameter("reference.frames", value=2), Parameter("map.publish_rate", value=20.0),
                  Parameter("map.save_path", value=str(saved))]
    node = PerceptionNode(context=ros_context, parameter_overrides=overrides)
    helper = rclpy_node("roll_test_helper", ros_context)
    image_pub = helper.create_publisher(Image, IMAGE_TOPIC, 10)
    from rclpy.node import Node

    sweep = Node(names.SWEEP_NODE, namespace=names.DEFAULT_NAMESPACE, context=ros_context)   # progress is the sweep's
    progress_pub = sweep.create_publisher(Float32, names.topic(names.SWEEP_PROGRESS), 10)
    executor = SingleThreadedExecutor(context=ros_context)
    executor.add_node(node)
    executor.add_node(helper)
    executor.add_node(sweep)

    def progress(value: float) -> None:
        assert spin_until(executor, lambda: progress_pub.get_subscription_count() > 0, timeout=10.0)
        progress_pub.publish(Float32(data=value))

    try:
        rng = np.random.default_rng(1)
        texture = rng.integers(0, 255, (CAMERA.height * 4, CAMERA.width, 3), dtype=np.uint8)
        frame = np.ascontiguousarray(texture[:CAMERA.height])
        for k in range(3):   # the approach: the roller stands still
            send(executor, spin_until, node, image_pub, array_to_image(frame, 1_000_000 * (k + 1)))
        approach = node.stitcher
        assert approach is not None
        progress(0.0)
        progress(0.01)   # the roll starts: a new map
        assert spin_until(executor, lambda: node.stitcher is None, timeout=20.0)
        for k in range(20):   # the surface slides along v by 5 px a frame
            frame = np.ascontiguousarray(texture[5 * k:5 * k + CAMERA.height])
            send(executor, spin_until, node, image_pub, array_to_image(frame, 10_000_000 * (k + 1)))
        assert node.stitcher is not approach and not saved.exists()
        progress(1.0)    # the roll ended: finalised, published and saved
        assert spin_until(executor, lambda: node.saved_maps == 1, timeout=20.0)
        written = cv2.imread(str(saved), cv2.IMREAD_UNCHANGED)
        assert written is not None and written.shape == node.stitcher.map_image().shape
        assert written.shape[0] >= 70 + 0.9 * 19 * 5, written.shape   # the roll (19 x 5 px), not one band
        # a path that cannot be written is one error line; the node keeps working
        unwritable = str(tmp_path / "missing" / "m.png")
        assert node.set_parameters([Parameter("map.save_path", value=unwritable)])[0].successful
        # progress and images are separate topics, delivered independently: wait until the node has taken
        # each progress message before the next step (else the frame could land before the roll began, or
        # the final check could run before 1.0 arrived and pass on the previous roll's state)
        progress(0.5)
        assert spin_until(executor, lambda: node._rolling, timeout=20.0)
        send(executor, spin_until, node, image_pub, array_to_image(frame, 900_000_000))
        progress(1.0)
        assert spin_until(executor, lambda: not node._rolling, timeout=20.0)
        assert node.saved_maps == 1 and node.stitcher is not None
    finally:
        executor.shutdown()
        node.destroy_node()
        helper.destroy_node()
        sweep.destroy_node()


def test_progress_from_another_publisher_does_not_end_the_map(ros_context, spin_until):
    """Issue #29: `ros2 topic pub sweep_progress 1.0` mid-roll (or a replay of a recording) finished the map
    early. Only the sweep node of the perception node's namespace starts and ends maps now."""
    from rclpy.node import Node
    from std_msgs.msg import Float32

    from touchroller_bringup.nodes.perception_node import PerceptionNode

    node = PerceptionNode(context=ros_context)
    sweep = Node(names.SWEEP_NODE, namespace=names.DEFAULT_NAMESPACE, context=ros_context)
    stray = Node("stray_progress", context=ros_context)
    ours, theirs = (n.create_publisher(Float32, names.topic(names.SWEEP_PROGRESS), 10) for n in (sweep, stray))
    executor = SingleThreadedExecutor(context=ros_context)
    for each in (node, sweep, stray):
        executor.add_node(each)
    try:
        assert spin_until(executor, lambda: ours.get_subscription_count() > 0 and theirs.get_subscription_count() > 0,
                          timeout=10.0)
        ours.publish(Float32(data=0.2))
        assert spin_until(executor, lambda: node._rolling, timeout=20.0)
        for value in (1.0, 0.5, 1.0):
            theirs.publish(Float32(data=value))
        def delivered() -> bool:   # taken (the map ends) or refused, all three
            return not node._rolling or getattr(getattr(node, "progress_filter", None), "rejected", 0) >= 3

        assert spin_until(executor, delivered, timeout=20.0)
        assert node._rolling, "a stray publisher's 1.0 ended the roll"   # the roll goes on
        assert node.progress_filter.last_rejected == "/stray_progress"
        ours.publish(Float32(data=1.0))
        assert spin_until(executor, lambda: not node._rolling, timeout=20.0)   # the sweep's own end is taken
    finally:
        executor.shutdown()
        for each in (node, sweep, stray):
            each.destroy_node()


def test_frames_lost_in_transport_come_from_the_message_lost_event(graph):
    from rclpy.event_handler import QoSMessageLostInfo

    node = graph[0]
    assert node._diagnostic_status().values["frames_lost_in_transport"] == 0
    # the image subscription hands DDS's message_lost events to the node
    assert node._on_message_lost in [handler.callback for handler in node.image_sub.event_handlers]
    assert {"total_count", "total_count_change"} <= set(dir(QoSMessageLostInfo))  # what rclpy hands over
    for total, change in ((3, 3), (5, 2)):   # its fields are read-only: stand-ins with the same fields
        node._on_message_lost(SimpleNamespace(total_count=total, total_count_change=change))
    assert node._diagnostic_status().values["frames_lost_in_transport"] == 5


def test_an_rmw_without_message_lost_still_subscribes_and_says_unknown(ros_context, monkeypatch):
    from rclpy.event_handler import UnsupportedEventTypeError
    from rclpy.node import Node

    from touchroller_bringup.nodes.perception_node import PerceptionNode

    create = Node.create_subscription

    def without_message_lost(self, msg_type, topic, callback, qos, **kwargs):
        if kwargs.get("event_callbacks") is not None and kwargs["event_callbacks"].message_lost:
            raise UnsupportedEventTypeError("message lost event not supported")
        return create(self, msg_type, topic, callback, qos, **kwargs)

    monkeypatch.setattr(Node, "create_subscription", without_message_lost)
    node = PerceptionNode(context=ros_context)
    try:
        assert node.image_sub.topic_name == IMAGE_TOPIC
        assert node.lost_in_transport is None
        assert node._diagnostic_status().values["frames_lost_in_transport"] == "unknown"
    finally:
        node.destroy_node()


def test_a_frame_of_another_size_or_encoding_is_refused_and_keeps_the_reference(graph, spin_until, monkeypatch):
    import touchroller_bringup.nodes.perception_node as perception_node
    from touchroller_bringup.image_conversion import array_to_image
    from touchroller_bringup.ros_diagnostics import ERROR, OK, WARN

    node, executor, image_pub, recapture, received = graph
    renderer = TapRenderer(CAMERA, seed=2)
    rng = np.random.default_rng(1)
    for i in range(3):
        send(executor, spin_until, node, image_pub, array_to_image(renderer.render([], rng), 1_000 + i))
    reference = node.detector.reference.mean.copy()
    # a camera that switched to half resolution, then to mono
    send(executor, spin_until, node, image_pub, array_to_image(renderer.render([], rng)[::2, ::2], 2_000))
    send(executor, spin_until, node, image_pub, array_to_image(renderer.render([], rng)[:, :, 1], 2_001))
    assert node.refused == 2 and node.malformed == 0
    status = node._diagnostic_status()
    assert status.level == ERROR and "recapture_reference" in status.message
    np.testing.assert_array_equal(node.detector.reference.mean, reference)
    # frames that fit again are detected against the same reference
    uv, _ = CAMERA.project(CAMERA.surface_point(0.0, 0.1))
    send(executor, spin_until, node, image_pub, array_to_image(renderer.render([uv], rng), 3_000))
    assert spin_until(executor, lambda: len(received) == 1, timeout=20.0)
    assert node._diagnostic_status().level == WARN   # for BAD_INPUT_HOLD_S: a 1 Hz diagnostics reader sees it
    monkeypatch.setattr(perception_node, "BAD_INPUT_HOLD_S", 0.0)
    assert node._diagnostic_status().level == OK


@pytest.fixture
def mapping(ros_context):
    """A perception node with the strip map on (50 Hz), a 2-frame reference, and a frame source."""
    from sensor_msgs.msg import Image

    from touchroller_bringup.nodes.perception_node import PerceptionNode

    overrides = [Parameter(name, value=value) for name, value in CAMERA.to_params().items()]
    overrides += [Parameter("reference.frames", value=2), Parameter("map.publish_rate", value=50.0)]
    node = PerceptionNode(context=ros_context, parameter_overrides=overrides)
    helper = rclpy_node("map_fault_helper", ros_context)
    image_pub = helper.create_publisher(Image, IMAGE_TOPIC, 10)
    executor = SingleThreadedExecutor(context=ros_context)
    executor.add_node(node)
    executor.add_node(helper)
    texture = np.random.default_rng(0).integers(0, 255, (CAMERA.height * 3, CAMERA.width, 3), dtype=np.uint8)
    yield node, executor, image_pub, texture
    executor.shutdown()
    node.destroy_node()
    helper.destroy_node()


def _surface(texture, k):
    return np.ascontiguousarray(texture[4 * k:4 * k + CAMERA.height])   # the surface slides 4 px a frame


def test_one_frame_the_map_cannot_take_is_skipped_counted_and_warned_and_the_map_goes_on(mapping, spin_until):
    from touchroller_bringup.image_conversion import array_to_image
    from touchroller_bringup.ros_diagnostics import OK, WARN

    node, executor, image_pub, texture = mapping
    for k in range(4):
        send(executor, spin_until, node, image_pub, array_to_image(_surface(texture, k), 1_000_000 * (k + 1)))
    assert node.stitcher is not None and node._diagnostic_status().level == OK
    stitcher, push = node.stitcher, node.stitcher.push
    failures = iter([RuntimeError("a frame the stitcher chokes on")])

    def push_failing_once(image, stamp_ns, *args):
        for exc in failures:
            raise exc
        return push(image, stamp_ns, *args)

    stitcher.push = push_failing_once
    send(executor, spin_until, node, image_pub, array_to_image(_surface(texture, 4), 5_000_000))
    status = node._diagnostic_status()
    assert node.map_errors == 1 and status.level == WARN and "chokes" in status.message
    assert status.values["map_frames_failed"] == 1
    # the next frames are mapped again, into the same map, and it is published
    node._map_dirty = False
    for k in range(5, 8):
        send(executor, spin_until, node, image_pub, array_to_image(_surface(texture, k), 1_000_000 * (k + 1)))
    assert node.stitcher is stitcher and node._map_timer is not None and node._map_dirty
    assert spin_until(executor, lambda: not node._map_dirty, timeout=20.0)   # the map timer published it
    assert node.map_errors == 1


def test_a_map_that_cannot_be_finished_is_an_error_and_the_node_goes_on(mapping, spin_until):
    """#29.5: the world map's MemoryError in finish_map (map.resolution:=1e-6) left the image callback and
    ended `touchroller scan`'s executor thread: the scan hung. Now the map's failure is counted and said, and
    frames and contacts keep flowing."""
    from touchroller_bringup.image_conversion import array_to_image
    from touchroller_bringup.ros_diagnostics import ERROR

    node, executor, image_pub, texture = mapping
    for k in range(4):
        send(executor, spin_until, node, image_pub, array_to_image(_surface(texture, k), 1_000_000 * (k + 1)))
    assert node.stitcher is not None

    def finalise_failing():
        raise MemoryError("one band needs 4.41e+08 pixels")

    node.stitcher.finalise = finalise_failing
    node._finish_after_ns = 0   # the roll ended: the next frame finishes the map (on the executor)
    send(executor, spin_until, node, image_pub, array_to_image(_surface(texture, 4), 5_000_000))
    status = node._diagnostic_status()
    assert status.level == ERROR and "could not be finished" in status.message and "4.41e+08" in status.message
    assert node.map_errors == 1
    send(executor, spin_until, node, image_pub, array_to_image(_surface(texture, 5), 6_000_000))   # goes on
    node.finish_map()   # the scan's own call, from its thread: no exception either


def test_a_map_stage_that_fails_every_frame_is_an_error_and_recovers_with_the_next_reference(
        mapping, spin_until, monkeypatch):
    """Frames of another size after a recapture: the strip map cannot take them (the camera model is
    320x240); that is ERROR on /diagnostics, and back at the model's size the map works again."""
    import touchroller_bringup.nodes.perception_node as perception_node
    from touchroller_bringup.image_conversion import array_to_image
    from touchroller_bringup.ros_diagnostics import ERROR, OK

    failing_frames = getattr(perception_node, "MAP_FAILING_FRAMES", 10)

    node, executor, image_pub, texture = mapping
    for k in range(3):
        send(executor, spin_until, node, image_pub, array_to_image(_surface(texture, k), 1_000_000 * (k + 1)))
    node.recapture_reference()
    stamp = 10_000_000
    for k in range(failing_frames + 2):   # a camera at half resolution
        stamp += 1_000_000
        send(executor, spin_until, node, image_pub, array_to_image(_surface(texture, k)[::2, ::2], stamp))
    status = node._diagnostic_status()
    assert status.level == ERROR and "tactile map" in status.message, status
    assert node.map_errors == failing_frames + 2   # every frame of that size, the reference frames too
    node.recapture_reference()
    for k in range(4):
        stamp += 1_000_000
        send(executor, spin_until, node, image_pub, array_to_image(_surface(texture, k), stamp))
    assert node._map_failing == 0 and node.stitcher is not None and node._map_timer is not None
    assert node._diagnostic_status().level != ERROR
    monkeypatch.setattr(perception_node, "BAD_INPUT_HOLD_S", 0.0)
    assert node._diagnostic_status().level == OK


def test_a_malformed_frame_shows_on_diagnostics(graph, spin_until, monkeypatch):
    from sensor_msgs.msg import Image

    import touchroller_bringup.nodes.perception_node as perception_node
    from touchroller_bringup.image_conversion import array_to_image
    from touchroller_bringup.ros_diagnostics import OK, WARN

    node, executor, image_pub, _recapture, _received = graph
    renderer = TapRenderer(CAMERA, seed=2)
    rng = np.random.default_rng(1)
    for i in range(3):
        send(executor, spin_until, node, image_pub, array_to_image(renderer.render([], rng), 1_000 + i))
    assert node._diagnostic_status().level == OK
    bad = Image(height=CAMERA.height, width=CAMERA.width, encoding="bgr8", step=CAMERA.width * 3)
    bad.data = bytes(1000)   # truncated pixel data
    send(executor, spin_until, node, image_pub, bad)
    send(executor, spin_until, node, image_pub, array_to_image(renderer.render([], rng), 2_000))  # a good one after
    status = node._diagnostic_status()
    assert node.malformed == 1 and status.level == WARN and "malformed" in status.message, status
    monkeypatch.setattr(perception_node, "BAD_INPUT_HOLD_S", 0.0)
    assert node._diagnostic_status().level == OK


def test_a_map_past_max_rows_keeps_a_window_and_warns(ros_context):
    """Frames with no sweep to start a new map: the strip map stays within map.max_rows, and
    /diagnostics says that rows were dropped (WARN), not OK."""
    from touchroller_bringup.image_conversion import array_to_image
    from touchroller_bringup.nodes.perception_node import PerceptionNode
    from touchroller_bringup.ros_diagnostics import WARN

    overrides = [Parameter(name, value=value) for name, value in CAMERA.to_params().items()]
    overrides += [Parameter("reference.frames", value=2), Parameter("map.publish_rate", value=1.0),
                  Parameter("map.max_rows", value=560)]
    node = PerceptionNode(context=ros_context, parameter_overrides=overrides)
    try:
        assert not node.set_parameters([Parameter("map.max_rows", value=100)])[0].successful  # < 8 x band_rows
        rng = np.random.default_rng(0)
        frames = 150
        texture = rng.integers(0, 255, (CAMERA.height + 8 * frames, CAMERA.width, 3), dtype=np.uint8)
        for k in range(frames):   # the surface slides along v by 8 px a frame: 1200 rows in all
            frame = np.ascontiguousarray(texture[8 * k:8 * k + CAMERA.height])
            node._on_image(array_to_image(frame, 33_333_333 * (k + 1)))
        assert node.stitcher is not None
        assert 0 < node.stitcher.map_image().shape[0] <= 560
        status = node._diagnostic_status()
        assert status.level == WARN and "map.max_rows" in status.message
        assert status.values["map_rows_dropped"] > 0
    finally:
        node.destroy_node()


@pytest.mark.parametrize("name, value, message", [
    ("map.bounds", [0.5, 0.0, 0.4, 0.1], "max > min"),                        # inverted
    ("map.bounds", [float("nan"), 0.0, 0.4, 0.1], "finite"),
    ("map.bounds", [-1000.0, -1000.0, 1000.0, 1000.0], "pixels"),             # huge
    ("map.bounds", [0.0, 0.0, 0.4], "needs 4 values"),
    ("contacts.frame_id", "", "must not be empty"),
    ("world_frame", "base link", "not a valid frame id"),
    ("frame_prefix", "left", "frame_prefix 'left' must be empty or a frame id followed by a slash"),
    ("map.save_path", "/", "not a regular file"),
])
def test_start_up_values_it_cannot_use_stop_the_node_in_one_line(ros_context, name, value, message):
    """#28: these started and ran silently (a map that could never be drawn)."""
    from touchroller_bringup.errors import UserError
    from touchroller_bringup.nodes.perception_node import PerceptionNode

    with pytest.raises(UserError, match=message):
        PerceptionNode(context=ros_context, parameter_overrides=[Parameter(name, value=value)])


@pytest.mark.parametrize("overrides", [{"map.resolution": 1e-6}, {"map.resolution": "1e-6"},
                                       {"map.resolution": 8e-6, "map.band_rows": 200}])
def test_a_resolution_no_band_fits_at_stops_the_node_at_start_up_and_is_refused_on_set(ros_context, overrides):
    """#29.5: `touchroller scan map.resolution:=1e-6` started, rolled the whole sweep with every frame's band
    refused by the world map (4.4e8 map pixels a band), then died in finish_map with a MemoryError traceback
    in the scan's executor thread and hung, leaving an empty output folder. Refused at start-up now, in one
    line, as a change at run time is."""
    from touchroller_bringup.errors import UserError
    from touchroller_bringup.nodes.perception_node import PerceptionNode

    with pytest.raises(UserError, match=r"map.resolution .* at least .* m/px") as refused:
        PerceptionNode(context=ros_context, parameter_overrides=[Parameter(k, value=v) for k, v in overrides.items()])
    assert "\n" not in str(refused.value)
    node = PerceptionNode(context=ros_context)   # the default resolution maps
    try:
        result = node.set_parameters_atomically([Parameter(k, value=float(v) if k == "map.resolution" else v)
                                                 for k, v in overrides.items()])
        assert not result.successful and "map.resolution" in result.reason and "\n" not in result.reason
        assert node.get_parameter("map.resolution").value == 1e-4
        assert node.set_parameters_atomically([Parameter("map.resolution", value=2e-5)]).successful   # fits
        # without a world map the resolution is not used: not refused
        assert node.set_parameters_atomically([Parameter("map.world", value=False),
                                               Parameter("map.resolution", value=1e-6)]).successful
    finally:
        node.destroy_node()


def test_a_resolution_given_as_text_is_the_number(ros_context):
    from touchroller_bringup.nodes.perception_node import PerceptionNode

    node = PerceptionNode(context=ros_context, parameter_overrides=[Parameter("map.resolution", value="1e-5")])
    try:
        assert node.get_parameter("map.resolution").value == 1e-5
    finally:
        node.destroy_node()


def test_the_world_height_map_is_published_latched_as_32fc1_metres(ros_context, spin_until, tmp_path):
    """map_height: sensor_msgs/Image 32FC1 in metres (REP 118), row 0 the top as the map, NaN unmapped,
    latched as `map`; map.height.* load the photometric model the world mapper gets."""
    from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy
    from sensor_msgs.msg import Image

    from touchroller_bringup.nodes.perception_node import PerceptionNode
    from touchroller_perception.world_map import WorldMapConfig, WorldMapper

    overrides = [Parameter(name, value=value) for name, value in CAMERA.to_params().items()]
    node = PerceptionNode(context=ros_context, parameter_overrides=overrides)
    helper = rclpy_node("height_test_helper", ros_context)
    executor = SingleThreadedExecutor(context=ros_context)
    executor.add_node(node)
    executor.add_node(helper)
    try:
        assert node._height_source() is None   # not asked for
        missing = [Parameter("map.height.photometric", value=str(tmp_path / "none.npz")),
                   Parameter("map.height.reference", value=str(tmp_path / "none.png"))]
        assert all(r.successful for r in node.set_parameters(missing))
        assert node._height_source() is None   # said on the log, no height map
        # the height map's config is a table of parameters: checked when set, applied to the next map
        refused = node.set_parameters([Parameter("map.height.outer_fraction", value=0.9)])[0]
        assert not refused.successful
        assert node.set_parameters([Parameter("map.height.axis_sigma", value=0.0)])[0].successful
        assert node.height_parameters.config.axis_sigma == 0.0
        assert node.set_parameters([Parameter("map.height.smoothing", value=1.0),
                                    Parameter("map.height.follow_arm", value=False)])[0].successful
        assert (node.height_parameters.config.smoothing, node.height_parameters.config.follow_arm) == (1.0, False)
        assert node.height_parameters.config.resampling == "lanczos4"
        assert not node.set_parameters([Parameter("map.height.resampling", value="nearest")])[0].successful
        assert node.set_parameters([Parameter("map.height.resampling", value="linear")])[0].successful
        assert node.height_parameters.config.resampling == "linear"
        assert node.height_parameters.config.slopes == "footprint"
        assert not node.set_parameters([Parameter("map.height.slopes", value="corner")])[0].successful
        assert node.set_parameters([Parameter("map.height.slopes", value="centre")])[0].successful
        assert node.height_parameters.config.slopes == "centre"
        # a world map of 3 x 4 cells, all mapped, with a height layer (the world height's is a ratio of two
        # layers of the canvas, as this one) known at two cells of its bottom row (rows grow with y)
        world = WorldMapper(CAMERA, lambda stamps: np.zeros((len(stamps), 4, 4)),
                            WorldMapConfig(resolution=1e-4, bounds=(0.40002, -0.09998, 0.40038, -0.09972)))
        assert world.canvas.shape == (3, 4)
        ones = np.ones((3, 4), np.float32)
        world.canvas.add([100 * ones, ones, ones], 0, 0)
        world.canvas.add_layer("h_sum")
        world.canvas.add_layer("h_w")
        world.canvas.add_named({"h_sum": np.float32([[1e-5, 2e-5]]), "h_w": np.ones((1, 2), np.float32)}, 0, 0)
        height_view = world.canvas.ratio_view("h_sum", "h_w", weight="h_w", min_denominator=0.5)
        world.height_view = lambda: height_view
        node.world, node._map_dirty = world, True
        node.publish_map()
        maps: list = []
        latched = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=1, reliability=ReliabilityPolicy.RELIABLE,
                             durability=DurabilityPolicy.TRANSIENT_LOCAL)
        helper.create_subscription(Image, names.topic(names.MAP_HEIGHT), maps.append, latched)
        assert spin_until(executor, lambda: len(maps) >= 1, timeout=20.0)
        msg = maps[0]
        assert (msg.encoding, msg.height, msg.width, msg.step) == ("32FC1", 3, 4, 16)
        assert msg.header.frame_id == node.world_frame
        values = np.frombuffer(bytes(msg.data), np.float32).reshape(3, 4)
        np.testing.assert_array_equal(values[2, :2], np.float32([1e-5, 2e-5]))   # the bottom row last
        assert np.isnan(values[:2]).all() and np.isnan(values[2, 2:]).all()
    finally:
        node.world = None
        executor.shutdown()
        node.destroy_node()
        helper.destroy_node()


def test_live_findings_have_a_timer_of_their_own_and_the_views_keep_the_tiles_it_took(ros_context):
    """findings.period (0.5 s) shorter than the map's publication period (1 s): the findings are inspected on
    a timer of their own, so a region mapped just after an inspection waits half a second, not a second; the
    tiles frames touched that such an inspection took still reach the map's views at their next publication."""
    import math as _math

    from touchroller_bringup.nodes.perception_node import PerceptionNode
    from touchroller_perception.world_map import WorldMapConfig, WorldMapper

    overrides = [Parameter(name, value=value) for name, value in CAMERA.to_params().items()]
    node = PerceptionNode(context=ros_context, parameter_overrides=overrides)
    try:
        assert node._findings_timer is not None and node._findings_timer.timer_period_ns == 500_000_000
        assert node.set_parameters([Parameter("findings.period", value=1.0)])[0].successful
        assert node._findings_timer is None            # as long as the map's: at its publications
        assert node.set_parameters([Parameter("findings.period", value=0.25)])[0].successful
        assert node._findings_timer.timer_period_ns == 250_000_000
        world = WorldMapper(CAMERA, lambda stamps: np.zeros((len(stamps), 4, 4)),
                            WorldMapConfig(resolution=1e-4, bounds=(0.40002, -0.09998, 0.40158, -0.09922)))
        ones = np.ones((8, 8), np.float32)
        world.canvas.add([100 * ones, ones, ones], 0, 0)
        given: list = []
        publish = node.map_views.publish
        node.map_views.publish = lambda w, touched, *args: given.append(set(touched)) or publish(w, touched, *args)
        node.world, node._map_dirty = world, True
        node.publish_map()
        world.canvas.add([120 * ones, ones, ones], 8, 0)      # frames land after that publication
        node.live_findings._next_s = -_math.inf               # an inspection due
        node.publish_findings()
        assert node.live_findings.inspections == 2            # the findings tick looked at them
        node._map_dirty = True
        node.publish_map()
        assert given[0] and given[1] == given[0]              # and the views still got their tiles
    finally:
        node.world = None
        node.destroy_node()
