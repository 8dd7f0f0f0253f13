"""Planted defects (`surface.defects`): the plan, its rendering into any window of the grid, its truth in the
findings' conventions (which the detector measures back from the simulator's own surface), and bad specs."""
from __future__ import annotations

import math

import numpy as np
import pytest

from touchroller_driver.sim.camera import surface_frame
from touchroller_driver.sim.defects import plan_defects, surface_defects
from touchroller_driver.sim.scene import load_scene
from touchroller_driver.sim.surfaces import make_surface
from touchroller_perception.inspection import inspect

SPEC = {"seed": 4, "cracks": 3, "dents": 2, "bumps": 2, "crack_width": [1.5e-4, 4e-4],
        "crack_depth": [3e-5, 1e-4], "crack_length": [6e-3, 1.2e-2], "blob_diameter": [1.5e-3, 3e-3],
        "blob_depth": [3e-5, 1e-4]}
SURFACE = {"kind": "flat", "width": 0.05, "length": 0.04, "resolution": 5e-5, "defects": SPEC}


def test_a_scene_plants_what_it_asks_for_within_the_limits_and_the_same_each_time():
    plan = surface_defects(SURFACE)
    assert len(plan.cracks) == 3 and sorted(b.depth_m > 0 for b in plan.blobs) == [False, False, True, True]
    again = surface_defects(SURFACE)
    for a, b in zip(plan.cracks, again.cracks, strict=True):
        np.testing.assert_array_equal(a.lines[0], b.lines[0])
    for crack in plan.cracks:
        assert 1.5e-4 <= crack.widths[0] <= 4e-4 and 6e-3 * 0.999 <= crack.length_m <= 1.2e-2 * 1.001
        # the depth varies along the crack and tapers to nothing at its ends
        depths = crack.depths[0]
        assert depths[0] == 0 and depths[-1] == 0 and np.ptp(depths[len(depths) // 4: -len(depths) // 4]) > 0
    other = surface_defects({**SURFACE, "defects": {**SPEC, "seed": 5}})
    assert not np.allclose(other.cracks[0].lines[0][:10], plan.cracks[0].lines[0][:10])


def test_no_defects_is_an_empty_plan_and_the_surface_unchanged():
    plain = {k: v for k, v in SURFACE.items() if k != "defects"}
    assert not surface_defects(plain) and not surface_defects({**plain, "defects": {}})
    assert float(np.abs(make_surface(plain, np.random.default_rng(0)).height).max()) == 0
    planted = make_surface(SURFACE, np.random.default_rng(0))
    assert planted.height.min() < -2e-5 and "planted 3 crack(s), 4 dent(s)/bump(s)" in planted.description


def test_rendered_by_tiles_the_surface_is_the_same_as_rendered_whole():
    """A lazily tiled surface draws each tile on its own: the defects cross tile borders seamlessly."""
    plan = surface_defects(SURFACE)
    rows, cols, res, x0, y0 = 800, 1000, 5e-5, -0.025, 0.0
    whole = np.zeros((rows, cols), np.float32)
    plan.render(whole, x0, y0, res)
    tiled = np.zeros_like(whole)
    for r in range(0, rows, 300):
        for c in range(0, cols, 350):
            tile = tiled[r:r + 300, c:c + 350]
            plan.render(tile, x0 + c * res, y0 + r * res, res)
    np.testing.assert_allclose(tiled, whole, atol=1e-9)
    assert whole.min() < -2e-5 and whole.max() > 2e-5   # depressions below the base plane, bumps above


def test_the_detector_measures_the_truth_back_from_the_simulators_own_surface():
    """Like with like: the planted truth's conventions (centroid, width at half depth, median depth, length
    along the trunk, a dent's diameter at half depth) are the detector's."""
    surface = make_surface({**SURFACE, "kind": "panel", "cracks": 0, "dents": 0}, np.random.default_rng(1))
    truth = surface_defects(SURFACE).truth()
    h = surface.height[::-1]      # image rows: row 0 the largest y
    h = h.reshape(h.shape[0] // 2, 2, h.shape[1] // 2, 2).mean(axis=(1, 3))   # 0.1 mm pixels
    found = inspect(h, 1e-4, (surface.x0, surface.y0)).findings
    assert len(found) == len(truth)
    for t in truth:
        f = min(found, key=lambda f: math.hypot(f.x - t.x, f.y - t.y))
        assert f.kind == t.kind and math.hypot(f.x - t.x, f.y - t.y) < 3e-4, (t, f)
        assert f.depth_m == pytest.approx(t.depth_m, rel=0.2)
        if t.kind == "crack":
            assert abs(f.width_m - t.width_m) < 5e-5 and f.length_m == pytest.approx(t.length_m, rel=0.1)
        else:
            assert f.width_m == pytest.approx(t.width_m, rel=0.25)


def test_the_truth_in_the_world_frame_follows_the_scenes_placement():
    scene = load_scene("inspection_panel")
    plan = surface_defects(scene.surface)
    in_s, in_world = plan.truth(), plan.truth(surface_frame(scene))
    origin = scene.world["surface_origin"]
    for s, w in zip(in_s, in_world, strict=True):
        # yaw 0: the surface's x (across the roller) is world y, its y (along the roll) world x
        assert (w.x, w.y) == pytest.approx((origin[0] + s.y, origin[1] + s.x), abs=1e-9)
        assert w.length_m == s.length_m and w.kind == s.kind
    assert {f.kind for f in in_world} == {"crack", "dent", "bump"}


@pytest.mark.parametrize("bad, words", [
    ({"cracks": -1}, "cracks must be a count"),
    ({"crack_width": [1e-5, 1e-4]}, "crack_width must be [min, max]"),
    ({"blob_depth": [1e-4, 5e-5]}, "blob_depth must be [min, max]"),
    ({"crack": 2}, "unknown key(s) crack"),
    ({"area": [0.1, 0.1, 0.2, 0.2]}, "leaves no room"),
])
def test_a_bad_spec_is_one_clear_line(bad, words):
    with pytest.raises(ValueError) as error:
        plan_defects({**SPEC, **bad}, (-0.025, 0.0, 0.025, 0.04), 5e-5)
    assert words in str(error.value) and "\n" not in str(error.value)


def test_a_scene_with_a_bad_defects_block_is_refused_when_loaded():
    with pytest.raises(ValueError, match="scene inspection_panel: surface.defects.cracks"):
        load_scene("inspection_panel", **{"surface.defects.cracks": "many"})
