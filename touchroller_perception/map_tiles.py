"""Views of a world map that fit a size budget, and the map cut into tiles of one level of detail.

A map raster (`MapRaster`: grey + mapped, row 0 the top (largest y), `origin` the lower-left corner of
its lower-left cell, as nav2's map_server and `WorldMapImage` have it) is shown at the level of detail
its extent allows: level k is the map downsampled by 2**k (each level cell the mean of the mapped cells
of a 2**k x 2**k block, mapped if any of them is), the lowest k whose view fits `max_pixels`
(`map_view`). Blocks and tiles are aligned to the world's grid of cells (cell index round(x /
resolution)), not to the map's current corner, so a tile keeps its index, its place and its content
while the map grows around it.

`TileTracker` cuts each view into `tile_px` x `tile_px` tiles (index (column, row) of the tile in x and
y) and reports the tiles whose pixels changed since the last call: new frames land in a few tiles, and
only those are sent again. A change of level (the map outgrew the budget of the one before) replaces
every tile. Pure geometry and arrays: the ROS messages are built by `touchroller_bringup.map_markers`.

`world_map_raster(mapper, max_pixels)` reads a world map for its views from the map's tile store at the
pyramid level that fits (a `MapRaster` with `level` set), never the whole map at full resolution.
"""
from __future__ import annotations

import hashlib
import math
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

if TYPE_CHECKING:
    from touchroller_perception.world_map import WorldMapper


@dataclass(frozen=True)
class MapRaster:
    """A map layer at full resolution: `grey` (uint8) and `mapped` (bool), row 0 the top (largest y);
    `origin` the world (x, y) of the lower-left cell's lower-left corner, m; `z` the height of the
    mapped surface in the map's frame, m; `level`: the raster is already the map's level `level` (read
    from a tiled store's pyramid at 2^level x the map's resolution), views count their levels from it."""

    grey: np.ndarray
    mapped: np.ndarray
    resolution: float
    origin: tuple[float, float]
    z: float = 0.0
    level: int = 0

    def __post_init__(self) -> None:
        if self.grey.shape != self.mapped.shape or self.grey.ndim != 2:
            raise ValueError(f"grey {self.grey.shape} and mapped {self.mapped.shape} must be one 2-D shape")
        if not (math.isfinite(self.resolution) and self.resolution > 0):
            raise ValueError(f"resolution must be a positive number, got {self.resolution}")
        if not all(math.isfinite(v) for v in (*self.origin, self.z)):
            raise ValueError(f"origin and z must be finite, got {self.origin}, {self.z}")


@dataclass(frozen=True)
class TileConfig:
    """tile_px: tile side, level pixels. max_pixels: the most pixels a view of the map may have (the
    level of detail is the finest that fits)."""

    tile_px: int = 512
    max_pixels: int = 4_000_000

    def __post_init__(self) -> None:
        if not (isinstance(self.tile_px, int) and 16 <= self.tile_px <= 8192):
            raise ValueError(f"tile_px must be an integer in 16..8192, got {self.tile_px}")
        if not (isinstance(self.max_pixels, int) and self.max_pixels >= self.tile_px ** 2):
            raise ValueError(f"max_pixels must be an integer of at least one tile ({self.tile_px ** 2}), "
                             f"got {self.max_pixels}")


@dataclass(frozen=True)
class MapView:
    """The map at level `level` (downsampled by `factor` = 2**level): grey and alpha (255 mapped, 0 not),
    row 0 the top; `origin` the lower-left corner, `resolution` = factor x the map's; `cell0` the world
    grid index (column, row) of the view's lower-left level cell."""

    grey: np.ndarray
    alpha: np.ndarray
    level: int
    factor: int
    resolution: float
    origin: tuple[float, float]
    cell0: tuple[int, int]
    z: float = 0.0


@dataclass(frozen=True)
class MapTile:
    """One tile of a view: `column`, `row` its index along x and y at `level` (tile (0, 0) has its
    lower-left corner at the world grid's cell (0, 0)); `corners` (4, 3) the world (x, y, z) of its
    lower-left, lower-right, upper-right and upper-left corners; grey and alpha tile_px square, row 0
    the top (largest y), alpha 0 outside the map."""

    level: int
    column: int
    row: int
    corners: np.ndarray
    grey: np.ndarray
    alpha: np.ndarray

    @property
    def key(self) -> tuple[int, int, int]:
        return self.level, self.column, self.row


