"""rosbag2 recordings of TouchRoller images through `rosbags` (pure Python; sqlite3 and MCAP).

`read_images` yields (stamp, image) records from `sensor_msgs/Image` or `CompressedImage`
topics; Image messages are parsed straight from their CDR bytes (one header, then a view of the
pixel buffer), which is several times faster than a generic deserialiser on VGA frames.
`read_images_and_tf(..., rows=(first, end))` reads only those image rows where the storage allows
it (an uncompressed sqlite3 bag: SQLite's incremental blob reads), and parses TF messages by hand.

Integrity: every MCAP file written here (`bag_writer`: the recorder, `write_images`, `write_scan`) stores
the CRC-32 of each chunk, which rosbags' reader checks, so a flipped byte anywhere in a message is one
line ("chunk checksum mismatch") instead of a wrong image. A chunk whose CRC is 0 (rosbags' own writer,
or a file still being written) cannot be checked; nor can sqlite3 bags (SQLite keeps no checksum of
the data): for those only what the messages say of themselves is verified (the CDR layout, and that an
image's size, step and encoding agree with its byte count).
"""
from __future__ import annotations

import struct
from collections.abc import Iterable, Iterator
from dataclasses import dataclass
from pathlib import Path, PurePath
from typing import Any, Literal

import numpy as np

from touchroller_bringup import names
from touchroller_bringup.errors import UserError
from touchroller_bringup.image_conversion import (
    ImageFormatError,
    compressed_to_array,
    decoded_to_array,
    image_to_array,
    stamp_to_ns,
)

IMAGE_TOPIC = names.IMAGE_TOPIC   # /touchroller/image_raw
IMAGE_TYPE = "sensor_msgs/msg/Image"
COMPRESSED_TYPE = "sensor_msgs/msg/CompressedImage"
COMPRESSED_SUFFIX = "/compressed"   # image_transport's compressed topic beside a raw image topic
MCAP_ZSTD_LEVEL = 1                 # zstd level of compressed MCAP chunks (bench/recording_size.py)
#: message types whose data is compressed already (sensor_msgs/CompressedImage: PNG or JPEG): an MCAP chunk
#: mostly of them is stored without chunk compression, which would save well under 1 % of a PNG camera
#: frame and cost every reader a decompression of the whole chunk (`bag_writer`)
PRECOMPRESSED_TYPES = frozenset({COMPRESSED_TYPE})
Storage = Literal["sqlite3", "mcap"]


@dataclass(frozen=True)
class ImageRecord:
    stamp_ns: int          # header stamp of the image (capture time)
    image: np.ndarray      # HxWx3 BGR uint8, or HxW mono; may be read-only
    row0: int = 0          # the frame row `image` starts at (not 0 when only some rows were read)
    frame_height: int | None = None   # the whole frame's height when `image` holds only some rows

    @property
    def frame_shape(self) -> tuple[int, int]:
        """(height, width) of the frame the image comes from."""
        height = self.image.shape[0] if self.frame_height is None else self.frame_height
        return int(height), int(self.image.shape[1])


@dataclass(frozen=True)
class CompressedRecord:
    """A sensor_msgs/CompressedImage not decoded yet (`read_images_and_tf(..., decode=False)`): decode it
    with `decode_compressed`, in whichever process has the time."""

    stamp_ns: int
    format: str
    data: Any   # the PNG (or JPEG) bytes, or a uint8 array of them


def decode_compressed(record: CompressedRecord, rows: tuple[int, int] | None = None) -> ImageRecord:
    """The image of a CompressedRecord; with `rows` (first, end) only those rows where the format allows it
    (a PNG: `png_rows.decode_rows` stops inflating after them; `row0` and `frame_height` say where they
    lie), else the whole frame. ImageFormatError if it does not decode."""
    if rows is not None:
        from touchroller_bringup.png_rows import decode_rows, png_size

        size = png_size(record.data)
        if size is not None:
            first, end = max(0, min(rows[0], size[0])), max(0, min(rows[1], size[0]))
            if end <= first:
                raise ValueError(f"rows {rows} are outside the {size[0]}-row image")
            image = decode_rows(record.data, end, first)
            if image is not None:
                return ImageRecord(record.stamp_ns, decoded_to_array(image), first, size[0])
    data = np.frombuffer(record.data, np.uint8)
    return ImageRecord(record.stamp_ns, compressed_to_array(_Compressed(record.format, data)))


