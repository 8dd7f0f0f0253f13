"""The world map's views within a size budget and its tiles (touchroller_perception.map_tiles)."""
from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

from touchroller_perception.map_tiles import (
    MapRaster,
    TileConfig,
    TileTracker,
    choose_level,
    map_view,
    tiles_of,
    view_at,
    world_map_raster,
)

RES = 1e-4


def raster(rows: int, cols: int, origin=(0.4, -0.1), seed: int = 0, hole: bool = True, z: float = 0.0) -> MapRaster:
    rng = np.random.default_rng(seed)
    grey = rng.integers(1, 255, (rows, cols), dtype=np.uint8)
    mapped = np.ones((rows, cols), bool)
    if hole:
        mapped[rows // 3:rows // 2, cols // 4:cols // 2] = False
        grey[~mapped] = 0
    return MapRaster(grey, mapped, RES, origin, z)


def reassemble(tiles, raster_: MapRaster):
    """The map rebuilt on its own grid from tiles: every texel's centre looked up in the map's cells
    (image rows from the top). Returns (grey, alpha) of the map's shape (-1: no texel fell there)."""
    return reassemble_quads([(t.corners, t.grey, t.alpha) for t in tiles], raster_.grey.shape, raster_.origin,
                            raster_.resolution)


def reassemble_quads(quads, shape, origin, resolution):
    """As `reassemble`, from (corners (4, 3): lower-left, lower-right, upper-right, upper-left; grey; alpha)."""
    rows, cols = shape
    grey, alpha = np.full(shape, -1, np.int32), np.full(shape, -1, np.int32)
    for corners, tile_grey, tile_alpha in quads:
        (x0, y0, _), _, (x1, y1, _), _ = corners
        h, w = tile_grey.shape
        xs = x0 + (np.arange(w) + 0.5) * (x1 - x0) / w
        ys = y1 - (np.arange(h) + 0.5) * (y1 - y0) / h     # texel row 0 is the top
        col = np.floor((xs - origin[0]) / resolution).astype(int)
        row = rows - 1 - np.floor((ys - origin[1]) / resolution).astype(int)
        inside = (row[:, None] >= 0) & (row[:, None] < rows) & (col[None, :] >= 0) & (col[None, :] < cols)
        assert not (tile_alpha[~inside] > 0).any()   # nothing drawn outside the map
        rr, cc = np.broadcast_arrays(row[:, None], col[None, :])
        assert (grey[rr[inside], cc[inside]] == -1).all()   # tiles do not overlap
        grey[rr[inside], cc[inside]] = tile_grey[inside]
        alpha[rr[inside], cc[inside]] = tile_alpha[inside]
    return grey, alpha


def test_the_finest_level_that_fits_the_budget():
    assert choose_level(1000, 1000, 4_000_000) == 0
    assert choose_level(3990, 3990, 4_000_000) == 1
    assert choose_level(4000, 4000, 4_000_000) == 2   # 2001 x 2001 with the block alignment: over
    assert choose_level(10_000, 10_000, 4_000_000) == 3   # 1 m^2 at 0.1 mm: 1250 x 1250 at level 3
    view = map_view(raster(300, 500), 20_000)
    assert view.factor == 4 and view.grey.size <= 20_000   # level 1 (151 x 251) does not fit


@pytest.mark.parametrize("origin", [(0.4, -0.1), (0.40003, -0.10004), (-0.0512, 0.0511)])
def test_tiles_at_full_resolution_hold_every_mapped_cell_in_place(origin):
    r = raster(300, 700, origin)
    view = view_at(r, 0)
    assert np.array_equal(view.grey, r.grey) and view.origin == pytest.approx(origin, abs=1e-12)
    tiles = tiles_of(view, 128)
    assert tiles
    grey, alpha = reassemble(tiles, r)
    assert np.array_equal(alpha == 255, r.mapped) and np.array_equal(grey[r.mapped], r.grey[r.mapped])
    assert ((alpha == 0) | (alpha == -1))[~r.mapped].all()
    for tile in tiles:   # squares of tile_px cells, on the world grid of cells
        (x0, y0, _), (x1, _, _), (_, y2, _), _ = tile.corners
        assert x1 - x0 == pytest.approx(128 * RES) and y2 - y0 == pytest.approx(128 * RES)
        off_x, off_y = origin[0] - round(origin[0] / RES) * RES, origin[1] - round(origin[1] / RES) * RES
        assert x0 == pytest.approx(tile.column * 128 * RES + off_x, abs=1e-12)
        assert y0 == pytest.approx(tile.row * 128 * RES + off_y, abs=1e-12)


def test_a_level_is_the_mean_of_the_mapped_cells_of_each_world_aligned_block():
    r = raster(64, 96, origin=(0.4001, -0.1003))   # first cell at grid (4001, -1003): blocks cut it unevenly
    view = view_at(r, 2)
    gx0, gy0 = 4001, -1003
    lx0, ly0 = gx0 // 4, gy0 // 4
    assert view.cell0 == (lx0, ly0) and view.resolution == pytest.approx(4 * RES)
    assert view.origin == pytest.approx((lx0 * 4 * RES, ly0 * 4 * RES), abs=1e-12)
    up_grey, up_mapped = np.flipud(r.grey).astype(float), np.flipud(r.mapped)
    vg, va = np.flipud(view.grey), np.flipud(view.alpha)
    for i in range(vg.shape[0]):
        for j in range(vg.shape[1]):
            rows = [k for k in range(64) if (gy0 + k) // 4 == ly0 + i]
            cols = [k for k in range(96) if (gx0 + k) // 4 == lx0 + j]
            block_m = up_mapped[np.ix_(rows, cols)] if rows and cols else np.zeros((0, 0), bool)
            if block_m.any():
                expected = up_grey[np.ix_(rows, cols)][block_m].mean()
                assert va[i, j] == 255 and abs(int(vg[i, j]) - expected) <= 0.5 + 1e-9
            else:
                assert va[i, j] == 0


def test_only_tiles_whose_pixels_changed_are_sent_again():
    tracker = TileTracker(TileConfig(tile_px=64, max_pixels=1_000_000))
    r = raster(200, 300, hole=False)
    _, first = tracker.update(r)
    assert first.replaced and len(first.tiles) == tracker.sent() >= 4 * 5
    _, again = tracker.update(r)
    assert not again.replaced and again.tiles == ()
    grey = r.grey.copy()
    grey[-10, 10] ^= 0xFF   # one cell near the lower-left corner (image rows count from the top)
    _, one = tracker.update(MapRaster(grey, r.mapped, RES, r.origin))
    assert len(one.tiles) == 1
    (x0, y0, _), _, (x1, y1, _), _ = one.tiles[0].corners
    x, y = r.origin[0] + 10.5 * RES, r.origin[1] + 9.5 * RES
    assert x0 <= x < x1 and y0 <= y < y1
    # the map grows to the right: the old tiles stay where they are, unchanged, and are not sent again
    bigger = np.zeros((200, 400), np.uint8)
    bigger[:, :300] = grey
    bigger[:, 300:] = 7
    _, grown = tracker.update(MapRaster(bigger, np.ones((200, 400), bool), RES, r.origin))
    assert not grown.replaced and grown.tiles
    assert all(t.corners[1, 0] > r.origin[0] + 300 * RES - 64 * RES for t in grown.tiles)
    # past the budget: the next level replaces every tile
    small = TileTracker(TileConfig(tile_px=64, max_pixels=64 * 64))
    _, coarse = small.update(MapRaster(bigger, np.ones((200, 400), bool), RES, r.origin))
    assert coarse.replaced and coarse.level >= 3
    tracker.reset()
    assert tracker.update(r)[1].replaced


@given(rows=st.integers(1, 40), cols=st.integers(1, 40), gx=st.integers(-500, 500), gy=st.integers(-500, 500),
       level=st.integers(0, 3), seed=st.integers(0, 5))
def test_levels_keep_every_mapped_cell_and_invent_none(rows, cols, gx, gy, level, seed):
    rng = np.random.default_rng(seed)
    mapped = rng.random((rows, cols)) < 0.6
    grey = np.where(mapped, rng.integers(0, 256, (rows, cols)), 0).astype(np.uint8)
    r = MapRaster(grey, mapped, RES, (gx * RES, gy * RES))
    view = view_at(r, level)
    f = 2 ** level
    assert view.factor == f
    # a view cell is mapped exactly when its block holds a mapped cell
    up = np.flipud(mapped)
    expect = np.zeros(view.grey.shape, bool)
    ys, xs = np.nonzero(up)
    vy = (gy + ys) // f - view.cell0[1]
    vx = (gx + xs) // f - view.cell0[0]
    expect_up = np.zeros(view.grey.shape, bool)
    expect_up[vy, vx] = True
    expect = np.flipud(expect_up)
    assert np.array_equal(view.alpha == 255, expect)
    assert (view.grey[~expect] == 0).all()
    tiles = tiles_of(view, 16)
    assert sum(int((t.alpha == 255).sum()) for t in tiles) == int(expect.sum())


def test_a_raster_refuses_what_it_cannot_place():
    with pytest.raises(ValueError):
        MapRaster(np.zeros((2, 2), np.uint8), np.zeros((2, 3), bool), RES, (0.0, 0.0))
    with pytest.raises(ValueError):
        MapRaster(np.zeros((2, 2), np.uint8), np.zeros((2, 2), bool), 0.0, (0.0, 0.0))
    with pytest.raises(ValueError):
        MapRaster(np.zeros((2, 2), np.uint8), np.zeros((2, 2), bool), RES, (float("nan"), 0.0))
    with pytest.raises(ValueError):
        TileConfig(tile_px=8)
    with pytest.raises(ValueError):
        TileConfig(tile_px=512, max_pixels=1000)


def test_the_adapter_reads_the_world_map_as_its_files_have_it():
    from touchroller_perception.geometry import CameraModel
    from touchroller_perception.world_map import WorldMapConfig, WorldMapper

    camera = CameraModel(fx=200.0, fy=200.0, cx=159.5, cy=119.5, width=320, height=240)
    mapper = WorldMapper(camera, lambda stamps: np.zeros((len(stamps), 4, 4)),
                         WorldMapConfig(bounds=(0.4, -0.1, 0.43, -0.08)))
    rng = np.random.default_rng(3)
    band = rng.uniform(10, 200, (50, 120)).astype(np.float32)
    ones = np.ones_like(band)
    mapper.canvas.add([band, ones, ones], 30, 20)
    r = world_map_raster(mapper)
    image = mapper.map_image()
    assert np.array_equal(r.grey, image.grey) and np.array_equal(r.mapped, image.alpha > 0)
    assert r.origin == image.origin and r.resolution == image.resolution and r.z == 0.0
    assert r.mapped.sum() == 50 * 120


def test_the_adapter_renders_a_large_map_at_the_level_that_fits_from_the_tiles(monkeypatch):
    """A map of many tiles (1600 x 1200 cells on 128-cell tiles, room in memory for 8 of them, the rest
    spilled) is read for a view at the coarsest level that fits the budget, from the tile store's pyramid:
    never built whole (`map_image` is not called), the view within the budget, read through the bounded
    cache, each level cell the mean of the cells it covers, in place."""
    from touchroller_perception.geometry import CameraModel
    from touchroller_perception.tiles import TileConfig as StoreConfig
    from touchroller_perception.world_map import WorldMapConfig, WorldMapper

    camera = CameraModel(fx=200.0, fy=200.0, cx=159.5, cy=119.5, width=320, height=240)
    res = 2.0 ** -13   # the bounds an exact number of cells
    mapper = WorldMapper(camera, lambda stamps: np.zeros((len(stamps), 4, 4)),
                         WorldMapConfig(resolution=res, bounds=(0.25, -0.125, 0.25 + 1600 * res, -0.125 + 1200 * res),
                                        tiles=StoreConfig(tile=128, cache_bytes=8 * 128 * 128 * 4)))
    rng = np.random.default_rng(5)
    band = rng.uniform(10, 200, (400, 400)).astype(np.float32)
    ones = np.ones_like(band)
    for r0 in range(0, 1200, 400):
        for c0 in range(0, 1600, 400):
            mapper.canvas.add([band, ones, ones], c0, r0)
    whole = mapper.map_image()
    assert whole.grey.shape == (1200, 1600) and (whole.alpha > 0).all()

    def built_whole(*args, **kwargs):
        raise AssertionError("the view built the whole map")

    monkeypatch.setattr(type(mapper), "map_image", built_whole)
    r = world_map_raster(mapper, 200_000)
    assert r.level == 2 and r.grey.shape == (300, 400) and r.resolution == 4 * res
    assert r.mapped.all() and r.origin == pytest.approx(whole.origin)
    assert mapper.canvas.store.resident() <= 8   # read a tile at a time through the bounded cache
    view = map_view(r, 200_000)
    assert view.level == 2 and view.grey.size <= 200_000
    # level cell (row, col) (row 0 the top) is the mean of the 4 x 4 full-resolution cells it covers
    means = whole.grey.astype(np.float64).reshape(300, 4, 400, 4).mean(axis=(1, 3))
    assert float(np.abs(r.grey - means).max()) <= 1.0
