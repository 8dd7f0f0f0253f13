"""bench/scan_square_metre.py: its scene is a lazy panel with planted defects under the raster, and its goal rows
judge the largest side (no scan here: the bench's own quick run is the report's)."""
from __future__ import annotations

import dataclasses

import numpy as np
import yaml

from touchroller_bringup.report import load_bench_script


def test_the_scene_is_a_lazy_panel_with_defects_under_the_whole_raster(tmp_path):
    bench = load_bench_script("scan_square_metre")
    from touchroller_driver.sim import load_scene
    from touchroller_driver.sim.defects import surface_defects
    from touchroller_driver.sim.surfaces import make_surface
    from touchroller_driver.sim.tiled_surface import TiledSurface

    data, (x, y, length, width) = bench.scene_data(1.0)
    path = tmp_path / "scene.yaml"
    path.write_text(yaml.safe_dump(data))
    scene = load_scene(str(path))   # as the camera node loads it: a path, no variant left to apply
    surface = scene.surface
    assert surface["kind"] == "panel" and surface["lazy"] and surface["resolution"] == bench.RESOLUTION
    # the surface (rows along world x from the origin, columns across y centred) holds the raster's area
    ox = scene.data["world"]["surface_origin"][0]
    assert ox <= x and x + length <= ox + surface["length"]
    assert -surface["width"] / 2 <= y and y + width <= surface["width"] / 2
    plan = surface_defects(surface)
    assert len(plan.cracks) >= 8 and len(plan.blobs) >= 8
    # the defects lie across the square (S x across the roller = world y; S y along the roll from the origin)
    centres = np.array([b.centre for b in plan.blobs])
    assert np.ptp(centres[:, 0]) > 0.5 and np.ptp(centres[:, 1]) > 0.5
    small, _ = bench.scene_data(0.06)
    made = make_surface(small["surface"], np.random.default_rng(0))
    assert isinstance(made, TiledSurface) and made.tiles_made == 0


def _case(bench, side, offline_rss, live_rss=600.0, fps=700.0, update_ms=1.2, outcome="done", recorded=15000):
    live = bench.LiveResult(outcome, "", 600.0, 900.0, 15000, 15000, 0, recorded, (1250, 1250), 99.0, 22, live_rss, (),
                            15000, update_ms, 3.0, 4.0, 9.0, 600, 10.0, 50.0, 400, 96, 6000.0, "")
    offline = bench.OfflineResult(0, offline_rss, 14900 / fps, 40.0, 14900, fps, "mapped")
    return bench.CaseResult(side, (10400, 10400), "8 cracks", 50.0, live, offline)


def test_the_goal_rows_judge_the_largest_side_and_a_failed_scan_meets_none():
    bench = load_bench_script("scan_square_metre")
    stamp = bench.Provenance("cmd", "machine", "now", "1.0")
    cases = [_case(bench, 1.0, 560.0), _case(bench, 0.5, 500.0)]
    result = bench.ScanSquareMetreResult(stamp, False, 0.05, cases, 560.0 / 500.0, 1.0, "1.0")
    rows = bench.goals(result)
    assert [met for _, met, _ in rows] == [True, True, True, True, True, True]
    assert "560 MB" in rows[0][2] and "x1.12" in rows[1][2]
    worse = dataclasses.replace(result, offline_rss_ratio=1.3,
                                cases=[_case(bench, 1.0, 650.0, live_rss=1100.0, fps=300.0, update_ms=2.5,
                                             recorded=14900), cases[1]])
    assert [met for _, met, _ in bench.goals(worse)] == [True, False, False, False, False, False]
    assert bench.goals(worse)[5][2] == "14900 of 15000 frames"
    failed = dataclasses.replace(result, cases=[_case(bench, 1.0, 560.0, outcome="timeout"), cases[1]])
    assert not any(met for _, met, _ in bench.goals(failed))
    text = bench.to_markdown(result)
    assert text.count("**Goal:") == 6 and "| 1 | 10400 x 10400 |" in text
    from touchroller_bringup import report

    goals = [g for g in report.GOALS if g.section == "scan_square_metre"]
    assert len(goals) == 6 and all(g.measure(result)[1] for g in goals)
    assert all(g.measure(dataclasses.replace(result, quick=True))[1] is None for g in goals)
