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


def scan_records(rng, n=5, shape=(40, 24, 3)):
    """Images and transforms interleaved as a recording holds them (two transforms share a message time)."""
    from touchroller_bringup.bags import TransformRecord

    out: list = [TransformRecord("tool0", "touchroller_cylinder", 0, (0.0, 0.0, -0.1), (1.0, 0.0, 0.0, 0.0), True)]
    for i in range(n):
        stamp = 1_700_000_000_000_000_000 + i * 33_333_333
        out.append(TransformRecord("base", "tool0", stamp - 5_000_000, (0.4 + 0.001 * i, -0.02, 0.1 + 1e-4 * i),
                                   (0.0, 1.0, 0.0, 0.0), False))
        out.append(ImageRecord(stamp, rng.integers(0, 256, shape, dtype=np.uint8)))
    return out


@pytest.mark.parametrize("storage", ["sqlite3", "mcap"])
def test_reading_only_some_rows_gives_those_rows_of_every_frame_and_the_same_transforms(tmp_path, rng, storage):
    from touchroller_bringup.bags import read_images_and_tf, write_scan

    written = scan_records(rng)
    write_scan(tmp_path / "scan", written, storage=storage)
    whole = list(read_images_and_tf(tmp_path / "scan"))
    rows = list(read_images_and_tf(tmp_path / "scan", rows=(7, 19)))
    assert [type(r) for r in whole] == [type(r) for r in written] == [type(r) for r in rows]
    for w, a, b in zip(written, whole, rows, strict=True):
        if isinstance(w, ImageRecord):
            assert a.stamp_ns == b.stamp_ns == w.stamp_ns
            np.testing.assert_array_equal(a.image, w.image)
            assert a.frame_shape == b.frame_shape == (40, 24)
            # sqlite3 reads the rows alone; MCAP (no partial reads) gives the whole frame
            assert (b.row0, b.image.shape[0]) == ((7, 12) if storage == "sqlite3" else (0, 40))
            np.testing.assert_array_equal(b.image, w.image[b.row0:b.row0 + b.image.shape[0]])
        else:
            assert a == b
            assert (a.parent, a.child, a.stamp_ns, a.static) == (w.parent, w.child, w.stamp_ns, w.static)
            assert a.translation == pytest.approx(w.translation) and a.rotation == pytest.approx(w.rotation)


def test_tf_messages_parse_as_rosbags_deserialises_them():
    """The hand parser against rosbags' deserialiser on a message of several transforms (odd-length names
    move the alignment of what follows)."""
    from rosbags.typesys.stores.ros2_kilted import builtin_interfaces__msg__Time as Time
    from rosbags.typesys.stores.ros2_kilted import geometry_msgs__msg__Quaternion as Quaternion
    from rosbags.typesys.stores.ros2_kilted import geometry_msgs__msg__Transform as TransformMsg
    from rosbags.typesys.stores.ros2_kilted import geometry_msgs__msg__TransformStamped as Stamped
    from rosbags.typesys.stores.ros2_kilted import geometry_msgs__msg__Vector3 as Vector3
    from rosbags.typesys.stores.ros2_kilted import std_msgs__msg__Header as Header
    from rosbags.typesys.stores.ros2_kilted import tf2_msgs__msg__TFMessage as TFMessage

    from touchroller_bringup.bags import TF_TYPE, _parse_tf_cdr

    names = [("base", "tool0"), ("a", "bc"), ("left/tool0", "left/touchroller_cylinder")]
    transforms = [Stamped(header=Header(stamp=Time(sec=17 + i, nanosec=5 * i + 1), frame_id=parent),
                          child_frame_id=child, transform=TransformMsg(translation=Vector3(x=0.1 * i, y=-0.2, z=3.0),
                                                 rotation=Quaternion(x=0.0, y=0.6, z=0.0, w=0.8)))
                  for i, (parent, child) in enumerate(names)]
    raw = typestore().serialize_cdr(TFMessage(transforms=transforms), TF_TYPE)
    parsed = _parse_tf_cdr(raw, static=False)
    assert [(p.parent, p.child, p.stamp_ns) for p in parsed] == [
        (parent, child, (17 + i) * 1_000_000_000 + 5 * i + 1) for i, (parent, child) in enumerate(names)]
    assert [p.translation for p in parsed] == [(0.1 * i, -0.2, 3.0) for i in range(3)]
    assert all(p.rotation == (0.0, 0.6, 0.0, 0.8) and not p.static for p in parsed)


def _flip_a_byte_in(storage_file, marker: bytes) -> None:
    """Flip one byte inside the first occurrence of `marker` (a run of pixel values) in the file."""
    data = bytearray(storage_file.read_bytes())
    at = data.index(marker) + len(marker) // 2
    data[at] ^= 0x01
    storage_file.write_bytes(bytes(data))


def test_a_flipped_payload_byte_in_an_mcap_we_wrote_is_one_line_not_a_wrong_image(bag_factory):
    """A corrupt MCAP (payload bytes flipped) was read as if whole: the writer stored chunk CRC 0."""
    images = [np.full((24, 32, 3), 90 + i, np.uint8) for i in range(6)]
    bag = bag_factory([(1_000 * i, image) for i, image in enumerate(images)], storage="mcap")
    assert [r.image.mean() for r in read_images(bag)] == [90 + i for i in range(6)]   # whole: read as written
    _flip_a_byte_in(bag / f"{bag.name}.mcap", bytes([93]) * 64)
    with pytest.raises(UserError, match="checksum mismatch"):
        list(read_images(bag))


