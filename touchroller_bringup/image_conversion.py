"""numpy <-> sensor_msgs/Image without cv_bridge (not installable here; used when present is not needed).

`image_to_array` reads any object with the Image fields (rclpy messages, rosbags messages):
it honours `step` (row padding) and `is_bigendian`, and returns BGR for colour encodings so the
rest of the code sees one layout. `array_to_image` fills a message in ~0.1 ms for VGA by copying
through a memoryview (assigning an ndarray to `msg.data` costs ~50-90 ms).
"""
from __future__ import annotations

import sys
from typing import Any

import cv2
import numpy as np

from touchroller_bringup import names

# encoding -> (channels, dtype, conversion to BGR or None)
_ENCODINGS: dict[str, tuple[int, np.dtype, int | None]] = {
    "bgr8": (3, np.dtype(np.uint8), None),
    "8UC3": (3, np.dtype(np.uint8), None),
    "rgb8": (3, np.dtype(np.uint8), cv2.COLOR_RGB2BGR),
    "bgra8": (4, np.dtype(np.uint8), cv2.COLOR_BGRA2BGR),
    "rgba8": (4, np.dtype(np.uint8), cv2.COLOR_RGBA2BGR),
    "mono8": (1, np.dtype(np.uint8), None),
    "8UC1": (1, np.dtype(np.uint8), None),
    "mono16": (1, np.dtype(np.uint16), None),
    "16UC1": (1, np.dtype(np.uint16), None),
}
SUPPORTED_ENCODINGS = tuple(_ENCODINGS)


class ImageFormatError(ValueError):
    """A malformed image message (size, step, encoding or data length)."""


def image_to_array(msg: Any) -> np.ndarray:
    """Image message -> HxWx3 BGR uint8 (colour) or HxW uint8/uint16 (mono).

    The result may be a read-only view of the message's buffer; copy it before writing to it.
    Raises ImageFormatError with a one-line reason on a malformed message.
    """
    encoding = str(msg.encoding)
    if encoding not in _ENCODINGS:
        raise ImageFormatError(f"unsupported image encoding {encoding!r} (supported: {', '.join(SUPPORTED_ENCODINGS)})")
    channels, dtype, conversion = _ENCODINGS[encoding]
    height, width, step = int(msg.height), int(msg.width), int(msg.step)
    if height <= 0 or width <= 0:
        raise ImageFormatError(f"empty image ({width}x{height})")
    row_bytes = width * channels * dtype.itemsize
    if step < row_bytes:
        raise ImageFormatError(f"step {step} is smaller than width*channels*bytes = {row_bytes} for {encoding}")
    buffer = np.frombuffer(msg.data, dtype=np.uint8) if not isinstance(msg.data, np.ndarray) else msg.data
    if buffer.size < step * height:
        raise ImageFormatError(f"data has {buffer.size} bytes, expected step*height = {step * height}")
    rows = buffer[: step * height].reshape(height, step)[:, :row_bytes]
    if dtype.itemsize > 1:
        wire = dtype.newbyteorder(">" if msg.is_bigendian else "<")
        array = rows.view(wire).astype(dtype, copy=False)   # copies only when the byte order differs
    else:
        array = rows
    array = array.reshape((height, width, channels) if channels > 1 else (height, width))
    if conversion is not None:
        array = cv2.cvtColor(array, conversion)
    return array


def compressed_to_array(msg: Any) -> np.ndarray:
    """sensor_msgs/CompressedImage -> BGR (or mono) array; ImageFormatError if it does not decode."""
    data = np.frombuffer(msg.data, dtype=np.uint8) if not isinstance(msg.data, np.ndarray) else msg.data
    image = cv2.imdecode(data, cv2.IMREAD_UNCHANGED) if data.size else None
    if image is None:
        raise ImageFormatError(f"compressed image ({msg.format!r}, {data.size} bytes) does not decode")
    return decoded_to_array(image)


def decoded_to_array(image: np.ndarray) -> np.ndarray:
    """`cv2.imdecode(..., IMREAD_UNCHANGED)`'s image as `compressed_to_array` gives it: BGR (or mono)."""
    if image.ndim == 3 and image.shape[2] == 4:
        image = cv2.cvtColor(image, cv2.COLOR_BGRA2BGR)
    return image


def encoding_for(array: np.ndarray) -> str:
    if array.ndim == 3 and array.shape[2] == 3 and array.dtype == np.uint8:
        return "bgr8"
    if array.ndim == 2 and array.dtype == np.uint8:
        return "mono8"
    if array.ndim == 2 and array.dtype == np.uint16:
        return "mono16"
    raise ImageFormatError(f"no image encoding for an array of shape {array.shape} and dtype {array.dtype}")


def fill_image(msg: Any, array: np.ndarray, stamp_ns: int, frame_id: str, encoding: str | None = None) -> Any:
    """Fill an Image-like message from an array (BGR, mono8 or mono16), fast, and return it."""
    encoding = encoding or encoding_for(array)
    if encoding not in ("bgr8", "mono8", "mono16", "rgb8"):
        raise ImageFormatError(f"cannot publish encoding {encoding!r}")
    array = np.ascontiguousarray(array)
    msg.header.stamp.sec, msg.header.stamp.nanosec = divmod(int(stamp_ns), 1_000_000_000)
    msg.header.frame_id = frame_id
    msg.height, msg.width = int(array.shape[0]), int(array.shape[1])
    msg.encoding = encoding
    msg.is_bigendian = int(sys.byteorder == "big" and array.dtype.itemsize > 1)
    msg.step = int(array.strides[0])
    if isinstance(msg.data, np.ndarray):     # rosbags messages
        msg.data = array.reshape(-1).view(np.uint8)
    else:                                     # rclpy: array.array('B')
        del msg.data[:]
        msg.data.frombytes(memoryview(array).cast("B"))
    return msg


def array_to_image(array: np.ndarray, stamp_ns: int, frame_id: str = names.CAMERA_FRAME,
                   encoding: str | None = None) -> Any:
    """A new sensor_msgs/msg/Image (rclpy) for the array."""
    from sensor_msgs.msg import Image

    return fill_image(Image(), array, stamp_ns, frame_id, encoding)


def stamp_to_ns(stamp: Any) -> int:
    """A builtin_interfaces/Time (any object with `sec` and `nanosec`) as integer nanoseconds."""
    return int(stamp.sec) * 1_000_000_000 + int(stamp.nanosec)
