"""Record ROS topics into a rosbag2 folder (sqlite3 or MCAP) like `ros2 bag record`, without rosbag2_py.

With `compress`, the recording is lossless but smaller (`touchroller_bringup.bag_compression`): every
sensor_msgs/Image topic is stored as sensor_msgs/CompressedImage PNG on `<topic>/compressed`, and MCAP
chunks are compressed with zstd but for those mostly of PNG frames (which zstd does not shrink). A writer
that falls `PNG_LAG_S` behind (PNG costs several ms a frame) writes frames raw on `<topic>` until it has
caught up; readers take both topics in recording order.

`Recorder` is a node: it discovers the wanted topics, subscribes with `raw=True` (serialized CDR,
never deserialised; `queue.depth` deep, in a callback group of its own) and hands each message to a writer
thread that owns the `rosbags` Writer through a queue bounded in bytes (`queue.max_bytes`,
`touchroller_bringup.recording_queue`), so callbacks stay short and take messages off the wire at once.
Nothing is lost silently: a message refused at the queue's bound (a writer behind a camera that cannot
wait) and a message DDS lost before the recorder took it (a gap in its publisher's sequence numbers) are
counted per topic (`stats()`), logged, and ERROR on `/diagnostics` ("touchroller recorder"). For every
sensor_msgs/Image topic it records, the recorder publishes on `<topic>/recorded` (std_msgs/Header) the
stamp of each frame once written: a simulated scan's clock waits for it as for the perception node
(`sweep` node, `sim.lockstep`), so a slow recorder slows the simulation down instead of losing frames.
The offered QoS profiles
of the publishers are stored in the bag's metadata, so `touchroller replay` (and `ros2 bag play`)
can publish with them again. `close()` drains what is in flight and finalises the bag: stopping
with Ctrl-C loses nothing that had arrived.

A recording survives a kill up to its last second: the writer commits (an sqlite3 transaction or an
MCAP chunk flushed to the file) once the oldest message not yet on disk arrived `COMMIT_AGE_S` ago (or
after `COMMIT_MESSAGES` messages). The clock is the messages' arrival, not the last commit: a writer
that falls behind under load commits as soon as it reaches messages that old, so no message waits
more than `COMMIT_INTERVAL_S` from its arrival to the disk (half of it in reserve for the commit itself), so
after SIGKILL, a lost terminal or a crash `touchroller reindex BAG` (`bag_recovery`) makes all of
it readable. A write that fails (a full disk) is reported at once through `failed` (the command
stops and says it in one line); what was committed before is kept and indexed.
"""
from __future__ import annotations

import importlib
import struct
import threading
import time
from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from rclpy.duration import Duration
from rclpy.node import Node
from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy

from touchroller_bringup.errors import UserError
from touchroller_bringup.recording_queue import BoundedQueue, QueueStats

#: Topics left out of "record everything" (ros2 bag record -a leaves out hidden topics; these are noise).
EXCLUDED_BY_DEFAULT = ("/rosout", "/parameter_events")
INFINITE_SEC, INFINITE_NSEC = 2147483647, 4294967295  # how rosbag2 writes RMW_DURATION_INFINITE
_INFINITE_NS = 2**63 - 1
COMMIT_INTERVAL_S = 1.0    # a kill loses at most this much of a recording
COMMIT_AGE_S = 0.5         # commit once the oldest uncommitted message arrived this long ago
COMMIT_MESSAGES = 200      # ... or this many messages, whichever comes first
#: room kept in the bag folder while recording and given back before it is finalised or indexed, so that a
#: full disk still leaves room for metadata.yaml (compressed chunks leave too little behind when cut short)
RESERVE_NAME, RESERVE_BYTES = ".touchroller-reserve", 256 * 1024
#: with compression, an image that reaches the writer this long after it arrived is written raw (lossless,
#: larger) instead of as PNG: the writer never falls further behind than this for the sake of compression
PNG_LAG_S = 0.25
_IDLE = ("idle",)
#: suffix of the topic on which the recorder says, per image topic, up to which frame it has written
RECORDED_SUFFIX = "/recorded"
IMAGE_MSGTYPE = "sensor_msgs/msg/Image"


