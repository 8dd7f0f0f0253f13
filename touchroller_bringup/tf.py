"""TF on the wire: tf2_msgs/msg/TFMessage on /tf and /tf_static, exactly as tf2 publishes them.

- `TransformPublisher` broadcasts dynamic transforms on /tf (reliable, volatile, depth 100: tf2_ros's
  TransformBroadcaster) and static ones on /tf_static (reliable, transient local, depth 1, every static
  transform of the node in one message, re-sent whole when one changes: tf2_ros's
  StaticTransformBroadcaster), so rviz and tf2 listeners on a real ROS machine use them unchanged.
- `TransformListener` feeds both topics into a `touchroller_perception.transforms.TransformBuffer`
  (thread-safe), for the perception node, the simulated camera and the scan runner.
- `from_msg` / `to_msg` convert one geometry_msgs/TransformStamped.

"""
from __future__ import annotations

import threading
from collections.abc import Callable, Iterable
from typing import Any

from rclpy.node import Node
from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy

from touchroller_bringup import names
from touchroller_bringup.image_conversion import stamp_to_ns
from touchroller_perception.geometry import CameraModel
from touchroller_perception.transforms import Transform, TransformBuffer, TransformError

TF_TOPIC = names.TF
TF_STATIC_TOPIC = names.TF_STATIC
# docs/design.md's frame names (before a node's frame prefix); the names live in touchroller_bringup.names
WORLD_FRAME = names.BASE_FRAME          # the robot's base; the world map lives here (parameter world_frame)
TOOL_FRAME = names.TOOL_FRAME           # the arm's flange (UR convention)
CYLINDER_FRAME = names.CYLINDER_FRAME
CAMERA_FRAME = names.CAMERA_FRAME

TF_QOS = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=100, reliability=ReliabilityPolicy.RELIABLE,
                    durability=DurabilityPolicy.VOLATILE)
TF_STATIC_QOS = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=1, reliability=ReliabilityPolicy.RELIABLE,
                           durability=DurabilityPolicy.TRANSIENT_LOCAL)
TF_STATIC_LISTENER_QOS = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=100,
                                    reliability=ReliabilityPolicy.RELIABLE,
                                    durability=DurabilityPolicy.TRANSIENT_LOCAL)


def tf_message_type() -> Any:
    """tf2_msgs.msg.TFMessage; ImportError with what to do when this install lacks it."""
    try:
        from tf2_msgs.msg import TFMessage
    except ImportError as exc:
        raise ImportError("tf2_msgs is not installed: run `make setup` (it builds tf2_msgs into the venv) "
                          "or install ros-<distro>-tf2-msgs") from exc
    return TFMessage


def to_msg(parent: str, child: str, stamp_ns: int, transform: Transform) -> Any:
    from geometry_msgs.msg import TransformStamped

    msg = TransformStamped()
    msg.header.stamp.sec, msg.header.stamp.nanosec = divmod(int(stamp_ns), 1_000_000_000)
    msg.header.frame_id = parent
    msg.child_frame_id = child
    t = msg.transform.translation
    t.x, t.y, t.z = transform.translation
    q = msg.transform.rotation
    q.x, q.y, q.z, q.w = transform.rotation
    return msg


def from_msg(msg: Any) -> tuple[str, str, int, Transform]:
    """(parent, child, stamp_ns, T_parent_child) of a geometry_msgs/TransformStamped."""
    t, q = msg.transform.translation, msg.transform.rotation
    return (msg.header.frame_id, msg.child_frame_id, stamp_to_ns(msg.header.stamp),
            Transform((t.x, t.y, t.z), (q.x, q.y, q.z, q.w)))


def camera_in_cylinder(model: CameraModel) -> Transform:
    """T_cylinder_camera of docs/design.md's geometry: the optical frame (z along the view) is the cylinder
    frame rotated by theta about x and shifted by d along z: p_cam = R_x(theta) p_cyl + (0, 0, d)."""
    import numpy as np

    c, s = float(np.cos(model.theta)), float(np.sin(model.theta))
    cam_from_cyl = np.array([[1.0, 0.0, 0.0, 0.0], [0.0, c, s, 0.0], [0.0, -s, c, model.d], [0.0, 0.0, 0.0, 1.0]])
    return Transform.from_matrix(np.linalg.inv(cam_from_cyl))


class TransformPublisher:
    """Publishes a node's transforms: `send` on /tf, `set_static` on /tf_static (see module docstring)."""

    def __init__(self, node: Node) -> None:
        tf_message = tf_message_type()
        self._node = node
        self._message = tf_message
        self._dynamic = node.create_publisher(tf_message, TF_TOPIC, TF_QOS)
        self._static_pub = node.create_publisher(tf_message, TF_STATIC_TOPIC, TF_STATIC_QOS)
        self._static: dict[str, Any] = {}
        self._lock = threading.Lock()

    def send(self, transforms: Iterable[tuple[str, str, int, Transform]]) -> None:
        self._dynamic.publish(self._message(transforms=[to_msg(*t) for t in transforms]))

    def set_static(self, parent: str, child: str, transform: Transform, stamp_ns: int | None = None) -> None:
        """Add or replace the static transform of `child`; all of them are re-published in one message."""
        if stamp_ns is None:
            stamp_ns = self._node.get_clock().now().nanoseconds
        with self._lock:
            self._static[child] = to_msg(parent, child, stamp_ns, transform)
            message = self._message(transforms=list(self._static.values()))
        self._static_pub.publish(message)

    def destroy(self) -> None:
        self._node.destroy_publisher(self._dynamic)
        self._node.destroy_publisher(self._static_pub)


class TransformListener:
    """Fills a TransformBuffer from /tf and /tf_static. `on_update(static)` (optional) is called after
    each message, on the executor's thread. `lock` guards the buffer: hold it while looking up."""

    def __init__(self, node: Node, buffer: TransformBuffer | None = None,
                 on_update: Callable[[bool], None] | None = None) -> None:
        tf_message = tf_message_type()
        self.buffer = buffer if buffer is not None else TransformBuffer()
        self.lock = threading.Lock()
        self.received = 0
        self._on_update = on_update
        self._subscriptions = [
            node.create_subscription(tf_message, TF_TOPIC, lambda m: self._on_message(m, False), TF_QOS),
            node.create_subscription(tf_message, TF_STATIC_TOPIC, lambda m: self._on_message(m, True),
                                     TF_STATIC_LISTENER_QOS),
        ]

    def _on_message(self, message: Any, static: bool) -> None:
        with self.lock:
            for transform in message.transforms:
                try:
                    parent, child, stamp_ns, value = from_msg(transform)
                    self.buffer.set_transform(parent, child, stamp_ns, value, static=static)
                except ValueError:   # a malformed transform (NaN, zero quaternion, empty frame): skipped
                    continue
                self.received += 1
        if self._on_update is not None:
            self._on_update(static)

    def lookup(self, target: str, source: str, stamp_ns: int | None = None) -> Transform | None:
        """T_target_source at `stamp_ns`, or None if the buffer cannot give it (yet)."""
        with self.lock:
            try:
                return self.buffer.lookup(target, source, stamp_ns)
            except TransformError:
                return None
