"""bench/table_ii.py: the paper's Table II evaluation harness (error sources, conditions, the paper fit)."""
from __future__ import annotations

import math

import numpy as np
import pytest

from bench.table_ii import (
    TABLE_II_CAMERA,
    ErrorSources,
    membrane_radius,
    sensitivities,
    table_ii,
    table_ii_markdown,
    true_tap_point,
)
from touchroller_perception.contacts import Contact
from touchroller_perception.geometry import CameraModel

# Half-size camera keeps the rendered Table II fast in tests.
SMALL_CAMERA = CameraModel(fx=200.0, fy=200.0, cx=159.5, cy=119.5, distortion=(-0.2, 0, 0, 0, 0),
                           width=320, height=240, theta=0.02, d=0.002)


def _contact(u, v):
    return Contact(u=float(u), v=float(v), area=100.0, confidence=1.0, score=20.0)


def test_sensitivities_match_the_geometry_at_the_centre():
    camera = CameraModel()
    s = sensitivities(camera, camera.surface_point(0.0, 0.0))
    assert s["mm_per_deg_theta"] == pytest.approx(50.0 * math.pi / 180, rel=1e-3)   # r * 1 deg
    assert s["mm_per_mm_d"] == pytest.approx(0.0, abs=1e-3)      # the ray is along z there
    assert s["mm_per_px_u"] == pytest.approx(0.1, rel=1e-3)      # r / fx
    assert s["mm_per_mm_radius"] == pytest.approx(1.0, rel=1e-3)
    off = sensitivities(camera, camera.surface_point(0.02, 0.3))
    assert off["mm_per_mm_d"] > 0.1
    # v = fy tan(alpha): on x = 0 one pixel is r cos^2(alpha) / fy of arc
    per_px = sensitivities(camera, camera.surface_point(0.0, 0.3))["mm_per_px_v"]
    assert per_px == pytest.approx(0.1 * math.cos(0.3) ** 2, rel=1e-3)


def test_uneven_membrane_moves_the_true_point_by_at_most_the_amplitude():
    camera = CameraModel()
    x, alpha = np.meshgrid(np.linspace(-0.05, 0.05, 21), np.linspace(-0.6, 0.6, 21))
    radius = membrane_radius(camera, x, alpha, 0.5e-3)
    assert np.abs(radius - camera.radius).max() <= 0.5e-3 + 1e-12
    assert np.ptp(radius) > 0.5e-3
    p = true_tap_point(camera, 0.01, 0.2, 0.0)
    np.testing.assert_allclose(np.hypot(p[1], p[2]), camera.radius)


def test_table_ii_exact_calibration_is_sub_quarter_millimetre():
    conditions = {"exact": ErrorSources(), "paper_detector": ErrorSources(detector="paper"),
                  "theta_1deg": ErrorSources(theta_error=math.radians(1.0))}
    result = table_ii(taps=1, camera=SMALL_CAMERA, conditions=conditions)
    summary = result["summary"]
    assert summary["exact"]["detected"] == 15
    assert summary["exact"]["mean_mm"] < 0.25
    # the naive centroid sits on the lit side; a 1 degree calibration error costs ~r * 1 deg
    assert summary["paper_detector"]["mean_mm"] > 2 * summary["exact"]["mean_mm"]
    assert summary["theta_1deg"]["mean_mm"] == pytest.approx(0.87, abs=0.25)
    text = table_ii_markdown(result, command="pytest")
    assert text.count("| pi/6 |") == 3 + 3          # error table rows + sensitivity rows
    assert "2.63 ± 0.74" in text


def test_table_ii_on_the_simulator_scene():
    result = table_ii(taps=1, source="sim", calibrations={})
    summary = result["summary"]
    assert "contact_localisation" in result["source"]
    assert summary["exact"]["detected"] == summary["exact"]["taps"] > 0
    assert summary["exact"]["mean_mm"] < 0.25
    # the scene's paper variant: 1 deg of theta alone costs ~0.87 mm, so the error must show it
    assert summary["error_sources"]["mean_mm"] > 0.5
    assert summary["paper_detector"]["mean_mm"] > 5 * summary["exact"]["mean_mm"]


