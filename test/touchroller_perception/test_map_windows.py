"""A world map read a window at a time for inspection: the height during a pass (the pass being rolled, not
yet levelled, moved onto the finished passes) and after it."""
from __future__ import annotations

import math
from types import SimpleNamespace

import numpy as np
import pytest

from touchroller_perception.geometry import CameraModel
from touchroller_perception.inspection import inspect
from touchroller_perception.map_windows import MapWindows
from touchroller_perception.tiles import TileConfig
from touchroller_perception.world_height import PASS, PASS_W, HeightLayer, WorldHeightConfig
from touchroller_perception.world_map import WorldMapConfig, WorldMapper

RES = 1e-4
ORIGIN = (0.40, -0.02)
PRESS = 5e-4      # the pass's unknown press depth: in its sums until its end levels it away


def relief(rows=400, cols=500, seed=1):
    """Canvas rows (growing with y): a crack along y (across the passes, which run along x), a dent, a bump."""
    rng = np.random.default_rng(seed)
    h = rng.normal(0, 0.4e-6, (rows, cols)).astype(np.float32)
    yy, xx = np.mgrid[0:rows, 0:cols]
    x, y = ORIGIN[0] + (xx + 0.5) * RES, ORIGIN[1] + (yy + 0.5) * RES
    crack_x = 0.425 + 0.05 * y
    inside = np.abs(y) < 0.012
    h -= np.where(inside, 60e-6 * np.exp(-4 * math.log(2) * ((x - crack_x) / 2.5e-4) ** 2), 0).astype(np.float32)
    for cx, cy, depth in ((0.41, -0.01, 50e-6), (0.44, 0.01, -50e-6)):
        r = np.hypot(x - cx, y - cy)
        h -= (depth * np.where(r < 1e-3, 0.5 * (1 + np.cos(np.pi * r / 1e-3)), 0)).astype(np.float32)
    return h


def world_of(h):
    rows, cols = h.shape
    bounds = (ORIGIN[0], ORIGIN[1], ORIGIN[0] + (cols - 0.1) * RES, ORIGIN[1] + (rows - 0.1) * RES)
    camera = CameraModel(fx=200.0, fy=200.0, cx=159.5, cy=119.5, width=320, height=240)
    world = WorldMapper(camera, lambda stamps: np.zeros((len(stamps), 4, 4)),
                        WorldMapConfig(resolution=RES, bounds=bounds, tiles=TileConfig(tile=128)))
    config = WorldHeightConfig(min_weight=0.5)
    world.height_source = SimpleNamespace(config=config)     # what the map's readers look at: its config
    world._height_layer = HeightLayer(config)
    HeightLayer.add_layers(world.canvas)
    return world


def roll(world, h, r0, r1, offset):
    """Rows [r0, r1) of the canvas rolled by one pass (all columns), pressed `offset` deep."""
    part = np.ascontiguousarray(h[r0:r1]) + np.float32(offset)
    ones = np.ones_like(part)
    world.canvas.add([128 * ones, ones, ones], 0, r0)
    world.canvas.add_named({PASS: part, PASS_W: ones}, 0, r0)


def kinds(found):
    return sorted(f.kind for f in found)


def test_during_the_first_pass_the_window_is_the_pass_s_own_height():
    h = relief()
    world = world_of(h)
    source = MapWindows(world)
    assert source.layer == "intensity"          # nothing has a height yet
    roll(world, h, 0, 250, PRESS)
    assert source.layer == "height" and world.height_view() is None   # the pass has not ended
    values, origin = source.window((0, 400, 0, 500))
    assert origin == pytest.approx(ORIGIN)
    rolled = values[::-1]
    assert np.isnan(rolled[250:]).all()
    np.testing.assert_allclose(rolled[:250], h[:250] + PRESS, atol=1e-9)
    found = inspect(values, RES, origin).findings
    assert kinds(found) == ["crack", "dent"] and all(math.isfinite(f.depth_m) for f in found)


def test_the_pass_being_rolled_is_moved_onto_the_finished_passes_no_step_along_the_seam():
    h = relief()
    world = world_of(h)
    roll(world, h, 0, 250, PRESS)
    world._height_layer.end_pass(world.canvas)            # levelled: its plane (the press depth) removed
    roll(world, h, 150, 400, 2 * PRESS)                   # the next pass, pressed otherwise, rolling
    values, origin = MapWindows(world).window((0, 400, 0, 500))
    off = values[::-1] - h
    assert np.isfinite(off).all()
    assert float(np.ptp(off)) < 2e-6                      # one surface: the 0.5 mm press step is gone
    found = inspect(values, RES, origin).findings
    # the crack across the seam is one, whole; nothing along the seam
    assert kinds(found) == kinds(inspect(h[::-1].copy(), RES, ORIGIN).findings) == ["bump", "crack", "dent"]
    crack = next(f for f in found if f.kind == "crack")
    assert crack.length_m == pytest.approx(0.024 * math.hypot(1, 0.05), rel=0.1)
