"""bench.calib_lighting: its result round-trips through its JSON, and the report's goal rows read it."""
from __future__ import annotations

import math

from bench import calib_lighting as lighting
from bench._common import provenance, to_json
from touchroller_bringup import report


def _trial(renderer: str, azimuth: float, seed: int, theta: float, refused: str = "",
           plain_solves: bool = True, theta_no_dark: float | None = None) -> lighting.Trial:
    nan = math.nan
    if refused:
        return lighting.Trial(renderer, azimuth, seed, refused, plain_solves, nan, nan, nan, nan, nan, nan, nan, "",
                              False, nan, nan, False, ())
    return lighting.Trial(renderer, azimuth, seed, "", True, theta, 0.01, 0.05, 0.01, 0.2,
                          theta if theta_no_dark is None else theta_no_dark, 0.01,
                          "terms chosen by held-out prediction", True, 0.3, 0.02, False,
                          ("row balance: kept, held-out margin +0.300 px (> 2 x spread 0.020 px, 10 presses "
                           "left out in turn)",), 0.05, 0.01)


def _result(trials) -> lighting.LightingResult:
    return lighting.LightingResult(provenance("calib_lighting", True), True, 1, 10, tuple(trials))


def test_the_result_round_trips_through_its_json(tmp_path):
    result = _result([_trial(r, a, 0, 0.02) for r in lighting.RENDERERS for a in lighting.AZIMUTHS])
    path = tmp_path / "calib_lighting.json"
    path.write_text(to_json(result))
    loaded = lighting.load(path)
    assert loaded == result
    assert loaded.met() and len(loaded.cells()) == 12
    text = lighting.to_markdown(loaded)
    assert "| simulator | 90° | 0.020 |" in text and "row balance: kept, held-out margin" in text


def test_the_recorded_run_has_its_title_and_the_json_the_report_reads(tmp_path, monkeypatch, capsys):
    result = _result([_trial(r, a, 0, 0.02) for r in lighting.RENDERERS for a in lighting.AZIMUTHS])
    monkeypatch.setattr(lighting, "run", lambda quick, progress, jobs: result)
    monkeypatch.setattr(lighting, "results_path", lambda name, quick: tmp_path / f"{name}.md")
    monkeypatch.setattr("sys.argv", ["calib_lighting", "--quick"])
    assert lighting.main() == 0
    out = tmp_path / "calib_lighting.md"
    assert out.read_text() == f"# Calibration under light from one side\n\n{lighting.to_markdown(result)}"
    assert lighting.load(out.with_suffix(".json")) == result

def test_the_goal_rows_fail_on_a_seed_off_or_a_refusal_the_plain_method_would_not_make():
    goals = [g for g in report.GOALS if g.section == "calib_lighting"]
    assert len(goals) == 7
    good = _result([_trial(lighting.SECOND, 0.0, 0, 0.05), _trial(lighting.SIMULATOR, 90.0, 0, -0.08)])
    assert all(g.measure(good)[1] for g in goals if g.measure is not None)
    off = _result([_trial(lighting.SECOND, 0.0, 0, 0.15), _trial(lighting.SIMULATOR, 90.0, 0, 0.0)])
    theta_text, theta_met = goals[0].measure(off)
    assert not theta_met and "second renderer: worst 0.150°" in theta_text
    refused = _result([_trial(lighting.SECOND, 0.0, 0, 0.0), _trial(lighting.SIMULATOR, 0.0, 0, 0.0, "only 0 of 10")])
    text, met = goals[4].measure(refused)
    assert not met and "1 of 2 sets refused (1 where the plain method solves)" in text
    assert not refused.met()


def test_a_seed_off_without_the_lights_off_frame_fails_its_own_goal_row():
    goals = [g for g in report.GOALS if g.section == "calib_lighting"]
    off = _result([_trial(lighting.CENTRED, 270.0, 0, 0.05, theta_no_dark=-0.22),
                   _trial(lighting.SIMULATOR, 90.0, 0, 0.0)])
    assert goals[0].measure(off)[1]
    text, met = goals[2].measure(off)
    assert not met and f"{lighting.CENTRED}: worst 0.220°" in text
    assert not off.met()


def test_sigmas_without_the_lights_off_frame_have_their_own_coverage_row():
    goals = [g for g in report.GOALS if g.section == "calib_lighting"]
    covered = _result([_trial(lighting.SECOND, 0.0, seed, 0.05) for seed in range(20)])
    assert goals[6].measure(covered)[1] and covered.within_2_sigma(no_dark=True) == (1.0, 40)
    uncovered = _result([_trial(lighting.SECOND, 0.0, seed, 0.05, theta_no_dark=0.2) for seed in range(20)])
    text, met = goals[6].measure(uncovered)
    assert not met and "50 % of 40" in text
    assert goals[5].measure(uncovered)[1]
    assert "| 100 % | 50 % |" in lighting.to_markdown(uncovered)