@dataclass(frozen=True)
class RecorderConfig:
    queue_max_bytes: int = 256 * 2**20   # messages taken but not written yet, at most this many bytes
    queue_depth: int = 300               # each subscription's DDS queue (messages): 10 s of a 30 fps camera

    def __post_init__(self) -> None:
        if not self.queue_max_bytes >= 2**20:
            raise ValueError(f"queue.max_bytes must be at least 1 MiB, got {self.queue_max_bytes}")
        if not self.queue_depth >= 1:
            raise ValueError(f"queue.depth must be at least 1, got {self.queue_depth}")


# ROS parameter -> (RecorderConfig field, description, min, max, read-only)
RECORDER_PARAMETERS: dict[str, tuple[str, str, int, int, bool]] = {
    "queue.max_bytes": ("queue_max_bytes", "Messages taken off the wire but not written yet, at most this many "
                        "bytes (a writer behind a camera that cannot wait: the messages past it are refused, counted "
                        "and reported ERROR on /diagnostics)", 2**20, 2**40, False),
    "queue.depth": ("queue_depth", "Depth of each subscription's queue (keep-last, messages) while the recorder's "
                    "thread is busy", 1, 100_000, True),
}


@dataclass(frozen=True)
class RecorderStats:
    """What a recording took, wrote and lost, per topic."""

    received: dict[str, int]             # messages taken off the wire and queued for the writer
    written: int                         # messages written to the bag
    written_raw: int                     # images written raw because the writer was behind (lossless, larger)
    queue: QueueStats                    # the writer's queue: bytes now, at most, and refused at its bound
    lost_in_transport: dict[str, int]    # gaps in the publishers' sequence numbers: lost before the recorder

    @property
    def overflowed(self) -> dict[str, int]:
        return self.queue.overflowed

    @property
    def lost(self) -> dict[str, int]:
        """Messages published while recording and not in the bag, per topic (refused at the bound or lost)."""
        topics = set(self.queue.overflowed) | set(self.lost_in_transport)
        return {t: self.queue.overflowed.get(t, 0) + self.lost_in_transport.get(t, 0) for t in sorted(topics)
                if self.queue.overflowed.get(t, 0) + self.lost_in_transport.get(t, 0)}

    def summary(self) -> str:
        """One line: what was lost and why ("" when nothing was)."""
        parts = [f"{n} on {topic}" for topic, n in self.lost.items()]
        if not parts:
            return ""
        why = []
        if self.queue.overflowed_total:
            why.append(f"{self.queue.overflowed_total} refused at the queue's bound of "
                       f"{self.queue.max_bytes / 2**20:g} MiB (the writer fell behind)")
        if sum(self.lost_in_transport.values()):
            why.append(f"{sum(self.lost_in_transport.values())} lost before the recorder took them")
        return f"recording lost {sum(self.lost.values())} messages ({', '.join(parts)}): {'; '.join(why)}"


def message_class(msgtype: str) -> Any:
    """`sensor_msgs/msg/Image` -> the rclpy message class; None when its package is not installed."""
    try:
        package, kind, name = msgtype.split("/")
        return getattr(importlib.import_module(f"{package}.{kind}"), name)
    except (ValueError, ImportError, AttributeError):
        return None


def _duration_to_qos_time(duration: Duration) -> Any:
    from rosbags.interfaces import QosTime

    nanoseconds = duration.nanoseconds
    if nanoseconds >= _INFINITE_NS:
        return QosTime(INFINITE_SEC, INFINITE_NSEC)
    return QosTime(*divmod(int(nanoseconds), 1_000_000_000))


def qos_time_to_duration(value: Any) -> Duration:
    if (value.sec, value.nsec) == (INFINITE_SEC, INFINITE_NSEC) or value.sec >= INFINITE_SEC:
        return Duration(nanoseconds=_INFINITE_NS)
    return Duration(seconds=value.sec, nanoseconds=value.nsec)


