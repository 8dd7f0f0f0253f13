"""Recorder: raw subscriptions into rosbag2 (sqlite3 and MCAP) with offered QoS, nothing lost on Ctrl-C."""
from __future__ import annotations

import os
import signal
import subprocess
import sys
import time

import numpy as np
import pytest

pytest.importorskip("rclpy")
from rclpy.duration import Duration  # noqa: E402
from rclpy.executors import SingleThreadedExecutor  # noqa: E402
from rclpy.node import Node  # noqa: E402
from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy  # noqa: E402
from std_msgs.msg import String  # noqa: E402

from touchroller_bringup.bags import read_images  # noqa: E402
from touchroller_bringup.errors import UserError  # noqa: E402
from touchroller_bringup.image_conversion import array_to_image  # noqa: E402
from touchroller_bringup.recorder import Recorder, subscription_qos  # noqa: E402

pytestmark = pytest.mark.ros
LATCHED = QoSProfile(depth=1, reliability=ReliabilityPolicy.RELIABLE, durability=DurabilityPolicy.TRANSIENT_LOCAL)


def bag_messages(path):
    from rosbags.rosbag2 import Reader

    with Reader(path) as reader:
        return {c.topic: c for c in reader.connections}, [(c.topic, t, bytes(d)) for c, t, d in reader.messages()]


def images(n):
    rng = np.random.default_rng(7)
    return [rng.integers(0, 256, (24, 32, 3), dtype=np.uint8) for _ in range(n)]


@pytest.mark.parametrize("storage", ["sqlite3", "mcap"])
def test_records_images_and_latched_topics_with_their_qos(ros_context, spin_until, tmp_path, storage):
    talker = Node("talker", context=ros_context)
    from sensor_msgs.msg import Image

    image_pub = talker.create_publisher(Image, "/touchroller/image_raw",
                                        QoSProfile(depth=20, reliability=ReliabilityPolicy.RELIABLE))
    status_pub = talker.create_publisher(String, "/touchroller/status", LATCHED)
    status_pub.publish(String(data="latched before the recorder started"))
    recorder = Recorder(tmp_path / "bag", storage=storage, context=ros_context)
    executor = SingleThreadedExecutor(context=ros_context)
    executor.add_node(talker)
    executor.add_node(recorder)
    try:
        assert spin_until(executor, lambda: image_pub.get_subscription_count() == 1, timeout=20)
        frames = images(10)
        for i, frame in enumerate(frames):
            image_pub.publish(array_to_image(frame, 5_000_000_000 + i * 1_000_000))
        assert spin_until(executor, lambda: recorder.counts.get("/touchroller/image_raw", 0) == 10
                          and recorder.counts.get("/touchroller/status", 0) == 1, timeout=20)
    finally:
        recorder.destroy_node()
        executor.shutdown()
        talker.destroy_node()
    connections, messages = bag_messages(tmp_path / "bag")
    assert set(connections) == {"/touchroller/image_raw", "/touchroller/status"}
    image_qos = connections["/touchroller/image_raw"].ext.offered_qos_profiles[0]
    status_qos = connections["/touchroller/status"].ext.offered_qos_profiles[0]
    assert image_qos.reliability.name == "RELIABLE"  # DDS discovery does not carry history or depth
    assert status_qos.durability.name == "TRANSIENT_LOCAL"
    assert connections["/touchroller/image_raw"].msgtype == "sensor_msgs/msg/Image"
    records = list(read_images(tmp_path / "bag"))
    assert [r.stamp_ns for r in records] == [5_000_000_000 + i * 1_000_000 for i in range(10)]
    assert all(np.array_equal(r.image, f) for r, f in zip(records, frames, strict=True))
    receive_times = [t for topic, t, _ in messages if topic == "/touchroller/image_raw"]
    assert receive_times == sorted(receive_times)
    if storage == "mcap":   # every chunk carries its CRC, which the reader checks
        from touchroller_bringup.bags import mcap_chunk_crcs

        crcs = mcap_chunk_crcs(tmp_path / "bag" / "bag.mcap")
        assert crcs and all(crcs)


def test_only_the_requested_topics_are_recorded(ros_context, spin_until, tmp_path):
    talker = Node("talker", context=ros_context)
    wanted = talker.create_publisher(String, "/wanted", 10)
    other = talker.create_publisher(String, "/other", 10)
    recorder = Recorder(tmp_path / "bag", topics=["wanted"], context=ros_context)
    executor = SingleThreadedExecutor(context=ros_context)
    executor.add_node(talker)
    executor.add_node(recorder)
    try:
        assert spin_until(executor, lambda: wanted.get_subscription_count() == 1, timeout=20)
        for i in range(3):
            wanted.publish(String(data=f"w{i}"))
            other.publish(String(data=f"o{i}"))
        assert spin_until(executor, lambda: recorder.message_count == 3, timeout=20)
        spin_until(executor, lambda: False, timeout=0.3)
        assert other.get_subscription_count() == 0
    finally:
        recorder.destroy_node()
        executor.shutdown()
        talker.destroy_node()
    connections, messages = bag_messages(tmp_path / "bag")
    assert list(connections) == ["/wanted"] and len(messages) == 3


