"""Lossless compressed recordings (touchroller_bringup.bag_compression): PNG CompressedImage on
<topic>/compressed, MCAP chunks of them stored as they are; read, mapped and replayed as raw recordings are."""
from __future__ import annotations

import numpy as np
import pytest

from touchroller_bringup.bag_compression import compress_recording, compressed_message
from touchroller_bringup.bags import (
    COMPRESSED_TYPE,
    IMAGE_TOPIC,
    ImageRecord,
    open_bag,
    read_images,
    read_images_and_tf,
    typestore,
    write_images,
)
from touchroller_bringup.image_conversion import compressed_to_array


def textured(n, shape=(48, 64, 3), dtype=np.uint8, seed=0):
    """Frames of a smooth texture with a little noise (compressible as camera frames are, not random)."""
    rng = np.random.default_rng(seed)
    top = 65535 if dtype == np.uint16 else 255
    y, x = np.mgrid[0:shape[0], 0:shape[1]]
    frames = []
    for k in range(n):
        base = (0.5 + 0.3 * np.sin((x + 3 * k) / 5.0) * np.cos(y / 7.0)) * top
        if len(shape) == 3:
            base = np.repeat(base[..., None], shape[2], axis=2)
        noisy = base + rng.normal(0, top / 200, base.shape)
        frames.append(np.clip(noisy, 0, top).astype(dtype))
    return frames


@pytest.mark.parametrize("shape, dtype", [((48, 64, 3), np.uint8), ((48, 64), np.uint8), ((48, 64), np.uint16)])
def test_a_png_message_holds_the_image_exactly_with_its_header(tmp_path, shape, dtype):
    frame = textured(1, shape, dtype)[0]
    write_images(tmp_path / "raw", [(1_234_567_890_123, frame)], frame_id="touchroller_camera")
    reader = open_bag(tmp_path / "raw")
    (_, _, raw), = list(reader.messages())
    reader.close()
    store = typestore()
    msg = store.deserialize_cdr(compressed_message(raw, store), COMPRESSED_TYPE)
    encoding = {3: "bgr8", 2: "mono16" if dtype == np.uint16 else "mono8"}[len(shape) if len(shape) == 3 else 2]
    assert msg.format == f"{encoding}; png compressed {encoding}"
    assert (msg.header.stamp.sec, msg.header.stamp.nanosec) == (1234, 567_890_123)
    assert msg.header.frame_id == "touchroller_camera"
    decoded = compressed_to_array(msg)
    assert decoded.dtype == frame.dtype and np.array_equal(decoded, frame)


@pytest.mark.parametrize("storage", ["sqlite3", "mcap"])
def test_a_compressed_recording_reads_back_the_same_frames_and_is_smaller(tmp_path, storage):
    frames = textured(12)
    write_images(tmp_path / "raw", [(1_000_000 * (k + 1), f) for k, f in enumerate(frames)], storage=storage)
    assert compress_recording(tmp_path / "raw", tmp_path / "small", storage=storage) == 12
    reader = open_bag(tmp_path / "small")
    topics = {c.topic: c.msgtype for c in reader.connections}
    compression = reader.compression_mode
    reader.close()
    assert topics == {IMAGE_TOPIC + "/compressed": COMPRESSED_TYPE} and not compression
    again = list(read_images(tmp_path / "small"))   # asked for image_raw: finds image_raw/compressed
    assert [r.stamp_ns for r in again] == [1_000_000 * (k + 1) for k in range(12)]
    assert all(np.array_equal(r.image, f) for r, f in zip(again, frames, strict=True))
    assert [r.stamp_ns for r in read_images_and_tf(tmp_path / "small", rows=(10, 20))
            if isinstance(r, ImageRecord)] == [r.stamp_ns for r in again]

    def size(folder):
        return sum(p.stat().st_size for p in folder.iterdir() if p.suffix in (".db3", ".mcap"))

    print("RATIO", size(tmp_path / "small") / size(tmp_path / "raw"))
    # Sub-filtered rows (bag_compression.PNG_FILTER) cost these small smooth grey-in-colour frames more than
    # camera frames: 0.89 of the raw size
    assert size(tmp_path / "small") < 0.9 * size(tmp_path / "raw")
    if storage == "mcap":   # chunks of PNG frames stored as they are (bags.PRECOMPRESSED_TYPES), with their CRC
        from touchroller_bringup.bags import mcap_chunk_crcs

        data = (tmp_path / "small" / "small.mcap").read_bytes()
        assert b"zstd" not in data and all(mcap_chunk_crcs(tmp_path / "small" / "small.mcap"))


def test_a_failed_rewrite_leaves_nothing(tmp_path):
    from touchroller_bringup.errors import UserError

    write_images(tmp_path / "raw", [(1, np.zeros((4, 4, 3), np.uint8))])
    (tmp_path / "taken").mkdir()
    with pytest.raises(UserError, match="already exists"):
        compress_recording(tmp_path / "raw", tmp_path / "taken")
    assert (tmp_path / "taken").exists() and not any((tmp_path / "taken").iterdir())