def to_bag_qos(profile: QoSProfile) -> Any:
    """An rclpy QoSProfile as a rosbags Qos (enum values are rmw's in both)."""
    from rosbags.interfaces import Qos, QosDurability, QosHistory, QosLiveliness, QosReliability

    return Qos(
        history=QosHistory(int(profile.history)),
        depth=int(profile.depth),
        reliability=QosReliability(int(profile.reliability)),
        durability=QosDurability(int(profile.durability)),
        deadline=_duration_to_qos_time(profile.deadline),
        lifespan=_duration_to_qos_time(profile.lifespan),
        liveliness=QosLiveliness(int(profile.liveliness)),
        liveliness_lease_duration=_duration_to_qos_time(profile.liveliness_lease_duration),
        avoid_ros_namespace_conventions=bool(profile.avoid_ros_namespace_conventions),
    )


def subscription_qos(offered: Sequence[QoSProfile], depth: int = 100) -> QoSProfile:
    """Adapt to the publishers like rosbag2: reliable / transient local only when every publisher offers it."""
    reliable = bool(offered) and all(p.reliability == ReliabilityPolicy.RELIABLE for p in offered)
    latched = bool(offered) and all(p.durability == DurabilityPolicy.TRANSIENT_LOCAL for p in offered)
    return QoSProfile(
        history=HistoryPolicy.KEEP_LAST, depth=depth,
        reliability=ReliabilityPolicy.RELIABLE if reliable else ReliabilityPolicy.BEST_EFFORT,
        durability=DurabilityPolicy.TRANSIENT_LOCAL if latched else DurabilityPolicy.VOLATILE,
    )