class _Compressed:
    """The fields of a sensor_msgs/CompressedImage `compressed_to_array` reads."""

    __slots__ = ("format", "data")

    def __init__(self, format: str, data: np.ndarray) -> None:   # noqa: A002 - the message's field name
        self.format, self.data = format, data


def typestore():
    from rosbags.typesys import Stores, get_typestore

    return get_typestore(Stores.ROS2_KILTED)


def bag_writer(path: str | Path, storage: Storage = "sqlite3", distro: str = "auto", compress: bool = False):
    """A rosbags Writer (not yet opened) for a new rosbag2 folder that `distro`'s rosbag2 reads
    (`touchroller_bringup.bag_format`); with MCAP every chunk carries its CRC-32, and `compress` compresses
    each chunk with zstd (rosbag2's MCAP chunk compression; sqlite3 has none: `compress` leaves it as is),
    except a chunk whose bytes are mostly messages of `PRECOMPRESSED_TYPES` (PNG frames), stored as it is:
    MCAP names each chunk's compression, so every MCAP reader reads both kinds."""
    from rosbags.rosbag2 import CompressionFormat, CompressionMode, StoragePlugin

    from touchroller_bringup import bag_format

    plugin = {"sqlite3": StoragePlugin.SQLITE3, "mcap": StoragePlugin.MCAP}.get(storage)
    if plugin is None:
        raise UserError(f"unknown bag storage {storage!r} (use sqlite3 or mcap)")
    path = Path(path)
    if path.exists():
        raise UserError(f"bag {path} already exists")
    distro = bag_format.resolve(distro)
    writer = _writer_class()(path, version=bag_format.writer_version(distro), storage_plugin=plugin)
    writer.distro = distro
    if compress and storage == "mcap":
        writer.set_compression(CompressionMode.STORAGE, CompressionFormat.ZSTD)
    return writer


def _writer_class():
    """rosbags' Writer with an MCAP storage that fills in the chunk CRCs it leaves 0."""
    from binascii import crc32

    from rosbags.rosbag2 import StoragePlugin, Writer
    from rosbags.rosbag2.storage_mcap import McapWriter

    class CrcMcapWriter(McapWriter):
        # A chunk record is opcode (1 byte), length (8), message start and end time (8 + 8), uncompressed
        # size (8), then the uncompressed CRC-32 (4): written 0 by McapWriter.close_chunk, set here.
        CRC_OFFSET = 1 + 8 + 8 + 8 + 8

        def __init__(self, *args, **kwargs) -> None:  # type: ignore[no-untyped-def]
            super().__init__(*args, **kwargs)
            if self.compression == "zstd":   # level 1: camera frames' noise compresses little better at 3, 9x slower
                compress = self.compressor
                self.compressor = lambda data: compress(data, level=MCAP_ZSTD_LEVEL)
            self.precompressed = 0   # bytes of the pending chunk's messages on already compressed topics

        def write(self, connection, timestamp, data) -> None:  # type: ignore[no-untyped-def]
            if connection.msgtype in PRECOMPRESSED_TYPES:
                self.precompressed += len(data)
            super().write(connection, timestamp, data)   # closes the chunk once it is full

        def close_chunk(self) -> None:
            crc = crc32(self.chunk.bio.getbuffer())
            start = self.bio.tell()
            chosen = self.compression, self.compressor
            if 2 * self.precompressed > self.chunk.bio.tell():   # mostly PNG or JPEG: stored as it is
                self.compression, self.compressor = "", bytes
            self.precompressed = 0
            try:
                super().close_chunk()
            finally:
                self.compression, self.compressor = chosen
            end = self.bio.tell()
            self.bio.seek(start + self.CRC_OFFSET)
            self.bio.write(struct.pack("<I", crc))
            self.bio.seek(end)

    class CrcWriter(Writer):
        STORAGE_PLUGINS = {**Writer.STORAGE_PLUGINS, StoragePlugin.MCAP: CrcMcapWriter}
        distro = "kilted"

        def add_connection(self, topic, msgtype, *, offered_qos_profiles=(), **kwargs):  # type: ignore[no-untyped-def]
            from touchroller_bringup.bag_format import offered_qos

            return super().add_connection(topic, msgtype, **kwargs,
                                          offered_qos_profiles=offered_qos(list(offered_qos_profiles), self.distro))

        def close(self) -> None:
            from touchroller_bringup.bag_format import rewrite_metadata

            super().close()
            rewrite_metadata(self.path, self.distro)

    return CrcWriter


