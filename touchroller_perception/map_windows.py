"""A world map read a window at a time, as its inspection needs it (docs/inspection.md, docs/world_map.md).

`MapWindows(world)` reads a `WorldMapper`'s map from its tile store: the cells each store tile has mapped
(`mapped_tile`, to find what is new since an earlier look), the map's extent, and any window of it as the
inspection takes it (`window`: float32 image rows, row 0 the largest y, NaN where nothing is known): the
height layer (metres) where the map has one (`layer` "height"), else the map's grey levels as `map_image`
rounds them ("intensity"). The window's cells are the mapped ones of the intensity, as `map_image`'s
alpha has them. Memory is the window's, never the whole map at full resolution, however large it grows.

The height is read live, during a pass too (`world_height`): where a finished pass has a height, the
finished passes' (levelled); where only the pass being rolled has one, that pass's own sums, not yet
levelled (its plane holds the press depth and the surface's tilt, which the inspection's local surface
takes out), moved by the median of its difference with the finished passes where both cover the window
(at least `min_overlap` cells), so no step of the press depth lies along the seam. So the findings of a
pass come while it is rolled, from its height, not from its grey levels; the finished map (the pass
levelled) is inspected again whole.

Frames placed provisionally (`WorldMapConfig.provisional`: waiting for the latency estimate, placed with the
fallback latency on layers of their own) are read with the map's, their sums added to its own (intensity)
and to the pass being rolled (height); `replacements` counts the times they were emptied, their frames
placed for good (a reader then looks again at what it saw of them).

`lock`: held around each read (the perception node maps frames into the same store from another thread).
"""
from __future__ import annotations

import contextlib
from typing import TYPE_CHECKING

import numpy as np

from touchroller_perception.tiles import to_grey
from touchroller_perception.world_canvas import _value
from touchroller_perception.world_height import DONE, DONE_W, PASS, PASS_W
from touchroller_perception.world_map import PROVISIONAL_LAYERS

if TYPE_CHECKING:
    from touchroller_perception.world_map import WorldMapper

LIVE_BAND, LIVE_FLAT, LIVE_WEIGHT, LIVE_HEIGHT, LIVE_HEIGHT_W = PROVISIONAL_LAYERS

Box = tuple[int, int, int, int]   # (row0, row1, column0, column1) of the store's absolute cells, rows growing with y


