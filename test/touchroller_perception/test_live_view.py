"""The world map's live views kept from the tiles bands touched (touchroller_perception.live_view)."""
from __future__ import annotations

import numpy as np
import pytest

from touchroller_perception.geometry import CameraModel
from touchroller_perception.live_view import LiveMapView
from touchroller_perception.map_tiles import TileConfig, TileTracker, map_view, world_map_raster
from touchroller_perception.tiles import TileConfig as StoreConfig
from touchroller_perception.world_map import WorldMapConfig, WorldMapper

CAMERA = CameraModel(fx=200.0, fy=200.0, cx=159.5, cy=119.5, width=320, height=240)


def mapper(tile: int = 64, bounds=None, cache_tiles: int = 1000) -> WorldMapper:
    return WorldMapper(CAMERA, lambda stamps: np.zeros((len(stamps), 4, 4)),
                       WorldMapConfig(resolution=1e-4, bounds=bounds,
                                      tiles=StoreConfig(tile=tile, cache_bytes=cache_tiles * tile * tile * 4)))


def land(world: WorldMapper, c0: int, r0: int, rows: int, cols: int, rng: np.random.Generator,
         weight: float = 1.0) -> tuple[int, int]:
    """A band of random grey at canvas cell (c0, r0) (the canvas grows around it as it does for frames, its
    cells renumbered); returns where it landed in the canvas's cells now."""
    band = rng.uniform(10, 240, (rows, cols)).astype(np.float32)
    ones = np.full_like(band, weight)
    dc, dr = world.canvas.ensure(c0, r0, c0 + cols, r0 + rows)
    world.canvas.add([band * ones, ones, ones], c0 + dc, r0 + dr)
    return c0 + dc, r0 + dr


def from_scratch(world: WorldMapper, config: TileConfig):
    """The view and every tile as the views were built before: the whole map rendered again."""
    raster = world_map_raster(world, config.max_pixels)
    view, update = TileTracker(config).update(raster)
    return view, {t.key: t for t in update.tiles}


def assert_same_view(live, scratch) -> None:
    assert live.level == scratch.level and live.factor == scratch.factor
    assert live.resolution == scratch.resolution and live.origin == scratch.origin and live.cell0 == scratch.cell0
    assert live.z == scratch.z
    np.testing.assert_array_equal(live.grey, scratch.grey)
    np.testing.assert_array_equal(live.alpha, scratch.alpha)


@pytest.mark.parametrize("bounds", [None, (0.40005, -0.1, 0.46, -0.05)])
def test_the_incremental_view_is_the_view_built_from_scratch_after_many_updates(bounds):
    """Bands land over a growing raster (new ground and ground mapped again, across tile borders, a change of
    level as the map outgrows the budget): after every update the view kept from the touched tiles is the
    one rendered from the whole map, and the tiles it has sent, each at its latest, are the whole view's."""
    world = mapper(tile=64, bounds=bounds)
    config = TileConfig(tile_px=32, max_pixels=40_000)
    live = LiveMapView(config)
    rng = np.random.default_rng(7)
    shown: dict = {}
    levels = set()
    for step in range(40):
        c0 = int(rng.integers(0, 420)) if step % 3 else 10 * step
        r0 = int(rng.integers(0, 380))
        land(world, c0, r0, int(rng.integers(5, 90)), int(rng.integers(5, 120)), rng,
             weight=float(rng.uniform(0.02, 1.0)))
        update = live.update(world, world.touched_tiles())
        if not world_map_raster(world, config.max_pixels).mapped.any():   # nothing above the mapped weight yet
            assert update is None
            continue
        view, tiles = from_scratch(world, config)
        assert update is not None
        assert_same_view(update.view, view)
        if update.tiles.replaced:
            shown = {}
        shown.update({t.key: t for t in update.tiles.tiles})
        assert shown.keys() == tiles.keys()
        for key, tile in tiles.items():
            np.testing.assert_array_equal(shown[key].grey, tile.grey)
            np.testing.assert_array_equal(shown[key].alpha, tile.alpha)
            np.testing.assert_array_equal(shown[key].corners, tile.corners)
        levels.add(view.level)
    assert len(levels) >= 2 or bounds is not None   # a growing map outgrew the budget on the way
    assert live.update(world, world.touched_tiles()).tiles.tiles == ()   # nothing new: nothing sent


