"""Replayer: serialized messages at recorded timing and QoS, rate factor, loop, topic filter, truncated bags."""
from __future__ import annotations

import time

import numpy as np
import pytest

pytest.importorskip("rclpy")
from rclpy.executors import SingleThreadedExecutor  # noqa: E402
from rclpy.node import Node  # noqa: E402
from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy  # noqa: E402
from rclpy.serialization import serialize_message  # noqa: E402
from std_msgs.msg import String  # noqa: E402

from touchroller_bringup.errors import UserError  # noqa: E402
from touchroller_bringup.image_conversion import image_to_array  # noqa: E402
from touchroller_bringup.replayer import Replayer, playback_qos  # noqa: E402

pytestmark = pytest.mark.ros


def latched_qos():
    from rosbags.interfaces import Qos, QosDurability, QosHistory, QosLiveliness, QosReliability, QosTime

    infinite = QosTime(2147483647, 4294967295)
    return Qos(QosHistory.UNKNOWN, 0, QosReliability.RELIABLE, QosDurability.TRANSIENT_LOCAL,
               infinite, infinite, QosLiveliness.AUTOMATIC, infinite, False)


def write_string_bag(path, stamps_ns, topic="/chatter", qos=None, storage="sqlite3"):
    from rosbags.rosbag2 import StoragePlugin, Writer
    from rosbags.typesys import Stores, get_typestore

    plugin = StoragePlugin.MCAP if storage == "mcap" else StoragePlugin.SQLITE3
    with Writer(path, version=9, storage_plugin=plugin) as writer:
        connection = writer.add_connection(topic, "std_msgs/msg/String", typestore=get_typestore(Stores.ROS2_KILTED),
                                           offered_qos_profiles=[qos] if qos else [])
        for i, stamp in enumerate(stamps_ns):
            writer.write(connection, stamp, serialize_message(String(data=f"m{i}")))
    return path


class Listener:
    def __init__(self, context, topic="/chatter", msg_type=String, qos=None):
        self.node = Node("listener", context=context)
        self.received: list[tuple[float, object]] = []
        self.node.create_subscription(msg_type, topic, lambda m: self.received.append((time.monotonic(), m)),
                                      qos or QoSProfile(depth=100, reliability=ReliabilityPolicy.RELIABLE))


def play(context, spin_until, replayer, listener, expected, timeout=20):
    executor = SingleThreadedExecutor(context=context)
    executor.add_node(replayer)
    executor.add_node(listener.node)
    try:
        pub = replayer.publisher_for(replayer.topics[0])
        assert spin_until(executor, lambda: pub.get_subscription_count() > 0, timeout=20)
        started = time.monotonic()
        replayer.start()
        assert spin_until(executor, lambda: replayer.finished and len(listener.received) >= expected, timeout=timeout)
        return started
    finally:
        executor.shutdown()


@pytest.mark.parametrize("storage", ["sqlite3", "mcap"])
def test_replays_in_order_at_the_recorded_timing_scaled_by_rate(ros_context, spin_until, tmp_path, storage):
    stamps = [0, 100_000_000, 200_000_000, 1_200_000_000]  # a 1 s pause before the last
    bag = write_string_bag(tmp_path / "bag", [10**18 + s for s in stamps], storage=storage)
    replayer = Replayer(bag, rate=4.0, context=ros_context)
    listener = Listener(ros_context)
    try:
        started = play(ros_context, spin_until, replayer, listener, expected=4)
    finally:
        replayer.destroy_node()
        listener.node.destroy_node()
    assert [m.data for _, m in listener.received] == ["m0", "m1", "m2", "m3"]
    arrivals = [t for t, _ in listener.received]
    # never earlier than the recorded offsets / rate after the start (lower bounds only: a loaded machine
    # may be late). Not between two arrivals: a late m2 (a stalled listener, or replayer catching up on
    # schedule) arrives closer to an on-time m3 - that failed under 0.2 s process stalls.
    for arrival, stamp in zip(arrivals, stamps, strict=True):
        assert arrival - started >= stamp * 1e-9 / 4.0 - 0.01
    assert replayer.published == 4 and replayer.error is None


def test_recorded_transient_local_qos_is_respected(ros_context, spin_until, tmp_path):
    bag = write_string_bag(tmp_path / "bag", [1, 2], topic="/touchroller/map_info", qos=latched_qos())
    replayer = Replayer(bag, rate=10.0, context=ros_context)
    try:
        qos = replayer.get_publishers_info_by_topic("/touchroller/map_info")[0].qos_profile
        assert qos.durability == DurabilityPolicy.TRANSIENT_LOCAL
        assert qos.reliability == ReliabilityPolicy.RELIABLE
        replayer.start()
        assert replayer.wait(20.0)
        # a late subscriber that asks for transient local still gets the messages: they were latched
        late = Listener(ros_context, topic="/touchroller/map_info",
                        qos=QoSProfile(depth=10, reliability=ReliabilityPolicy.RELIABLE,
                                       durability=DurabilityPolicy.TRANSIENT_LOCAL))
        assert spin_until(late.node, lambda: len(late.received) == 2, timeout=20)
        late.node.destroy_node()
    finally:
        replayer.destroy_node()