def mcap_chunk_crcs(path: str | Path) -> list[int]:
    """The uncompressed CRC-32 stored in each chunk of an MCAP file, in file order (0: not stored)."""
    data = Path(path).read_bytes()
    crcs, at = [], 8   # after the magic: records of opcode (1 byte), content length (8), content
    while at + 9 <= len(data) - 8:
        opcode, length = data[at], struct.unpack_from("<Q", data, at + 1)[0]
        if opcode == 0x06:   # chunk: message start and end time, uncompressed size, uncompressed CRC, ...
            crcs.append(struct.unpack_from("<I", data, at + 9 + 24)[0])
        at += 9 + length
    return crcs


def open_bag(path: str | Path):
    """An opened rosbags Reader; UserError (one line) for a missing or unreadable bag."""
    from rosbags.rosbag2 import Reader

    path = Path(path)
    if not path.exists():
        raise UserError(f"no such bag: {path}")
    if path.is_file():   # a bare .db3/.mcap file: rosbags wants the folder with metadata.yaml
        path = path.parent
    if path.is_dir() and not (path / "metadata.yaml").exists() \
            and any(p.suffix in (".db3", ".mcap") for p in path.iterdir()):
        raise UserError(f"bag {path} has no metadata.yaml (its recorder was killed?): run `touchroller reindex {path}` "
                        "to make it readable")
    try:
        reader = Reader(path)
        reader.open()
    except Exception as exc:  # noqa: BLE001 - rosbags raises several types for unreadable bags
        first_line = str(exc).splitlines()[0] if str(exc) else type(exc).__name__
        raise UserError(f"cannot open bag {path}: {first_line}") from None
    return reader


def _image_connections(reader, path, topic: str):
    """The connections of the images on `topic` and where image_transport puts them compressed
    (`topic`/compressed): a compressed recording can hold both (frames the recorder wrote raw while it
    was behind), read together in recording order."""
    connections = [c for c in reader.connections if c.topic in (topic, topic + COMPRESSED_SUFFIX)]
    if not connections:
        topics = ", ".join(sorted({c.topic for c in reader.connections})) or "none"
        raise UserError(f"bag {path} has no topic {topic} (topics: {topics})")
    bad = [c.msgtype for c in connections if c.msgtype not in (IMAGE_TYPE, COMPRESSED_TYPE)]
    if bad:
        raise UserError(f"topic {topic} in {path} has type {bad[0]}, expected {IMAGE_TYPE} or {COMPRESSED_TYPE}")
    return connections


def check_image_bag(path: str | Path, topic: str = IMAGE_TOPIC) -> None:
    """UserError (one line) unless `path` is a bag with images on `topic`."""
    reader = open_bag(path)
    try:
        connections = _image_connections(reader, path, topic)
        if not sum(getattr(c, "msgcount", 1) for c in connections):
            raise UserError(f"bag {path} has no images on {topic}")
    finally:
        reader.close()


