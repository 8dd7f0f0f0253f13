"""`png_rows.decode_rows`: the first rows of a PNG, exactly as a whole decode gives them."""
from __future__ import annotations

import cv2
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from touchroller_bringup.bag_compression import png_of
from touchroller_bringup.png_rows import decode_rows, png_size


def _png(image: np.ndarray, **params: int) -> np.ndarray:
    ok, data = cv2.imencode(".png", image, [k for kv in params.items() for k in (getattr(cv2, kv[0]), kv[1])])
    assert ok
    return data


@settings(max_examples=40, deadline=None)
@given(rows=st.integers(2, 60), cols=st.integers(1, 50), kind=st.sampled_from(["bgr8", "mono8", "mono16", "bgra8"]),
       level=st.sampled_from([0, 1, 6, 9]), smooth=st.booleans(), seed=st.integers(0, 2**16),
       filtering=st.sampled_from(["adaptive", "IMWRITE_PNG_FILTER_SUB", "IMWRITE_PNG_FILTER_AVG",
                                   "IMWRITE_PNG_FILTER_NONE"]), data=st.data())
def test_the_rows_are_those_of_a_whole_decode(rows, cols, kind, level, smooth, seed, filtering, data):
    rng = np.random.default_rng(seed)
    shape = {"bgr8": (rows, cols, 3), "mono8": (rows, cols), "mono16": (rows, cols), "bgra8": (rows, cols, 4)}[kind]
    dtype = np.uint16 if kind == "mono16" else np.uint8
    image = rng.integers(0, np.iinfo(dtype).max, shape, dtype=dtype, endpoint=True)
    if smooth:   # every PNG filter gets chosen somewhere (a noisy frame takes one or two)
        image = cv2.GaussianBlur(image, (5, 5), 2.0)
    extra = {} if filtering == "adaptive" else {"IMWRITE_PNG_FILTER": getattr(cv2, filtering)}
    png = _png(image, IMWRITE_PNG_COMPRESSION=level, **extra)
    end = data.draw(st.integers(1, rows - 1))
    first = data.draw(st.integers(0, end - 1))
    whole = cv2.imdecode(png, cv2.IMREAD_UNCHANGED)
    got = decode_rows(png, end)
    assert got is not None and got.dtype == whole.dtype and np.array_equal(got, whole[:end])
    band = decode_rows(png, end, first)
    assert band is not None and np.array_equal(band, whole[first:end])
    assert png_size(png) == (rows, cols)


def test_the_recorders_pngs_decode_by_rows():
    image = np.random.default_rng(1).integers(0, 256, (48, 64, 3), dtype=np.uint8)
    _fmt, data = png_of(image)
    assert np.array_equal(decode_rows(data, 20), image[:20])


@pytest.mark.parametrize("shape", [(40, 50, 3), (40, 50)])
def test_rows_that_stand_alone_are_unfiltered_without_a_second_png_decode(monkeypatch, shape):
    """The recorder's rows (8-bit, every one Sub): unfiltered by a running sum, not by building a PNG of the
    rows for OpenCV to decode again; the same values, a band starting anywhere."""
    import touchroller_bringup.png_rows as png_rows

    image = np.random.default_rng(5).integers(0, 256, shape, dtype=np.uint8)
    _fmt, data = png_of(image)
    monkeypatch.setattr(png_rows.cv2, "imdecode", lambda *a: pytest.fail("decoded a second PNG"))
    for first, end in ((0, 39), (17, 18), (12, 33)):
        band = decode_rows(data, end, first)
        assert band is not None and band.dtype == np.uint8 and band.flags.c_contiguous
        assert np.array_equal(band, image[first:end])


def test_a_transparency_chunk_is_applied_as_a_whole_decode_applies_it():
    """A chunk before the image data may change what the decoder gives (tRNS: an alpha channel): such PNGs
    go through OpenCV's own decoder, so the rows are still those of a whole decode."""
    import struct
    import zlib

    image = np.random.default_rng(6).integers(0, 256, (30, 20, 3), dtype=np.uint8)
    image[5:9] = (7, 8, 9)   # BGR: RGB (9, 8, 7), made transparent below
    png = _png(image, IMWRITE_PNG_FILTER=cv2.IMWRITE_PNG_FILTER_SUB).tobytes()
    body = struct.pack(">HHH", 9, 8, 7)
    trns = struct.pack(">I", len(body)) + b"tRNS" + body + struct.pack(">I", zlib.crc32(b"tRNS" + body))
    at = 8 + 25   # after the signature and IHDR
    with_trns = png[:at] + trns + png[at:]
    whole = cv2.imdecode(np.frombuffer(with_trns, np.uint8), cv2.IMREAD_UNCHANGED)
    band = decode_rows(with_trns, 12, 3)
    assert band is not None and band.shape == whole[3:12].shape and np.array_equal(band, whole[3:12])


@pytest.mark.parametrize("case", ["end at the height", "end 0", "not a png", "truncated", "damaged", "interlaced"])
def test_what_only_a_whole_decode_can_read_is_none(case):
    image = np.random.default_rng(2).integers(0, 256, (30, 20, 3), dtype=np.uint8)
    png = _png(image).tobytes()
    end = 10
    if case == "end at the height":
        end = 30
    elif case == "end 0":
        end = 0
    elif case == "not a png":
        png = b"\xff\xd8" + png[2:]
    elif case == "truncated":
        png = png[:len(png) // 3]
    elif case == "damaged":   # a flipped bit in the first rows' data: its chunk's CRC says so
        damaged = bytearray(png)
        damaged[60] ^= 1
        png = bytes(damaged)
        assert cv2.imdecode(np.frombuffer(png, np.uint8), cv2.IMREAD_UNCHANGED) is None
    else:   # the header says Adam7: rows are spread over the whole stream
        header = bytearray(png)
        header[28] = 1
        png = bytes(header)
    assert decode_rows(png, end) is None


def test_rows_past_one_stored_block_decode_whole():
    # the rows handed to the PNG decoder span several deflate stored blocks (65535 bytes each)
    image = np.random.default_rng(3).integers(0, 256, (120, 640, 3), dtype=np.uint8)
    _fmt, data = png_of(image)
    for end in (34, 35, 100, 119):   # 34 rows: 65314 bytes (one block); 35: 67235 (two)
        assert np.array_equal(decode_rows(data, end), image[:end])


def test_a_band_of_rows_decodes_from_the_last_row_that_stands_alone():
    # rows filtered Sub (as the recorder writes them) or None refer to no row above: a band is unfiltered
    # from its own first row on; a mix of filters from the last such row before it
    rng = np.random.default_rng(4)
    image = cv2.GaussianBlur(rng.integers(0, 256, (80, 96, 3), dtype=np.uint8), (5, 5), 2.0)
    _fmt, data = png_of(image)
    assert np.array_equal(decode_rows(data, 50, 30), image[30:50])
    for name in ("IMWRITE_PNG_FILTER_UP", "IMWRITE_PNG_FILTER_PAETH"):
        png = _png(image, IMWRITE_PNG_FILTER=getattr(cv2, name))
        assert np.array_equal(decode_rows(png, 50, 30), image[30:50])
        assert np.array_equal(decode_rows(png, 50, 49), image[49:50])
