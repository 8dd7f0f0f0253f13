"""Live findings: a growing world map inspected region by region, stable ids, deletions, and the markers."""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import pytest

from touchroller_bringup.live_findings import MARKERS_PER_FINDING, LiveFindings, LiveFindingsConfig, label, markers
from touchroller_perception.inspection import Finding, InspectionConfig

RES = 1e-4
ORIGIN = (0.40, -0.02)


@dataclass
class MapImage:      # a WorldMapImage with the height layer the world height map adds
    grey: np.ndarray
    alpha: np.ndarray
    resolution: float
    origin: tuple[float, float]
    height: np.ndarray | None = None


def panel(shape=(400, 600), seed=0):
    """Height (m) with a crack along x across the map's middle and a dent and a bump; row 0 the top."""
    rng = np.random.default_rng(seed)
    h = rng.normal(0, 0.4e-6, shape).astype(np.float32)
    rows, cols = shape
    yy, xx = np.mgrid[0:rows, 0:cols]
    x, y = ORIGIN[0] + (xx + 0.5) * RES, ORIGIN[1] + (rows - yy - 0.5) * RES
    crack_y = -0.005 + 0.05 * (x - 0.43)
    inside = (x > 0.410) & (x < 0.450)
    h -= np.where(inside, 60e-6 * np.exp(-4 * math.log(2) * ((y - crack_y) / 2.5e-4) ** 2), 0).astype(np.float32)
    for cx, cy, depth in ((0.415, 0.010, 50e-6), (0.445, 0.010, -50e-6)):
        r = np.hypot(x - cx, y - cy)
        h -= (depth * np.where(r < 1e-3, 0.5 * (1 + np.cos(np.pi * r / 1e-3)), 0)).astype(np.float32)
    return h


def image(h, mapped):
    return MapImage(np.full(h.shape, 128, np.uint8), np.where(mapped, 255, 0).astype(np.uint8), RES, ORIGIN,
                    np.where(mapped, h, np.nan).astype(np.float32))


