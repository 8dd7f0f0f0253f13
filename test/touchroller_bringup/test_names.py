"""ROS names compose: one namespace argument moves every topic, service and frame id of a roller."""
from __future__ import annotations

import numpy as np
import pytest

from touchroller_bringup import names
from touchroller_bringup.graph import GraphError, build_graph


def test_topics_and_services_resolve_in_the_namespace():
    assert names.topic(names.IMAGE) == "/touchroller/image_raw"
    assert names.topic(names.CONTACTS, "left") == "/left/contacts"
    assert names.topic(names.MAP, "/robot1/left/") == "/robot1/left/map"
    assert names.topic(names.IMAGE, "") == "/image_raw"
    assert names.topic(names.DIAGNOSTICS, "left") == "/diagnostics"   # absolute stays absolute
    assert names.service(names.SWEEP_NODE, names.START, "left") == "/left/sweep/start"
    assert names.IMAGE_TOPIC == "/touchroller/image_raw"
    assert names.qos_override(names.IMAGE, "left", "subscription", "depth") == \
        "qos_overrides./left/image_raw.subscription.depth"


def test_the_frame_prefix_follows_the_namespace():
    assert names.frame_prefix("touchroller") == names.frame_prefix("/touchroller") == ""
    assert names.frame_prefix("") == ""
    assert names.frame_prefix("left") == "left/"
    assert names.frame_prefix("/robot1/left") == "robot1/left/"
    assert names.frame(names.CYLINDER_FRAME, "left/") == "left/touchroller_cylinder"


@pytest.mark.parametrize("bad", ["1left", "left-roller", "le ft", "left//x"])
def test_an_invalid_namespace_is_one_line(bad):
    with pytest.raises(names.InvalidName, match="not a valid ROS namespace"):
        names.check_namespace(bad)
    with pytest.raises(GraphError, match="not a valid ROS namespace"):
        build_graph("scan", {"namespace": bad})


def test_the_graph_puts_every_node_in_the_namespace():
    for launch, values in (("scan", {}), ("calibrate", {}), ("replay", {"bag": "x"})):
        graph = build_graph(launch, {**values, "namespace": "left"})
        assert graph.namespace == "left"
        assert {spec.launch_kwargs()["namespace"] for spec in graph.nodes} == {"/left"}
        assert all("__ns:=/left" in spec.node_kwargs()["cli_args"] for spec in graph.nodes)
    assert build_graph("scan").node("sweep").full_name == "/touchroller/sweep"
    replay = build_graph("replay", {"bag": "x", "namespace": "left"}).node("perception").parameters
    assert replay["qos_overrides./left/image_raw.subscription.reliability"] == "reliable"