def read_images(path: str | Path, topic: str = IMAGE_TOPIC) -> Iterator[ImageRecord]:
    """Images on `topic` in recording order. UserError on a missing, unreadable or truncated bag."""
    reader = open_bag(path)
    store = None
    try:
        connections = _image_connections(reader, path, topic)
        try:
            for connection, _timestamp, raw in reader.messages(connections=connections):
                if connection.msgtype == IMAGE_TYPE:
                    stamp_ns, image = _parse_image_cdr(raw)
                else:
                    store = store or typestore()
                    msg = store.deserialize_cdr(raw, connection.msgtype)
                    stamp_ns = stamp_to_ns(msg.header.stamp)
                    image = compressed_to_array(msg)
                yield ImageRecord(stamp_ns, image)
        except (ImageFormatError, struct.error, ValueError) as exc:
            raise UserError(f"bag {path}: malformed image message: {exc}") from None
        except UserError:
            raise
        except Exception as exc:  # noqa: BLE001 - truncated sqlite/mcap files surface as various errors
            raise UserError(f"bag {path} is truncated or corrupt: {type(exc).__name__}: {exc}") from None
    finally:
        reader.close()


TF_TYPE = "tf2_msgs/msg/TFMessage"


@dataclass(frozen=True)
class TransformRecord:
    """One transform of a /tf or /tf_static message."""

    parent: str
    child: str
    stamp_ns: int
    translation: tuple[float, float, float]
    rotation: tuple[float, float, float, float]   # x, y, z, w
    static: bool


def tf_topics(path: str | Path) -> tuple[str, ...]:
    """The TF topics (/tf, /tf_static) a recording has, typed tf2_msgs/msg/TFMessage. Read from the bag's
    metadata.yaml, where rosbags' reader takes its topics from too (`_metadata_topics`); a bag whose
    metadata is not plainly readable is opened by rosbags (its errors as `open_bag`'s)."""
    topics = _metadata_topics(path)
    if topics is None:
        reader = open_bag(path)
        try:
            topics = [(c.topic, c.msgtype) for c in reader.connections]
        finally:
            reader.close()
    return tuple(sorted({topic for topic, msgtype in topics if topic in ("/tf", "/tf_static") and msgtype == TF_TYPE}))


def _metadata_topics(path: str | Path) -> list[tuple[str, str]] | None:
    """(topic, type) of every topic in a rosbag2 folder's metadata.yaml, as rosbags' Reader lists its
    connections (from `topics_with_message_count`), parsed with PyYAML's C loader: a few milliseconds
    where opening the bag with rosbags (its pure-Python YAML parsing every topic's QoS, the storage
    opened) takes tens. None (the caller opens the bag instead) unless the metadata is one rosbags
    reads: a version it knows, a storage plugin it has, every listed file there."""
    import yaml

    path = Path(path)
    folder = path.parent if path.is_file() else path
    try:
        text = (folder / "metadata.yaml").read_text(encoding="utf-8")
        info = yaml.load(text, Loader=getattr(yaml, "CSafeLoader", yaml.SafeLoader))["rosbag2_bagfile_information"]
        if not (isinstance(info["version"], int) and info["version"] <= 9
                and info["storage_identifier"] in ("sqlite3", "mcap")
                and all((folder / PurePath(name).name).exists() for name in info["relative_file_paths"])):
            return None
        return [(str(t["topic_metadata"]["name"]), str(t["topic_metadata"]["type"]))
                for t in info["topics_with_message_count"]]
    except (OSError, UnicodeError, yaml.YAMLError, KeyError, TypeError, AttributeError):
        return None


