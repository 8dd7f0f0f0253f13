"""The one grey conversion gives OpenCV's luminance for every image layout the sensor code sees."""
from __future__ import annotations

import cv2
import numpy as np
import pytest

from touchroller_perception.images import to_grey


def test_colour_images_give_opencvs_luminance(rng):
    bgr = rng.integers(0, 256, (6, 7, 3), dtype=np.uint8)
    expected = cv2.cvtColor(bgr, cv2.COLOR_BGR2GRAY)
    np.testing.assert_array_equal(to_grey(bgr), expected)
    bgra = np.dstack([bgr, np.full((6, 7), 17, np.uint8)])
    np.testing.assert_array_equal(to_grey(bgra), expected)          # alpha ignored
    as_float = to_grey(bgr, uint8=False)
    assert as_float.dtype == np.float32
    np.testing.assert_allclose(as_float, expected, atol=0.5)        # unrounded


def test_mono_and_deep_images(rng):
    mono = rng.integers(0, 256, (5, 4), dtype=np.uint8)
    assert to_grey(mono) is mono or np.array_equal(to_grey(mono), mono)
    np.testing.assert_array_equal(to_grey(mono[:, :, None]), mono)
    deep = rng.integers(0, 65536, (5, 4), dtype=np.uint16)
    np.testing.assert_array_equal(to_grey(deep), (deep >> 8).astype(np.uint8))
    np.testing.assert_array_equal(to_grey(np.array([[-3.0, 12.6, 300.0]])), [[0, 13, 255]])
    assert to_grey(deep, uint8=False).dtype == np.float32


@pytest.mark.parametrize("shape", [(4,), (3, 3, 2), (2, 2, 3, 1)])
def test_other_shapes_are_refused_in_one_line(shape):
    with pytest.raises(ValueError, match="expected an HxW"):
        to_grey(np.zeros(shape, np.uint8))