def test_every_mcap_chunk_we_write_carries_its_crc(tmp_path):
    """Large enough for several chunks (rosbags closes one per MiB), scan bags with TF included."""
    from touchroller_bringup.bags import TransformRecord, mcap_chunk_crcs, write_scan

    records = []
    for i in range(8):
        records.append(ImageRecord(1_000 * i, np.full((480, 640, 3), i, np.uint8)))
        records.append(TransformRecord("base", "tool0", 1_000 * i, (0.0, 0.0, float(i)), (0.0, 0.0, 0.0, 1.0), False))
    bag = tmp_path / "scan"
    write_scan(bag, records, storage="mcap")
    crcs = mcap_chunk_crcs(bag / "scan.mcap")
    assert len(crcs) >= 3 and all(crcs)
    assert len([r for r in read_images(bag)]) == 8


@pytest.mark.parametrize("storage", ["sqlite3", "mcap"])
def test_tf_topics_come_from_the_metadata_as_rosbags_lists_them_without_opening_the_bag(tmp_path, rng, storage,
                                                                                      monkeypatch):
    """`tf_topics` reads metadata.yaml (a few milliseconds) instead of opening the bag with rosbags (tens):
    the same topics as rosbags' reader lists, for a folder or its data file; only a bag whose metadata is
    not plainly readable is opened (and its errors are open_bag's)."""
    import touchroller_bringup.bags as bags
    from touchroller_bringup.bags import ImageRecord, open_bag, tf_topics, write_scan

    images_only = tmp_path / "images"
    write_scan(images_only, [r for r in scan_records(rng) if isinstance(r, ImageRecord)], storage=storage)
    write_scan(tmp_path / "scan", scan_records(rng), storage=storage)
    expected = {}
    for bag in (images_only, tmp_path / "scan"):
        reader = open_bag(bag)
        expected[bag] = tuple(sorted(c.topic for c in reader.connections if c.topic in ("/tf", "/tf_static")))
        reader.close()
    assert expected == {images_only: (), tmp_path / "scan": ("/tf", "/tf_static")}

    def no_open(path):
        raise AssertionError("opened with rosbags")

    monkeypatch.setattr(bags, "open_bag", no_open)
    for bag, topics in expected.items():
        assert tf_topics(bag) == topics
        (data_file,) = [p for p in bag.iterdir() if p.suffix in (".db3", ".mcap")]
        assert tf_topics(data_file) == topics
    monkeypatch.undo()
    with pytest.raises(UserError, match="no such bag"):
        tf_topics(tmp_path / "nope")
    (tmp_path / "scan" / "metadata.yaml").write_text("rosbag2_bagfile_information: {version: 99}\n")
    with pytest.raises(UserError, match="cannot open bag"):
        tf_topics(tmp_path / "scan")


def _chunk_compressions(path) -> list[str]:
    """The compression each chunk of an MCAP file names, in file order."""
    import struct

    data = path.read_bytes()
    names, at = [], 8
    while at + 9 <= len(data) - 8:
        opcode, length = data[at], struct.unpack_from("<Q", data, at + 1)[0]
        if opcode == 0x06:   # chunk: start, end, uncompressed size (8 each), CRC (4), then the compression's name
            size = struct.unpack_from("<I", data, at + 9 + 28)[0]
            names.append(data[at + 9 + 32:at + 9 + 32 + size].decode())
        at += 9 + length
    return names


def test_mcap_chunks_of_png_frames_are_stored_as_they_are_and_the_rest_compressed(tmp_path):
    """zstd saves well under 1 % of a PNG camera frame and costs every reader a decompression: a chunk mostly
    of CompressedImage messages is stored as is; a chunk of other messages still gets zstd. Read back the same."""
    from touchroller_bringup.bag_compression import compressed_message
    from touchroller_bringup.bags import COMPRESSED_TYPE, bag_writer, open_bag

    store = typestore()
    rng = np.random.default_rng(3)
    raw = tmp_path / "raw"
    write_images(raw, [(i, rng.integers(0, 256, (480, 640, 3), np.uint8)) for i in range(4)])
    reader = open_bag(raw)
    pngs = [compressed_message(data, store) for _, _, data in reader.messages()]
    reader.close()
    text = [(b"touchroller " * 8000)[:90_000] for _ in range(30)]   # 2.7 MB of compressible messages
    bag = tmp_path / "mixed"
    writer = bag_writer(bag, "mcap", compress=True)
    with writer:
        images = writer.add_connection("/touchroller/image_raw/compressed", COMPRESSED_TYPE, typestore=store)
        other = writer.add_connection("/notes", "std_msgs/msg/String", typestore=store)
        for i, png in enumerate(pngs):
            writer.write(images, i, png)
        for i, note in enumerate(text):
            writer.write(other, 10 + i, note)
    names = _chunk_compressions(bag / "mixed.mcap")
    assert "" in names and "zstd" in names
    assert names[0] == "" and names[-1] == "zstd"   # the frames come first, the notes last
    reader = open_bag(bag)
    assert [bytes(data) for _, _, data in reader.messages()] == [*pngs, *text]
    reader.close()