def read_images_and_tf(path: str | Path, topic: str = IMAGE_TOPIC, rows: tuple[int, int] | None = None,
                       decode: bool = True) -> Iterator[ImageRecord | CompressedRecord | TransformRecord]:
    """The images on `topic` and the transforms on /tf and /tf_static, in recording order (as they
    arrived: a frame's pose may come after the frame). UserError as `read_images`.

    rows: (first, end) the image rows the caller needs. An uncompressed sqlite3 bag of sensor_msgs/Image
    then has only those rows read (`ImageRecord.row0`, `frame_height` say where they lie), a PNG
    CompressedImage only the rows up to `end` decoded; other bags give whole frames (row0 0).
    decode: False gives compressed images as CompressedRecord (decode them with `decode_compressed`)."""
    reader = open_bag(path)
    try:
        images = _image_connections(reader, path, topic)
        tf = [c for c in reader.connections if c.topic in ("/tf", "/tf_static") and c.msgtype == TF_TYPE]
        try:
            if rows is not None and _rows_readable(reader, images):
                yield from _sqlite_rows_and_tf(reader, topic, rows)
                return
            for connection, _timestamp, raw in reader.messages(connections=images + tf):
                if connection.msgtype == TF_TYPE:
                    yield from _parse_tf_cdr(raw, connection.topic == "/tf_static")
                elif connection.msgtype == IMAGE_TYPE:
                    stamp_ns, image = _parse_image_cdr(raw)
                    yield ImageRecord(stamp_ns, image)
                else:
                    record = _parse_compressed_cdr(raw)
                    yield decode_compressed(record, rows) if decode else record
        except (ImageFormatError, struct.error, ValueError) as exc:
            raise UserError(f"bag {path}: malformed message: {exc}") from None
        except UserError:
            raise
        except Exception as exc:  # noqa: BLE001 - truncated sqlite/mcap files surface as various errors
            raise UserError(f"bag {path} is truncated or corrupt: {type(exc).__name__}: {exc}") from None
    finally:
        reader.close()


def _rows_readable(reader, images) -> bool:
    """Whether image rows can be read alone: uncompressed sqlite3 files of sensor_msgs/Image."""
    from rosbags.rosbag2.storage_sqlite3 import Sqlite3Reader

    storages = _storages(reader)
    return (not reader.compression_mode and all(c.msgtype == IMAGE_TYPE for c in images) and bool(storages)
            and all(isinstance(s, Sqlite3Reader) and s.dbconn is not None for s in storages))


def _storages(reader) -> list:
    """The opened storage files of a rosbags Reader (a folder's files, or the one file)."""
    storage = getattr(reader, "storage", None)
    return list(getattr(storage, "storages", [storage] if storage is not None else []))


def _sqlite_rows_and_tf(reader, topic: str, rows: tuple[int, int]) -> Iterator[ImageRecord | TransformRecord]:
    """`read_images_and_tf` straight from the sqlite3 files: an image's header, then only its rows
    `rows` (SQLite incremental blob I/O; the rest of the pixels is never copied); /tf and /tf_static
    messages whole. Files in turn merged by log time, each in (log time, insertion) order."""
    import heapq

    def one(storage) -> Iterator[tuple[int, int, ImageRecord | list[TransformRecord]]]:
        connection = storage.dbconn
        # the file is opened immutable and read-only: memory-mapped, a blob's overflow pages are not copied
        connection.execute(f"PRAGMA mmap_size={1 << 31}")
        cursor = connection.cursor().execute(
            "SELECT m.id, m.timestamp, t.name, CASE WHEN t.name = ? THEN NULL ELSE m.data END "
            "FROM messages m JOIN topics t ON m.topic_id = t.id "
            "WHERE (t.name = ? AND t.type = ?) OR (t.name IN ('/tf', '/tf_static') AND t.type = ?) "
            "ORDER BY m.timestamp, m.id", (topic, topic, IMAGE_TYPE, TF_TYPE))
        blob = None
        for rowid, timestamp, name, raw in cursor:
            if raw is None:
                if blob is None:
                    blob = connection.blob_open("main", "messages", "data", rowid, False)
                else:
                    blob.reopen(rowid)
                yield timestamp, rowid, _read_image_rows(blob, rows)
            else:
                yield timestamp, rowid, _parse_tf_cdr(raw, name == "/tf_static")
        if blob is not None:
            blob.close()

    streams = [one(storage) for storage in _storages(reader)]
    merged = streams[0] if len(streams) == 1 else heapq.merge(*streams, key=lambda item: item[:2])
    for _timestamp, _rowid, item in merged:
        if isinstance(item, ImageRecord):
            yield item
        else:
            yield from item