def test_a_publication_reads_the_tiles_new_frames_touched_not_the_whole_map():
    """A raster grows over 30 bands in new ground: the level-0 tiles each update renders stay those the
    band touched (at most 4 of 64-cell tiles for a 50 x 60 band), while the map grows to dozens of tiles;
    rendering from scratch reads every tile each time."""
    world = mapper(tile=64)
    live = LiveMapView(TileConfig(tile_px=32, max_pixels=4_000_000))
    rng = np.random.default_rng(2)
    per_update = []
    for step in range(30):
        before = live.tiles_rendered
        land(world, (step % 10) * 64 + 3, (step // 10) * 64 + 3, 50, 60, rng)
        assert live.update(world, world.touched_tiles()) is not None
        per_update.append(live.tiles_rendered - before)
    assert len(world.canvas.store.tiles("weight")) >= 30
    assert live.rebuilds == 1   # the first update only
    assert max(per_update[1:]) <= 4 and per_update[-1] <= per_update[1]


def test_the_height_map_is_kept_at_the_views_level():
    """A height layer (here a ratio of two layers of the canvas, as the world height's) is kept at the view's
    level over the view's cells, the same as `WorldMapper.height_level`."""
    world = mapper(tile=64)
    world.canvas.add_layer("h_sum")
    world.canvas.add_layer("h_w")
    view_of_height = world.canvas.ratio_view("h_sum", "h_w", weight="h_w", min_denominator=0.5)
    world.height_view = lambda: view_of_height   # type: ignore[method-assign]
    live = LiveMapView(TileConfig(tile_px=32, max_pixels=20_000))
    rng = np.random.default_rng(4)
    for _ in range(12):
        c0, r0 = int(rng.integers(0, 300)), int(rng.integers(0, 250))
        c0, r0 = land(world, c0, r0, 60, 80, rng)
        h = rng.normal(0, 1e-5, (60, 80)).astype(np.float32)
        world.canvas.add_named({"h_sum": h, "h_w": np.ones_like(h)}, c0, r0)
        update = live.update(world, world.touched_tiles())
        assert update is not None and update.height is not None
        rows = world.level_extent(update.view.level)
        expected = np.full((rows[1] - rows[0], rows[3] - rows[2]), np.nan, np.float32)
        from touchroller_perception.tiles import pyramid_tile

        t = 64
        for iy in range(rows[0] // t, (rows[1] - 1) // t + 1):
            for ix in range(rows[2] // t, (rows[3] - 1) // t + 1):
                value, weight = pyramid_tile(view_of_height, update.view.level, ix, iy)
                y0, y1 = max(rows[0], iy * t), min(rows[1], (iy + 1) * t)
                x0, x1 = max(rows[2], ix * t), min(rows[3], (ix + 1) * t)
                part = (slice(y0 - iy * t, y1 - iy * t), slice(x0 - ix * t, x1 - ix * t))
                expected[y0 - rows[0]:y1 - rows[0], x0 - rows[2]:x1 - rows[2]] = np.where(
                    weight[part] > view_of_height.mapped_weight, value[part], np.nan)
        np.testing.assert_array_equal(update.height, expected[::-1])
        assert update.height.shape == update.view.grey.shape


def test_a_moved_map_and_a_new_subscriber():
    """The map moved (the final latency estimate moves its anchor): rebuilt and every tile replaced;
    `resend` (a new subscriber): every tile again, nothing re-rendered."""
    world = mapper(tile=64)
    config = TileConfig(tile_px=32, max_pixels=4_000_000)
    live = LiveMapView(config)
    rng = np.random.default_rng(5)
    land(world, 0, 0, 100, 150, rng)
    first = live.update(world, world.touched_tiles())
    assert first is not None and first.tiles.replaced and len(first.tiles.tiles) > 4
    live.resend()
    rendered = live.tiles_rendered
    again = live.update(world, world.touched_tiles())
    assert again.tiles.replaced and len(again.tiles.tiles) == len(first.tiles.tiles)
    assert live.tiles_rendered == rendered
    origin = world.canvas.origin
    world.canvas.origin = (origin[0] + 3.3e-4, origin[1] - 1.2e-4)
    moved = live.update(world, world.touched_tiles())
    assert moved.tiles.replaced and live.rebuilds == 2
    view, tiles = from_scratch(world, config)
    assert_same_view(moved.view, view)
    assert {t.key for t in moved.tiles.tiles} == tiles.keys()


def test_nothing_mapped_is_no_view_and_the_touched_tiles_wait():
    world = mapper(tile=64)
    live = LiveMapView(TileConfig(tile_px=32))
    assert live.update(world, world.touched_tiles()) is None
    rng = np.random.default_rng(1)
    land(world, 0, 0, 20, 20, rng, weight=0.01)   # below the mapped weight
    assert live.update(world, world.touched_tiles()) is None
    land(world, 0, 0, 20, 20, rng, weight=1.0)
    update = live.update(world, world.touched_tiles())
    view = map_view(world_map_raster(world, 4_000_000), 4_000_000)
    assert_same_view(update.view, view)
