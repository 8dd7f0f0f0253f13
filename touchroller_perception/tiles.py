"""Tiled layers: a map's planes (named layers, each with its own dtype) kept as fixed square tiles created
when first touched, a bounded cache of them in memory (least recently used go first), the rest spilled to
files in a folder (the output folder, or a temporary one). Nothing is dropped for size: the bound is the
disk, checked before a new tile is made (`StorageFull`, the tiles so far kept).

Cells are addressed by (row, column) on an unbounded integer grid (negative too): tile (ix, iy) of a
layer holds rows [iy T, (iy + 1) T) and columns [ix T, (ix + 1) T), T = `TileConfig.tile`.

Besides the layers themselves: `touched()` (the tiles written to since the last call, for live views)
and the pyramid of a value layer with its weights (`LayerView`, `pyramid_tile`, `render_tile`): level k
averages 2^k x 2^k cells (weighted by their weights), tile (level, ix, iy) covers level-0 cells
[iy T 2^k, (iy + 1) T 2^k) x [ix T 2^k, (ix + 1) T 2^k). No rclpy here.
"""
from __future__ import annotations

import math
import shutil
import tempfile
from collections import OrderedDict
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Protocol

import cv2
import numpy as np

Key = tuple[str, int, int]   # (layer, ix, iy)


class StorageFull(OSError):
    """A new tile would leave the spill folder's disk with less than `TileConfig.min_free_bytes`."""


@dataclass(frozen=True)
class TileConfig:
    """How a `TileStore` keeps its tiles.

    tile: the side of a tile, cells (a multiple of 16: GeoTIFF tiles are written at the same size).
    cache_bytes: the most bytes of tiles held in memory; the least recently used beyond it go to disk.
    folder: where tiles are spilled: a temporary folder made in it (None: in the system's temporary folder),
      removed with its tiles on `close()`.
    min_free_bytes: a new tile is refused (`StorageFull`) when its bytes, and those of the tiles in memory
      that were never written out, would leave less than this free on the folder's disk.
    """

    tile: int = 512
    cache_bytes: int = 256 * 2 ** 20
    folder: str | None = None
    min_free_bytes: int = 256 * 2 ** 20

    def __post_init__(self) -> None:
        if self.tile < 16 or self.tile % 16:
            raise ValueError(f"tile must be a multiple of 16, at least 16, got {self.tile}")
        if self.cache_bytes < 0 or self.min_free_bytes < 0:
            raise ValueError("cache_bytes and min_free_bytes must be >= 0")


@dataclass(frozen=True)
class Layer:
    name: str
    dtype: np.dtype
    fill: float = 0.0