def _read_image_rows(blob, rows: tuple[int, int]) -> ImageRecord:
    """Rows [first, end) of the sensor_msgs/Image in `blob` (clipped to the frame)."""
    head = blob.read(min(blob.length(), 512))
    stamp_ns, msg, data_offset, size = _parse_image_header(head)
    first, end = max(0, min(rows[0], msg.height)), max(0, min(rows[1], msg.height))
    if end <= first:
        raise ValueError(f"rows {rows} are outside the {msg.height}-row image")
    if size < msg.step * msg.height:
        raise ImageFormatError(f"data has {size} bytes, expected step*height = {msg.step * msg.height}")
    if data_offset + size > blob.length():
        raise ValueError(f"pixel data truncated ({blob.length() - data_offset} of {size} bytes)")
    buffer = np.empty((end - first) * msg.step, np.uint8)
    blob.seek(data_offset + first * msg.step)
    blob.read_into(buffer)
    frame_height = msg.height
    msg.height, msg.data = end - first, buffer
    return ImageRecord(stamp_ns, image_to_array(msg), first, frame_height)


def _parse_tf_cdr(raw: bytes | memoryview, static: bool) -> list[TransformRecord]:
    """The transforms of a CDR-encoded tf2_msgs/TFMessage (XCDR1): a sequence of TransformStamped
    (header stamp and frame_id, child_frame_id, translation and rotation as float64)."""
    buf = memoryview(raw)
    if len(buf) < 8:
        raise ValueError("TF message shorter than its CDR header")
    endian = "<" if buf[1] == 1 else ">"
    u32, f64x7 = struct.Struct(endian + "I"), struct.Struct(endian + "7d")
    stamp = struct.Struct(endian + "iI")

    def string(pos: int) -> tuple[str, int]:
        pos += (-(pos - 4)) % 4
        (length,) = u32.unpack_from(buf, pos)
        pos += 4
        if length == 0 or pos + length > len(buf):
            raise ValueError("bad string length in a TF message")
        return bytes(buf[pos:pos + length - 1]).decode(), pos + length

    (count,) = u32.unpack_from(buf, 4)
    pos = 8
    out = []
    for _ in range(count):
        pos += (-(pos - 4)) % 4
        sec, nanosec = stamp.unpack_from(buf, pos)
        parent, pos = string(pos + 8)
        child, pos = string(pos)
        pos += (-(pos - 4)) % 8
        x, y, z, qx, qy, qz, qw = f64x7.unpack_from(buf, pos)
        pos += 56
        out.append(TransformRecord(parent, child, sec * 1_000_000_000 + nanosec, (x, y, z), (qx, qy, qz, qw), static))
    return out


class _ImageView:
    """The fields of a sensor_msgs/Image, enough for `image_to_array`."""

    __slots__ = ("frame_id", "height", "width", "encoding", "is_bigendian", "step", "data")


def _parse_image_header(raw: bytes | memoryview) -> tuple[int, _ImageView, int, int]:
    """(stamp ns, the message's fields but its data, the offset and size of its pixel data) of a CDR-encoded
    sensor_msgs/Image (XCDR1, as rosbag2 stores it); `raw` need only reach the pixel data."""
    buf = memoryview(raw)
    if len(buf) < 4:
        raise ValueError("message shorter than its CDR header")
    endian = "<" if buf[1] == 1 else ">"
    offset = 4                                    # CDR encapsulation header; alignment is relative to here

    def align(pos: int, n: int) -> int:
        return pos + (-(pos - 4)) % n

    def read_u32(pos: int) -> tuple[int, int]:
        pos = align(pos, 4)
        return struct.unpack_from(endian + "I", buf, pos)[0], pos + 4

    def read_string(pos: int) -> tuple[str, int]:
        length, pos = read_u32(pos)
        if length == 0 or pos + length > len(buf):
            raise ValueError("bad string length")
        return bytes(buf[pos:pos + length - 1]).decode(), pos + length

    sec, offset = read_u32(offset)
    nanosec, offset = read_u32(offset)
    sec = sec - (1 << 32) if sec >= 1 << 31 else sec   # int32
    frame_id, offset = read_string(offset)
    msg = _ImageView()
    msg.frame_id = frame_id
    msg.height, offset = read_u32(offset)
    msg.width, offset = read_u32(offset)
    msg.encoding, offset = read_string(offset)
    if offset >= len(buf):
        raise ValueError("message ends in its header")
    msg.is_bigendian = buf[offset]
    offset += 1
    msg.step, offset = read_u32(offset)
    size, offset = read_u32(offset)
    return sec * 1_000_000_000 + nanosec, msg, offset, size


