"""TF on the wire: the sweep and perception nodes' transforms, read by an rclpy client in another process."""
from __future__ import annotations

import json
import math
import os
import subprocess
import sys
import threading

import numpy as np
import pytest

pytest.importorskip("rclpy")
pytest.importorskip("tf2_msgs.msg")

from touchroller_bringup.tf import camera_in_cylinder, from_msg, to_msg  # noqa: E402
from touchroller_perception.geometry import CameraModel  # noqa: E402
from touchroller_perception.transforms import Transform  # noqa: E402

# The type hash real tf2_msgs/msg/TFMessage carries (ros2 topic info -v /tf on Jazzy and Kilted): ours,
# built from the same one-line definition, must match it or tf2 on a real ROS machine would not match.
TF_MESSAGE_HASH = "RIHS01_e369d0f05a23ae52508854b66f6aa0437f3449d652e8cbf22d5abe85d020f087"

CLIENT = r"""
import json, sys, time
import rclpy
from rclpy.node import Node
from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy
from tf2_msgs.msg import TFMessage

rclpy.init()
node = Node("outside_tf_client")
seen = {"static": {}, "dynamic": {}}

def keep(kind):
    def on(msg):
        for t in msg.transforms:
            r, q = t.transform.translation, t.transform.rotation
            seen[kind][f"{t.header.frame_id}->{t.child_frame_id}"] = {
                "t": [r.x, r.y, r.z], "q": [q.x, q.y, q.z, q.w],
                "stamp": t.header.stamp.sec * 10**9 + t.header.stamp.nanosec}
    return on

node.create_subscription(TFMessage, "/tf_static", keep("static"),
                         QoSProfile(depth=100, reliability=ReliabilityPolicy.RELIABLE,
                                    durability=DurabilityPolicy.TRANSIENT_LOCAL))
node.create_subscription(TFMessage, "/tf", keep("dynamic"), QoSProfile(depth=100))
deadline = time.monotonic() + 30.0
while time.monotonic() < deadline and (len(seen["static"]) < 2 or not seen["dynamic"]):
    rclpy.spin_once(node, timeout_sec=0.05)
info = node.get_publishers_info_by_topic("/tf_static")
seen["static_publishers"] = [{"type": i.topic_type, "durability": i.qos_profile.durability.name,
                              "hash": str(i.topic_type_hash)} for i in info]
seen["types"] = dict(node.get_topic_names_and_types())
print(json.dumps(seen))
"""


def test_messages_round_trip():
    transform = Transform.from_rpy((0.1, -0.2, 0.3), (0.4, -0.5, 0.6))
    parent, child, stamp, back = from_msg(to_msg("base", "tool0", 1_700_000_000_123_456_789, transform))
    assert (parent, child, stamp) == ("base", "tool0", 1_700_000_000_123_456_789)
    assert np.allclose(back.matrix(), transform.matrix())


@pytest.mark.parametrize("theta, d", [(0.0, 0.0), (0.3, 0.01), (-0.2, -0.02)])
def test_the_camera_frame_is_the_papers_extrinsics(theta, d):
    model = CameraModel().replace(theta=theta, d=d)
    in_camera = camera_in_cylinder(model).inverse()
    points = np.array([[0.01, 0.005, 0.049], [-0.02, -0.01, 0.048], [0.0, 0.0, 0.05]])
    projected, valid = model.project(points)
    p = in_camera.apply(points)
    pinhole = np.stack([model.fx * p[:, 0] / p[:, 2] + model.cx, model.fy * p[:, 1] / p[:, 2] + model.cy], axis=1)
    assert valid.all()
    assert np.allclose(projected, pinhole, atol=1e-9)


@pytest.mark.slow
def test_an_outside_rclpy_client_sees_the_tf_tree(ros_context):
    from rclpy.executors import MultiThreadedExecutor
    from rclpy.parameter import Parameter

    from touchroller_bringup.nodes.perception_node import PerceptionNode
    from touchroller_bringup.nodes.sweep_node import SweepNode

    mount_rpy = [0.0, 0.0, -math.pi / 2]
    sweep = SweepNode(context=ros_context, parameter_overrides=[Parameter("mount.xyz", value=[0.0, 0.01, 0.12]),
                                                                Parameter("mount.rpy", value=mount_rpy)])
    perception = PerceptionNode(context=ros_context, parameter_overrides=[Parameter("extrinsics.theta", value=0.1)])
    executor = MultiThreadedExecutor(num_threads=2, context=ros_context)
    for node in (sweep, perception):
        executor.add_node(node)
    stop = threading.Event()
    spinner = threading.Thread(target=lambda: [executor.spin_once(0.05) for _ in iter(stop.is_set, True)])
    spinner.start()
    try:
        result = subprocess.run([sys.executable, "-c", CLIENT], capture_output=True, text=True, timeout=90,
                                env=dict(os.environ))
    finally:
        stop.set()
        spinner.join()
        executor.shutdown()
        for node in (sweep, perception):
            node.destroy_node()
    assert result.returncode == 0, result.stderr[-2000:]
    seen = json.loads(result.stdout.strip().splitlines()[-1])
    assert seen["types"]["/tf"] == ["tf2_msgs/msg/TFMessage"]
    assert seen["types"]["/tf_static"] == ["tf2_msgs/msg/TFMessage"]
    assert {p["durability"] for p in seen["static_publishers"]} == {"TRANSIENT_LOCAL"}
    assert all(p["hash"] == TF_MESSAGE_HASH for p in seen["static_publishers"]), seen["static_publishers"]
    mount = seen["static"]["tool0->touchroller_cylinder"]
    expected = Transform.from_rpy((0.0, 0.01, 0.12), mount_rpy)
    assert np.allclose(mount["t"], expected.translation)
    assert np.allclose(np.abs(np.dot(mount["q"], expected.rotation)), 1.0)
    camera = seen["static"]["touchroller_cylinder->touchroller_camera"]
    assert np.allclose(camera["q"], camera_in_cylinder(perception.camera).rotation, atol=1e-9)
    tool = seen["dynamic"]["base->tool0"]
    assert np.allclose(tool["t"], [0.4, 0.0, 0.2 + 0.002], atol=1e-6)   # the simulated arm at rest, above the start