class MapWindows:
    """Windows of a world map for inspection; see the module docstring."""

    def __init__(self, world: WorldMapper, lock: contextlib.AbstractContextManager | None = None) -> None:
        self.world = world
        self.lock = lock if lock is not None else contextlib.nullcontext()
        with self.lock:
            view = world.view()
            self.tile: int = view.tile
            self.resolution: float = float(view.resolution)
            self.anchor: tuple[float, float] = (float(view.origin[0]), float(view.origin[1]))
            self.mapped_weight: float = view.mapped_weight
            source = world.height_source
            self.min_height_weight: float = source.config.min_weight if source is not None else 0.0
            self.min_overlap: int = source.config.min_overlap if source is not None else 0
            self.fixed: Box | None = view.extent() if world.canvas.fixed else None

    @property
    def layer(self) -> str:
        """"height" once a finished pass or the pass being rolled has a height, else "intensity"."""
        with self.lock:
            return self._layer()

    def _layer(self) -> str:
        world = self.world
        if world.height_source is None:
            return "intensity"
        store = world.canvas.store
        rolling = bool(store.tiles(PASS_W)) or (world.config.provisional and bool(store.tiles(LIVE_HEIGHT_W)))
        return "height" if world.height_view() is not None or rolling else "intensity"

    @property
    def replacements(self) -> int:
        """How many times the world's provisional frames were placed for good (`WorldMapper.replacements`)."""
        return int(getattr(self.world, "replacements", 0))

    def mapped_tile(self, ix: int, iy: int) -> np.ndarray | None:
        """The mapped cells (bool, rows growing with y) of store tile (ix, iy); None: no such tile."""
        with self.lock:
            store = self.world.canvas.store
            if not store.has("weight", ix, iy) and not self._provisional_in(ix, ix + 1, iy, iy + 1):
                return None
            t = self.tile
            _, weight = self._intensity(iy * t, (iy + 1) * t, ix * t, (ix + 1) * t)
        return weight > self.mapped_weight

    def _provisional_in(self, ix0: int, ix1: int, iy0: int, iy1: int) -> bool:
        """Whether tiles [ix0, ix1) x [iy0, iy1) hold a provisionally placed frame."""
        if not self.world.config.provisional:
            return False
        store = self.world.canvas.store
        return any(store.has(LIVE_WEIGHT, ix, iy) for ix in range(ix0, ix1) for iy in range(iy0, iy1))

    def _provisional_box(self, r0: int, r1: int, c0: int, c1: int) -> bool:
        t = self.tile
        return self._provisional_in(c0 // t, (c1 - 1) // t + 1, r0 // t, (r1 - 1) // t + 1)

    def _intensity(self, r0: int, r1: int, c0: int, c1: int) -> tuple[np.ndarray, np.ndarray]:
        """(grey value, weight) over the box: the map's, with the provisional frames' sums added."""
        view = self.world.view()
        if not self._provisional_box(r0, r1, c0, c1):
            return view.read(r0, r1, c0, c1)
        store = self.world.canvas.store
        band, flat, weight = (store.read(name, r0, r1, c0, c1) + store.read(live, r0, r1, c0, c1)
                              for name, live in (("band", LIVE_BAND), ("flat", LIVE_FLAT), ("weight", LIVE_WEIGHT)))
        return _value(band, flat, weight, float(getattr(view, "level", 1.0)))

    def extent(self) -> Box | None:
        """The cells a file of the map holds (a fixed map's bounds, else around what was mapped): read over
        every tile's weights, once."""
        with self.lock:
            return self.world.view().extent()

    def window(self, box: Box) -> tuple[np.ndarray, tuple[float, float]]:
        """(values as the inspection takes them, float32 image rows with NaN where unknown; the world (x, y)
        of the window's lower-left corner) over `box`."""
        r0, r1, c0, c1 = box
        with self.lock:
            value, weight = self._intensity(r0, r1, c0, c1)
            mapped = weight > self.mapped_weight
            if self._layer() == "height":
                height = self._height(r0, r1, c0, c1)
                values = np.where(mapped, height, np.float32(np.nan)).astype(np.float32, copy=False)
            else:
                grey = to_grey(value, flip=False)   # the grey levels map_image has
                values = np.where(mapped, grey.astype(np.float32), np.float32(np.nan))
        res = self.resolution
        return np.ascontiguousarray(values[::-1]), (self.anchor[0] + c0 * res, self.anchor[1] + r0 * res)

    def _height(self, r0: int, r1: int, c0: int, c1: int) -> np.ndarray:
        """float32 metres over the box (rows growing with y), NaN where no pass has a height: the finished
        passes' where they have one, else the pass being rolled moved onto them (the module docstring)."""
        store, least = self.world.canvas.store, np.float32(self.min_height_weight)
        done, done_w = store.read(DONE, r0, r1, c0, c1), store.read(DONE_W, r0, r1, c0, c1)
        theirs = done_w >= least
        out = np.full(done.shape, np.nan, np.float32)
        np.divide(done, done_w, out=out, where=theirs)
        rolled_w, rolled_sum = store.read(PASS_W, r0, r1, c0, c1), store.read(PASS, r0, r1, c0, c1)
        if self._provisional_box(r0, r1, c0, c1):   # the frames placed provisionally: the pass's too
            rolled_w += store.read(LIVE_HEIGHT_W, r0, r1, c0, c1)
            rolled_sum += store.read(LIVE_HEIGHT, r0, r1, c0, c1)
        mine = rolled_w >= least
        only = mine & ~theirs
        if only.any():
            rolled = np.divide(rolled_sum, rolled_w, out=np.zeros_like(rolled_w), where=mine)
            both = mine & theirs
            offset = (float(np.median(out[both] - rolled[both])) if int(np.count_nonzero(both)) >= self.min_overlap
                      else 0.0)
            out[only] = rolled[only] + np.float32(offset)
        return out