def _parse_compressed_cdr(raw: bytes | memoryview) -> CompressedRecord:
    """A CDR-encoded sensor_msgs/CompressedImage (XCDR1) as a CompressedRecord, its data a view of `raw`
    (a tenth of the time of a generic deserialiser, which matters at hundreds of frames a second)."""
    buf = memoryview(raw)
    if len(buf) < 4:
        raise ValueError("message shorter than its CDR header")
    u32 = struct.Struct(("<" if buf[1] == 1 else ">") + "I")

    def read_u32(pos: int) -> tuple[int, int]:
        pos += (-(pos - 4)) % 4
        return u32.unpack_from(buf, pos)[0], pos + 4

    def read_string(pos: int) -> tuple[str, int]:
        length, pos = read_u32(pos)
        if length == 0 or pos + length > len(buf):
            raise ValueError("bad string length")
        return bytes(buf[pos:pos + length - 1]).decode(), pos + length

    sec, offset = read_u32(4)
    nanosec, offset = read_u32(offset)
    sec = sec - (1 << 32) if sec >= 1 << 31 else sec   # int32
    _frame_id, offset = read_string(offset)
    fmt, offset = read_string(offset)
    size, offset = read_u32(offset)
    if offset + size > len(buf):
        raise ValueError(f"compressed data truncated ({len(buf) - offset} of {size} bytes)")
    return CompressedRecord(sec * 1_000_000_000 + nanosec, fmt, np.frombuffer(buf, np.uint8, size, offset))


def _parse_image_cdr(raw: bytes | memoryview) -> tuple[int, np.ndarray]:
    """Parse a CDR-encoded sensor_msgs/Image (XCDR1, as rosbag2 stores it) without copying pixels."""
    stamp_ns, _frame_id, image = parse_image_message(raw)
    return stamp_ns, image


def parse_image_message(raw: bytes | memoryview) -> tuple[int, str, np.ndarray]:
    """(stamp ns, frame id, pixels as `image_to_array` gives them) of a CDR-encoded sensor_msgs/Image."""
    buf = memoryview(raw)
    stamp_ns, msg, offset, size = _parse_image_header(buf)
    if offset + size > len(buf):
        raise ValueError(f"pixel data truncated ({len(buf) - offset} of {size} bytes)")
    msg.data = np.frombuffer(buf, dtype=np.uint8, count=size, offset=offset)
    return stamp_ns, msg.frame_id, image_to_array(msg)


def offered_qos(latched: bool = False):
    """The QoS our publishers offer (reliable; transient local for latched topics such as /tf_static), as
    a bag stores it, so `ros2 bag play` offers the same."""
    from rosbags.interfaces import Qos, QosDurability, QosHistory, QosLiveliness, QosReliability, QosTime

    unspecified = QosTime(0, 0)
    return Qos(QosHistory.KEEP_LAST, 1 if latched else 10, QosReliability.RELIABLE,
               QosDurability.TRANSIENT_LOCAL if latched else QosDurability.VOLATILE, unspecified, unspecified,
               QosLiveliness.AUTOMATIC, unspecified, False)


def write_images(
    path: str | Path,
    records: Iterable[ImageRecord | tuple[int, np.ndarray]],
    topic: str = IMAGE_TOPIC,
    storage: Storage = "sqlite3",
    frame_id: str = names.CAMERA_FRAME,
    distro: str = "auto",
) -> int:
    """Write images as sensor_msgs/Image to a new rosbag2 folder; returns the number written."""
    from rosbags.typesys.stores.ros2_kilted import builtin_interfaces__msg__Time as Time
    from rosbags.typesys.stores.ros2_kilted import sensor_msgs__msg__Image as Image
    from rosbags.typesys.stores.ros2_kilted import std_msgs__msg__Header as Header

    from touchroller_bringup.image_conversion import encoding_for

    store = typestore()
    count = 0
    with bag_writer(path, storage, distro) as writer:
        connection = writer.add_connection(topic, IMAGE_TYPE, typestore=store, offered_qos_profiles=[offered_qos()])
        for record in records:
            stamp_ns, image = (record.stamp_ns, record.image) if isinstance(record, ImageRecord) else record
            image = np.ascontiguousarray(image)
            sec, nanosec = divmod(int(stamp_ns), 1_000_000_000)
            msg = Image(
                header=Header(stamp=Time(sec=sec, nanosec=nanosec), frame_id=frame_id),
                height=image.shape[0], width=image.shape[1], encoding=encoding_for(image),
                is_bigendian=0, step=int(image.strides[0]), data=image.reshape(-1).view(np.uint8),
            )
            writer.write(connection, int(stamp_ns), store.serialize_cdr(msg, IMAGE_TYPE))
            count += 1
    return count


