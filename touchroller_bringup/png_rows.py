"""The first rows of a PNG, decoded without the rest: what `touchroller map` needs of a compressed frame.

A compressed recording holds each frame as a lossless PNG (`bag_compression`). The map uses one band of
rows around the contact line; decoding a VGA frame whole spends most of its time inflating the deflate
stream, a byte at a time, rows the map never reads. The deflate stream can only be inflated in order, so
`decode_rows(data, end, first)` inflates the bytes of rows [0, end) (zlib, stopping at their length) and
nothing after. Unfiltering is in order too where a row's filter refers to the row above (Up, Average,
Paeth), but a row filtered None or Sub stands alone: the rows are unfiltered from the last such row at
or before `first` (row 0 if none; the recorder writes every row Sub, so a band starts at its own first
row). Those rows go to OpenCV's PNG decoder as a PNG of their own (the chunks before the image data kept;
the rows stored uncompressed), so the unfiltering is libpng's own and the rows are exactly those of a
whole decode; 8-bit grey or colour rows filtered only None or Sub (what the recorder writes), with no
chunk before the image data that a decoder would apply (transparency, a palette), are unfiltered here
instead (a running sum along each row, modulo 256: the same bytes, without a second decode). Every
chunk read is checked against its CRC as a whole decode checks it. An interlaced PNG (Adam7 spreads
every row over the whole stream), a malformed one, or `end` at or past the image's height: None, and the
caller decodes the whole image.

Inflating is the cost: with `isal` installed (Intel's ISA-L, `pip install isal`; pinned in
requirements.txt) it inflates two to three times as fast as zlib, with the same bytes out; without it,
zlib.
"""
from __future__ import annotations

import struct
import zlib
from typing import Any

import cv2
import numpy as np

try:   # the same inflate, faster (optional)
    from isal import isal_zlib as _inflate
except ImportError:   # pragma: no cover - isal is pinned in requirements.txt; a ROS install may lack it
    _inflate = zlib  # type: ignore[misc]
_INFLATE_ERROR: Any = _inflate.error
_ERRORS: tuple[type[BaseException], ...] = (zlib.error, _INFLATE_ERROR)


def _view(data: Any) -> memoryview:
    """The bytes of `data` (bytes, memoryview or a uint8 array) without a copy."""
    return memoryview(data).cast("B")

_SIGNATURE = b"\x89PNG\r\n\x1a\n"
_CHUNK = struct.Struct(">I4s")
_IHDR = struct.Struct(">IIBBBBB")
_CRC = struct.Struct(">I")
_CHANNELS = {0: 1, 2: 3, 3: 1, 4: 2, 6: 4}   # PNG colour type -> samples per pixel


def png_size(data: Any) -> tuple[int, int] | None:
    """(height, width) a PNG declares in its header (`data`: bytes, memoryview or a uint8 array); None if
    `data` does not start as a PNG."""
    raw = _view(data)
    if len(raw) < 8 + 8 + _IHDR.size or bytes(raw[:8]) != _SIGNATURE or bytes(raw[12:16]) != b"IHDR":
        return None
    width, height = _IHDR.unpack_from(raw, 16)[:2]
    return int(height), int(width)


def _chunk(kind: bytes, body: bytes | memoryview) -> bytes:
    return _CHUNK.pack(len(body), kind) + bytes(body) + struct.pack(">I", zlib.crc32(body, zlib.crc32(kind)))


_STORED = 65535   # the most bytes a deflate stored block holds
_STORED_HEADER = struct.Struct("<BHH")   # final-block flag and type 00, length, its one's complement


def _stored_idat(rows: memoryview) -> list[bytes | memoryview]:
    """An IDAT chunk holding `rows` as a zlib stream of stored (uncompressed) blocks, as pieces to join:
    `zlib.compress(rows, 0)` in its chunk, without copying the rows twice (their checksums by `_inflate`,
    ISA-L's when installed)."""
    pieces: list[bytes | memoryview] = [b"\x78\x01"]   # zlib header: deflate, 32 KiB window, no dictionary
    for start in range(0, max(len(rows), 1), _STORED):
        block = rows[start:start + _STORED]
        final = int(start + _STORED >= len(rows))
        pieces += [_STORED_HEADER.pack(final, len(block), len(block) ^ 0xFFFF), block]
    pieces.append(struct.pack(">I", _inflate.adler32(rows) & 0xFFFFFFFF))
    crc = _inflate.crc32(b"IDAT")
    for piece in pieces:
        crc = _inflate.crc32(piece, crc)
    return [_CHUNK.pack(sum(len(piece) for piece in pieces), b"IDAT"), *pieces, _CRC.pack(crc & 0xFFFFFFFF)]


