"""rosbag2 image recordings: both storages, stamps, compressed images, broken bags."""
from __future__ import annotations

import numpy as np
import pytest

from touchroller_bringup.bags import ImageRecord, read_images, typestore, write_images
from touchroller_bringup.errors import UserError


def frames(rng, n=6, shape=(24, 32, 3)):
    return [ImageRecord(1_700_000_000_000_000_000 + i * 33_333_333, rng.integers(0, 256, shape, dtype=np.uint8))
            for i in range(n)]


@pytest.mark.parametrize("storage", ["sqlite3", "mcap"])
def test_images_round_trip_with_their_stamps(bag_factory, rng, storage):
    written = frames(rng)
    bag = bag_factory(written, storage=storage)
    read = list(read_images(bag))
    assert [r.stamp_ns for r in read] == [w.stamp_ns for w in written]
    for r, w in zip(read, written, strict=True):
        np.testing.assert_array_equal(r.image, w.image)


def test_mono_images_and_other_topics(bag_factory, rng):
    written = frames(rng, shape=(10, 12))
    bag = bag_factory(written, topic="/other/image")
    assert [r.image.shape for r in read_images(bag, topic="/other/image")] == [(10, 12)] * len(written)
    with pytest.raises(UserError, match="has no topic /touchroller/image_raw .*topics: /other/image"):
        list(read_images(bag))


def test_compressed_image_recordings_are_read(tmp_path, rng):
    cv2 = pytest.importorskip("cv2")
    from rosbags.rosbag2 import Writer
    from rosbags.typesys.stores.ros2_kilted import builtin_interfaces__msg__Time as Time
    from rosbags.typesys.stores.ros2_kilted import sensor_msgs__msg__CompressedImage as CompressedImage
    from rosbags.typesys.stores.ros2_kilted import std_msgs__msg__Header as Header

    image = rng.integers(0, 256, (16, 16, 3), dtype=np.uint8)
    ok, png = cv2.imencode(".png", image)
    store = typestore()
    with Writer(tmp_path / "c", version=9) as writer:
        conn = writer.add_connection("/touchroller/image_raw", "sensor_msgs/msg/CompressedImage", typestore=store)
        msg = CompressedImage(header=Header(stamp=Time(sec=3, nanosec=5), frame_id="c"), format="png",
                              data=png.reshape(-1))
        writer.write(conn, 3_000_000_005, store.serialize_cdr(msg, "sensor_msgs/msg/CompressedImage"))
    (record,) = read_images(tmp_path / "c")
    assert record.stamp_ns == 3_000_000_005
    np.testing.assert_array_equal(record.image, image)


def test_missing_and_truncated_bags_are_one_line_errors(bag_factory, rng, tmp_path):
    with pytest.raises(UserError, match="no such bag"):
        list(read_images(tmp_path / "nope"))
    bag = bag_factory(frames(rng, n=20, shape=(64, 64, 3)), storage="mcap")
    (data_file,) = bag.glob("*.mcap")
    data_file.write_bytes(data_file.read_bytes()[: data_file.stat().st_size // 2])
    with pytest.raises(UserError) as info:
        list(read_images(bag))
    assert "\n" not in str(info.value)


def test_writer_refuses_to_overwrite_and_unknown_storage(bag_factory, rng, tmp_path):
    bag = bag_factory(frames(rng, n=1))
    with pytest.raises(UserError, match="already exists"):
        write_images(bag, frames(rng, n=1))
    with pytest.raises(UserError, match="unknown bag storage"):
        write_images(tmp_path / "x", frames(rng, n=1), storage="rosbag1")
