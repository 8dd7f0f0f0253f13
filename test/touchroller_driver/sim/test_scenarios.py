"""The scenes' own motions: rolls follow the trapezoid, either direction."""
import numpy as np
import pytest

from touchroller_driver.sim import SimulatedSensor, load_scene
from touchroller_driver.sim.scenarios import timeline

SMALL = {"surface.width": 0.07, "surface.length": 0.03, "surface.resolution": 1e-4, "motion.length": 0.03,
         "motion.duration": 0.3, "motion.accel": 2.0}


def _sensor(effect_list, seed=0, **extra):
    overrides = dict(SMALL)
    overrides.update(extra)
    return SimulatedSensor(load_scene("surface_mapping", effects=effect_list, **overrides), seed=seed)


def test_roll_frames_follow_the_trapezoid():
    sensor = _sensor([])
    frames = list(sensor.frames())
    assert len(frames) == int(0.3 * 30) + 1
    travel = [f.truth["state"]["travel"] for f in frames]
    assert travel[0] == 0.0 and travel[-1] == pytest.approx(0.03)
    assert np.all(np.diff(travel) > 0)
    stamps = np.diff([f.stamp_ns for f in frames])
    assert np.all(stamps == pytest.approx(1e9 / 30, abs=1))
    assert frames[-1].truth["state"]["roll"] == pytest.approx(0.03 / 0.05)


def test_reverse_roll_starts_at_the_far_end():
    scene = load_scene("surface_mapping", variant="reverse", **{"surface.resolution": 2e-4})
    sensor = SimulatedSensor(scene, seed=0)
    steps = list(timeline(scene, sensor))
    assert steps[0].state.travel == pytest.approx(0.11)
    assert steps[-1].state.travel == pytest.approx(0.0, abs=1e-9)
    assert all(s.state.speed <= 0 for s in steps)
