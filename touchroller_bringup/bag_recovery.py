"""Recover a rosbag2 folder whose writer was killed: `touchroller reindex BAG` (like `ros2 bag reindex`).

A recording that is SIGKILLed, loses its terminal or fills the disk never writes its metadata.yaml
(and an MCAP file never gets its summary and footer), so no reader opens it. The `Recorder` commits
what it has at least once a second (sqlite3 transactions, MCAP chunks flushed to the file), so the
storage file holds everything up to its last second; `reindex` makes that readable again:

- sqlite3: opening the database read-write lets SQLite roll back a transaction cut off half-way (its
  journal); topics, counts and times come from the `topics` and `messages` tables.
- MCAP: the file is cut after its last complete record and closed with a DataEnd record and a
  Footer without a summary (valid MCAP: readers then scan the data section); a chunk cut off half-way
  is dropped whole. Topics come from the channel records, counts and times from the message records.

Then metadata.yaml is written, atomically, in the form of the QoS text the storage holds
(`touchroller_bringup.bag_format`: Humble's version 5, or version 9 for a bag written for Jazzy or Kilted).
"""
from __future__ import annotations

import os
import re
import sqlite3
import struct
from binascii import crc32
from collections.abc import Iterator
from dataclasses import dataclass, field
from io import BytesIO
from pathlib import Path
from typing import Any

from touchroller_bringup.errors import UserError

MCAP_MAGIC = b"\x89MCAP0\r\n"
OP_FOOTER, OP_SCHEMA, OP_CHANNEL, OP_MESSAGE, OP_CHUNK, OP_DATA_END = 0x02, 0x03, 0x04, 0x05, 0x06, 0x0F
KNOWN_OPS = frozenset(range(0x01, 0x10))


@dataclass
class _Topic:
    name: str
    msgtype: str
    serialization_format: str
    offered_qos_profiles: Any        # as stored: a YAML string (sqlite3, MCAP channel metadata)
    type_description_hash: str = ""
    count: int = 0


@dataclass
class RecoveredBag:
    """What `reindex` found."""

    path: Path
    storage: str                     # sqlite3 or mcap
    storage_file: Path
    message_count: int
    topics: dict[str, int]           # topic -> messages
    repaired: bool                   # the storage file itself had to be repaired (MCAP footer)
    dropped_bytes: int = 0           # bytes of an incomplete trailing record cut off (MCAP)
    notes: list[str] = field(default_factory=list)


def reindex(path: str | Path) -> RecoveredBag:
    """Make the bag at `path` readable again; UserError (one line) when there is nothing to recover.
    The metadata takes the form of the QoS text the storage holds (`bag_format.stored_form`)."""
    path = Path(path)
    if path.is_file():
        path = path.parent
    if not path.is_dir():
        raise UserError(f"no such bag folder: {path}")
    files = sorted((p for p in path.iterdir() if p.suffix in (".db3", ".mcap") and p.is_file()), key=_split_order)
    if not files:
        raise UserError(f"{path} has no .db3 or .mcap storage file to reindex")
    if len({p.suffix for p in files}) > 1:
        raise UserError(f"{path} mixes .db3 and .mcap files")
    storage = "sqlite3" if files[0].suffix == ".db3" else "mcap"
    topics: dict[str, _Topic] = {}
    start, end = 2**63 - 1, 0
    repaired, dropped = False, 0
    per_file: list[_FileSpan] = []
    for file in files:
        if storage == "sqlite3":
            found, first, last = _scan_sqlite3(file)
        else:
            fixed, cut = _repair_mcap(file)
            repaired, dropped = repaired or fixed, dropped + cut
            found, first, last = _scan_mcap(file)
        for topic in found:
            known = topics.setdefault(topic.name, topic)
            if known is not topic:
                known.count += topic.count
        start, end = min(start, first), max(end, last)
        per_file.append(_FileSpan(file.name, sum(t.count for t in found), first, last))
    from touchroller_bringup.bag_format import stored_form

    distro = stored_form([t.offered_qos_profiles for t in topics.values()])
    _write_metadata(path, storage, per_file, list(topics.values()), start, end, distro)
    counts = {t.name: t.count for t in topics.values()}
    return RecoveredBag(path, storage, files[0], sum(counts.values()), counts, repaired, dropped)


@dataclass
class _FileSpan:
    """One storage file's own messages: rosbag2 keeps count, start and duration per file."""
    name: str
    count: int
    first: int     # earliest timestamp (2**63 - 1 when empty)
    last: int


def _split_order(file: Path) -> tuple[str, int, str]:
    """rosbag2 names a split bag's files NAME_0, NAME_1, ..., NAME_10: order by that number, not as text."""
    match = re.fullmatch(r"(.*?)_?(\d+)", file.stem)
    return (match.group(1), int(match.group(2)), file.name) if match else (file.stem, -1, file.name)


# -- sqlite3 ------------------------------------------------------------------------------------------