@pytest.mark.ros
@pytest.mark.timeout(120)
@pytest.mark.parametrize("namespace, prefix", [("touchroller", ""), ("left", "left/")])
def test_nodes_built_from_the_graph_use_the_namespace_and_frame_prefix(namespace, prefix, ros_context, spin_until):
    """Every node of the scan and calibrate graphs, built exactly as `touchroller scan` builds them
    (`NodeSpec.node_kwargs`: `-r __ns:=/left`), publishes, subscribes and serves under /<namespace>
    and names its own frames with the prefix (the robot's base keeps the driver's name)."""
    pytest.importorskip("rclpy")
    from geometry_msgs.msg import PoseStamped
    from rclpy.executors import SingleThreadedExecutor
    from rclpy.node import Node
    from rclpy.parameter import Parameter
    from sensor_msgs.msg import Image

    from touchroller_bringup.nodes.camera_node import CameraNode
    from touchroller_driver.sources import Frame, SourceStats

    class OneFrame:   # an external source: one grey frame, then finished
        info, stats = "one frame", SourceStats()

        def __init__(self) -> None:
            self.sent = False

        def open(self) -> None:
            self.stats.connected = True

        def read(self, timeout: float) -> Frame | None:
            if self.sent:
                return None
            self.sent = True
            return Frame(1_000_000_000, np.full((48, 64, 3), 90, np.uint8), 0)

        def close(self) -> None:
            pass

    scan = build_graph("scan", {"namespace": namespace})
    calibrate = build_graph("calibrate", {"namespace": namespace})
    quiet = {"map.publish_rate": 0.0}
    nodes = [
        CameraNode(context=ros_context, source=OneFrame(), autostart=False, **scan.node("camera").node_kwargs()),
        scan.node("perception").load_class()(context=ros_context, **scan.node("perception").node_kwargs(quiet)),
        scan.node("sweep").load_class()(context=ros_context, **scan.node("sweep").node_kwargs()),
        calibrate.node("calibration").load_class()(
            context=ros_context, **calibrate.node("calibration").node_kwargs({"output_path": ""})),
    ]
    probe = Node("names_probe", context=ros_context)
    images: list = []
    poses: list = []
    probe.create_subscription(Image, names.topic(names.IMAGE, namespace), images.append, 10)
    probe.create_subscription(PoseStamped, names.topic(names.TCP_POSE, namespace), poses.append, 10)
    from touchroller_bringup.tf import TransformListener

    tf = TransformListener(probe)   # /tf and /tf_static: absolute, the frames carry the prefix
    executor = SingleThreadedExecutor(context=ros_context)
    for node in (*nodes, probe):
        executor.add_node(node)
    camera, perception, sweep, calibration = nodes
    try:
        assert [n.get_fully_qualified_name() for n in nodes] == [
            f"/{namespace}/{name}" for name in ("camera", "perception", "sweep", "calibration")]
        published = {(topic, tuple(types)) for node in nodes
                     for topic, types in probe.get_publisher_names_and_types_by_node(node.get_name(), f"/{namespace}")}
        spin_until(executor, lambda: camera.image_pub.get_subscription_count() > 0, timeout=20.0)
        ours = {topic for topic, _ in published if topic.startswith(f"/{namespace}/")}
        expected_topics = {names.topic(t, namespace) for t in (names.IMAGE, names.CAMERA_INFO, names.CONTACTS,
                                                               names.MAP, names.TCP_POSE, names.SWEEP_PROGRESS)}
        assert expected_topics <= ours
        assert all(topic.startswith(f"/{namespace}/") or topic in ("/diagnostics", "/tf", "/tf_static", "/clock",
                                                                           "/parameter_events", "/rosout")
                   for topic, _ in published)
        services = {name for name, _ in probe.get_service_names_and_types()}
        for node, service in ((names.SWEEP_NODE, names.START), (names.SWEEP_NODE, names.STOP),
                              (names.PERCEPTION_NODE, names.RECAPTURE_REFERENCE),
                              (names.CALIBRATION_NODE, names.CAPTURE), (names.CALIBRATION_NODE, names.SOLVE)):
            assert spin_until(executor, lambda n=node, s=service: names.service(n, s, namespace) in
                              {name for name, _ in probe.get_service_names_and_types()}, timeout=20.0), services
        assert perception.image_sub.topic_name == names.topic(names.IMAGE, namespace)

        # frame ids: the camera's images, the sweep's poses, the contacts' frame, TF
        camera.start()
        assert spin_until(executor, lambda: images and poses, timeout=20.0)
        # the robot's base is the driver's name (shared); the simulated arm's flange is its own in a namespace
        chain = ["base", f"{prefix}tool0", f"{prefix}touchroller_cylinder", f"{prefix}touchroller_camera",
                 f"{prefix}touchroller_camera_optical_frame"]   # the images' frame links to the robot's base

        def tf_chain_known() -> bool:
            with tf.lock:
                return all(tf.buffer.can_transform(chain[0], child) for child in chain[1:])

        assert spin_until(executor, tf_chain_known, timeout=20.0)
        assert images[0].header.frame_id == f"{prefix}touchroller_camera_optical_frame"
        assert poses[-1].header.frame_id == "base"
        assert perception.frame_id == f"{prefix}touchroller_cylinder"
        assert all(n.get_parameter("frame_prefix").value == prefix for n in nodes)
        assert not camera.set_parameters([Parameter("frame_prefix", value="x/")])[0].successful   # read-only
    finally:
        executor.shutdown()
        for node in (*nodes, probe):
            node.destroy_node()