def write_scan(
    path: str | Path,
    records: Iterable[ImageRecord | TransformRecord],
    topic: str = IMAGE_TOPIC,
    storage: Storage = "sqlite3",
    frame_id: str = names.CAMERA_FRAME,
    distro: str = "auto",
) -> int:
    """Write a scan as a recording would hold it: images (sensor_msgs/Image) and transforms (one
    tf2_msgs/TFMessage per record, on /tf or /tf_static as `static` says), logged in the order given
    (the order they would have arrived in); returns the number of images written."""
    from rosbags.typesys.stores.ros2_kilted import builtin_interfaces__msg__Time as Time
    from rosbags.typesys.stores.ros2_kilted import geometry_msgs__msg__Quaternion as Quaternion
    from rosbags.typesys.stores.ros2_kilted import geometry_msgs__msg__Transform as TransformMsg
    from rosbags.typesys.stores.ros2_kilted import geometry_msgs__msg__TransformStamped as TransformStamped
    from rosbags.typesys.stores.ros2_kilted import geometry_msgs__msg__Vector3 as Vector3
    from rosbags.typesys.stores.ros2_kilted import sensor_msgs__msg__Image as Image
    from rosbags.typesys.stores.ros2_kilted import std_msgs__msg__Header as Header
    from rosbags.typesys.stores.ros2_kilted import tf2_msgs__msg__TFMessage as TFMessage

    from touchroller_bringup.image_conversion import encoding_for

    store = typestore()
    images = 0
    last = 0

    def time(stamp_ns: int) -> Time:
        sec, nanosec = divmod(int(stamp_ns), 1_000_000_000)
        return Time(sec=sec, nanosec=nanosec)

    with bag_writer(path, storage, distro) as writer:
        image_connection = writer.add_connection(topic, IMAGE_TYPE, typestore=store,
                                                 offered_qos_profiles=[offered_qos()])
        tf_connections: dict[bool, Any] = {}   # made at their first message: a topic nobody published is not there
        for record in records:
            last = max(last, int(record.stamp_ns))   # log time: when it arrived, in the order given
            if isinstance(record, ImageRecord):
                image = np.ascontiguousarray(record.image)
                msg = Image(header=Header(stamp=time(record.stamp_ns), frame_id=frame_id), height=image.shape[0],
                            width=image.shape[1], encoding=encoding_for(image), is_bigendian=0,
                            step=int(image.strides[0]), data=image.reshape(-1).view(np.uint8))
                writer.write(image_connection, last, store.serialize_cdr(msg, IMAGE_TYPE))
                images += 1
                continue
            t, q = record.translation, record.rotation
            transform = TransformStamped(
                header=Header(stamp=time(record.stamp_ns), frame_id=record.parent), child_frame_id=record.child,
                transform=TransformMsg(translation=Vector3(x=t[0], y=t[1], z=t[2]),
                                       rotation=Quaternion(x=q[0], y=q[1], z=q[2], w=q[3])))
            if record.static not in tf_connections:
                tf_connections[record.static] = writer.add_connection(
                    "/tf_static" if record.static else "/tf", TF_TYPE, typestore=store,
                    offered_qos_profiles=[offered_qos(latched=record.static)])
            writer.write(tf_connections[record.static], last,
                         store.serialize_cdr(TFMessage(transforms=[transform]), TF_TYPE))
    return images
