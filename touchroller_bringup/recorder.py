"""Record ROS topics into a rosbag2 folder (sqlite3 or MCAP) like `ros2 bag record`, without rosbag2_py.

With `compress`, the recording is lossless but smaller (`touchroller_bringup.bag_compression`): every
sensor_msgs/Image topic is stored as sensor_msgs/CompressedImage PNG on `<topic>/compressed`, and MCAP
chunks are compressed with zstd. A writer that falls `PNG_LAG_S` behind (PNG costs several ms a frame)
writes frames raw on `<topic>` until it has caught up; readers take both topics in recording order.

`Recorder` is a node: it discovers the wanted topics, subscribes with `raw=True` (serialized CDR,
never deserialised), and hands each message to a writer thread that owns the `rosbags` Writer,
so callbacks stay short and nothing is dropped while the disk is busy. The offered QoS profiles
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
import queue
import struct
import threading
import time
from collections.abc import Iterable, Sequence
from pathlib import Path
from typing import Any

from rclpy.duration import Duration
from rclpy.node import Node
from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy

from touchroller_bringup.errors import UserError

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

    def __init__(self, path: Path, storage: str, distro: str = "auto", compress: bool = False) -> None:
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
        self._queue: queue.SimpleQueue[tuple[Any, ...] | None] = queue.SimpleQueue()
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
        self._queue.put(("topic", topic, msgtype, offered))

    def write(self, topic: str, stamp_ns: int, data: bytes, arrived: float | None = None) -> None:
        """Queue a message; `arrived`: when it arrived (time.monotonic(), default now), the commit's clock."""
        self._queue.put(("message", topic, stamp_ns, data, time.monotonic() if arrived is None else arrived))

    def finish(self) -> None:
        self._queue.put(None)
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
                return self._queue.get(timeout=COMMIT_INTERVAL_S)
            return self._queue.get(timeout=max(0.0, oldest + COMMIT_AGE_S - time.monotonic()))
        except queue.Empty:
            return _IDLE

    def _handle(self, item: tuple[Any, ...]) -> None:
        from touchroller_bringup.bags import COMPRESSED_SUFFIX, COMPRESSED_TYPE, IMAGE_TYPE

        if item[0] == "topic":
            _, topic, msgtype, offered = item
            stored_topic = topic
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
                        return
            self._writer.write(connection, stamp_ns, data)
            self.written += 1

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


def _one_line(exc: BaseException) -> str:
    text = " ".join(str(exc).split())
    return f"{type(exc).__name__}: {text}" if text else type(exc).__name__


class Recorder(Node):
    """Records `topics` (all but /rosout and /parameter_events when None) to a new bag at `path`."""

    def __init__(self, path: str | Path, *, topics: Iterable[str] | None = None, storage: str = "sqlite3",
                 distro: str = "auto", compress: bool = False, discovery_period: float = 0.2,
                 node_name: str = "touchroller_recorder", **node_kwargs: Any) -> None:
        # What close() and destroy_node use comes before Node.__init__: from there on the context tracks
        # the node and destroys it at shutdown, also when the rest of this constructor raises.
        self.path = Path(path)
        self.topics = None if topics is None else [t if t.startswith("/") else "/" + t for t in topics]
        self.counts: dict[str, int] = {}
        self._recorded_subscriptions: dict[str, Any] = {}
        self._warned: set[str] = set()
        self._lock = threading.Lock()
        self._closed = False
        self._timer: Any = None
        self._writer = _BagWriter(self.path, storage, distro, compress)
        self._writer.start()   # opens the bag: UserError (e.g. a read-only folder) before any node exists
        try:
            super().__init__(node_name, **node_kwargs)
        except BaseException:
            self._writer.finish()
            raise
        self._discover()
        self._timer = self.create_timer(discovery_period, self._discover)

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

    def _wanted(self, topic: str) -> bool:
        if self.topics is None:
            return topic not in EXCLUDED_BY_DEFAULT
        return topic in self.topics

    def _discover(self) -> None:
        if self._closed:
            return
        for topic, types in self.get_topic_names_and_types():
            if topic in self._recorded_subscriptions or not self._wanted(topic):
                continue
            offered = [info.qos_profile for info in self.get_publishers_info_by_topic(topic)]
            if not offered:
                continue  # only subscribers so far: wait for a publisher to learn its QoS
            msgtype = types[0]
            cls = message_class(msgtype)
            if cls is None:
                self._warn_once(topic, f"not recording {topic}: message type {msgtype} is not installed")
                continue
            self._writer.add_topic(topic, msgtype, [to_bag_qos(p) for p in offered])
            self.counts[topic] = 0
            self._recorded_subscriptions[topic] = self.create_subscription(
                cls, topic, self._callback_for(topic), subscription_qos(offered), raw=True)
            self.get_logger().info(f"recording {topic} ({msgtype})")

    def _callback_for(self, topic: str):
        def on_message(data: bytes) -> None:
            stamp_ns = self.get_clock().now().nanoseconds  # receive time, as rosbag2 records
            with self._lock:
                if self._closed:
                    return
                self.counts[topic] += 1
                self._writer.write(topic, stamp_ns, data)

        return on_message

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
        if self._writer.error:
            raise UserError(f"writing bag {self.path} failed: {self._writer.error}; {self._writer.recovered}")

    def destroy_node(self) -> None:
        try:
            self.close()
        finally:
            super().destroy_node()
