"""bench/world_map_grid.py on the second raster generator: the quick grid runs and reads back, the mapper's
summary is parsed, and issue 22's required test: a blended raster with an untold latency through
`touchroller map` is placed where the truth says."""
from __future__ import annotations

import dataclasses
import math
import subprocess
import sys
from pathlib import Path

import pytest

from bench import world_map_grid
from bench.raster_generator import MotionConfig, RasterSpec, generate
from bench.raster_score import parse_map_output, score_map

ROOT = Path(__file__).resolve().parents[2]


def test_the_summary_line_of_touchroller_map_is_read() -> None:
    today = ("295 frames -> map.png + map.yaml (670x1000 px at 0.1 mm, origin (0.3965, -0.0500) m in base); "
             "182 frames mapped in 2 pass(es), camera latency estimated 2.9 ms")
    run = parse_map_output(today + "\n", "", 1.5)
    assert (run.latency_ms, run.latency_estimated, run.warned) == (2.9, True, False)
    assert (run.mapped_frames, run.passes, run.latency_sigma_ms) == (182, 2, None)
    given = parse_map_output(today.replace("estimated 2.9", "given 35.0"), "", 1.0)
    assert (given.latency_ms, given.latency_estimated) == (35.0, False)
    missing = parse_map_output(today.replace("estimated 2.9 ms", "given not found"), "", 1.0)
    assert (missing.latency_ms, missing.latency_estimated) == (None, False)
    sigma = parse_map_output(today.replace("2.9 ms", "35.2 ms ± 0.8 ms (passes)"), "", 1.0)
    assert (sigma.latency_ms, sigma.latency_sigma_ms) == (35.2, 0.8)
    warned = parse_map_output(today, "WARN: camera latency not observable; using 0.0 ms\n", 1.0)
    assert warned.warned


@pytest.fixture(scope="module")
def quick() -> world_map_grid.GridResult:
    return world_map_grid.run(quick=True)


@pytest.mark.slow
def test_the_quick_grid_films_maps_and_scores_every_cell(quick: world_map_grid.GridResult) -> None:
    size = world_map_grid.QUICK
    assert len(quick.cells) == len(size.profiles) * len(size.latencies_ms) * len(size.yaws)
    assert [c.surface for c in quick.surfaces] == [s[0] for s in size.surfaces]
    for cell in quick.cells + quick.surfaces:
        assert cell.frames > 50
        assert cell.map.summary and cell.map.mapped_frames is not None
        assert 0.0 < cell.score.coverage_percent <= 100.0
        assert len(cell.score.pass_residual_mm) == quick.passes
    for cell in quick.cells:   # the grained surface: a real SSIM and measured residuals
        assert -1.0 <= cell.score.ssim <= 1.0
        assert all(math.isfinite(dx) for dx, _ in cell.score.pass_residual_mm)
    markdown = world_map_grid.to_markdown(quick)
    assert "second raster generator" in markdown and "touchroller_driver.sim" in markdown
    assert markdown.count("| grained |") == len(quick.cells)
    assert len(world_map_grid.goals(quick)) >= 7


@pytest.mark.slow
def test_the_reports_goal_rows_read_the_grid(quick: world_map_grid.GridResult) -> None:
    from touchroller_bringup.report import GOALS, SECTIONS

    assert "world_map_grid" in {s.key for s in SECTIONS}
    rows = [goal for goal in GOALS if goal.section == "world_map_grid"]
    assert len(rows) == len(world_map_grid.goals(quick)) == 9
    for goal in rows:
        figure, met = goal.measure(quick)
        assert "second raster generator" in figure and "second generator" in goal.text
        assert met in (True, False, None)
    weave = next(goal for goal in rows if "weave" in goal.text)
    assert weave.measure(quick)[1] is None        # the quick run has no weave raster: no verdict, not a pass


@pytest.mark.slow
def test_the_recorded_result_reads_back(quick: world_map_grid.GridResult, tmp_path: Path) -> None:
    from bench._common import to_json

    path = tmp_path / "world_map_grid.json"
    path.write_text(to_json(quick, indent=1))
    back = world_map_grid.load(path)
    assert world_map_grid.to_markdown(back) == world_map_grid.to_markdown(quick)


def test_a_cell_is_judged_on_its_estimate_not_on_a_given_value() -> None:
    cell = world_map_grid.Cell("grained", "blend", 35.0, 0.0, 100,
                               parse_map_output("camera latency given 35.0 ms", "", 1.0),
                               world_map_grid.MapScore(0.97, 100.0, [(0.0, 0.0)], 0.0, 0.0, [], [], math.nan))
    assert cell.latency_error_ms == 0.0
    assert not cell.latency_ok        # every grid raster is observable: the value must be estimated
    estimated = dataclasses.replace(cell, map=parse_map_output("camera latency estimated 37.5 ms", "", 1.0))
    assert estimated.latency_ok
    off = dataclasses.replace(cell, map=parse_map_output("camera latency estimated 38.5 ms", "", 1.0))
    assert not off.latency_ok


@pytest.mark.slow
def test_a_blended_raster_with_an_untold_latency_is_placed_by_touchroller_map(tmp_path: Path) -> None:
    """Issue 22's required test, on the second generator: 2 boustrophedon passes over 6 x 10 cm, touchdown and
    lift-off at 20 mm/s, the speed varying 1 % along a pass, images 35 ms late, /tf at 125 Hz; `touchroller
    map` not told the latency must find it and place every pass where the surface is."""
    spec = RasterSpec(surface="grained", corner=(0.40, -0.05), length=0.06, width=0.10, passes=2, latency=0.035,
                      tf_rate=125.0, motion=MotionConfig(profile="blend"))
    truth = generate(spec, tmp_path / "raster")
    done = subprocess.run([sys.executable, "-m", "touchroller_bringup.cli", "map", str(tmp_path / "raster" / "bag"),
                           "--out", str(tmp_path / "map.png")], capture_output=True, text=True, cwd=ROOT, check=True)
    run = parse_map_output(done.stdout, done.stderr, 0.0)
    assert run.latency_estimated, run.summary
    assert run.latency_ms == pytest.approx(35.0, abs=3.0), run.summary
    score = score_map(tmp_path / "map.yaml", truth)
    assert score.worst_residual_mm <= 0.1, score.pass_residual_mm
    assert score.ssim >= 0.90
    assert score.coverage_percent >= 98.0