class TileStore:
    """Named layers of fixed tiles; see the module docstring."""

    def __init__(self, config: TileConfig | None = None) -> None:
        self.config = config = config or TileConfig()
        self.tile = config.tile
        self.layers: dict[str, Layer] = {}
        self._memory: OrderedDict[Key, np.ndarray] = OrderedDict()   # least recently used first
        self._dirty: set[Key] = set()        # in memory and changed since last written to disk
        self._on_disk: set[Key] = set()
        self._bytes = 0
        self._unwritten = 0                  # bytes in memory never written to disk yet
        self._new: set[Key] = set()          # in memory, never written to disk
        self._touched: set[tuple[int, int]] = set()
        self._temporary: tempfile.TemporaryDirectory[str] | None = None
        self._folder: Path | None = None
        self.spilled = 0                     # tiles written out to disk so far (for benches)
        self.loaded = 0                      # tiles read back from disk

    # -- layers -----------------------------------------------------------------------------------------
    def add_layer(self, name: str, dtype: type | np.dtype | str = np.float32, fill: float = 0.0) -> None:
        """A new layer (cells not yet touched read as `fill`); an existing one of the same dtype is kept."""
        layer = Layer(name, np.dtype(dtype), float(fill))
        known = self.layers.get(name)
        if known is not None and known.dtype != layer.dtype:
            raise ValueError(f"layer {name!r} exists as {known.dtype}, not {layer.dtype}")
        if "/" in name or not name:
            raise ValueError(f"a layer name is a non-empty word without '/', got {name!r}")
        self.layers.setdefault(name, layer)

    def drop_layer(self, name: str) -> None:
        """Forget a layer and its tiles (in memory and on disk)."""
        for key in [k for k in self._memory if k[0] == name]:
            self._forget_memory(key)
        for key in [k for k in self._on_disk if k[0] == name]:
            self._on_disk.discard(key)
            self._path(key).unlink(missing_ok=True)
        self.layers.pop(name, None)

    def tiles(self, name: str) -> set[tuple[int, int]]:
        """(ix, iy) of every tile of a layer that exists (in memory or on disk)."""
        return {(k[1], k[2]) for k in (*self._memory, *self._on_disk) if k[0] == name}

    def has(self, name: str, ix: int, iy: int) -> bool:
        key = (name, ix, iy)
        return key in self._memory or key in self._on_disk

    def resident(self) -> int:
        """How many tiles are in memory now."""
        return len(self._memory)

    @property
    def resident_bytes(self) -> int:
        return self._bytes

    # -- tiles ------------------------------------------------------------------------------------------
    def get(self, name: str, ix: int, iy: int, create: bool = False, write: bool = False) -> np.ndarray | None:
        """The tile (a T x T array, in memory until evicted); None when it does not exist and not `create`.
        `write`: the caller changes it (written out when evicted; counted by `touched`)."""
        key = (name, ix, iy)
        tile = self._memory.get(key)
        if tile is not None:
            self._memory.move_to_end(key)
        elif key in self._on_disk:
            layer = self.layers[name]
            tile = np.fromfile(self._path(key), layer.dtype).reshape(self.tile, self.tile)
            self.loaded += 1
            self._hold(key, tile)
        elif create:
            self.reserve([key])
            layer = self.layers[name]
            shape = (self.tile, self.tile)   # zeros: calloc'd, its pages made only as bands land
            tile = np.zeros(shape, layer.dtype) if layer.fill == 0 else np.full(shape, layer.fill, layer.dtype)
            self._hold(key, tile)
            self._new.add(key)
            self._unwritten += tile.nbytes
            write = True
        else:
            return None
        if write:
            self._dirty.add(key)
            self._touched.add((ix, iy))
        self._evict()
        return tile

    def reserve(self, keys: list[Key]) -> None:
        """Raise `StorageFull` unless the tiles `keys` that do not exist yet can be made."""
        memory, disk = self._memory, self._on_disk
        new = [k for k in keys if k not in memory and k not in disk]
        if not new:
            return
        need = self._unwritten + sum(self.tile * self.tile * self.layers[k[0]].dtype.itemsize for k in new)
        free = shutil.disk_usage(self.folder).free
        if free - need < self.config.min_free_bytes:
            raise StorageFull(f"the map's tiles need {need / 2 ** 20:.0f} MB more and {self.folder} has "
                              f"{free / 2 ** 20:.0f} MB free (at least {self.config.min_free_bytes / 2 ** 20:.0f} "
                              "MB are kept free)")

    def touched(self) -> set[tuple[int, int]]:
        """(ix, iy) of the tiles written to (any layer) since the last call."""
        out, self._touched = self._touched, set()
        return out

    def note_touched(self, tiles: set[tuple[int, int]]) -> None:
        """Count tiles (ix, iy) as written to (a layer dropped over them): the next `touched` has them."""
        self._touched |= tiles

    @property
    def folder(self) -> Path:
        """The spill folder: a temporary folder in `config.folder` (or the system's), made when first needed."""
        if self._folder is None:
            parent = None
            if self.config.folder is not None:
                Path(self.config.folder).mkdir(parents=True, exist_ok=True)
                parent = self.config.folder
            self._temporary = tempfile.TemporaryDirectory(prefix=".touchroller-tiles-", dir=parent)
            self._folder = Path(self._temporary.name)
        return self._folder

    def close(self) -> None:
        """Forget every tile and remove the spilled files (a temporary folder with them)."""
        for name in list(self.layers):
            self.drop_layer(name)
        if self._temporary is not None:
            self._temporary.cleanup()
            self._temporary, self._folder = None, None

    def __del__(self) -> None:   # best effort: spilled files do not outlive the store
        try:
            self.close()
        except Exception:  # noqa: BLE001
            pass

    def _path(self, key: Key) -> Path:
        name, ix, iy = key
        return self.folder / f"{name}_{ix}_{iy}.tile"

    def _hold(self, key: Key, tile: np.ndarray) -> None:
        self._memory[key] = tile
        self._bytes += tile.nbytes

    def _forget_memory(self, key: Key) -> None:
        tile = self._memory.pop(key)
        self._bytes -= tile.nbytes
        self._dirty.discard(key)
        if key in self._new:
            self._new.discard(key)
            self._unwritten -= tile.nbytes

    def _evict(self) -> None:
        while self._bytes > self.config.cache_bytes and len(self._memory) > 1:
            key, tile = next(iter(self._memory.items()))
            if key in self._dirty:
                tile.tofile(self._path(key))
                self._on_disk.add(key)
                self.spilled += 1
            self._forget_memory(key)

    # -- windows ----------------------------------------------------------------------------------------
    def _spans(self, r0: int, r1: int, c0: int, c1: int) -> Iterator[tuple[int, int, slice, slice, slice, slice]]:
        """(ix, iy, rows in the tile, columns in the tile, rows in the window, columns in the window)."""
        t = self.tile
        for iy in range(r0 // t, (r1 - 1) // t + 1):
            a0, a1 = max(r0, iy * t), min(r1, (iy + 1) * t)
            for ix in range(c0 // t, (c1 - 1) // t + 1):
                b0, b1 = max(c0, ix * t), min(c1, (ix + 1) * t)
                yield (ix, iy, slice(a0 - iy * t, a1 - iy * t), slice(b0 - ix * t, b1 - ix * t),
                       slice(a0 - r0, a1 - r0), slice(b0 - c0, b1 - c0))

    def read(self, name: str, r0: int, r1: int, c0: int, c1: int) -> np.ndarray:
        """Rows [r0, r1) x columns [c0, c1) of a layer (a copy; `fill` where no tile exists)."""
        layer = self.layers[name]
        out = np.full((max(r1 - r0, 0), max(c1 - c0, 0)), layer.fill, layer.dtype)
        if out.size:
            for ix, iy, tr, tc, wr, wc in self._spans(r0, r1, c0, c1):
                tile = self.get(name, ix, iy)
                if tile is not None:
                    out[wr, wc] = tile[tr, tc]
        return out

    def write(self, name: str, data: np.ndarray, r0: int, c0: int) -> None:
        """Set the cells of `data` (rows from r0, columns from c0), tiles made as needed."""
        h, w = data.shape
        if not h or not w:
            return
        spans = list(self._spans(r0, r0 + h, c0, c0 + w))
        self.reserve([(name, s[0], s[1]) for s in spans])
        for ix, iy, tr, tc, wr, wc in spans:
            tile = self.get(name, ix, iy, create=True, write=True)
            assert tile is not None
            tile[tr, tc] = data[wr, wc]

    def add(self, name: str, data: np.ndarray, r0: int, c0: int, track_max: bool = False,
            reserved: bool = False) -> float:
        """Add `data` (float32) to the cells from (r0, c0), tiles made as needed; `track_max`: returns the
        largest of the sums where it was added (else 0); `reserved`: the caller checked the room (`reserve`)."""
        h, w = data.shape
        if not h or not w:
            return 0.0
        spans = self.windows(r0, r0 + h, c0, c0 + w)
        if not reserved:
            self.reserve([(name, s[0], s[1]) for s in spans])
        return self.add_windows(name, data, spans, track_max)

    def windows(self, r0: int, r1: int, c0: int, c1: int) -> list[tuple[int, int, slice, slice, slice, slice]]:
        """The tiles rows [r0, r1) x columns [c0, c1) fall in, each as (ix, iy, rows in the tile, columns in
        the tile, rows in the window, columns in the window): for `add_windows`, computed once for the
        layers a window adds to."""
        if r1 <= r0 or c1 <= c0:
            return []
        return list(self._spans(r0, r1, c0, c1))

    def add_windows(self, name: str, data: np.ndarray, windows: list[tuple[int, int, slice, slice, slice, slice]],
                    track_max: bool = False) -> float:
        """`add` of `data` over `windows` (`windows()` of its rows and columns; the room reserved)."""
        largest = 0.0
        for ix, iy, tr, tc, wr, wc in windows:
            tile = self.get(name, ix, iy, create=True, write=True)
            assert tile is not None
            view = tile[tr, tc]
            cv2.add(view, data[wr, wc], dst=view)   # cv2.add: about twice numpy's speed on these views
            if track_max:
                largest = max(largest, float(cv2.minMaxLoc(view)[1]))
        return largest

    def spans(self, r0: int, r1: int, c0: int, c1: int) -> list[tuple[int, int]]:
        """(ix, iy) of the tiles rows [r0, r1) x columns [c0, c1) fall in."""
        if r1 <= r0 or c1 <= c0:
            return []
        return [(s[0], s[1]) for s in self._spans(r0, r1, c0, c1)]


# ------------------------------------------------------------------------------------------------ pyramid
class LayerView(Protocol):
    """A value with weights on a tiled grid, as files and live views read it: `read(r0, r1, c0, c1)` ->
    (value float32, weight float32; weight 0 where nothing is known), cells in the grid's own (row,
    column), rows growing with y. `tile`: the grid's tile side; `resolution` m per cell; `origin` the
    world (x, y) of cell (0, 0)'s lower-left corner; `extent()` the (row0, row1, column0, column1) of
    what there is (None: nothing), `mapped_weight` the weight above which a cell counts as mapped."""

    tile: int
    resolution: float
    origin: tuple[float, float]
    mapped_weight: float

    def read(self, r0: int, r1: int, c0: int, c1: int) -> tuple[np.ndarray, np.ndarray]: ...

    def extent(self) -> tuple[int, int, int, int] | None: ...


def reduce2(value: np.ndarray, weight: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """One pyramid step: 2 x 2 blocks (an odd side padded with weight 0) to their weighted mean value and
    their mean weight."""
    h, w = value.shape
    if h % 2 or w % 2:
        value = np.pad(value, ((0, h % 2), (0, w % 2)))
        weight = np.pad(weight, ((0, h % 2), (0, w % 2)))
    size = (value.shape[1] // 2, value.shape[0] // 2)
    weight = weight.astype(np.float32, copy=False)
    # INTER_AREA at exactly half the size: the mean of each 2 x 2 block (OpenCV's fast path)
    mean_weight = cv2.resize(weight, size, interpolation=cv2.INTER_AREA)
    mean_weighted = cv2.resize(cv2.multiply(value.astype(np.float32, copy=False), weight), size,
                               interpolation=cv2.INTER_AREA)
    mean = np.divide(mean_weighted, mean_weight, out=np.zeros_like(mean_weight), where=mean_weight > 0)
    return mean, mean_weight


def pyramid_tile(view: LayerView, level: int, ix: int, iy: int) -> tuple[np.ndarray, np.ndarray]:
    """(value, weight) of tile (level, ix, iy) of a view's pyramid: T x T cells of 2^level x 2^level grid
    cells each (rows growing with y), read a tile of level 0 at a time."""
    t = view.tile
    if level <= 0:
        return view.read(iy * t, (iy + 1) * t, ix * t, (ix + 1) * t)
    value, weight = np.zeros((2, t, t), np.float32)
    half = t // 2
    for dy in (0, 1):
        for dx in (0, 1):
            child_v, child_w = pyramid_tile(view, level - 1, 2 * ix + dx, 2 * iy + dy)
            if child_w.any():
                value[dy * half:(dy + 1) * half, dx * half:(dx + 1) * half], \
                    weight[dy * half:(dy + 1) * half, dx * half:(dx + 1) * half] = reduce2(child_v, child_w)
    return value, weight


def render_tile(view: LayerView, level: int, ix: int, iy: int, low: float = 0.0,
                high: float = 255.0) -> tuple[np.ndarray, np.ndarray]:
    """Tile (level, ix, iy) as images: (grey uint8, alpha uint8: 255 mapped, 0 not), row 0 the top
    (largest y) as in an image; grey = 255 (value - low) / (high - low), clipped (0..255 by default: the
    map's own grey levels)."""
    value, weight = pyramid_tile(view, level, ix, iy)
    return to_grey(value, low, high), to_alpha(weight, view.mapped_weight)


def to_grey(value: np.ndarray, low: float = 0.0, high: float = 255.0, flip: bool = True) -> np.ndarray:
    """Value rows (growing with y) to uint8 image rows (row 0 the top): 255 (value - low) / (high - low),
    rounded, clipped."""
    scale = 255.0 / (high - low) if high > low else 1.0
    image = value if (low == 0.0 and scale == 1.0) else (value - np.float32(low)) * np.float32(scale)
    image = np.add(image, np.float32(0.5))
    np.clip(image, 0, 255, out=image)
    grey = image.astype(np.uint8)
    return grey[::-1].copy() if flip else grey


def to_alpha(weight: np.ndarray, mapped_weight: float, flip: bool = True) -> np.ndarray:
    alpha = (weight > mapped_weight).view(np.uint8) * np.uint8(255)
    return alpha[::-1].copy() if flip else alpha


def levels_for(shape: tuple[int, int], tile: int) -> int:
    """How many levels a pyramid of an image of `shape` has: halved until it fits one tile."""
    rows, cols = shape
    levels = 1
    while max(rows, cols) > tile:
        rows, cols = math.ceil(rows / 2), math.ceil(cols / 2)
        levels += 1
    return levels