@dataclass(frozen=True)
class TileUpdate:
    """What changed since the last view: `tiles` to (re)send; `replaced`: the level changed (or the map
    was emptied), so every tile sent before is gone and `tiles` is the whole view."""

    tiles: tuple[MapTile, ...]
    level: int
    replaced: bool


def choose_level(rows: int, cols: int, max_pixels: int) -> int:
    """The lowest level k whose view (each side / 2**k, rounded up, plus one cell of block alignment)
    has at most `max_pixels` pixels."""
    level = 0
    while (math.ceil(rows / 2 ** level) + 1) * (math.ceil(cols / 2 ** level) + 1) > max_pixels and level < 30:
        level += 1
    return level


def fitting_level(box: tuple[int, int, int, int], max_pixels: int) -> int:
    """The lowest pyramid level k at which the map's extent `box` (row0, row1, column0, column1 of level-0
    cells) is a view of at most `max_pixels` pixels: its level-k cells (blocks aligned to the grid of
    `box`) plus one of alignment each way, as `map_view` counts them, so the level image needs no further
    level of its own."""
    r0, r1, c0, c1 = box
    level = 0
    while level < 30:
        f = 2 ** level
        rows, cols = -(-r1 // f) - r0 // f, -(-c1 // f) - c0 // f
        if (rows + 1) * (cols + 1) <= max_pixels:
            break
        level += 1
    return level


def surface_z(mapper: WorldMapper) -> float:
    """The height of the surface the roller pressed on in the map's frame (the pressed height of its axis
    less the radius; 0 until it is known): where the views are drawn."""
    pressed = mapper.stats.pressed_height
    return pressed - mapper.camera.radius if pressed is not None and math.isfinite(pressed) else 0.0


def grid_offset(origin: float, resolution: float) -> tuple[int, float]:
    """(world grid index of the map's first cell, what its corner lies off the grid: |offset| <= res / 2)."""
    index = round(origin / resolution)
    return index, origin - index * resolution


def map_view(raster: MapRaster, max_pixels: int) -> MapView:
    """The map at the finest level whose view fits `max_pixels` (see the module docstring)."""
    rows, cols = raster.grey.shape
    level = choose_level(rows, cols, max_pixels)
    return view_at(raster, level)


def view_at(raster: MapRaster, level: int) -> MapView:
    """The map downsampled by 2**level, blocks aligned to the world grid (mean of mapped cells)."""
    factor = 2 ** level
    res = raster.resolution
    gx, dx = grid_offset(raster.origin[0], res)
    gy, dy = grid_offset(raster.origin[1], res)
    rows, cols = raster.grey.shape
    # rows growing with y from here on (row 0 the lowest y)
    grey = np.flipud(raster.grey)
    mapped = np.flipud(raster.mapped)
    lx0, ly0 = gx // factor, gy // factor                              # level cell of the first map cell
    lx1, ly1 = -(-(gx + cols) // factor), -(-(gy + rows) // factor)     # one past the last
    if factor == 1:
        value = grey.astype(np.float32)
        count = mapped.astype(np.float32)
    else:
        pad_x0, pad_y0 = gx - lx0 * factor, gy - ly0 * factor
        padded_rows, padded_cols = (ly1 - ly0) * factor, (lx1 - lx0) * factor
        weight = np.zeros((padded_rows, padded_cols), np.float32)
        total = np.zeros((padded_rows, padded_cols), np.float32)
        weight[pad_y0:pad_y0 + rows, pad_x0:pad_x0 + cols] = mapped
        total[pad_y0:pad_y0 + rows, pad_x0:pad_x0 + cols] = np.where(mapped, grey, 0)
        shape = (ly1 - ly0, factor, lx1 - lx0, factor)
        count = weight.reshape(shape).sum(axis=(1, 3))
        value = total.reshape(shape).sum(axis=(1, 3))
        np.divide(value, count, out=value, where=count > 0)
    known = count > 0
    level_grey = np.where(known, np.clip(np.rint(value), 0, 255), 0).astype(np.uint8)
    alpha = np.where(known, np.uint8(255), np.uint8(0))
    origin = (lx0 * factor * res + dx, ly0 * factor * res + dy)
    return MapView(np.ascontiguousarray(np.flipud(level_grey)), np.ascontiguousarray(np.flipud(alpha)),
                   raster.level + level, 2 ** (raster.level + level), res * factor, origin, (int(lx0), int(ly0)),
                   raster.z)


def tiles_of(view: MapView, tile_px: int, only: set[tuple[int, int]] | None = None) -> list[MapTile]:
    """Every tile of the view that holds a mapped cell (`only`: of those (column, row))."""
    out = []
    grey = np.flipud(view.grey)     # rows growing with y
    alpha = np.flipud(view.alpha)
    rows, cols = grey.shape
    lx0, ly0 = view.cell0
    # where the view's corner lies off the level grid (the map's own sub-cell offset)
    dx = view.origin[0] - lx0 * view.resolution
    dy = view.origin[1] - ly0 * view.resolution
    for ty in range(ly0 // tile_px, -(-(ly0 + rows) // tile_px)):
        for tx in range(lx0 // tile_px, -(-(lx0 + cols) // tile_px)):
            if only is not None and (tx, ty) not in only:
                continue
            # the tile's level cells [tx * T, (tx + 1) * T) in view coordinates, clipped to the view
            c0, r0 = tx * tile_px - lx0, ty * tile_px - ly0
            a0, a1 = max(r0, 0), min(r0 + tile_px, rows)
            b0, b1 = max(c0, 0), min(c0 + tile_px, cols)
            if not alpha[a0:a1, b0:b1].any():
                continue
            tile_grey = np.zeros((tile_px, tile_px), np.uint8)
            tile_alpha = np.zeros((tile_px, tile_px), np.uint8)
            tile_grey[a0 - r0:a1 - r0, b0 - c0:b1 - c0] = grey[a0:a1, b0:b1]
            tile_alpha[a0 - r0:a1 - r0, b0 - c0:b1 - c0] = alpha[a0:a1, b0:b1]
            size = tile_px * view.resolution
            x0, y0 = tx * size + dx, ty * size + dy
            corners = np.array([[x0, y0, view.z], [x0 + size, y0, view.z], [x0 + size, y0 + size, view.z],
                                [x0, y0 + size, view.z]])
            out.append(MapTile(view.level, tx, ty, corners, np.flipud(tile_grey).copy(),
                               np.flipud(tile_alpha).copy()))
    return out


def digest(tile: MapTile) -> bytes:
    h = hashlib.blake2b(digest_size=16)
    h.update(tile.grey.tobytes())
    h.update(tile.alpha.tobytes())
    h.update(tile.corners.tobytes())
    return h.digest()


class TileTracker:
    """The tiles of successive views, and which of them changed (see the module docstring)."""

    def __init__(self, config: TileConfig | None = None) -> None:
        self.config = config or TileConfig()
        self._level: int | None = None
        self._sent: dict[tuple[int, int, int], bytes] = {}

    def reset(self) -> None:
        """Forget what was sent: the next update replaces everything (a new map)."""
        self._level = None
        self._sent = {}

    def update(self, raster: MapRaster) -> tuple[MapView, TileUpdate]:
        """The view of `raster` within the budget and the tiles changed since the last update."""
        view = map_view(raster, self.config.max_pixels)
        tiles = tiles_of(view, self.config.tile_px)
        replaced = self._level != view.level
        if replaced:
            self._sent = {}
        self._level = view.level
        changed = []
        for tile in tiles:
            code = digest(tile)
            if self._sent.get(tile.key) != code:
                self._sent[tile.key] = code
                changed.append(tile)
        return view, TileUpdate(tuple(changed), view.level, replaced)

    def sent(self) -> int:
        """How many tiles the current level has sent."""
        return len(self._sent)


def world_map_raster(mapper: WorldMapper, max_pixels: int | None = None) -> MapRaster:
    """The adapter between the world map and its views, at the height of the surface the roller pressed
    on (the pressed height of its axis less the radius; 0 until it is known). The map is read from its
    tile store (`WorldMapper.level_image`): at the coarsest pyramid level whose view fits `max_pixels`
    (`fitting_level` on the mapped extent; None: full resolution), rendered a tile at a time, so building
    a view costs memory for the view alone however large the map grows. Empty while nothing is mapped."""
    z = surface_z(mapper)
    box = mapper.level_extent(0)
    level = 0 if box is None or max_pixels is None else fitting_level(box, max_pixels)
    image = mapper.level_image(level)
    if image is None:
        empty = np.zeros((0, 0), np.uint8)
        return MapRaster(empty, empty.astype(bool), mapper.config.resolution, (0.0, 0.0), z)
    return MapRaster(image.grey, image.alpha > 0, image.resolution, image.origin, z, level)