class _BagWriter(threading.Thread):
    """Owns the rosbags Writer; every call on it happens on this thread, in arrival order."""

    def __init__(self, path: Path, storage: str, distro: str = "auto", compress: bool = False,
                 max_bytes: int = RecorderConfig.queue_max_bytes,
                 on_image_written: Callable[[str, int], None] | None = None) -> None:
        super().__init__(name="touchroller-bag-writer", daemon=True)
        from rosbags.typesys import Stores, get_typestore

        from touchroller_bringup.bags import bag_writer

        self.path = path
        self._typestore = get_typestore(Stores.ROS2_KILTED)
        self._writer = bag_writer(path, storage, distro, compress)   # MCAP chunks carry their CRC
        self.compress = compress
        self._png: dict[str, list[Any]] = {}   # raw image topics written as PNG on <topic>/compressed: their QoS
        self._raw_fallback: dict[str, Any] = {}   # ... and their raw connections, made when first needed
        self.unconvertible = 0        # image messages that could not be compressed (malformed): left out
        self.written_raw = 0          # images written raw because the writer was behind (PNG costs time)
        self.distro = self._writer.distro
        self._opened = threading.Event()
        self.queue = BoundedQueue(max_bytes)
        self._on_image_written = on_image_written   # (topic, stamp_ns) of each image written, on this thread
        self._images: set[str] = set()               # the sensor_msgs/Image topics
        self._connections: dict[str, Any] = {}
        self.written = 0
        self.committed = 0          # messages on disk: a kill from now on loses none of them
        self.error: str | None = None
        self.failed = threading.Event()   # set at once when a write fails (e.g. the disk is full)
        self.recovered: str | None = None  # after a failure: what `reindex` made readable

    def start(self) -> None:
        """Start the thread and open the bag on it (sqlite objects must stay on one thread)."""
        super().start()
        self._opened.wait()
        if self.error is not None:
            self.join()
            raise UserError(f"cannot write bag: {self.error}")

    def add_topic(self, topic: str, msgtype: str, offered: list[Any]) -> None:
        self.queue.put_always(("topic", topic, msgtype, offered))

    def write(self, topic: str, stamp_ns: int, data: bytes, arrived: float | None = None) -> bool:
        """Queue a message; `arrived`: when it arrived (time.monotonic(), default now), the commit's clock.
        False when the queue's bound refused it (counted in `queue.stats().overflowed`)."""
        return self.queue.put(("message", topic, stamp_ns, data, time.monotonic() if arrived is None else arrived),
                              len(data), topic)

    def finish(self) -> None:
        self.queue.put_always(None)
        self.join()

    def run(self) -> None:
        try:
            self._writer.open()
            self._reserve()
        except Exception as exc:  # noqa: BLE001 - reported by start() as one line
            self.error = _one_line(exc)
            return
        finally:
            self._opened.set()
        oldest: float | None = None   # arrival of the oldest message not yet committed
        uncommitted = 0
        try:
            while (item := self._next(oldest)) is not None:
                if self.error is not None:
                    continue  # keep draining so producers never block; the error is reported
                try:
                    if item is not _IDLE:
                        self._handle(item)
                        uncommitted += 1
                        if item[0] == "message" and oldest is None:
                            oldest = item[4]
                    if uncommitted and (uncommitted >= COMMIT_MESSAGES
                                        or (oldest is not None and time.monotonic() - oldest >= COMMIT_AGE_S)):
                        self._commit()
                        oldest, uncommitted = None, 0
                except Exception as exc:  # noqa: BLE001 - e.g. disk full: report once, stop writing
                    self._fail(exc)
        finally:
            self._close()

    def _next(self, oldest: float | None) -> tuple[Any, ...] | None:
        """The next item, or _IDLE when the oldest uncommitted message comes of commit age without one."""
        try:
            if oldest is None:
                return self.queue.get(timeout=COMMIT_INTERVAL_S)   # type: ignore[no-any-return]
            return self.queue.get(timeout=max(0.0, oldest + COMMIT_AGE_S - time.monotonic()))  # type: ignore[no-any-return]
        except TimeoutError:
            return _IDLE

    def _handle(self, item: tuple[Any, ...]) -> None:
        from touchroller_bringup.bags import COMPRESSED_SUFFIX, COMPRESSED_TYPE, IMAGE_TYPE

        if item[0] == "topic":
            _, topic, msgtype, offered = item
            stored_topic = topic
            if msgtype == IMAGE_TYPE:
                self._images.add(topic)
            if self.compress and msgtype == IMAGE_TYPE:
                self._png[topic] = offered
                stored_topic, msgtype = topic + COMPRESSED_SUFFIX, COMPRESSED_TYPE
            self._connections[topic] = self._writer.add_connection(
                stored_topic, msgtype, typestore=self._typestore, offered_qos_profiles=offered)
        else:
            _, topic, stamp_ns, data, arrived = item
            connection = self._connections[topic]
            if topic in self._png:
                if time.monotonic() - arrived > PNG_LAG_S:
                    # behind (a loaded machine): this frame raw on <topic>, so the writer catches up and a
                    # failure is seen as soon as without compression; readers merge both topics in order
                    if topic not in self._raw_fallback:
                        self._raw_fallback[topic] = self._writer.add_connection(
                            topic, IMAGE_TYPE, typestore=self._typestore, offered_qos_profiles=self._png[topic])
                    connection = self._raw_fallback[topic]
                    self.written_raw += 1
                else:
                    from touchroller_bringup.bag_compression import compressed_message

                    try:
                        data = compressed_message(data, self._typestore)
                    except (ValueError, struct.error):   # a malformed image: what it holds cannot be kept
                        self.unconvertible += 1
                        self._done_with(topic, item[3])
                        return
            self._writer.write(connection, stamp_ns, data)
            self.written += 1
            self._done_with(topic, item[3])

    def _done_with(self, topic: str, data: bytes) -> None:
        """An image is written (or could not be): say so with its stamp (the simulated clock waits for it)."""
        if self._on_image_written is not None and topic in self._images:
            stamp = header_stamp_ns(data)
            if stamp is not None:
                self._on_image_written(topic, stamp)

    def _commit(self) -> None:
        """Put everything written so far on disk: an sqlite3 commit, or the MCAP chunk in progress
        closed and flushed to the file (rosbags' storage writers keep both open until close)."""
        storage = self._writer.storage
        if storage is None:
            return
        connection = getattr(storage, "conn", None)
        if connection is not None:    # sqlite3
            connection.commit()
        else:                         # MCAP
            if storage.chunk.bio.tell():
                storage.close_chunk()
            storage.bio.flush()
        self.committed = self.written

    def _fail(self, exc: BaseException) -> None:
        self.error = _one_line(exc)
        self.failed.set()

    def _reserve(self) -> None:
        """Hold RESERVE_BYTES in the bag folder (best effort: a disk already full holds none)."""
        try:
            with open(self.path / RESERVE_NAME, "wb") as reserve:
                reserve.write(b"\0" * RESERVE_BYTES)
        except OSError:
            pass

    def _close(self) -> None:
        """Finalise the bag; after a failure keep what was committed and index it (no traceback here:
        a thread's exception would print one, e.g. a full disk while MCAP writes its summary). The reserve
        is given back first: room for the summary and metadata.yaml. A bag whose writing failed is not
        finalised (its last chunk may hold what a full disk made of it) but indexed as a killed one is."""
        (self.path / RESERVE_NAME).unlink(missing_ok=True)
        closed = False
        if self.error is None:
            try:
                self._writer.close()
                closed = True
            except Exception as exc:  # noqa: BLE001 - reported through error / failed
                self._fail(exc)
        if self.error is None:
            return
        if not closed:
            storage, self._writer.storage = self._writer.storage, None
            for handle in (getattr(storage, "conn", None), getattr(storage, "bio", None)):
                try:
                    if handle is not None:
                        handle.close()
                except Exception:  # noqa: BLE001, S110 - the disk is full: buffered bytes cannot be written
                    pass
        try:   # counts from what is on disk (a failed commit rolled back its messages)
            from touchroller_bringup.bag_recovery import counts_by_topic, reindex

            found = reindex(self.path)
            self.recovered = f"{found.message_count} messages kept ({counts_by_topic(found)})"
        except Exception as exc:  # noqa: BLE001 - e.g. no room even for metadata.yaml
            self.recovered = f"not indexed ({_one_line(exc)}); run `touchroller reindex {self.path}` once there is room"


