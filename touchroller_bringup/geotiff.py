"""Tiled, pyramidal GeoTIFF of a tiled map layer, written streamed a tile at a time (`tifffile`).

`write_geotiff(path, view, ...)` writes a `touchroller_perception.tiles.LayerView` (a value with weights
on a tiled grid) over its extent: the full resolution as the first page, overviews at 1/2, 1/4, ... (each
the weighted mean of 2 x 2 cells of the one before) as its SubIFDs, until the image fits one tile; BigTIFF
when the file could pass 4 GB. Two kinds: `intensity` (uint8 grey and an alpha band, 255 mapped, 0 not:
the map's own grey levels, unstretched) and `float` (float32, NaN where nothing is known: e.g. a height
in metres). Placement as GeoTIFF tags: ModelPixelScale (res, res), ModelTiepoint (the upper-left
corner's world x, y) and a GeoKeyDirectory naming a local (engineering) frame in metres, pixel is area;
GDAL reads it as an ENGCRS, QGIS places it. Overviews are built while the page before is written: each
page's tiles are read from the view (level 0) or from the level before it, kept in a temporary
`TileStore` (the cache bounded, the rest on disk), never a whole layer in memory.

`read_window(path, level, row0, col0, rows, cols)` reads a window of one level, only the tiles it needs.
"""
from __future__ import annotations

import contextlib
import math
import shutil
import tempfile
import zlib
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Literal

import numpy as np

from touchroller_perception.files import atomic_path
from touchroller_perception.tiles import (
    LayerView,
    StorageFull,
    TileConfig,
    TileStore,
    levels_for,
    reduce2,
    to_alpha,
    to_grey,
)

Kind = Literal["intensity", "float"]
_GEO_PIXEL_SCALE, _GEO_TIEPOINT, _GEO_KEYS, _GEO_ASCII, _GDAL_NODATA = 33550, 33922, 34735, 34737, 42113


@dataclass
class TiffResult:
    """What `write_geotiff` wrote: the image's size (rows, columns) at full resolution, the number of
    levels (1 + overviews), its upper-left corner in the world (x, y), the resolution (m per pixel), and,
    when asked for, one level kept in memory (value, weight as image rows, row 0 the top) for a view."""

    path: Path
    shape: tuple[int, int]
    levels: int
    top_left: tuple[float, float]
    resolution: float
    bigtiff: bool
    kept_level: int | None = None
    kept: tuple[np.ndarray, np.ndarray] | None = None

    @property
    def origin(self) -> tuple[float, float]:
        """The lower-left corner (nav2's `origin`) of the full-resolution image."""
        return self.top_left[0], self.top_left[1] - self.shape[0] * self.resolution


def level_shape(shape: tuple[int, int], level: int) -> tuple[int, int]:
    return math.ceil(shape[0] / 2 ** level), math.ceil(shape[1] / 2 ** level)


def view_level(shape: tuple[int, int], max_pixels: int) -> int:
    """The first level of a pyramid of `shape` with at most `max_pixels` pixels."""
    level = 0
    while level_shape(shape, level)[0] * level_shape(shape, level)[1] > max_pixels:
        level += 1
    return level


def _geokeys(citation: str) -> tuple[tuple[int, ...], str]:
    """The GeoKeyDirectory (user-defined model: a local frame, pixel is area, metres) and its ASCII params."""
    text = citation.replace("|", "/") + "|"
    keys = [(1024, 0, 1, 32767),           # GTModelTypeGeoKey: user-defined (a local, engineering frame)
            (1025, 0, 1, 1),               # GTRasterTypeGeoKey: pixel is area
            (1026, _GEO_ASCII, len(text), 0),   # GTCitationGeoKey
            (3076, 0, 1, 9001)]            # ProjLinearUnitsGeoKey: metre
    flat = [1, 1, 0, len(keys)] + [v for key in keys for v in key]
    return tuple(flat), text


