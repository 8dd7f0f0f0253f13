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


def test_ball_presses_scene_presses_one_ball_per_frame():
    from touchroller_driver.sim.scenarios import frame_count

    scene = load_scene("ball_presses", **{"motion.presses": 3})
    sensor = SimulatedSensor(scene, seed=1)
    frames = list(sensor.frames())
    assert len(frames) == frame_count(scene) == 5 + 3 * 2
    pressed = [f for f in frames if f.truth["phase"] == "press"]
    assert len(pressed) == 3
    for frame in pressed:
        contact = frame.truth["contacts"][0]
        u, v = contact["pixel"]
        assert 5 < contact["radius_px"] < 40 and contact["ball_radius"] == 0.004
        change = np.abs(frame.image.astype(int) - frames[0].image.astype(int)).sum(axis=2)
        near = change[int(v) - 5:int(v) + 6, int(u) - 5:int(u) + 6]
        assert near.max() > 20                                       # the ball is where the truth says


@pytest.mark.parametrize("count", [7, 24, 30])
def test_stratified_press_places_cover_the_band_evenly(count):
    # every row across the band and every stratum along the axis within a row holds its share, whatever the draw
    # (independent uniform places, the scene's `random`, leave holes: a third of the band with a fifth of them)
    from touchroller_driver.sim.scenarios import stratified_places

    for seed in range(5):
        places = np.array(stratified_places(count, 0.03, 0.2, 0.01, np.random.default_rng(seed)))
        assert places.shape == (count, 2)
        assert (np.abs(places[:, 0]) <= 0.03).all() and (np.abs(places[:, 1]) <= 0.2).all()
        rows = int(round(np.sqrt(count * 0.01 / 0.03)))
        row = np.minimum(((places[:, 1] + 0.2) / 0.4 * rows).astype(int), rows - 1)
        for j in range(rows):
            xs = np.sort(places[row == j, 0])
            n = len(xs)
            assert count // rows <= n <= count // rows + 1
            strata = np.minimum(((xs + 0.03) / 0.06 * n).astype(int), n - 1)
            assert sorted(strata) == list(range(n))      # one press per stratum along the axis


def test_ball_presses_scene_places_presses_stratified():
    scene = load_scene("ball_presses", **{"motion.presses": 12, "motion.placement": "stratified",
                                          "motion.alpha_span": 0.2})
    frames = [f for f in SimulatedSensor(scene, seed=2).frames() if f.truth["phase"] == "press"]
    alphas = np.array([f.truth["contacts"][0]["alpha"] for f in frames])
    xs = np.array([f.truth["contacts"][0]["x"] for f in frames])
    assert len(frames) == 12
    assert np.array_equal(np.histogram(alphas, bins=2, range=(-0.2, 0.2))[0], [6, 6])   # two rows across the band
    assert np.histogram(xs, bins=3, range=(-0.04, 0.04))[0].min() == 4
    with pytest.raises(ValueError, match="placement"):
        list(SimulatedSensor(load_scene("ball_presses", **{"motion.placement": "grid"}), seed=0).frames())
