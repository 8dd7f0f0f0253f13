"""bench.calib_centres: its result round-trips through its JSON, and the report's goal rows read it."""
from __future__ import annotations

import numpy as np

from bench import calib_centres as centres
from bench import calib_lighting as lighting
from bench._common import provenance, to_json
from touchroller_bringup import report


def _result(shading_pull: float) -> centres.CentresResult:
    cells = [centres.Cell(r, a, c, 20, {"shading": shading_pull, "symmetric": 0.13, "centroid": -0.4}[c], 0.0, 0.05)
             for r in lighting.RENDERERS for a in lighting.AZIMUTHS for c in centres.ESTIMATORS]
    return centres.CentresResult(provenance("calib_centres", True), True, 1, 3, tuple(cells))


def test_the_result_round_trips_through_its_json(tmp_path):
    result = _result(0.02)
    path = tmp_path / "calib_centres.json"
    path.write_text(to_json(result))
    loaded = centres.load(path)
    assert loaded == result and loaded.met()
    assert "| simulator | 90° | shading | 20 | +0.020 | +0.000 | 0.050 |" in centres.to_markdown(loaded)


def test_a_cell_measures_the_pull_towards_the_light_and_across_it():
    errors = np.array([[0.0, 0.2], [0.0, 0.0]]) + np.array([0.05, 0.0])   # light from +v (90 deg)
    found = centres.cell("simulator", 90.0, "shading", errors)
    assert np.isclose(found.towards_px, 0.1) and np.isclose(found.across_px, -0.05)
    assert np.isclose(found.spread_px, 0.1)


def test_the_goal_rows_fail_when_a_centre_moves_with_the_light():
    goals = [g for g in report.GOALS if g.section == "calib_centres"]
    assert len(goals) == 2
    assert all(g.measure(_result(0.02))[1] for g in goals)
    assert not any(g.measure(_result(0.12))[1] for g in goals)


def test_the_recorded_run_has_its_title_and_the_json_the_report_reads(tmp_path, monkeypatch, capsys):
    result = _result(0.02)
    monkeypatch.setattr(centres, "run", lambda quick, progress: result)
    monkeypatch.setattr(centres, "results_path", lambda name, quick: tmp_path / f"{name}.md")
    monkeypatch.setattr("sys.argv", ["calib_centres", "--quick"])
    assert centres.main() == 0
    out = tmp_path / "calib_centres.md"
    assert out.read_text() == f"# Imprint centres under light from one side\n\n{centres.to_markdown(result)}"
    assert centres.load(out.with_suffix(".json")) == result