def _scan_sqlite3(file: Path) -> tuple[list[_Topic], int, int]:
    try:
        # read-write: SQLite rolls back a transaction the killed writer left half-done (a hot journal)
        connection = sqlite3.connect(f"file:{file}?mode=rw", uri=True)
    except sqlite3.Error as exc:
        raise UserError(f"cannot open {file}: {exc}") from None
    try:
        rows = connection.execute("SELECT id, name, type, serialization_format, offered_qos_profiles FROM topics "
                                  "ORDER BY id").fetchall()
        hashes: dict[str, str] = {}
        columns = {row[1] for row in connection.execute("PRAGMA table_info(topics)")}
        if "type_description_hash" in columns:
            hashes = {name: digest for name, digest in
                      connection.execute("SELECT name, type_description_hash FROM topics")}
        counts = {topic_id: (n, first, last) for topic_id, n, first, last in connection.execute(
            "SELECT topic_id, COUNT(*), MIN(timestamp), MAX(timestamp) FROM messages GROUP BY topic_id")}
    except sqlite3.DatabaseError as exc:
        raise UserError(f"cannot read {file}: {exc}") from None
    finally:
        connection.close()
    topics, start, end = [], 2**63 - 1, 0
    for topic_id, name, msgtype, serialization, qos in rows:
        n, first, last = counts.get(topic_id, (0, None, None))
        topics.append(_Topic(name, msgtype, serialization, qos, hashes.get(name, ""), int(n)))
        if n:
            start, end = min(start, int(first)), max(end, int(last))
    return topics, start, end


# -- MCAP ---------------------------------------------------------------------------------------------

def _records(data: bytes | memoryview, offset: int, end: int) -> Iterator[tuple[int, int, int, int]]:
    """(opcode, start, content start, content end) of each complete record in data[offset:end]."""
    while offset + 9 <= end:
        op = data[offset]
        (length,) = struct.unpack_from("<Q", data, offset + 1)
        if op not in KNOWN_OPS or offset + 9 + length > end:
            return
        yield op, offset, offset + 9, offset + 9 + length
        offset += 9 + length


def _complete_end(data: bytes) -> tuple[int, bool]:
    """Where the data section's last complete record ends, and whether the file is closed already
    (a Footer record and the closing magic at its end)."""
    if not data.startswith(MCAP_MAGIC):
        raise ValueError("no MCAP magic at the start")
    footer = len(data) - len(MCAP_MAGIC) - 29        # opcode, length, 20 bytes of footer
    if footer >= len(MCAP_MAGIC) and data.endswith(MCAP_MAGIC) and data[footer] == OP_FOOTER:
        return len(data), True
    end = len(MCAP_MAGIC)
    for op, _start, content, stop in _records(data, end, len(data)):
        if op in (OP_DATA_END, OP_FOOTER) or (op == OP_CHUNK and not _chunk_is_whole(data, content, stop)):
            break   # a summary cut off half-way is dropped with the DataEnd before it, and rewritten
        end = stop
    return end, False


def _chunk_is_whole(data: bytes, content: int, stop: int) -> bool:
    try:
        records = _chunk_records(data[content:stop])
    except (ValueError, struct.error):
        return False
    return sum(1 for _ in _records(records, 0, len(records))) > 0 or not records


def _chunk_records(chunk: bytes) -> bytes:
    _start, _end, uncompressed_size, _crc = struct.unpack_from("<QQQI", chunk, 0)
    (name_length,) = struct.unpack_from("<I", chunk, 28)
    compression = bytes(chunk[32:32 + name_length]).decode()
    offset = 32 + name_length
    (size,) = struct.unpack_from("<Q", chunk, offset)
    payload = bytes(chunk[offset + 8:offset + 8 + size])
    if len(payload) != size:
        raise ValueError("chunk shorter than its records")
    try:   # a compressed chunk cut short or overwritten (a full disk) does not decompress: not whole
        if compression == "zstd":
            try:
                from compression import zstd  # type: ignore[import-not-found]
            except ImportError:
                from backports import zstd  # type: ignore[import-not-found,no-redef]
            payload = zstd.decompress(payload)
        elif compression == "lz4":
            from lz4.frame import decompress

            payload = decompress(payload)
        elif compression:
            raise ValueError(f"unknown chunk compression {compression!r}")
    except ValueError:
        raise
    except Exception as exc:  # noqa: BLE001 - ZstdError, lz4's RuntimeError
        raise ValueError(f"{compression} chunk does not decompress: {exc}") from None
    if len(payload) != uncompressed_size:
        raise ValueError("chunk records do not have their stated size")
    if _crc and crc32(payload) != _crc:
        raise ValueError("chunk records do not match their CRC")
    return payload


