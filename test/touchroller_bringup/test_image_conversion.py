"""numpy <-> sensor_msgs/Image: encodings, row padding, byte order, malformed messages."""
from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest

from touchroller_bringup.image_conversion import (
    ImageFormatError,
    array_to_image,
    compressed_to_array,
    fill_image,
    image_to_array,
)


def fake_msg(data: bytes, height: int, width: int, encoding: str, step: int, big: int = 0):
    return SimpleNamespace(height=height, width=width, encoding=encoding, step=step, is_bigendian=big,
                           data=np.frombuffer(data, dtype=np.uint8))


def test_bgr_round_trip_through_a_real_message(rng):
    pytest.importorskip("sensor_msgs")
    image = rng.integers(0, 256, (48, 64, 3), dtype=np.uint8)
    msg = array_to_image(image, stamp_ns=12_345_678_901, frame_id="cam")
    assert (msg.encoding, msg.step, msg.header.frame_id) == ("bgr8", 192, "cam")
    assert (msg.header.stamp.sec, msg.header.stamp.nanosec) == (12, 345_678_901)
    np.testing.assert_array_equal(image_to_array(msg), image)


def test_refilling_a_message_replaces_its_data(rng):
    pytest.importorskip("sensor_msgs")
    first, second = (rng.integers(0, 256, (4, 5), dtype=np.uint8) for _ in range(2))
    msg = array_to_image(first, 1)
    fill_image(msg, second, 2, "cam")
    assert len(msg.data) == second.size
    np.testing.assert_array_equal(image_to_array(msg), second)


def test_row_padding_is_honoured():
    rows = np.arange(2 * 8, dtype=np.uint8).reshape(2, 8)   # width 2 px bgr8 = 6 bytes + 2 padding
    out = image_to_array(fake_msg(rows.tobytes(), 2, 2, "bgr8", step=8))
    np.testing.assert_array_equal(out.reshape(2, 6), rows[:, :6])


def test_rgb_is_returned_as_bgr():
    rgb = np.array([[[10, 20, 30]]], dtype=np.uint8)
    out = image_to_array(fake_msg(rgb.tobytes(), 1, 1, "rgb8", step=3))
    assert out.tolist() == [[[30, 20, 10]]]


@pytest.mark.parametrize("big", [0, 1])
def test_mono16_byte_order(big):
    values = np.array([[1, 258, 65535]], dtype=">u2" if big else "<u2")
    out = image_to_array(fake_msg(values.tobytes(), 1, 3, "mono16", step=6, big=big))
    assert out.dtype == np.uint16 and out.tolist() == [[1, 258, 65535]]


@pytest.mark.parametrize("height, width, encoding, step, size, reason", [
    (2, 2, "bgr8", 5, 100, "step 5 is smaller"),
    (2, 2, "bgr8", 6, 11, "data has 11 bytes"),
    (2, 2, "yuv422", 4, 8, "unsupported image encoding"),
    (0, 2, "mono8", 2, 0, "empty image"),
])
def test_malformed_messages_raise_one_line_errors(height, width, encoding, step, size, reason):
    with pytest.raises(ImageFormatError, match=reason) as info:
        image_to_array(fake_msg(bytes(size), height, width, encoding, step))
    assert "\n" not in str(info.value)


def test_compressed_images_decode_and_garbage_is_refused():
    cv2 = pytest.importorskip("cv2")
    image = np.full((8, 8, 3), 77, dtype=np.uint8)
    ok, png = cv2.imencode(".png", image)
    assert ok
    decoded = compressed_to_array(SimpleNamespace(format="png", data=png.reshape(-1)))
    np.testing.assert_array_equal(decoded, image)
    with pytest.raises(ImageFormatError, match="does not decode"):
        compressed_to_array(SimpleNamespace(format="jpeg", data=np.zeros(10, np.uint8)))