def write_geotiff(path: str | Path, view: LayerView, kind: Kind = "intensity", frame_id: str = "base",
                  tile: int = 512, keep_level: int | None = None, compression: str | None = None,
                  bigtiff: bool | None = None, scratch: TileConfig | None = None,
                  into: Path | None = None) -> TiffResult:
    """Write `view` over its `extent()` as a tiled pyramidal GeoTIFF (module docstring); `keep_level`: also
    return that level's value and weight (e.g. a view under 16 megapixels for map.png); `compression`:
    None (the default: writing and window reads several times faster, the files about twice the size) or
    "zlib" (deflate, level 1). Written whole
    or not at all (a temporary renamed into place; `into`: written there instead, the caller renames it).
    ValueError when the view holds nothing."""
    import tifffile

    box = view.extent()
    if box is None:
        raise ValueError("the layer holds nothing to write")
    r0, r1, c0, c1 = box
    shape = (r1 - r0, c1 - c0)
    levels = max(levels_for(shape, tile), (keep_level or 0) + 1)
    samples = 2 if kind == "intensity" else 1
    dtype = np.dtype(np.uint8 if kind == "intensity" else np.float32)
    raw = sum(level_shape(shape, k)[0] * level_shape(shape, k)[1] for k in range(levels)) * samples * dtype.itemsize
    big = raw > 3_900_000_000 if bigtiff is None else bigtiff
    res = view.resolution
    top_left = (view.origin[0] + c0 * res, view.origin[1] + r1 * res)
    keys, ascii_params = _geokeys(f"{frame_id} (TouchRoller map frame, metres)")
    geotags = [(_GEO_PIXEL_SCALE, "d", 3, (res, res, 0.0), True),
               (_GEO_TIEPOINT, "d", 6, (0.0, 0.0, 0.0, top_left[0], top_left[1], 0.0), True),
               (_GEO_KEYS, "H", len(keys), keys, True),
               (_GEO_ASCII, "s", 0, ascii_params, True)]
    if kind == "float":
        geotags.append((_GDAL_NODATA, "s", 0, "nan", True))
    options = {"tile": (tile, tile), "photometric": "minisblack", "metadata": None,
               "compression": compression, "compressionargs": {"level": 1} if compression == "zlib" else None,
               **({"extrasamples": ["unassalpha"]} if samples == 2 else {})}
    result = TiffResult(Path(path), shape, levels, top_left, res, big)
    Path(path).parent.mkdir(parents=True, exist_ok=True)
    free = shutil.disk_usage(Path(path).parent).free
    if compression is None and raw + raw // 20 > free:   # checked before writing: nothing half-written
        raise StorageFull(f"{Path(path).name} needs {raw / 2 ** 20:.0f} MB and {Path(path).parent} has "
                          f"{free / 2 ** 20:.0f} MB free")
    with contextlib.ExitStack() as stack:
        folder = stack.enter_context(tempfile.TemporaryDirectory(prefix=".pyramid-", dir=Path(path).parent))
        temporary = Path(path) if into is not None else stack.enter_context(atomic_path(path))
        if into is not None:
            temporary = into
        # the levels being built are read back in the order they were written: a small cache does
        store = TileStore(scratch or TileConfig(tile=tile, folder=folder, cache_bytes=32 * 2 ** 20))
        try:
            with tifffile.TiffWriter(temporary, bigtiff=big) as tif:
                for level in range(levels):
                    rows, cols = level_shape(shape, level)
                    kept = None
                    if level == keep_level:
                        kept = (np.zeros((rows, cols), np.float32), np.zeros((rows, cols), np.float32))
                    tiles = _level_tiles(view, box, store, level, (rows, cols), tile, kind, levels, kept)
                    page_shape = (rows, cols, samples) if samples == 2 else (rows, cols)
                    if level == 0:
                        tif.write(tiles, shape=page_shape, dtype=dtype, subifds=levels - 1, extratags=geotags,
                                  **options)
                    else:
                        tif.write(tiles, shape=page_shape, dtype=dtype, subfiletype=1, **options)
                    if kept is not None:
                        result.kept_level, result.kept = level, kept
                    store.drop_layer(f"v{level}")
                    store.drop_layer(f"w{level}")
        finally:
            store.close()
    return result


