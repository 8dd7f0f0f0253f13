"""Surfaces made tile by tile (touchroller_driver.sim.tiled_surface, lazy_surfaces): the same heights as
the eager grid, rendered frames alike, and a square metre held in a bounded number of tiles."""
from __future__ import annotations

import cv2
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from touchroller_driver.sim import RollerState, SimulatedSensor, load_scene
from touchroller_driver.sim.defects import surface_defects
from touchroller_driver.sim.surfaces import Surface, make_surface
from touchroller_driver.sim.tiled_surface import TileCacheConfig, TiledSurface, cubic_window

RELIEF = 3e-4
SPEC = {"width": 0.03, "length": 0.05, "resolution": 1e-4, "relief": RELIEF}
TOL = 1e-6 * RELIEF   # float32 rounding of the sums: the two agree to 1e-7 of the relief


@given(rows=st.integers(2, 300), cols=st.integers(2, 300), scale=st.floats(1.0, 40.0), r=st.integers(0, 299),
       c=st.integers(0, 299), h=st.integers(1, 80), w=st.integers(1, 80), seed=st.integers(0, 3))
@settings(max_examples=60)
def test_a_window_of_the_bicubic_resize_is_cv2s(rows, cols, scale, r, c, h, w, seed):
    small = np.random.default_rng(seed).standard_normal((max(2, int(rows / scale) + 3),
                                                         max(2, int(cols / scale) + 3))).astype(np.float32)
    whole = cv2.resize(small, (cols, rows), interpolation=cv2.INTER_CUBIC)
    r0, c0 = min(r, rows - 1), min(c, cols - 1)
    r1, c1 = min(r0 + h, rows), min(c0 + w, cols)
    np.testing.assert_allclose(cubic_window(small, rows, cols, r0, r1, c0, c1), whole[r0:r1, c0:c1],
                               atol=1e-5 * max(1.0, float(np.abs(whole).max())))   # float32 sums: ~30 ulp


@pytest.mark.parametrize("kind", ["grain", "stripes", "flat"])
def test_lazy_tiles_equal_the_eager_surface_and_its_low_pass(kind):
    eager = make_surface({"kind": kind, **SPEC}, np.random.default_rng(5))
    lazy = make_surface({"kind": kind, **SPEC, "lazy": True, "tile_cells": 64, "max_tiles": 8},
                        np.random.default_rng(5))
    assert isinstance(eager, Surface) and isinstance(lazy, TiledSurface)
    assert lazy.tiles_made == 0   # nothing made until read
    assert (lazy.x0, lazy.y0, lazy.resolution, lazy.shape) == (eager.x0, eager.y0, eager.resolution,
                                                                eager.height.shape)
    assert lazy.max_height == eager.max_height
    # tile by tile, each as made, against the eager grid
    t = 64
    for ti in range(0, 500, t):
        for tj in range(0, 300, t):
            r1, c1 = min(ti + t, 500), min(tj + t, 300)
            np.testing.assert_allclose(lazy.window(ti, r1, tj, c1), eager.height[ti:r1, tj:c1], atol=TOL)
    assert lazy.peak_tiles <= 8 and lazy.tiles_made == 8 * 5   # 500 x 300 cells in 64-cell tiles
    low_eager, low_lazy = eager.lowpassed(2.5e-4), lazy.lowpassed(2.5e-4)
    np.testing.assert_allclose(low_lazy.height, low_eager.height, atol=TOL)
    rng = np.random.default_rng(1)
    mx = rng.uniform(-5, 310, (200, 300)).astype(np.float32)
    my = rng.uniform(-5, 505, (200, 300)).astype(np.float32)
    mx[0, :10] = -1e6   # the renderer's "not on the membrane"
    np.testing.assert_allclose(low_lazy.remap(mx, my), low_eager.remap(mx, my), atol=TOL)
    x, y = rng.uniform(-0.02, 0.02, 5000), rng.uniform(-0.01, 0.06, 5000)
    np.testing.assert_allclose(low_lazy.sample(x, y), low_eager.sample(x, y), atol=TOL)
    if kind == "grain":
        assert np.ptp(eager.height) > 0.5 * RELIEF   # the comparison is not of two flat planes


