"""Lossless compressed recordings: a camera's sensor_msgs/Image stored as sensor_msgs/CompressedImage PNG
on `<topic>/compressed` (image_transport's name and `format` string, "bgr8; png compressed bgr8"), as
`image_transport republish` or rosbag2 with the compressed transport would store it; MCAP chunks of the
other messages are also compressed with zstd (`bags.bag_writer(compress=True)`: a chunk mostly of PNG frames,
which zstd would not shrink, is stored as it is).

The PNG holds the pixels exactly (8- and 16-bit, colour or mono), so every reader of the recording
(`bags.read_images`, `read_images_and_tf`: `touchroller map`, `contacts`, `calibrate`) gets the frames the
camera published; `touchroller replay` publishes the decoded frames on the raw topic too, so a graph
listening to `image_raw` runs on a compressed recording as on a raw one.
"""
from __future__ import annotations

from pathlib import Path
from typing import Any

import cv2
import numpy as np

from touchroller_bringup.bags import COMPRESSED_SUFFIX, COMPRESSED_TYPE, parse_image_message
from touchroller_bringup.image_conversion import encoding_for

#: zlib level of the PNGs, with Huffman coding only: a camera frame's noise leaves deflate's string matching
#: nothing to find, so Huffman coding alone writes smaller PNGs than level 1 or 3, in less time, and they
#: decode faster (bench/recording_size.py)
PNG_LEVEL = 1
#: PNG row filter: Sub (each byte less the one to its left) refers to no other row, so a reader needing a
#: band of rows unfilters only those (`png_rows.decode_rows`); libpng's adaptive choice takes Average on
#: camera frames, which chains every row to the one above, for a file a few per cent smaller
PNG_FILTER = cv2.IMWRITE_PNG_FILTER_SUB


def png_of(image: np.ndarray, level: int = PNG_LEVEL) -> tuple[str, bytes]:
    """(image_transport's format string, PNG bytes) of an image as `image_to_array` gives it."""
    encoding = encoding_for(image)
    ok, data = cv2.imencode(".png", image, [cv2.IMWRITE_PNG_COMPRESSION, int(level),
                                            cv2.IMWRITE_PNG_STRATEGY, cv2.IMWRITE_PNG_STRATEGY_HUFFMAN_ONLY,
                                            cv2.IMWRITE_PNG_FILTER, PNG_FILTER])
    if not ok:
        raise ValueError(f"PNG encoding of a {encoding} image failed")
    return f"{encoding}; png compressed {encoding}", data.tobytes()


def compressed_message(raw: bytes | memoryview, store: Any, level: int = PNG_LEVEL) -> bytes:
    """The CDR of a sensor_msgs/CompressedImage (PNG) holding the CDR-encoded sensor_msgs/Image `raw`:
    the same header (stamp, frame id) and pixels. ValueError for a malformed image."""
    from rosbags.typesys.stores.ros2_kilted import builtin_interfaces__msg__Time as Time
    from rosbags.typesys.stores.ros2_kilted import sensor_msgs__msg__CompressedImage as CompressedImage
    from rosbags.typesys.stores.ros2_kilted import std_msgs__msg__Header as Header

    stamp_ns, frame_id, image = parse_image_message(raw)
    fmt, data = png_of(np.ascontiguousarray(image), level)
    sec, nanosec = divmod(int(stamp_ns), 1_000_000_000)
    msg = CompressedImage(header=Header(stamp=Time(sec=sec, nanosec=nanosec), frame_id=frame_id), format=fmt,
                          data=np.frombuffer(data, np.uint8))
    return bytes(store.serialize_cdr(msg, COMPRESSED_TYPE))


def compress_recording(source: str | Path, target: str | Path, storage: str = "mcap", distro: str = "auto",
                       level: int = PNG_LEVEL, png: bool = True, zstd: bool = True) -> int:
    """Rewrite a recording as `touchroller record` writes it compressed: every sensor_msgs/Image topic as
    CompressedImage PNG on `<topic>/compressed` (`png`), the rest as they are, MCAP chunks zstd (`zstd`; but
    those mostly of PNG frames, `bags.bag_writer`); the receive times and offered QoS kept. Returns the number
    of messages written; the target is written whole or not at all (a failure removes it)."""
    import shutil

    from touchroller_bringup.bags import IMAGE_TYPE, bag_writer, open_bag, typestore

    store = typestore()
    target = Path(target)
    reader = open_bag(source)
    count = 0
    try:
        writer = bag_writer(target, storage, distro, compress=zstd)   # type: ignore[arg-type]
        try:
            with writer:
                out: dict[int, Any] = {}
                for connection in reader.connections:
                    image = png and connection.msgtype == IMAGE_TYPE
                    offered = list(getattr(connection.ext, "offered_qos_profiles", []) or [])
                    out[connection.id] = (writer.add_connection(
                        connection.topic + COMPRESSED_SUFFIX if image else connection.topic,
                        COMPRESSED_TYPE if image else connection.msgtype, typestore=store,
                        offered_qos_profiles=offered), image)
                for connection, timestamp, raw in reader.messages():
                    stored, image = out[connection.id]
                    writer.write(stored, timestamp, compressed_message(raw, store, level) if image else bytes(raw))
                    count += 1
        except BaseException:
            shutil.rmtree(target, ignore_errors=True)
            raise
    finally:
        reader.close()
    return count