def test_the_map_grows_and_findings_keep_their_ids_until_they_are_gone():
    h = panel()
    cols = h.shape[1]
    live = LiveFindings(LiveFindingsConfig(period_s=1.0, reach_m=5e-3, margin_m=7.5e-3))
    left = np.zeros(h.shape, bool)
    left[:, : cols * 2 // 3] = True      # the first pass: the dent and most of the crack
    first = live.update(image(h, left), now_s=10.0)
    assert first is not None and first.layer == "height"
    kinds = {f.kind: f for f in first.findings}
    assert set(kinds) == {"crack", "dent"} and first.removed == []
    assert kinds["dent"].x == pytest.approx(0.415, abs=2e-4) and kinds["dent"].depth_m > 0
    assert live.update(image(h, np.ones(h.shape, bool)), now_s=10.5) is None    # within the period
    assert live.update(image(h, left), now_s=20.0) is None                       # nothing new mapped
    second = live.update(image(h, np.ones(h.shape, bool)), now_s=20.0)
    assert second is not None and second.removed == []
    now = {f.kind: f for f in second.findings}
    assert set(now) == {"crack", "dent", "bump"}
    # the crack, mapped whole now, is the same finding (same id), measured longer
    assert now["crack"].id == kinds["crack"].id and now["crack"].length_m > kinds["crack"].length_m + 5e-3
    assert now["crack"].length_m == pytest.approx(0.04 * math.hypot(1, 0.05), rel=0.1)
    assert now["dent"].id == kinds["dent"].id and now["bump"].id not in (kinds["crack"].id, kinds["dent"].id)
    # the map grows to the left (its origin moves) and the dent's place is re-mapped smooth: the dent is gone
    grown = np.pad(h, ((0, 0), (50, 0)))
    rows = grown.shape[0]
    yy, xx = np.mgrid[0:rows, 0:grown.shape[1]]
    x = ORIGIN[0] - 50 * RES + (xx + 0.5) * RES
    y = ORIGIN[1] + (rows - yy - 0.5) * RES
    grown[np.hypot(x - 0.415, y - 0.010) < 1.5e-3] = 0.0
    moved = MapImage(np.full(grown.shape, 128, np.uint8), np.full(grown.shape, 255, np.uint8), RES,
                     (ORIGIN[0] - 50 * RES, ORIGIN[1]), grown)
    third = live.update(moved, now_s=30.0)      # only the new strip (and what reaches into it) is inspected
    assert third is not None and third.removed == [] and {f.kind for f in third.findings} == set(now)
    finished = live.update(moved, now_s=30.1, force=True, whole=True)   # the finished map: all of it
    assert finished is not None and finished.removed == [kinds["dent"].id]
    assert {f.kind for f in finished.findings} == {"crack", "bump"}
    assert live.reset() == sorted(f.id for f in finished.findings) and live.findings == {}


def test_without_a_height_layer_the_intensity_is_inspected_and_depths_are_unknown():
    h = panel()
    gy, gx = np.gradient(h.astype(np.float64), RES)
    noise = np.random.default_rng(1).normal(0, 0.5, h.shape)
    grey = np.clip(np.rint(128 + 400 * (0.8 * gx + 0.6 * gy) + noise), 0, 255).astype(np.uint8)
    shown = MapImage(grey, np.full(h.shape, 255, np.uint8), RES, ORIGIN)
    update = LiveFindings().update(shown, now_s=0.0)
    assert update is not None and update.layer == "intensity"
    crack = [f for f in update.findings if f.kind == "crack"]
    assert len(crack) == 1 and all(math.isnan(f.depth_m) for f in update.findings)
    assert len(update.findings) == 3, update.findings


def test_the_declared_blur_reaches_the_detector():
    # findings.blur (LiveFindingsConfig.blur_m) is what the live detector and the scan's own inspection use
    h = panel()
    mapped = np.ones(h.shape, bool)
    plain = {f.kind: f for f in LiveFindings().update(image(h, mapped), 0.0).findings}
    live = LiveFindings(LiveFindingsConfig(blur_m=0.2e-3))
    assert live.inspection_config().blur_fwhm_m == pytest.approx(0.2e-3)
    blurred = {f.kind: f for f in live.update(image(h, mapped), 0.0).findings}
    assert blurred["crack"].width_m < plain["crack"].width_m - 0.05e-3
    assert blurred["crack"].depth_m > plain["crack"].depth_m


def test_a_timer_of_the_same_period_with_jitter_is_never_skipped():
    # the node's map timer fires once per findings.period, a few ms late or early: every tick inspects
    h = panel()
    cols = h.shape[1]
    live = LiveFindings(LiveFindingsConfig(period_s=1.0))
    ticks = [10.004, 10.998, 12.003, 12.996, 14.0]
    done = []
    for k, now in enumerate(ticks):
        mapped = np.zeros(h.shape, bool)
        mapped[:, : cols * (k + 1) // len(ticks)] = True        # a strip more at every tick
        done.append(live.update(image(h, mapped), now_s=now) is not None)
    assert done == [True] * len(ticks)
    assert live.update(image(h, np.ones(h.shape, bool)), now_s=14.5) is None     # still at most once a period


def test_disabled_does_nothing():
    h = panel()
    assert LiveFindings(LiveFindingsConfig(enabled=False)).update(image(h, np.ones(h.shape, bool)), 0.0) is None


@pytest.mark.parametrize("field, value", [("period_s", -1.0), ("reach_m", math.nan), ("text_size_m", 0.0)])
def test_a_bad_configuration_is_refused(field, value):
    with pytest.raises(ValueError, match=field):
        LiveFindingsConfig(**{field: value})


def test_markers_draw_each_finding_in_the_map_frame_with_stable_ids_and_delete_the_gone():
    pytest.importorskip("visualization_msgs")
    from visualization_msgs.msg import Marker

    crack = Finding(3, "crack", 0.42, 0.01, 0.012, 2.5e-4, 60e-6, 3e-6, 0.99,
                    polylines=(((0.414, 0.01), (0.426, 0.01)), ((0.42, 0.01), (0.422, 0.013))))
    bump = Finding(5, "bump", 0.44, 0.0, 1e-3, 0.9e-3, -40e-6, 7e-7, 0.9,
                   polygon=((0.4395, 0.0), (0.44, 0.0005), (0.4405, 0.0), (0.4395, 0.0)))
    array = markers([crack, bump], [7], "base", None, 0.05, LiveFindingsConfig())
    by_id = {m.id: m for m in array.markers}
    assert all(m.header.frame_id == "base" and m.ns == "findings" for m in array.markers)
    trunk, branch = by_id[MARKERS_PER_FINDING * 3], by_id[MARKERS_PER_FINDING * 3 + 2]
    assert trunk.type == branch.type == Marker.LINE_STRIP and trunk.action == Marker.ADD
    assert [(p.x, p.y, p.z) for p in trunk.points] == [(0.414, 0.01, 0.05), (0.426, 0.01, 0.05)]
    assert trunk.scale.x == pytest.approx(2.5e-4)
    # the crack's other branch slots are deleted (a branch it had before is gone from RViz)
    assert all(by_id[MARKERS_PER_FINDING * 3 + k].action == Marker.DELETE for k in range(3, MARKERS_PER_FINDING))
    disc = by_id[MARKERS_PER_FINDING * 5]
    assert disc.type == Marker.CYLINDER and (disc.pose.position.x, disc.pose.position.y) == (0.44, 0.0)
    assert disc.scale.x == disc.scale.y == pytest.approx(1e-3)
    text = by_id[MARKERS_PER_FINDING * 5 + 1]
    assert text.type == Marker.TEXT_VIEW_FACING and text.text == label(bump) == "#5 bump 0.9 mm, 40 um high"
    assert label(crack) == "#3 crack 12.0 x 0.25 mm, 60 um deep"
    gone = [m for m in array.markers if MARKERS_PER_FINDING * 7 <= m.id < MARKERS_PER_FINDING * 8]
    assert len(gone) == MARKERS_PER_FINDING and all(m.action == Marker.DELETE for m in gone)


def _world_of(h, tile=128, provisional=False):
    """A world map over the panel's cells (the map's own grid) with the world height's layers
    (`world_height.HeightLayer`) and nothing mapped yet. `roll(c0, c1)` maps columns [c0, c1) into the pass
    being rolled (its height as the pass's weighted sums, `offset` m added: the pass's press depth, which its
    end levels away); `end_pass()` ends the pass (levelled and added to the finished passes)."""
    from types import SimpleNamespace

    from touchroller_perception.geometry import CameraModel
    from touchroller_perception.tiles import TileConfig as StoreConfig
    from touchroller_perception.world_height import PASS, PASS_W, HeightLayer, WorldHeightConfig
    from touchroller_perception.world_map import WorldMapConfig, WorldMapper

    camera = CameraModel(fx=200.0, fy=200.0, cx=159.5, cy=119.5, width=320, height=240)
    rows, cols = h.shape
    bounds = (ORIGIN[0], ORIGIN[1], ORIGIN[0] + (cols - 0.1) * RES, ORIGIN[1] + (rows - 0.1) * RES)
    world = WorldMapper(camera, lambda stamps: np.zeros((len(stamps), 4, 4)),
                        WorldMapConfig(resolution=RES, bounds=bounds, tiles=StoreConfig(tile=tile),
                                       provisional=provisional))
    assert world.canvas.shape == h.shape and world.canvas.origin == pytest.approx(ORIGIN, abs=1e-9)
    config = WorldHeightConfig(min_weight=0.5)
    world.height_source = SimpleNamespace(config=config)     # what the map's readers look at: its config
    world._height_layer = HeightLayer(config)
    HeightLayer.add_layers(world.canvas)

    def roll(c0, c1, r0=0, r1=None, offset=0.0):   # rows grow with y in the canvas
        part = np.ascontiguousarray(h[::-1][r0:r1, c0:c1]) + np.float32(offset)
        ones = np.ones_like(part)
        world.canvas.add([128 * ones, ones, ones], c0, r0)
        world.canvas.add_named({PASS: part, PASS_W: ones}, c0, r0)

    def end_pass():
        world._height_layer.end_pass(world.canvas)

    roll.end_pass = end_pass
    return world, roll


def _same(a, b):
    assert [(f.id, f.kind) for f in a] == [(f.id, f.kind) for f in b]
    for f, g in zip(a, b, strict=True):
        assert (f.x, f.y) == pytest.approx((g.x, g.y), abs=1e-6) and f.length_m == pytest.approx(g.length_m, rel=1e-3)


def test_from_the_tiles_the_findings_are_those_of_the_map_image_without_reading_the_whole_map(monkeypatch):
    """The live findings read from a world map's tiles (what the perception node does): the new cells found in
    the tiles touched, the region read as one window, never `map_image`; the same findings, ids and
    removals as inspecting the map image."""
    from touchroller_perception.map_windows import MapWindows
    from touchroller_perception.world_map import WorldMapper

    h = panel()
    cols = h.shape[1]
    world, roll = _world_of(h)

    def whole_map(*args, **kwargs):
        raise AssertionError("the live findings read the whole map")

    monkeypatch.setattr(WorldMapper, "map_image", whole_map)
    windows: list = []
    source = MapWindows(world)
    read = source.window
    monkeypatch.setattr(source, "window", lambda box: windows.append(box) or read(box))
    config = LiveFindingsConfig(period_s=1.0, reach_m=5e-3, margin_m=7.5e-3)
    tiles, images = LiveFindings(config), LiveFindings(config)
    left = np.zeros(h.shape, bool)
    left[:, : cols * 2 // 3] = True
    roll(0, cols * 2 // 3)
    tiles.note(world.touched_tiles())
    first = tiles.update_tiles(source, now_s=10.0)
    assert first is not None and first.layer == "height"
    _same(first.findings, images.update(image(h, left), now_s=10.0).findings)
    assert {f.kind for f in first.findings} == {"crack", "dent"}
    assert tiles.update_tiles(source, now_s=20.0) is None   # nothing new mapped
    roll(cols * 2 // 3, cols)
    tiles.note(world.touched_tiles())
    second = tiles.update_tiles(source, now_s=20.0)
    expected = images.update(image(h, np.ones(h.shape, bool)), now_s=20.0)
    _same(second.findings, expected.findings)
    assert second.removed == expected.removed == [] and {f.kind for f in second.findings} == {"crack", "dent", "bump"}
    # the first window: the first two thirds with the reach and margin beyond them, not the whole canvas
    assert windows[0][2] == 0 and windows[0][3] == cols * 2 // 3 + 125
    finished = tiles.update_tiles(source, now_s=30.0, force=True, whole=True)
    _same(finished.findings, images.update(image(h, np.ones(h.shape, bool)), 30.0, force=True, whole=True).findings)


def test_a_large_finished_map_is_inspected_window_by_window_and_a_crack_across_windows_is_measured_whole(
        monkeypatch):
    """Past `WHOLE_CELLS` the finished map is inspected in windows (here 128 cells square over a 400 x 600
    map): each window read alone (memory for a window and the findings reaching into it), the crack that
    crosses four of them one finding, as long as inspecting the whole map at once measures it."""
    from touchroller_bringup import live_findings
    from touchroller_bringup.scan_findings import inspect_map, inspect_world
    from touchroller_perception.map_windows import MapWindows

    h = panel()
    world, roll = _world_of(h)
    roll(0, h.shape[1])
    whole = inspect_map(image(h, np.ones(h.shape, bool)))
    assert inspect_world(world).findings == whole.findings   # a map within WHOLE_CELLS: as one window
    # the declared blur (findings.blur) reaches the scan's final inspection as it reaches the live one's
    blurred = inspect_map(image(h, np.ones(h.shape, bool)), InspectionConfig(blur_fwhm_m=4e-4))
    assert blurred.findings != whole.findings
    assert inspect_world(world, blur_m=4e-4).findings == blurred.findings
    monkeypatch.setattr(live_findings, "WHOLE_CELLS", 10_000)
    monkeypatch.setattr(live_findings, "WINDOW_CELLS", 128)
    sizes: list = []
    read = MapWindows.window
    monkeypatch.setattr(MapWindows, "window", lambda self, box: sizes.append((box[1] - box[0]) * (box[3] - box[2]))
                        or read(self, box))
    found = inspect_world(world)
    # 4 x 5 windows, each its 128 cells and the margin around (larger where a finding reaching into it is
    # measured again whole)
    assert len(sizes) == 20 and max(sizes) < h.size and float(np.median(sizes)) < h.size / 4
    assert sorted(f.kind for f in found.findings) == ["bump", "crack", "dent"]
    crack = next(f for f in found.findings if f.kind == "crack")
    expected = next(f for f in whole.findings if f.kind == "crack")
    assert crack.length_m == pytest.approx(expected.length_m, rel=0.05)
    assert found.result.diagnostics.valid_pixels > 0


def test_frames_placed_for_good_after_a_provisional_placement_are_inspected_again_where_they_lie():
    """Frames waiting for the latency estimate are placed provisionally (0.4 mm along the roll off, the
    fallback latency's error) and inspected there; when they are placed for good, what the live findings saw
    of them is looked at again, so the dent far from the few cells that are new lies where it is, not where
    the provisional placement put it, before the map is finished."""
    from touchroller_perception.map_windows import MapWindows
    from touchroller_perception.world_map import PROVISIONAL_LAYERS

    h = panel()
    rows, cols = h.shape
    world, roll = _world_of(h, provisional=True)
    live_band, live_flat, live_weight, live_height, live_height_w = PROVISIONAL_LAYERS
    part = np.ascontiguousarray(h[::-1, : cols - 4])
    ones = np.ones_like(part)
    world.canvas.add_named({live_band: 128 * ones, live_flat: ones, live_weight: ones, live_height: part,
                            live_height_w: ones}, 4, 0)
    world._provisional_frames = 1
    live = LiveFindings(LiveFindingsConfig(period_s=1.0, reach_m=5e-3, margin_m=7.5e-3))
    live.note(world.touched_tiles())
    first = live.update_tiles(MapWindows(world), now_s=10.0)
    dent = next(f for f in first.findings if f.kind == "dent")
    assert dent.x == pytest.approx(0.4154, abs=1e-4)      # where the provisional placement put it
    world._clear_provisional()                            # the estimate came: placed for good
    roll(0, cols)
    live.note(world.touched_tiles())
    second = live.update_tiles(MapWindows(world), now_s=20.0)
    moved = next(f for f in second.findings if f.kind == "dent")
    assert moved.id == dent.id and moved.x == pytest.approx(0.415, abs=1e-4)