DEFECTS = {"seed": 2, "cracks": 2, "dents": 1, "bumps": 1, "crack_width": [1.5e-4, 4e-4],
           "crack_depth": [3e-5, 1e-4], "crack_length": [4e-3, 8e-3], "blob_diameter": [1.5e-3, 3e-3],
           "blob_depth": [3e-5, 1e-4], "clearance": 1e-3}


@given(kind=st.sampled_from(["panel", "glass", "grain", "stripes", "flat"]), seed=st.integers(0, 2**16),
       defects=st.integers(-1, 50), cracks=st.integers(0, 4), dents=st.integers(0, 4),
       rows=st.integers(40, 160), cols=st.integers(40, 160), tile=st.integers(8, 70),
       windows=st.lists(st.tuples(st.integers(-10, 170), st.integers(-10, 170), st.integers(1, 90),
                                  st.integers(1, 90)), min_size=1, max_size=4))
@settings(max_examples=25, deadline=None)
def test_lazy_surfaces_with_planted_defects_equal_the_eager_ones(kind, seed, defects, cracks, dents, rows, cols,
                                                                  tile, windows):
    """Any lazy kind (the smooth panel and glass among them), with or without `surface.defects`, at any
    size and tile: every window and the low-passed surface are the eager grid's, and `max_height` bounds
    it (equal but where the background's highest lies under a defect)."""
    res = 2e-4
    spec = {"kind": kind, "width": cols * res, "length": rows * res, "resolution": res, "relief": RELIEF,
            "cracks": cracks, "dents": dents, "x_offset": 1e-3, "y_offset": -2e-3}
    if defects >= 0:
        spec["defects"] = {**DEFECTS, "seed": defects}
    eager = make_surface(spec, np.random.default_rng(seed))
    lazy = make_surface({**spec, "lazy": True, "tile_cells": tile, "max_tiles": 4}, np.random.default_rng(seed))
    assert isinstance(eager, Surface) and isinstance(lazy, TiledSurface) and lazy.tiles_made == 0
    assert lazy.description == eager.description and lazy.shape == eager.height.shape
    tol = 1e-6 * max(float(np.abs(eager.height).max()), 1e-9)
    whole = np.zeros((rows + 300, cols + 300), np.float32)   # 0 outside the grid
    whole[20:20 + rows, 20:20 + cols] = eager.height
    for r0, c0, h, w in windows:
        np.testing.assert_allclose(lazy.window(r0, r0 + h, c0, c0 + w),
                                   whole[r0 + 20:r0 + h + 20, c0 + 20:c0 + w + 20], atol=tol)
    assert lazy.peak_tiles <= 4
    np.testing.assert_allclose(lazy.lowpassed(1.5e-4).height, eager.lowpassed(1.5e-4).height, atol=tol)
    deepest = max([float(np.max(d)) for c in surface_defects(spec).cracks for d in c.depths] +
                  [abs(b.depth_m) for b in surface_defects(spec).blobs] + [0.0])
    assert eager.max_height - tol <= lazy.max_height <= eager.max_height + deepest + tol
    if defects < 0:
        assert lazy.max_height == pytest.approx(eager.max_height, abs=tol)


def test_a_lazy_panel_is_its_eager_grid_and_keeps_its_planted_defects():
    spec = {"kind": "panel", **SPEC, "cracks": 2, "dents": 3, "defects": {**DEFECTS, "seed": 7}}
    eager = make_surface(spec, np.random.default_rng(1))
    lazy = make_surface({**spec, "lazy": True, "tile_cells": 64, "max_tiles": 6}, np.random.default_rng(1))
    assert isinstance(lazy, TiledSurface) and "planted 2 crack(s), 2 dent(s)/bump(s)" in lazy.description
    np.testing.assert_allclose(lazy.height, eager.height, atol=1e-6 * float(np.abs(eager.height).max()))
    # the defects are there: deeper than the panel's own relief (2 um of peel and its shallow grooves)
    assert float(lazy.height.min()) < -2e-5 and lazy.max_height == pytest.approx(eager.max_height, rel=1e-6)
    # a lazy grain plants them as well (they were left out once)
    plain = make_surface({"kind": "grain", **SPEC, "lazy": True}, np.random.default_rng(0))
    grain = make_surface({"kind": "grain", **SPEC, "lazy": True, "defects": DEFECTS}, np.random.default_rng(0))
    assert float(np.abs(grain.height - plain.height).max()) > 2e-5