def test_bad_output_is_one_clear_error(ros_context, tmp_path):
    (tmp_path / "exists").mkdir()
    with pytest.raises(UserError, match="already exists"):
        Recorder(tmp_path / "exists", context=ros_context)
    with pytest.raises(UserError, match="unknown bag storage"):
        Recorder(tmp_path / "new", storage="rosbag1", context=ros_context)


def test_a_bag_that_cannot_be_opened_is_the_error_not_a_failing_cleanup(tmp_path):
    """`touchroller record --out <read-only dir>` said `'Recorder' object has no attribute '_timer'`. As the
    user runs it; a folder under a regular file fails for root too."""
    (tmp_path / "file").write_text("not a folder")
    done = subprocess.run([sys.executable, "-m", "touchroller_bringup.cli", "record", "--out",
                           str(tmp_path / "file" / "bag"), "--duration", "1"], capture_output=True, text=True,
                          timeout=120, env=dict(os.environ, ROS_AUTOMATIC_DISCOVERY_RANGE="LOCALHOST"))
    assert done.returncode == 2, done.stderr
    assert done.stderr.count("\n") == 1 and "cannot write bag" in done.stderr and "Error" in done.stderr, done.stderr
    assert "AttributeError" not in done.stderr


def test_failing_right_after_node_init_finalises_the_bag_and_shuts_down_cleanly(ros_context, tmp_path,
                                                                                fail_after_node_init):
    failure = fail_after_node_init(Recorder)
    with pytest.raises(failure) as raised:
        Recorder(tmp_path / "partial", context=ros_context)
    ros_context.try_shutdown()   # destroys the half-built node, which the traceback keeps alive
    assert raised.value is not None and not ros_context.ok()
    assert (tmp_path / "partial" / "metadata.yaml").is_file()   # the writer was closed, not left open


def test_subscription_qos_adapts_to_the_publishers():
    reliable = QoSProfile(depth=5, reliability=ReliabilityPolicy.RELIABLE)
    best_effort = QoSProfile(depth=5, reliability=ReliabilityPolicy.BEST_EFFORT)
    assert subscription_qos([reliable]).reliability == ReliabilityPolicy.RELIABLE
    assert subscription_qos([reliable, best_effort]).reliability == ReliabilityPolicy.BEST_EFFORT
    assert subscription_qos([LATCHED]).durability == DurabilityPolicy.TRANSIENT_LOCAL
    assert subscription_qos([LATCHED, reliable]).durability == DurabilityPolicy.VOLATILE


def test_cli_record_stopped_with_ctrl_c_keeps_every_message(ros_context, spin_until, tmp_path):
    bag = tmp_path / "ctrl_c"
    process = subprocess.Popen(
        [sys.executable, "-m", "touchroller_bringup.cli", "record", "--out", str(bag), "--topics", "/chatter"],
        stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=dict(os.environ))
    talker = Node("talker", context=ros_context)
    reliable = QoSProfile(depth=100, reliability=ReliabilityPolicy.RELIABLE)
    publisher = talker.create_publisher(String, "/chatter", reliable)
    try:
        assert spin_until(talker, lambda: publisher.get_subscription_count() == 1, timeout=30), \
            "recorder never subscribed"
        for i in range(50):
            publisher.publish(String(data=f"message {i}"))
        # wait until the recorder has acknowledged them all (reliable), then interrupt at once
        assert publisher.wait_for_all_acked(Duration(seconds=10.0))
        process.send_signal(signal.SIGINT)
        out, err = process.communicate(timeout=30)
    finally:
        if process.poll() is None:
            process.kill()
        talker.destroy_node()
    assert process.returncode == 0, err
    assert "Traceback" not in err
    assert "recorded 50 messages" in out
    _, messages = bag_messages(bag)
    from rclpy.serialization import deserialize_message

    assert [deserialize_message(d, String).data for _, _, d in messages] == [f"message {i}" for i in range(50)]


def test_cli_record_duration_and_bad_arguments(ros_context, tmp_path, capsys):
    from touchroller_bringup.cli import main

    started = time.monotonic()
    assert main(["record", "--out", str(tmp_path / "short"), "--duration", "0.3"]) == 0
    assert time.monotonic() - started >= 0.3
    assert (tmp_path / "short" / "metadata.yaml").is_file()
    assert main(["record", "--out", str(tmp_path / "short"), "--duration", "0.3"]) == 2
    assert main(["record", "--out", str(tmp_path / "x"), "--duration", "-1"]) == 2
    err = capsys.readouterr().err
    assert "already exists" in err and "--duration must be positive" in err and "Traceback" not in err
