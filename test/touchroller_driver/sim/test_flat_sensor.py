"""Flat GelSight press-lift-shift timing against one roll."""
import pytest

from touchroller_driver.sim import load_scene


def test_flat_sensor_comparison_counts_the_papers_presses():
    from touchroller_driver.sim.flat_sensor import compare, presses_needed

    scene = load_scene("flat_sensor_comparison")
    result = compare(scene.data["comparison"], scene.motion)
    assert result["flat_sensor"]["presses"] == 49
    assert result["touchroller"]["roll_s"] == pytest.approx(10.0)
    assert result["flat_sensor"]["total_s"] > 49 * result["flat_sensor"]["dwell_s"]
    assert result["speedup"] > 5
    assert presses_needed(0.08, 0.012, 0.0) == 7 and presses_needed(0.11, 0.016, 0.0) == 7
    assert presses_needed(0.08, 0.012, 0.5) == 13