def _level_tiles(view: LayerView, box: tuple[int, int, int, int], store: TileStore, level: int,
                 shape: tuple[int, int], tile: int, kind: Kind, levels: int,
                 kept: tuple[np.ndarray, np.ndarray] | None) -> Iterator[np.ndarray]:
    """The file tiles of one level, row by row; each also reduced into the next level's store layers."""
    r0, r1, c0, c1 = box
    rows, cols = shape
    half = tile // 2
    if level + 1 < levels:
        store.add_layer(f"v{level + 1}", np.float32)
        store.add_layer(f"w{level + 1}", np.float32)
    for ti in range(math.ceil(rows / tile)):
        for tj in range(math.ceil(cols / tile)):
            if level == 0:   # image rows ti*T.. from the top: absolute rows r1 - (ti + 1) T .. r1 - ti T
                a1 = r1 - ti * tile
                a0 = a1 - tile
                b0 = c0 + tj * tile
                value, weight = view.read(a0, a1, b0, b0 + tile)
                value, weight = value[::-1], weight[::-1].copy()
                # outside the extent (below its bottom, right of its right side): nothing
                if a0 < r0:
                    weight[tile - (r0 - a0):] = 0
                if b0 + tile > c1:
                    weight[:, tile - (b0 + tile - c1):] = 0
            else:
                value = store.read(f"v{level}", ti * tile, (ti + 1) * tile, tj * tile, (tj + 1) * tile)
                weight = store.read(f"w{level}", ti * tile, (ti + 1) * tile, tj * tile, (tj + 1) * tile)
            if level + 1 < levels and weight.any():
                small_v, small_w = reduce2(value, weight)
                store.write(f"v{level + 1}", small_v, ti * half, tj * half)
                store.write(f"w{level + 1}", small_w, ti * half, tj * half)
            if kept is not None:
                h, w = min(tile, rows - ti * tile), min(tile, cols - tj * tile)
                kept[0][ti * tile:ti * tile + h, tj * tile:tj * tile + w] = value[:h, :w]
                kept[1][ti * tile:ti * tile + h, tj * tile:tj * tile + w] = weight[:h, :w]
            yield _file_tile(value, weight, kind, view.mapped_weight)


def _file_tile(value: np.ndarray, weight: np.ndarray, kind: Kind, mapped_weight: float) -> np.ndarray:
    if kind == "intensity":
        return np.stack([to_grey(value, flip=False), to_alpha(weight, mapped_weight, flip=False)], axis=-1)
    return np.where(weight > mapped_weight, value, np.float32(np.nan)).astype(np.float32)


class PyramidReader:
    """A tiled (pyramidal) TIFF kept open for window reads: `window(level, row0, col0, rows, cols)` decodes
    only the tiles the window touches. A context manager (closes the file)."""

    def __init__(self, path: str | Path) -> None:
        import tifffile

        self.path = Path(path)
        self._tif = tifffile.TiffFile(path)
        self.pages = [level.keyframe for level in self._tif.series[0].levels]

    def __enter__(self) -> PyramidReader:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def close(self) -> None:
        self._tif.close()

    @staticmethod
    def _decode(page: Any, data: bytes, index: int) -> np.ndarray:
        """One tile: deflate (or none) without a predictor decoded here (five times tifffile's generic path),
        anything else by tifffile."""
        shape = (page.tilelength, page.tilewidth, *page.shape[2:])
        if int(page.predictor) == 1 and int(page.compression) in (1, 8, 32946):
            raw = data if int(page.compression) == 1 else zlib.decompress(data)
            return np.frombuffer(raw, page.dtype).reshape(shape)
        segment = page.decode(data, index)[0]
        assert segment is not None
        return segment.reshape(shape)

    def window(self, level: int, row0: int, col0: int, rows: int, cols: int) -> np.ndarray:
        """Rows [row0, row0 + rows) x columns [col0, ...) of one level (0: full resolution), clipped to it."""
        if not 0 <= level < len(self.pages):
            raise ValueError(f"{self.path} has levels 0..{len(self.pages) - 1}, not {level}")
        page = self.pages[level]
        height, width = page.imagelength, page.imagewidth
        th, tw = page.tilelength, page.tilewidth
        if not th or not tw:
            raise ValueError(f"{self.path} is not tiled")
        row1, col1 = min(row0 + rows, height), min(col0 + cols, width)
        row0, col0 = max(row0, 0), max(col0, 0)
        out = np.zeros((max(row1 - row0, 0), max(col1 - col0, 0), *page.shape[2:]), page.dtype)
        across = math.ceil(width / tw)
        handle = self._tif.filehandle
        for ti in range(row0 // th, (row1 - 1) // th + 1) if out.size else ():
            for tj in range(col0 // tw, (col1 - 1) // tw + 1):
                index = ti * across + tj
                handle.seek(page.dataoffsets[index])
                segment = self._decode(page, handle.read(page.databytecounts[index]), index)
                y0, y1 = max(row0, ti * th), min(row1, (ti + 1) * th)
                x0, x1 = max(col0, tj * tw), min(col1, (tj + 1) * tw)
                out[y0 - row0:y1 - row0, x0 - col0:x1 - col0] = segment[y0 - ti * th:y1 - ti * th,
                                                                        x0 - tj * tw:x1 - tj * tw]
        return out


def read_window(path: str | Path, level: int, row0: int, col0: int, rows: int, cols: int) -> np.ndarray:
    """One window of one level of a tiled TIFF (`PyramidReader.window`, the file opened for it)."""
    with PyramidReader(path) as reader:
        return reader.window(level, row0, col0, rows, cols)