def test_playback_qos_falls_back_to_best_effort_when_publishers_disagreed():
    from rosbags.interfaces import QosReliability

    reliable = latched_qos()
    best_effort = reliable._replace(reliability=QosReliability.BEST_EFFORT)
    assert playback_qos([reliable, best_effort]).reliability == ReliabilityPolicy.BEST_EFFORT
    assert playback_qos([reliable]).depth == 10
    assert playback_qos([]).reliability == ReliabilityPolicy.RELIABLE


def test_images_round_trip_record_then_replay_bit_exact(ros_context, spin_until, bag_factory):
    from sensor_msgs.msg import Image

    rng = np.random.default_rng(3)
    frames = [rng.integers(0, 256, (30, 40, 3), dtype=np.uint8) for _ in range(5)]
    bag = bag_factory([(2_000_000_000 + i * 16_000_000, f) for i, f in enumerate(frames)], storage="mcap")
    replayer = Replayer(bag, rate=5.0, topics=["/touchroller/image_raw"], context=ros_context)
    listener = Listener(ros_context, topic="/touchroller/image_raw", msg_type=Image)
    try:
        play(ros_context, spin_until, replayer, listener, expected=5)
    finally:
        replayer.destroy_node()
        listener.node.destroy_node()
    got = [m for _, m in listener.received]
    assert [m.header.stamp.nanosec for m in got] == [i * 16_000_000 for i in range(5)]
    assert all(np.array_equal(image_to_array(m), f) for m, f in zip(got, frames, strict=True))


def test_loop_plays_again_until_stopped(ros_context, spin_until, tmp_path):
    bag = write_string_bag(tmp_path / "bag", [0, 1_000_000])
    replayer = Replayer(bag, rate=1.0, loop=True, context=ros_context)
    listener = Listener(ros_context)
    executor = SingleThreadedExecutor(context=ros_context)
    executor.add_node(replayer)
    executor.add_node(listener.node)
    try:
        assert spin_until(executor, lambda: replayer.publisher_for("/chatter").get_subscription_count() > 0)
        replayer.start()
        assert spin_until(executor, lambda: len(listener.received) >= 7, timeout=20)
        replayer.stop()
        assert replayer.finished and replayer.error is None
    finally:
        executor.shutdown()
        replayer.destroy_node()
        listener.node.destroy_node()
    assert [m.data for _, m in listener.received[:6]] == ["m0", "m1"] * 3


def test_unknown_topic_missing_bag_and_bad_rate_are_one_line_errors(ros_context, tmp_path):
    bag = write_string_bag(tmp_path / "bag", [0])
    with pytest.raises(UserError, match="has no topic /nope"):
        Replayer(bag, topics=["/nope"], context=ros_context)
    with pytest.raises(UserError, match="no such bag"):
        Replayer(tmp_path / "missing", context=ros_context)
    with pytest.raises(UserError, match="rate must be positive"):
        Replayer(bag, rate=0.0, context=ros_context)


def test_failing_right_after_node_init_shuts_down_cleanly(ros_context, tmp_path, fail_after_node_init):
    bag = write_string_bag(tmp_path / "bag", [0])
    failure = fail_after_node_init(Replayer)
    with pytest.raises(failure) as raised:
        Replayer(bag, context=ros_context)
    ros_context.try_shutdown()   # destroys the half-built node, which the traceback keeps alive
    assert raised.value is not None and not ros_context.ok()


def test_cli_replay_plays_a_bag_and_reports_errors_in_one_line(ros_context, tmp_path, capsys):
    from touchroller_bringup.cli import main

    bag = write_string_bag(tmp_path / "bag", [0, 50_000_000, 100_000_000])
    assert main(["replay", str(bag), "--rate", "10"]) == 0
    assert "replayed 3 messages" in capsys.readouterr().out
    assert main(["replay", str(tmp_path / "missing")]) == 2
    assert main(["replay", str(bag), "--rate", "-2"]) == 2
    err = capsys.readouterr().err
    assert "no such bag" in err and "--rate must be positive" in err
    assert "Traceback" not in err and len(err.strip().splitlines()) == 2


@pytest.mark.parametrize("flags", [["--rate", "1e-300"], ["--rate", "1e300"], ["--rate", "nan"], ["--rate", "inf"],
                                   ["--delay", "inf"], ["--delay", "nan"], ["--delay", "1e9"]])
def test_cli_replay_refuses_an_absurd_rate_or_delay_in_one_line(tmp_path, capsys, flags):
    """--rate 1e-300 overflowed the playback thread's wait (a traceback, exit 0); --delay inf waited for ever."""
    from touchroller_bringup.cli import main

    bag = write_string_bag(tmp_path / "bag", [0, 50_000_000])
    assert main(["replay", str(bag), *flags]) == 2
    err = capsys.readouterr().err
    assert flags[0] in err and "Traceback" not in err and len(err.strip().splitlines()) == 1
