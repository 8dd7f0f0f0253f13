"""Play a rosbag2 folder (sqlite3 or MCAP) back like `ros2 bag play`, without rosbag2_py.

Messages are published serialized (`publish(bytes)`, never deserialised) at their recorded
receive timing scaled by `rate`, with the QoS the recorded publishers offered (reliability and
durability kept when every recorded publisher agreed, like rosbag2). A truncated bag plays up to
the damage and then reports one clear line. Images recorded compressed (sensor_msgs/CompressedImage on
`<topic>/compressed`, `touchroller_bringup.bag_compression`) are published as recorded and, decoded, as
sensor_msgs/Image on `<topic>` (as `image_transport republish` would; beside the frames the recording holds
raw there, if any): a graph listening to `image_raw` runs on a compressed recording as on a raw one.
"""
from __future__ import annotations

import math
import threading
import time
from collections.abc import Iterable
from pathlib import Path
from typing import Any

from rclpy.node import Node
from rclpy.qos import DurabilityPolicy, HistoryPolicy, LivelinessPolicy, QoSProfile, ReliabilityPolicy

from touchroller_bringup.bags import COMPRESSED_SUFFIX, COMPRESSED_TYPE, open_bag
from touchroller_bringup.errors import UserError
from touchroller_bringup.recorder import message_class, qos_time_to_duration

#: --rate's range: a thousand times slower than recorded (a gap of a second then lasts 17 min) up to a
#: million times faster (in effect as fast as the messages can be published)
MIN_RATE, MAX_RATE = 1e-3, 1e6


def check_rate(rate: float) -> float:
    """`rate` as a float, or UserError (one line) unless it is a number in [MIN_RATE, MAX_RATE]."""
    if not (math.isfinite(rate) and MIN_RATE <= rate <= MAX_RATE):
        raise UserError(f"--rate must be positive, between {MIN_RATE:g} and {MAX_RATE:g}, got {rate:g}")
    return float(rate)


def playback_qos(offered: list[Any]) -> QoSProfile:
    """The QoS to publish with, from the recorded offered profiles (rosbags Qos tuples)."""
    if not offered:
        return QoSProfile(depth=10)
    reliabilities = {q.reliability.name for q in offered}
    durabilities = {q.durability.name for q in offered}
    reliable = reliabilities == {"RELIABLE"}
    latched = durabilities == {"TRANSIENT_LOCAL"}
    first = offered[0]
    profile = QoSProfile(
        history=HistoryPolicy.KEEP_LAST,
        depth=max(int(first.depth), 10),  # discovery reports depth 0 (unknown): keep 10
        reliability=ReliabilityPolicy.RELIABLE if reliable else ReliabilityPolicy.BEST_EFFORT,
        durability=DurabilityPolicy.TRANSIENT_LOCAL if latched else DurabilityPolicy.VOLATILE,
    )
    if len(offered) == 1:  # one publisher: its deadline/lifespan/liveliness too
        profile.deadline = qos_time_to_duration(first.deadline)
        profile.lifespan = qos_time_to_duration(first.lifespan)
        profile.liveliness_lease_duration = qos_time_to_duration(first.liveliness_lease_duration)
        if first.liveliness.name in ("AUTOMATIC", "MANUAL_BY_TOPIC"):
            profile.liveliness = LivelinessPolicy[first.liveliness.name]
    return profile


