"""A world map read a window at a time for inspection: the height during a pass (the pass being rolled, not
yet levelled, moved onto the finished passes) and after it."""
from __future__ import annotations

import importlib.util
import math
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest

from touchroller_perception.geometry import CameraModel
from touchroller_perception.inspection import inspect
from touchroller_perception.map_windows import MapWindows
from touchroller_perception.tiles import TileConfig
from touchroller_perception.world_height import PASS, PASS_W, HeightLayer, WorldHeightConfig
from touchroller_perception.world_map import WorldMapConfig, WorldMapper

_spec = importlib.util.spec_from_file_location(
    "sim_scans", Path(__file__).parents[1] / "touchroller_driver" / "sim" / "sim_scans.py")
assert _spec is not None and _spec.loader is not None
sim_scans = importlib.util.module_from_spec(_spec)
_spec.loader.exec_module(sim_scans)

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


def _one_pass(provisional: bool):
    """A 3 cm pass over the grained surface filmed 35 ms late and mapped with the latency estimated (frames
    wait for the estimate), pushed frame by frame: per frame, the frames placed for good and the cells a live
    reader (`MapWindows`) sees mapped; and the mapper, not finalised."""
    sensor = sim_scans.large_surface(seed=0)
    plan = sim_scans.raster((0.42, -0.045, 0.03, 0.04))
    world, buffer = sim_scans.world_mapper(sensor.camera, WorldMapConfig(bounds=(0.40, -0.07, 0.47, 0.03),
                                                                         provisional=provisional))
    seen = []
    for event in sim_scans.sweep(sensor, plan, latency_s=0.035):
        if not sim_scans.feed(world, buffer, event):
            continue
        source = MapWindows(world)
        tiles = world.canvas.store.tiles("weight") | (world.canvas.store.tiles("live_weight") if provisional
                                                        else set())
        cells = sum(int(np.count_nonzero(source.mapped_tile(ix, iy))) for ix, iy in tiles)
        seen.append((world.stats.mapped, cells))
    return world, seen


def test_frames_waiting_for_the_latency_estimate_are_read_provisionally_and_never_reach_the_map():
    """With the latency being estimated, frames wait for the estimate (a pass's end here); placed meanwhile
    with the fallback latency on layers of their own, a live reader sees them, and once the estimate comes
    they are placed for good and the provisional layers emptied: the map is the one made without them."""
    live, seen = _one_pass(provisional=True)
    plain, seen_plain = _one_pass(provisional=False)
    waited = [cells for mapped, cells in seen if mapped == 0 and cells > 0]
    assert len(waited) >= 20                               # read live while nothing was placed for good
    assert not any(cells for mapped, cells in seen_plain if mapped == 0)   # without: nothing to read
    assert [mapped for mapped, _ in seen] == [mapped for mapped, _ in seen_plain]
    for world in (live, plain):
        world.finalise()
    assert live.replacements >= 1 and live._provisional_frames == 0
    assert not any(live.canvas.store.tiles(name) for name in ("live_band", "live_flat", "live_weight"))
    assert live.stats.latency_estimated and live.stats.mapped == plain.stats.mapped > 0
    box = live.canvas.used()
    for name in ("band", "flat", "weight"):                # the map: to the bit, the one made without them
        assert np.array_equal(live.canvas.read(name, box), plain.canvas.read(name, box))