def header_stamp_ns(data: bytes | memoryview) -> int | None:
    """The header stamp of a CDR-encoded message that starts with a std_msgs/Header (an Image), in ns;
    None when `data` is too short."""
    if len(data) < 12:
        return None
    order = "<" if data[1] & 1 else ">"   # the encapsulation: CDR_LE / CDR_BE
    sec, nanosec = struct.unpack_from(order + "iI", data, 4)
    return int(sec) * 1_000_000_000 + int(nanosec)


def _one_line(exc: BaseException) -> str:
    text = " ".join(str(exc).split())
    return f"{type(exc).__name__}: {text}" if text else type(exc).__name__


class Recorder(Node):
    """Records `topics` (all but /rosout and /parameter_events when None) to a new bag at `path`.

    `config` (or the ROS parameters of RECORDER_PARAMETERS, given as `parameter_overrides`) bounds the
    writer's queue and sets the subscriptions' depth. Spin it on an executor (and thread) of its own where
    other nodes' callbacks can be long (`touchroller scan` does): its callbacks only queue."""

    def __init__(self, path: str | Path, *, topics: Iterable[str] | None = None, storage: str = "sqlite3",
                 distro: str = "auto", compress: bool = False, discovery_period: float = 0.2,
                 node_name: str = "touchroller_recorder", config: RecorderConfig | None = None,
                 **node_kwargs: Any) -> None:
        # What close() and destroy_node use comes before Node.__init__: from there on the context tracks
        # the node and destroys it at shutdown, also when the rest of this constructor raises.
        self.path = Path(path)
        self.topics = None if topics is None else [t if t.startswith("/") else "/" + t for t in topics]
        self.counts: dict[str, int] = {}
        self._recorded_subscriptions: dict[str, Any] = {}
        self._progress: dict[str, Any] = {}          # image topic -> publisher of <topic>/recorded
        self._last_sequence: dict[tuple[str, Any], int] = {}   # (topic, publisher gid) -> last sequence number
        self._lost: dict[str, int] = {}              # topic -> messages lost before the recorder took them
        self._warned: set[str] = set()
        self._lock = threading.Lock()
        self._closed = False
        self._timer: Any = None
        self._diagnostics: Any = None
        self.config = config or RecorderConfig()
        self._writer = _BagWriter(self.path, storage, distro, compress, self.config.queue_max_bytes,
                                  self._image_written)
        self._writer.start()   # opens the bag: UserError (e.g. a read-only folder) before any node exists
        try:
            super().__init__(node_name, **node_kwargs)
            self._declare_parameters(config)
        except BaseException:
            self._writer.finish()
            raise
        from rclpy.callback_groups import MutuallyExclusiveCallbackGroup

        from touchroller_bringup.ros_diagnostics import DiagnosticsPublisher

        self._group = MutuallyExclusiveCallbackGroup()   # the subscriptions: never behind the discovery timer
        self._diagnostics = DiagnosticsPublisher(self, "touchroller recorder", hardware_id=str(self.path))
        self._diagnostics.add(self._status)
        self._discover()
        self._timer = self.create_timer(discovery_period, self._discover)

    def _declare_parameters(self, config: RecorderConfig | None) -> None:
        from touchroller_bringup.ros_params import ConfigParameters

        self.parameters = ConfigParameters(self, config or RecorderConfig(), RECORDER_PARAMETERS,
                                           on_change=self._configure)
        self._configure(self.parameters.config)

    def _configure(self, config: RecorderConfig) -> None:
        """The config of the parameters, at start-up and after a change (queue.max_bytes applies at once)."""
        self.config = config
        self._writer.queue.max_bytes = config.queue_max_bytes

    @property
    def message_count(self) -> int:
        return sum(self.counts.values())

    @property
    def written(self) -> int:
        return self._writer.written

    @property
    def failed(self) -> threading.Event:
        """Set at once when writing fails (e.g. the disk is full); `close()` then raises UserError."""
        return self._writer.failed

    def stats(self) -> RecorderStats:
        with self._lock:
            received, lost = dict(self.counts), dict(self._lost)
        return RecorderStats(received, self._writer.written, self._writer.written_raw, self._writer.queue.stats(),
                             lost)

    def _wanted(self, topic: str) -> bool:
        if self.topics is None:
            return topic not in EXCLUDED_BY_DEFAULT and topic not in self._progress_topics()
        return topic in self.topics

    def _progress_topics(self) -> set[str]:
        return {topic + RECORDED_SUFFIX for topic in self._progress}

    def _others(self, topic: str) -> list[Any]:
        """The publishers on `topic` but this node (its /diagnostics and <image>/recorded)."""
        me = (self.get_name(), self.get_namespace())
        return [info for info in self.get_publishers_info_by_topic(topic)
                if (info.node_name, info.node_namespace) != me]

    def _discover(self) -> None:
        if self._closed:
            return
        for topic, types in self.get_topic_names_and_types():
            if topic in self._recorded_subscriptions or not self._wanted(topic):
                continue
            offered = [info.qos_profile for info in
                       (self._others(topic) if self.topics is None else self.get_publishers_info_by_topic(topic))]
            if not offered:
                continue  # only subscribers (or only this node) so far: wait for a publisher to learn its QoS
            msgtype = types[0]
            cls = message_class(msgtype)
            if cls is None:
                self._warn_once(topic, f"not recording {topic}: message type {msgtype} is not installed")
                continue
            if msgtype == IMAGE_MSGTYPE:   # before the writer can say a frame of it is written
                from std_msgs.msg import Header

                self._progress[topic] = self.create_publisher(Header, topic + RECORDED_SUFFIX, QoSProfile(
                    history=HistoryPolicy.KEEP_LAST, depth=10, reliability=ReliabilityPolicy.RELIABLE))
            self._writer.add_topic(topic, msgtype, [to_bag_qos(p) for p in offered])
            self.counts[topic] = 0
            self._recorded_subscriptions[topic] = self.create_subscription(
                cls, topic, self._callback_for(topic), subscription_qos(offered, self.config.queue_depth), raw=True,
                callback_group=self._group)
            self.get_logger().info(f"recording {topic} ({msgtype})")

    def _callback_for(self, topic: str) -> Callable[..., None]:
        def on_message(data: bytes, info: Any) -> None:   # two arguments: rclpy hands MessageInfo
            stamp_ns = self.get_clock().now().nanoseconds  # receive time, as rosbag2 records
            with self._lock:
                if self._closed:
                    return
                gap = self._sequence_gap(topic, info)
                queued = self._writer.write(topic, stamp_ns, data)
                if queued:
                    self.counts[topic] += 1
            if gap:
                self.get_logger().error(f"recording {topic}: {gap} message(s) lost before the recorder took them "
                                        f"({self._lost[topic]} in all)", throttle_duration_sec=5.0)
            if not queued:
                self.get_logger().error(
                    f"recording {topic}: the writer is behind and its queue is full "
                    f"({self.config.queue_max_bytes / 2**20:g} MiB, queue.max_bytes): messages refused "
                    f"({self._writer.queue.stats().overflowed.get(topic, 0)} in all)", throttle_duration_sec=5.0)

        if not _has_message_info():
            return lambda data: on_message(data, None)
        return on_message

    def _sequence_gap(self, topic: str, info: Any) -> int:
        """Messages of `topic`'s publisher skipped since the last one taken (0 without MessageInfo)."""
        sequence = info.get("publication_sequence_number") if isinstance(info, dict) else None
        if not sequence:
            return 0
        gid = info.get("publisher_gid")
        key = (topic, tuple(gid.get("data", ())) if isinstance(gid, dict) else None)
        last = self._last_sequence.get(key)
        self._last_sequence[key] = max(int(sequence), last or 0)
        gap = int(sequence) - last - 1 if last is not None and sequence > last + 1 else 0
        if gap:
            self._lost[topic] = self._lost.get(topic, 0) + gap
        return gap

    def _image_written(self, topic: str, stamp_ns: int) -> None:
        """On the writer thread: a frame of image topic `topic` is in the bag; say so on `<topic>/recorded`."""
        publisher = self._progress.get(topic)
        if publisher is None:
            return
        from std_msgs.msg import Header

        header = Header()
        header.stamp.sec, header.stamp.nanosec = divmod(int(stamp_ns), 1_000_000_000)
        try:
            publisher.publish(header)
        except Exception:  # noqa: BLE001 - the context went down while the writer finished
            if self.context.ok():
                raise

    def _status(self) -> Any:
        from touchroller_bringup.ros_diagnostics import ERROR, OK, WARN, Status

        stats = self.stats()
        values = {"messages": sum(stats.received.values()), "written": stats.written,
                  "written_raw": stats.written_raw, "queued_bytes": stats.queue.queued_bytes,
                  "queue_peak_bytes": stats.queue.peak_bytes, "queue_max_bytes": stats.queue.max_bytes,
                  "refused_queue_full": stats.queue.overflowed_total,
                  "lost_before_taken": sum(stats.lost_in_transport.values())}
        if self._writer.error:
            return Status(ERROR, f"writing failed: {self._writer.error}", values)
        if stats.lost:
            return Status(ERROR, stats.summary(), values)
        if stats.queue.queued_bytes > stats.queue.max_bytes // 2:
            return Status(WARN, "the writer is behind: its queue is over half full", values)
        return Status(OK, "recording", values)

    def _warn_once(self, key: str, message: str) -> None:
        if key not in self._warned:
            self._warned.add(key)
            self.get_logger().warning(message)

    def close(self) -> None:
        """Stop recording, write everything queued, finalise metadata. Idempotent."""
        with self._lock:
            if self._closed:
                return
            self._closed = True
        # The timer and subscriptions stay until destroy_node: `_closed` makes them no-ops, and
        # destroying them here, under an executor spinning in another thread (touchroller scan), can
        # hit one while spin adds it to its wait set ("cannot use Destroyable because destruction
        # was requested", a thread traceback).
        self._writer.finish()
        for publisher in self._progress.values():   # a simulated clock no longer waits for this recorder
            self.destroy_publisher(publisher)
        if self._writer.error:
            raise UserError(f"writing bag {self.path} failed: {self._writer.error}; {self._writer.recovered}")

    def destroy_node(self) -> None:
        try:
            self.close()
        finally:
            super().destroy_node()


def _has_message_info() -> bool:
    import rclpy.subscription

    return hasattr(rclpy.subscription, "MessageInfo")