def _unfilter_alone(rows: bytes, first: int, end: int, width: int, channels: int,
                    filters: np.ndarray) -> np.ndarray:
    """Rows [first, end) of inflated 8-bit grey or RGB PNG rows each filtered None or Sub, unfiltered here
    (Sub: each byte plus the unfiltered one a pixel to its left, modulo 256: a running sum along the row),
    as OpenCV's decoder gives them (BGR, or 2-D grey)."""
    count = end - first
    row_bytes = width * channels + 1
    block = np.frombuffer(rows, np.uint8, count * row_bytes, first * row_bytes).reshape(count, row_bytes)
    pixels = block[:, 1:].reshape(count, width, channels)
    if channels == 3:
        pixels = pixels[..., ::-1]   # RGB in the file, BGR as OpenCV gives it
    if filters.min() == 1:   # every row Sub (as the recorder writes them)
        image = np.cumsum(pixels, axis=1, dtype=np.uint8)
    else:
        image = pixels.copy()
        sub = filters == 1
        image[sub] = np.cumsum(pixels[sub], axis=1, dtype=np.uint8)
    return image if channels == 3 else image[..., 0]


def decode_rows(data: Any, end: int, first: int = 0) -> np.ndarray | None:
    """Rows [first, end) of the PNG `data` as `cv2.imdecode(data, IMREAD_UNCHANGED)[first:end]` gives them
    (the same values); None when only a whole decode will do (see the module docstring)."""
    raw = _view(data)
    size = png_size(raw)
    if size is None or not 0 < end < size[0] or not 0 <= first < end:
        return None
    width, _height, depth, colour, method, filtering, interlace = _IHDR.unpack_from(raw, 16)
    if interlace != 0 or method != 0 or filtering != 0 or colour not in _CHANNELS or depth not in (1, 2, 4, 8, 16):
        return None
    row_bytes = (width * depth * _CHANNELS[colour] + 7) // 8 + 1   # a filter byte, then the samples
    before: list[bytes] = []   # the chunks between the header and the image data (a palette, ...)
    idat: list[memoryview] = []
    pos = 8 + 8 + _IHDR.size + 4
    while pos + 8 <= len(raw):
        length, kind = _CHUNK.unpack_from(raw, pos)
        body = raw[pos + 8:pos + 8 + length]
        if len(body) < length or pos + 12 + length > len(raw) \
                or _inflate.crc32(body, _inflate.crc32(kind)) != _CRC.unpack_from(raw, pos + 8 + length)[0]:
            return None   # truncated or damaged: the whole decode says so
        if kind == b"IDAT":
            idat.append(body)
        elif idat or kind == b"IEND":
            break   # the image data ended: nothing after it is needed
        else:
            before.append(bytes(raw[pos:pos + 12 + length]))
        pos += 12 + length
    if not idat:
        return None
    try:
        rows = _inflate.decompressobj().decompress(b"".join(idat), end * row_bytes)
    except _ERRORS:
        return None
    if len(rows) < end * row_bytes:
        return None
    filters = np.frombuffer(rows, np.uint8, end * row_bytes)[::row_bytes]
    if filters.max() > 4:
        return None   # not a PNG filter: the whole decode fails
    if depth == 8 and colour in (0, 2) and not before and filters[first:end].max() <= 1:
        return _unfilter_alone(rows, first, end, width, _CHANNELS[colour], filters[first:end])
    # unfiltered from the last row at or before `first` that stands alone (filter None or Sub: it does not
    # refer to the row above), as the first row of a PNG of its own; row 0 always stands alone
    alone = np.flatnonzero(filters[1:first + 1] <= 1)
    start = int(alone[-1]) + 1 if alone.size else 0
    header = _chunk(b"IHDR", _IHDR.pack(width, end - start, depth, colour, 0, 0, 0))
    png = b"".join((_SIGNATURE, header, *before,
                    *_stored_idat(memoryview(rows)[start * row_bytes:end * row_bytes]), _chunk(b"IEND", b"")))
    image = cv2.imdecode(np.frombuffer(png, np.uint8), cv2.IMREAD_UNCHANGED)
    if image is None or image.shape[0] != end - start:
        return None
    return image[first - start:]