def test_our_calibration_condition_runs_in_quick_mode_with_a_complete_table():
    result = table_ii(quick=True, taps=1, sim_conditions=())
    summary = result["summary"]["our_calibration"]
    assert set(result["summary"]) == {"our_calibration", "paper"}
    counts = [row["our_calibration"]["n"] for row in result["rows"]]
    assert all(n > 0 and n % 3 == 0 for n in counts)          # every cell, the same taps for each of 3 seeds
    assert summary["detected"] == summary["taps"] == sum(counts)
    runs = summary["errors"]["calibration"]["per_seed"]
    assert [r["seed"] for r in runs] == [0, 1, 2]
    # the error is what the calibration got wrong: never exactly zero, and the scene's injected error is not used
    assert all(0 < abs(r["theta_err_deg"]) < 1.0 and 0 < abs(r["d_err_mm"]) < 0.5 for r in runs)
    assert summary["errors"]["theta_error"] == summary["errors"]["d_error"] == 0.0
    assert summary["errors"]["thickness_amplitude"] > 0 and summary["errors"]["noise_sigma"] > 0
    cell_means = [row["our_calibration"]["mean_mm"] for row in result["rows"]]
    assert summary["max_cell_mean_mm"] == pytest.approx(max(cell_means))
    assert summary["worst_seed_max_cell_mean_mm"] >= max(r["max_cell_mean_mm"] for r in runs) - 1e-12
    assert summary["worst_seed_max_cell_mean_mm"] >= summary["max_cell_mean_mm"] - 1e-12
    text = table_ii_markdown(result)
    assert "`our_calibration`: the calibration each seed found" in text
    assert "recalibrated for each of 3 seeds" in text


def test_our_calibration_figures_come_from_the_calibration_it_ran():
    from bench.table_ii import calibrate_with_ours

    found = []

    def ours(chessboard, reference, presses):
        found.append(calibrate_with_ours(chessboard, reference, presses))
        return found[-1]

    def off_by_one_degree(chessboard, reference, presses):
        return found[-1].replace(theta=found[-1].theta + math.radians(1.0))

    result = table_ii(taps=1, sim_conditions=(), calibration_seeds=1,
                      calibrations={"ours": ours, "off_by_one_degree": off_by_one_degree})
    summary = result["summary"]
    truth = CameraModel.from_params(result["camera"])
    [run] = summary["ours"]["errors"]["calibration"]["per_seed"]
    [wrong] = summary["off_by_one_degree"]["errors"]["calibration"]["per_seed"]
    assert run["theta_err_deg"] == pytest.approx(math.degrees(found[0].theta - truth.theta))
    assert run["d_err_mm"] == pytest.approx(1e3 * (found[0].d - truth.d))
    assert wrong["theta_err_deg"] - run["theta_err_deg"] == pytest.approx(1.0)
    # one more degree of theta costs ~r * 1 deg = 0.87 mm more wherever the calibration was good
    assert summary["off_by_one_degree"]["mean_mm"] > summary["ours"]["mean_mm"] + 0.4
    assert summary["off_by_one_degree"]["max_cell_mean_mm"] > summary["ours"]["max_cell_mean_mm"]


def test_explain_paper_table_recovers_a_known_calibration_error():
    import bench.table_ii as loc

    camera = TABLE_II_CAMERA
    # make the "paper" table the errors of a known theta/d offset, then fit it back
    truth = {"theta": math.radians(1.5), "d": 4e-3}
    points = np.array([camera.surface_point((f - 0.5) * camera.length, a)
                       for a in loc.TABLE_II_ALPHAS for f in loc.TABLE_II_FRACTIONS])
    located, _ = camera.replace(theta=camera.theta + truth["theta"], d=camera.d + truth["d"]).back_project(
        camera.project(points)[0])
    synthetic = (1e3 * np.linalg.norm(located - points, axis=1)).reshape(5, 3)
    original = loc.PAPER_TABLE_II_MEAN
    try:
        loc.PAPER_TABLE_II_MEAN = synthetic
        fit = loc.explain_paper_table(camera, names=("theta", "d"), starts=5)
    finally:
        loc.PAPER_TABLE_II_MEAN = original
    assert fit["rms_residual_mm"] < 1e-3
    assert fit["offsets"]["theta"] == pytest.approx(truth["theta"], rel=1e-2)
    assert fit["offsets"]["d"] == pytest.approx(truth["d"], rel=1e-2)
    assert "What would explain" in loc.explain_markdown(fit)
