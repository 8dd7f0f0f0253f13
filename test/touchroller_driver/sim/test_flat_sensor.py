"""Flat GelSight press-lift-shift timing against one roll."""
import pytest

from touchroller_driver.sim import load_scene


def test_flat_sensor_comparison_counts_the_papers_presses():
    from touchroller_driver.sim.flat_sensor import compare, presses_needed

    scene = load_scene("flat_sensor_comparison")
    result = compare(scene.data["comparison"], scene.motion)
    assert result.flat_sensor.presses == 49 and result.flat_sensor.grid == (7, 7)
    assert result.touchroller.roll_s == pytest.approx(10.0)
    assert result.flat_sensor.total_s > 49 * result.flat_sensor.dwell_s
    assert result.speedup == pytest.approx(result.flat_sensor.total_s / result.touchroller.total_s)
    assert result.speedup > 5
    assert presses_needed(0.08, 0.012, 0.0) == 7 and presses_needed(0.11, 0.016, 0.0) == 7
    assert presses_needed(0.08, 0.012, 0.5) == 13


def test_flat_press_mosaic_tiles_the_presses(tmp_path):
    import yaml

    from touchroller_bringup.cli import main
    from touchroller_driver.sim import SimulatedSensor
    from touchroller_driver.sim.flat_sensor import flat_press_mosaic

    scene = load_scene("flat_sensor_comparison", **{"surface.resolution": 1e-4})
    sensor = SimulatedSensor(scene, seed=0)
    mosaic = flat_press_mosaic(sensor, scene.data["comparison"])
    assert mosaic.shape == (7 * 160, 7 * 120, 3)
    assert mosaic.std() > 2      # texture, not a flat grey
    out = tmp_path / "cmp"
    assert main(["simulate", "flat_sensor_comparison", "--out", str(out), "--set", "surface.resolution=1e-4",
                 "--set", "motion.duration=3", "--set", "fps=2"]) == 0
    truth = yaml.safe_load((out / "ground_truth.yaml").read_text())
    assert truth["comparison"]["flat_sensor"]["presses"] == 49
    assert (out / truth["comparison"]["presses_image"]).is_file()