@pytest.mark.parametrize("variant", [None, "panel"])
def test_a_lazy_scene_renders_the_frames_the_eager_one_does(variant):
    overrides = {"surface.width": 0.08, "surface.length": 0.06, "effects": []}
    if variant == "panel":
        overrides["surface.defects"] = {**DEFECTS, "area": [-0.03, 0.005, 0.03, 0.055], "cracks": 4, "dents": 2}
    eager = SimulatedSensor(load_scene("large_surface", variant, **overrides), seed=3)
    lazy = SimulatedSensor(load_scene("large_surface", variant, **overrides, **{"surface.lazy": True,
                                                                                 "surface.tile_cells": 128}), seed=3)
    assert isinstance(lazy.surface, TiledSurface) and isinstance(eager.surface, Surface)
    for travel in (0.01, 0.03, 0.05):
        state = RollerState(travel=travel, depth=5e-4)
        a, b = eager.render(state), lazy.render(state)
        assert np.abs(a.astype(int) - b.astype(int)).max() <= 1   # rounding of a 1e-7 difference, at most
        assert (a != b).mean() < 1e-3
    assert lazy._relief.tiles_made < 48   # 600 x 800 cells: 4 x 7 tiles of 128 (blurred), read where rolled


def test_a_square_metre_raster_holds_a_bounded_number_of_tiles():
    """1 m x 1 m of grain (at 0.5 mm here, so the pass over it for its range stays short), a raster of 16
    passes read frame by frame: the surface is never held whole, only the tiles under the band."""
    scene = load_scene("large_surface", **{"surface.width": 1.0, "surface.length": 1.0,
                                           "surface.resolution": 5e-4, "surface.lazy": True,
                                           "surface.tile_cells": 64, "surface.max_tiles": 24, "effects": []})
    sensor = SimulatedSensor(scene, seed=0)
    relief, raw = sensor._relief, sensor.surface
    assert isinstance(relief, TiledSurface) and isinstance(raw, TiledSurface)
    assert relief.tiles_made == raw.tiles_made == 0
    total = -(-relief.rows // 64) * -(-relief.cols // 64)   # 32 x 32 tiles of 3.2 cm
    seen: set[tuple[int, int]] = set()
    passes = 16
    for k in range(passes):   # passes 6 cm apart across the metre, each read every 20 cm along it
        x = -0.45 + k * 0.06
        for travel in np.arange(0.05, 0.96, 0.2)[:: 1 if k % 2 == 0 else -1]:
            image = sensor.render(RollerState(travel=float(travel), x_along=x, depth=5e-4))
            assert image.std() > 0
            seen |= set(relief._cache)
    assert relief.peak_tiles <= 24 and raw.peak_tiles <= 24 and relief.tiles_held <= 24
    # the raster reached across the surface: far more tiles than the cache holds were made and let go
    assert len(seen) > 3 * 24 and relief.tiles_made >= len(seen) and total == 1024


def test_a_surface_too_large_to_hold_is_lazy_or_a_clear_error():
    big = {"width": 1.0, "length": 1.0, "resolution": 1e-4, "relief": RELIEF}
    flat = make_surface({"kind": "flat", **big}, np.random.default_rng(0))
    assert isinstance(flat, TiledSurface) and flat.shape == (10_000, 10_000) and flat.tiles_made == 0
    with pytest.raises(ValueError, match="too large for a fabric surface"):
        make_surface({"kind": "fabric", **big}, np.random.default_rng(0))
    with pytest.raises(ValueError, match="tile by tile"):
        make_surface({"kind": "fabric", **SPEC, "lazy": True}, np.random.default_rng(0))
    with pytest.raises(ValueError):
        TileCacheConfig(tile_cells=4)
    with pytest.raises(ValueError):
        TileCacheConfig(max_tiles=1)