@pytest.mark.ros
def test_the_recorder_stores_images_as_png_and_replay_decodes_them(ros_context, spin_until, tmp_path):
    from rclpy.executors import SingleThreadedExecutor
    from rclpy.node import Node
    from rclpy.qos import QoSProfile, ReliabilityPolicy
    from sensor_msgs.msg import Image

    from touchroller_bringup.image_conversion import array_to_image, image_to_array
    from touchroller_bringup.recorder import Recorder
    from touchroller_bringup.replayer import Replayer

    talker = Node("talker", context=ros_context)
    image_pub = talker.create_publisher(Image, "/touchroller/image_raw",
                                        QoSProfile(depth=20, reliability=ReliabilityPolicy.RELIABLE))
    recorder = Recorder(tmp_path / "bag", storage="mcap", compress=True, context=ros_context)
    executor = SingleThreadedExecutor(context=ros_context)
    executor.add_node(talker)
    executor.add_node(recorder)
    frames = textured(8)
    try:
        assert spin_until(executor, lambda: image_pub.get_subscription_count() == 1, timeout=20)
        for i, frame in enumerate(frames):
            image_pub.publish(array_to_image(frame, 5_000_000_000 + i * 1_000_000))
        assert spin_until(executor, lambda: recorder.counts.get("/touchroller/image_raw", 0) == 8, timeout=20)
    finally:
        recorder.destroy_node()
    reader = open_bag(tmp_path / "bag")
    assert {c.topic: c.msgtype for c in reader.connections} == {"/touchroller/image_raw/compressed": COMPRESSED_TYPE}
    reader.close()
    assert all(np.array_equal(r.image, f) for r, f in zip(read_images(tmp_path / "bag"), frames, strict=True))
    # replayed: as recorded on image_raw/compressed, and decoded on image_raw for a graph that listens there
    received: list = []
    listener = Node("listener", context=ros_context)
    listener.create_subscription(Image, "/touchroller/image_raw", received.append,
                                 QoSProfile(depth=20, reliability=ReliabilityPolicy.RELIABLE))
    replayer = Replayer(tmp_path / "bag", rate=20.0, context=ros_context)
    executor.add_node(listener)
    executor.add_node(replayer)
    try:
        assert set(replayer.topics) == {"/touchroller/image_raw", "/touchroller/image_raw/compressed"}
        assert spin_until(executor, lambda: replayer.publisher_for("/touchroller/image_raw").get_subscription_count(),
                          timeout=20)
        replayer.start()
        assert spin_until(executor, lambda: len(received) == 8, timeout=20)
        assert all(np.array_equal(image_to_array(m), f) for m, f in zip(received, frames, strict=True))
        assert received[3].header.stamp.sec == 5 and received[3].header.stamp.nanosec == 3_000_000
    finally:
        replayer.destroy_node()
        listener.destroy_node()
        executor.shutdown()
        talker.destroy_node()


@pytest.mark.parametrize("storage", ["sqlite3", "mcap"])
def test_a_writer_behind_writes_frames_raw_and_the_recording_reads_every_frame_in_order(tmp_path, storage):
    """PNG costs several ms a frame: a writer that fell PNG_LAG_S behind writes raw until it caught up.
    Readers merge image_raw and image_raw/compressed in recording order; nothing is lost or reordered."""
    import time

    from touchroller_bringup.recorder import PNG_LAG_S, _BagWriter

    frames = textured(10)
    write_images(tmp_path / "raw", [(1_000 + k, f) for k, f in enumerate(frames)])
    reader = open_bag(tmp_path / "raw")
    raws = [bytes(raw) for _, _, raw in reader.messages()]
    reader.close()
    writer = _BagWriter(tmp_path / "bag", storage, compress=True)
    writer.start()
    try:
        writer.add_topic(IMAGE_TOPIC, "sensor_msgs/msg/Image", [])
        for k, raw in enumerate(raws):   # frames 3-6 reach the writer late
            late = 3 <= k <= 6
            writer.write(IMAGE_TOPIC, 5_000 + k, raw, arrived=time.monotonic() - (10 * PNG_LAG_S if late else 0.0))
    finally:
        writer.finish()
    assert writer.written_raw == 4 and writer.written == 10 and writer.error is None
    reader = open_bag(tmp_path / "bag")
    counts = {c.topic: c.msgcount for c in reader.connections}
    reader.close()
    assert counts == {IMAGE_TOPIC + "/compressed": 6, IMAGE_TOPIC: 4}
    again = list(read_images(tmp_path / "bag"))
    assert [r.stamp_ns for r in again] == [1_000 + k for k in range(10)]
    assert all(np.array_equal(r.image, f) for r, f in zip(again, frames, strict=True))


def test_the_recorders_png_rows_are_filtered_sub():
    # every row refers to no other row: a reader needing a band of rows unfilters only those (png_rows)
    import zlib

    from touchroller_bringup.bag_compression import png_of

    frame = textured(1, shape=(40, 64, 3))[0]
    _fmt, data = png_of(frame)
    body = data[8 + 25:]   # past the signature and IHDR: the IDAT chunks (no other chunk before them)
    idat = b"".join(body[pos + 8:pos + 8 + int.from_bytes(body[pos:pos + 4], "big")]
                    for pos in _chunk_starts(body) if body[pos + 4:pos + 8] == b"IDAT")
    rows = zlib.decompress(idat)
    assert set(rows[::64 * 3 + 1]) == {1}


def _chunk_starts(body):
    pos = 0
    while pos + 8 <= len(body):
        yield pos
        pos += 12 + int.from_bytes(body[pos:pos + 4], "big")
