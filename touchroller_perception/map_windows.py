"""A world map read a window at a time, as its inspection needs it (docs/inspection.md, docs/world_map.md).

`MapWindows(world)` reads a `WorldMapper`'s map from its tile store: the cells each store tile has mapped
(`mapped_tile`, to find what is new since an earlier look), the map's extent, and any window of it as the
inspection takes it (`window`: float32 image rows, row 0 the largest y, NaN where nothing is known): the
height layer (metres) where the map has one (`layer` "height"), else the map's grey levels as `map_image`
rounds them ("intensity"). The window's cells are the mapped ones of the intensity, as `map_image`'s
alpha has them. Memory is the window's, never the whole map at full resolution, however large it grows.

`lock`: held around each read (the perception node maps frames into the same store from another thread).
"""
from __future__ import annotations

import contextlib
from typing import TYPE_CHECKING

import numpy as np

from touchroller_perception.tiles import to_grey

if TYPE_CHECKING:
    from touchroller_perception.world_map import WorldMapper

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
            self.layer = "height" if world.height_view() is not None else "intensity"
            self.fixed: Box | None = view.extent() if world.canvas.fixed else None

    def mapped_tile(self, ix: int, iy: int) -> np.ndarray | None:
        """The mapped cells (bool, rows growing with y) of store tile (ix, iy); None: no such tile."""
        with self.lock:
            if not self.world.canvas.store.has("weight", ix, iy):
                return None
            t = self.tile
            _, weight = self.world.view().read(iy * t, (iy + 1) * t, ix * t, (ix + 1) * t)
        return weight > self.mapped_weight

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
            value, weight = self.world.view().read(r0, r1, c0, c1)
            mapped = weight > self.mapped_weight
            if self.layer == "height":
                height_view = self.world.height_view()
                assert height_view is not None
                value, known = height_view.read(r0, r1, c0, c1)
                mapped &= known > height_view.mapped_weight
                values = np.where(mapped, value, np.float32(np.nan)).astype(np.float32, copy=False)
            else:
                grey = to_grey(value, flip=False)   # the grey levels map_image has
                values = np.where(mapped, grey.astype(np.float32), np.float32(np.nan))
        res = self.resolution
        return np.ascontiguousarray(values[::-1]), (self.anchor[0] + c0 * res, self.anchor[1] + r0 * res)