def _repair_mcap(file: Path) -> tuple[bool, int]:
    """Close an MCAP file cut off by a kill: truncate after the last complete record, then DataEnd,
    a Footer without summary and the closing magic. (repaired, bytes dropped); untouched if closed."""
    data = file.read_bytes()
    if len(data) < len(MCAP_MAGIC):
        raise UserError(f"{file} is empty: the recording was stopped before anything was written")
    try:
        end, closed = _complete_end(data)
    except ValueError as exc:
        raise UserError(f"{file} is not an MCAP file ({exc})") from None
    if closed:
        return False, 0
    tail = BytesIO()
    tail.write(bytes([OP_DATA_END]) + struct.pack("<Q", 4) + struct.pack("<I", 0))
    # Footer: summary start 0 (none), summary offset start 0, summary CRC 0
    tail.write(bytes([OP_FOOTER]) + struct.pack("<Q", 20) + struct.pack("<QQI", 0, 0, 0))
    tail.write(MCAP_MAGIC)
    with open(file, "r+b") as stream:
        stream.truncate(end)
        stream.seek(end)
        stream.write(tail.getvalue())
        stream.flush()
        os.fsync(stream.fileno())
    return True, len(data) - end


def _scan_mcap(file: Path) -> tuple[list[_Topic], int, int]:
    data = file.read_bytes()
    schemas: dict[int, str] = {}
    channels: dict[int, _Topic] = {}
    start, end = 2**63 - 1, 0

    def visit(buffer: bytes, offset: int, stop: int) -> None:
        nonlocal start, end
        for op, _record, content, record_end in _records(buffer, offset, stop):
            if op == OP_SCHEMA:
                (schema_id,) = struct.unpack_from("<H", buffer, content)
                schemas[schema_id] = _string(buffer, content + 2)[0]
            elif op == OP_CHANNEL:
                channel_id, schema_id = struct.unpack_from("<HH", buffer, content)
                topic, position = _string(buffer, content + 4)
                encoding, position = _string(buffer, position)
                qos = _channel_metadata(buffer, position).get("offered_qos_profiles", "")
                channels[channel_id] = _Topic(topic, schemas.get(schema_id, ""), encoding, qos)
            elif op == OP_MESSAGE:
                channel_id, _sequence, log_time = struct.unpack_from("<HIQ", buffer, content)
                if channel_id in channels:
                    channels[channel_id].count += 1
                    start, end = min(start, log_time), max(end, log_time)
            elif op == OP_CHUNK:
                records = _chunk_records(buffer[content:record_end])
                visit(records, 0, len(records))
            elif op in (OP_DATA_END, OP_FOOTER):
                return

    visit(data, len(MCAP_MAGIC), len(data))
    return list(channels.values()), start, end


def _string(buffer: bytes, offset: int) -> tuple[str, int]:
    (length,) = struct.unpack_from("<I", buffer, offset)
    return bytes(buffer[offset + 4:offset + 4 + length]).decode(), offset + 4 + length


def _channel_metadata(buffer: bytes, offset: int) -> dict[str, str]:
    (size,) = struct.unpack_from("<I", buffer, offset)
    position, stop, pairs = offset + 4, offset + 4 + size, {}
    while position < stop:
        key, position = _string(buffer, position)
        value, position = _string(buffer, position)
        pairs[key] = value
    return pairs


# -- metadata.yaml ------------------------------------------------------------------------------------

def _type_hash(msgtype: str) -> str:
    """RIHS01 hash of a type the ROS 2 Kilted typestore knows ('' otherwise; readers accept that)."""
    try:
        from touchroller_bringup.bags import typestore

        return str(typestore().hash_rihs01(msgtype))
    except Exception:  # noqa: BLE001 - an unknown type: no hash
        return ""


def _write_metadata(path: Path, storage: str, files: list[_FileSpan], topics: list[_Topic], start: int,
                    end: int, distro: str) -> None:
    from rosbags.rosbag2.metadata import dump_qos_v9, parse_qos

    from touchroller_bringup import bag_format

    count = sum(t.count for t in topics)
    start = start if count else 0
    duration = max(0, end - start) if count else 0
    information = {
        "version": 9,
        "storage_identifier": storage,
        "relative_file_paths": [f.name for f in files],
        "duration": {"nanoseconds": duration},
        "starting_time": {"nanoseconds_since_epoch": start},
        "message_count": count,
        "topics_with_message_count": [
            {"topic_metadata": {"name": t.name, "type": t.msgtype, "serialization_format": t.serialization_format,
                                "offered_qos_profiles": dump_qos_v9(parse_qos(t.offered_qos_profiles or "")),
                                "type_description_hash": t.type_description_hash or _type_hash(t.msgtype)},
             "message_count": t.count}
            for t in topics],
        "compression_format": "",
        "compression_mode": "",
        "files": [{"path": f.name, "starting_time": {"nanoseconds_since_epoch": f.first if f.count else 0},
                   "duration": {"nanoseconds": max(0, f.last - f.first) if f.count else 0},
                   "message_count": f.count} for f in files],
        "custom_data": None,
        "ros_distro": distro,
    }
    bag_format.write_metadata(path, bag_format.metadata(information, distro))


def counts_by_topic(found: RecoveredBag) -> str:
    return ", ".join(f"{topic}: {n}" for topic, n in sorted(found.topics.items())) or "no topics"

