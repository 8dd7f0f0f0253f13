"""The world map's live views kept up to date from the tiles bands touched, not rebuilt from the whole map.

A `LiveMapView` holds what the perception node publishes while a map grows: the map's view at the level of
detail that fits the budget (`map_tiles.fitting_level`: level k of the tile store's pyramid, each level
cell the weighted mean of 2^k x 2^k cells), the height map at the same level when there is one, and the
digests of the RViz tiles sent (`map_tiles.MapTile`, `map_tiles.TileUpdate`). Each `update(mapper,
touched)` is given the level-0 tiles of the store that bands changed since the last one
(`WorldMapper.touched_tiles()`) and re-renders only those: a level-0 tile is read once, reduced k times
(`tiles.reduce2`, as the pyramid reduces it) and pasted into the level image, and only the view tiles it
overlaps are cut and compared again. A publication then costs in proportion to the area new frames
reached, not to the area mapped (the view message itself is the view, within its budget). The result is
the one built from scratch (`map_tiles.world_map_raster` + `map_view` + `tiles_of`).

The view is built again from every tile only when it must be: the first update, a change of level (the
map outgrew the budget), the map moved (its anchor: `WorldMapper.finalise` applies the final latency
estimate), a height map appearing, a level whose cell spans more than a store tile, or after `reset()`;
`resend()` (a new subscriber) cuts every tile of the current view again without re-rendering it. The
map's extent is kept the same way, from each touched tile's mapped rows and columns. Pure arrays, no
rclpy: the messages are `touchroller_bringup.map_markers`'.
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from touchroller_perception.map_tiles import (
    MapTile,
    MapView,
    TileConfig,
    TileUpdate,
    digest,
    fitting_level,
    grid_offset,
    surface_z,
    tiles_of,
)
from touchroller_perception.tiles import LayerView, pyramid_tile, reduce2, to_alpha, to_grey
from touchroller_perception.world_canvas import MAPPED_WEIGHT

if TYPE_CHECKING:
    from touchroller_perception.world_map import WorldMapper

Box = tuple[int, int, int, int]   # (row0, row1, column0, column1), absolute cells, rows growing with y


@dataclass(frozen=True)
class LiveUpdate:
    """One publication's worth: the view (`MapView`, image rows, row 0 the top), the RViz tiles changed
    since the last update (`TileUpdate`), and the height map over the view's cells (float32 metres, image
    rows, NaN where unknown; None without a height map)."""

    view: MapView
    tiles: TileUpdate
    height: np.ndarray | None


def reduced_tile(view: LayerView, level: int, ix: int, iy: int) -> tuple[np.ndarray, np.ndarray]:
    """(value, weight) of level-0 tile (ix, iy) of `view` reduced `level` times (rows growing with y): the
    (T / 2^level)^2 cells of pyramid level `level` it covers, the numbers `tiles.pyramid_tile` gives there.
    Needs 2^level <= T."""
    t = view.tile
    value, weight = view.read(iy * t, (iy + 1) * t, ix * t, (ix + 1) * t)
    for _ in range(level):
        if not weight.any():   # nothing there: the pyramid leaves it zero
            side = value.shape[0] // 2
            return np.zeros((side, side), np.float32), np.zeros((side, side), np.float32)
        value, weight = reduce2(value, weight)
    return value, weight


class _Planes:
    """Named planes of one level over a box of level cells (absolute, rows growing with y)."""

    def __init__(self, box: Box, kinds: dict[str, tuple[type, float]]) -> None:
        self.box, self.kinds = box, kinds
        shape = (box[1] - box[0], box[3] - box[2])
        self.planes: dict[str, np.ndarray] = {name: np.full(shape, fill, dtype)
                                              for name, (dtype, fill) in kinds.items()}

    def grow(self, box: Box) -> None:
        """Cover `box` (which holds the present one): new planes, the old content copied into place."""
        if box == self.box:
            return
        old, (o0, o1, p0, p1) = self.planes, self.box
        self.__init__(box, self.kinds)   # type: ignore[misc]
        for name, plane in old.items():
            self.planes[name][o0 - box[0]:o1 - box[0], p0 - box[2]:p1 - box[2]] = plane

    def paste(self, r0: int, c0: int, parts: dict[str, np.ndarray]) -> Box | None:
        """Write `parts` (their cell (0, 0) at level cell (r0, c0)) clipped to the box; the box written."""
        h, w = next(iter(parts.values())).shape
        b = self.box
        a0, a1, k0, k1 = max(r0, b[0]), min(r0 + h, b[1]), max(c0, b[2]), min(c0 + w, b[3])
        if a1 <= a0 or k1 <= k0:
            return None
        for name, part in parts.items():
            self.planes[name][a0 - b[0]:a1 - b[0], k0 - b[2]:k1 - b[2]] = part[a0 - r0:a1 - r0, k0 - c0:k1 - c0]
        return a0, a1, k0, k1


def _contains(outer: Box, inner: Box) -> bool:
    return outer[0] <= inner[0] and outer[1] >= inner[1] and outer[2] <= inner[2] and outer[3] >= inner[3]


class LiveMapView:
    """The live views of one world map, updated from the tiles bands touched (see the module docstring).

    `tiles_rendered` counts the level-0 tiles read to render them (for tests and benches: it grows with
    the area new frames reach, not with the area mapped), `rebuilds` the times the view was built whole."""

    def __init__(self, config: TileConfig | None = None) -> None:
        self.config = config or TileConfig()
        self.tiles_rendered = 0
        self.rebuilds = 0
        self.reset()

    def reset(self) -> None:
        """A new map: the next update builds the view from every tile and replaces every RViz tile."""
        self._anchor: tuple[float, float] | None = None
        self._bboxes: dict[tuple[int, int], Box] = {}   # mapped cells (absolute) of each level-0 tile with any
        self._pending: set[tuple[int, int]] = set()     # touched, not rendered yet
        self._map: _Planes | None = None
        self._height: _Planes | None = None
        self._level: int | None = None
        self._z: float | None = None
        self._grid: tuple[int, int, float, float] | None = None
        self._sent: dict[tuple[int, int, int], bytes] = {}
        self._resend = True

    def resend(self) -> None:
        """The next update sends every tile of the view again (a new subscriber), without re-rendering."""
        self._resend = True

    def update(self, mapper: WorldMapper, touched: set[tuple[int, int]]) -> LiveUpdate | None:
        """The views after the tiles `touched` (level-0 (ix, iy), absolute) changed; None while nothing is
        mapped (the tiles are kept for the next update)."""
        view = mapper.view()
        store = mapper.canvas.store
        t = view.tile
        anchor = (float(view.origin[0]), float(view.origin[1]))
        moved = self._anchor is not None and anchor != self._anchor
        if self._anchor is None or moved:   # everything there is, from scratch
            resend = self._resend or moved
            self.reset()
            self._resend, self._anchor = resend, anchor
            self._pending = set(store.tiles("weight"))
        self._pending |= touched
        for ix, iy in self._pending:
            weight = store.get("weight", ix, iy)
            if weight is not None:
                self._note_mapped(ix, iy, weight > MAPPED_WEIGHT, t)
        if not self._bboxes:
            return None
        if mapper.canvas.fixed:
            extent = view.extent()
            assert extent is not None
        else:
            boxes = np.array(list(self._bboxes.values()))
            extent = (int(boxes[:, 0].min()), int(boxes[:, 1].max()), int(boxes[:, 2].min()), int(boxes[:, 3].max()))
        level = fitting_level(extent, self.config.max_pixels)
        f = 2 ** level
        box = (extent[0] // f, -(-extent[1] // f), extent[2] // f, -(-extent[3] // f))
        height_view = mapper.height_view()
        replaced = self._resend or level != self._level
        rebuild = (self._map is None or level != self._level or not _contains(box, self._map.box)
                   or (height_view is None) != (self._height is None) or f > t)
        if rebuild:
            self.rebuilds += 1
            self._map = _Planes(box, {"grey": (np.uint8, 0), "alpha": (np.uint8, 0)})
            self._height = None if height_view is None else _Planes(box, {"height": (np.float32, math.nan)})
            todo = set(store.tiles("weight"))
        else:
            assert self._map is not None
            self._map.grow(box)
            if self._height is not None:
                self._height.grow(box)
            todo = {key for key in self._pending if store.has("weight", *key)}
        self._pending = set()
        self._level = level
        written: list[Box] = []
        if f > t:   # a level cell spans several store tiles: render the level's tiles (rare: a map > 2^9 tiles)
            written += self._render_level_tiles(view, height_view, level, box)
        else:
            for ix, iy in sorted(todo):
                part = self._render(view, height_view, level, ix, iy)
                if part is not None:
                    written.append(part)
        return self._publishable(mapper, level, box, written, replaced)

    # -- internals ------------------------------------------------------------------------------------
    def _note_mapped(self, ix: int, iy: int, mapped: np.ndarray, t: int) -> None:
        rows, cols = np.flatnonzero(mapped.any(axis=1)), np.flatnonzero(mapped.any(axis=0))
        if len(rows):
            self._bboxes[(ix, iy)] = (iy * t + int(rows[0]), iy * t + int(rows[-1]) + 1,
                                      ix * t + int(cols[0]), ix * t + int(cols[-1]) + 1)

    def _render(self, view: LayerView, height_view: LayerView | None, level: int, ix: int,
                iy: int) -> Box | None:
        assert self._map is not None
        self.tiles_rendered += 1
        value, weight = reduced_tile(view, level, ix, iy)
        side = view.tile >> level
        r0, c0 = iy * side, ix * side
        written = self._map.paste(r0, c0, _grey_alpha(value, weight, view.mapped_weight))
        if self._height is not None and height_view is not None:
            h_value, h_weight = reduced_tile(height_view, level, ix, iy)
            self._height.paste(r0, c0, {"height": _known(h_value, h_weight, height_view.mapped_weight)})
        return written

    def _render_level_tiles(self, view: LayerView, height_view: LayerView | None, level: int,
                            box: Box) -> list[Box]:
        assert self._map is not None
        t = view.tile
        written = []
        for jy in range(box[0] // t, (box[1] - 1) // t + 1):
            for jx in range(box[2] // t, (box[3] - 1) // t + 1):
                self.tiles_rendered += 4 ** level
                value, weight = pyramid_tile(view, level, jx, jy)
                part = self._map.paste(jy * t, jx * t, _grey_alpha(value, weight, view.mapped_weight))
                if part is not None:
                    written.append(part)
                if self._height is not None and height_view is not None:
                    h_value, h_weight = pyramid_tile(height_view, level, jx, jy)
                    self._height.paste(jy * t, jx * t, {"height": _known(h_value, h_weight,
                                                                          height_view.mapped_weight)})
        return written

    def _publishable(self, mapper: WorldMapper, level: int, box: Box, written: list[Box],
                     replaced: bool) -> LiveUpdate:
        assert self._map is not None
        f = 2 ** level
        res = mapper.config.resolution * f
        anchor = mapper.canvas.anchor
        # placed as `map_tiles.view_at` places the level image `WorldMapper.level_image` renders
        gx, dx = grid_offset(anchor[0] + box[2] * res, res)
        gy, dy = grid_offset(anchor[1] + box[0] * res, res)
        z = surface_z(mapper)
        view = MapView(np.ascontiguousarray(self._map.planes["grey"][::-1]),
                       np.ascontiguousarray(self._map.planes["alpha"][::-1]), level, f, res,
                       (gx * res + dx, gy * res + dy), (gx, gy), z)
        size = self.config.tile_px
        if replaced:
            self._sent = {}
        # the world grid's cell of the box's corner (rounding may put a corner lying half a cell off the grid
        # on either side as the box grows) and where the cells lie off it: the tiles' cut and corners
        grid = (gx - box[2], gy - box[0], dx, dy)
        if replaced or z != self._z or grid != self._grid:   # every tile (a new level or subscriber; moved)
            tiles = tiles_of(view, size)
        else:
            only: set[tuple[int, int]] = set()
            for a0, a1, k0, k1 in written:   # level cells -> view cells -> the world grid's tiles
                c0, c1 = gx + k0 - box[2], gx + k1 - box[2]
                r0, r1 = gy + a0 - box[0], gy + a1 - box[0]
                only.update((tx, ty) for ty in range(r0 // size, (r1 - 1) // size + 1)
                            for tx in range(c0 // size, (c1 - 1) // size + 1))
            tiles = tiles_of(view, size, only) if only else []
        self._z, self._grid, self._resend = z, grid, False
        changed: list[MapTile] = []
        for tile in tiles:
            code = digest(tile)
            if self._sent.get(tile.key) != code:
                self._sent[tile.key] = code
                changed.append(tile)
        height = None if self._height is None else np.ascontiguousarray(self._height.planes["height"][::-1])
        return LiveUpdate(view, TileUpdate(tuple(changed), level, replaced), height)


def _grey_alpha(value: np.ndarray, weight: np.ndarray, mapped_weight: float) -> dict[str, np.ndarray]:
    """Grey levels and alpha (rows growing with y) as the view has them: grey 0 where not mapped."""
    alpha = to_alpha(weight, mapped_weight, flip=False)
    grey = to_grey(value, flip=False)
    grey[alpha == 0] = 0
    return {"grey": grey, "alpha": alpha}


def _known(value: np.ndarray, weight: np.ndarray, mapped_weight: float) -> np.ndarray:
    return np.where(weight > mapped_weight, value, np.float32(np.nan)).astype(np.float32, copy=False)