class Replayer(Node):
    """Publishes the messages of a bag; `start()` begins playback on a thread, `finished` tells when done."""

    def __init__(self, path: str | Path, *, rate: float = 1.0, loop: bool = False,
                 topics: Iterable[str] | None = None, node_name: str = "touchroller_replayer",
                 **node_kwargs: Any) -> None:
        self.path = Path(path)
        self.rate, self.loop = check_rate(rate), loop
        reader = open_bag(self.path)  # UserError before any node exists
        wanted = None if topics is None else {t if t.startswith("/") else "/" + t for t in topics}
        connections = [c for c in reader.connections if wanted is None or c.topic in wanted]
        reader.close()
        if wanted is not None and (missing := wanted - {c.topic for c in connections}):
            raise UserError(f"bag {self.path} has no topic {', '.join(sorted(missing))}")
        self._stop = threading.Event()   # what stop() uses, before the context tracks the node
        self._thread: threading.Thread | None = None
        super().__init__(node_name, **node_kwargs)
        self._playback_publishers: dict[int, Any] = {}
        by_topic: dict[str, Any] = {}
        for connection in connections:
            cls = message_class(connection.msgtype)
            if cls is None:
                self.get_logger().warning(f"skipping {connection.topic}: type {connection.msgtype} is not installed")
                continue
            if connection.topic not in by_topic:
                offered = list(getattr(connection.ext, "offered_qos_profiles", []) or [])
                by_topic[connection.topic] = self.create_publisher(cls, connection.topic, playback_qos(offered))
            self._playback_publishers[connection.id] = by_topic[connection.topic]
        # compressed images: also decoded, on the raw topic (with the recording's own raw frames there, if any)
        self._decoded_publishers: dict[int, Any] = {}
        for connection in connections:
            raw_topic = connection.topic.removesuffix(COMPRESSED_SUFFIX)
            if connection.msgtype != COMPRESSED_TYPE or raw_topic == connection.topic \
                    or connection.id not in self._playback_publishers:
                continue
            if raw_topic not in by_topic:
                from sensor_msgs.msg import Image

                offered = list(getattr(connection.ext, "offered_qos_profiles", []) or [])
                by_topic[raw_topic] = self.create_publisher(Image, raw_topic, playback_qos(offered))
            self._decoded_publishers[connection.id] = by_topic[raw_topic]
        self.undecodable = 0   # compressed images that did not decode (published as recorded only)
        self.topics = sorted(by_topic)
        self.published = 0
        self._store: Any = None
        self.error: str | None = None
        self._done = threading.Event()

    @property
    def finished(self) -> bool:
        return self._done.is_set()

    def publisher_for(self, topic: str) -> Any:
        publishers = [*self._playback_publishers.values(), *self._decoded_publishers.values()]
        return next(p for p in publishers if p.topic_name == topic)

    def start(self) -> None:
        if self._thread is None:
            self._thread = threading.Thread(target=self._play, name="touchroller-replay", daemon=True)
            self._thread.start()

    def wait(self, timeout: float | None = None) -> bool:
        return self._done.wait(timeout)

    def stop(self) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout=5.0)

    def destroy_node(self) -> None:
        self.stop()
        super().destroy_node()

    def _play(self) -> None:
        try:
            while not self._stop.is_set():
                self._play_once()
                if not self.loop or self.error:
                    break
        finally:
            self._done.set()

    def _publish_decoded(self, connection_id: int, data: Any) -> None:
        from touchroller_bringup.bags import typestore
        from touchroller_bringup.image_conversion import (
            ImageFormatError,
            array_to_image,
            compressed_to_array,
            stamp_to_ns,
        )

        if self._store is None:
            self._store = typestore()
        try:
            msg = self._store.deserialize_cdr(bytes(data), COMPRESSED_TYPE)
            image = compressed_to_array(msg)
        except (ImageFormatError, ValueError) as exc:
            self.undecodable += 1
            self.get_logger().warning(f"a compressed image did not decode: {exc}", throttle_duration_sec=5.0)
            return
        self._decoded_publishers[connection_id].publish(
            array_to_image(image, stamp_to_ns(msg.header.stamp), frame_id=msg.header.frame_id))

    def _play_once(self) -> None:
        reader = open_bag(self.path)
        try:
            start_wall: float | None = None
            first_ns = 0
            messages = reader.messages(connections=[c for c in reader.connections if c.id in self._playback_publishers])
            while not self._stop.is_set():
                try:
                    item = next(messages, None)
                except Exception as exc:  # noqa: BLE001 - truncated/corrupt storage: stop with one line
                    self.error = f"bag {self.path} is truncated or corrupt after {self.published} messages: " \
                                 f"{type(exc).__name__}: {str(exc).splitlines()[0] if str(exc) else ''}"
                    self.get_logger().error(self.error)
                    return
                if item is None:
                    return
                connection, stamp_ns, data = item
                if start_wall is None:
                    start_wall, first_ns = time.monotonic(), stamp_ns
                due = start_wall + (stamp_ns - first_ns) * 1e-9 / self.rate
                delay = due - time.monotonic()
                if delay > 0 and self._stop.wait(delay):
                    return
                self._playback_publishers[connection.id].publish(bytes(data))
                self.published += 1
                if connection.id in self._decoded_publishers:
                    self._publish_decoded(connection.id, data)
        finally:
            reader.close()
