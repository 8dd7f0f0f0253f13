"""Effects: each one's signature and its function calls disappear when a scene leaves it out; determinism."""
import hashlib

import numpy as np
import pytest

from touchroller_driver.sim import (
    EFFECTS,
    RollerState,
    SimulatedSensor,
    effects,
    load_scene,
)

SMALL = {"surface.width": 0.07, "surface.length": 0.03, "surface.resolution": 1e-4, "motion.length": 0.03,
         "motion.duration": 0.3, "motion.accel": 2.0}


def _sensor(effect_list, seed=0, **extra):
    overrides = dict(SMALL)
    overrides.update(extra)
    return SimulatedSensor(load_scene("surface_mapping", effects=effect_list, **overrides), seed=seed)


STATE = RollerState(travel=0.012, depth=5e-4, speed=0.03)


def _digest(frames):
    h = hashlib.sha256()
    for f in frames:
        h.update(str(f.stamp_ns).encode())
        h.update(f.image.tobytes())
    return h.hexdigest()

def test_deterministic_for_a_seed():
    all_effects = list(EFFECTS)
    a = _digest(_sensor(all_effects, seed=7).frames())
    b = _digest(_sensor(all_effects, seed=7).frames())
    c = _digest(_sensor(all_effects, seed=8).frames())
    assert a == b
    assert a != c


class _Counter:
    def __init__(self, fn):
        self.fn, self.calls = fn, 0

    def __call__(self, *args, **kwargs):
        self.calls += 1
        return self.fn(*args, **kwargs)


@pytest.mark.parametrize("effect, function", [
    ("noise", "add_noise"), ("blur", "motion_blur"), ("compression", "compress"),
    ("background", "gel_background"), ("vignetting", "vignetting"), ("dropped_frames", "frame_dropped"),
])
def test_effect_left_out_is_never_called(monkeypatch, effect, function):
    counter = _Counter(getattr(effects, function))
    monkeypatch.setattr(effects, function, counter)
    with_it = _sensor([effect])
    list(with_it.frames())
    assert counter.calls > 0
    counter.calls = 0
    others = [e for e in EFFECTS if e != effect]
    without = _sensor(others)
    list(without.frames())
    assert counter.calls == 0
    assert effect not in without.pipeline or effect in ("background", "vignetting")


def test_noise_signature_disappears_without_noise():
    noisy = _sensor(["noise"])
    assert not np.array_equal(noisy.render(STATE), noisy.render(STATE))
    clean = _sensor([])
    first = clean.render(STATE)
    assert np.array_equal(first, clean.render(STATE))
    # without noise (and without background) the rows the contact cannot reach are one flat colour
    assert (first[:20].reshape(-1, 3) == first[0, 0]).all()
    diff = noisy.render(STATE).astype(float) - first
    assert 1.0 < diff[:20].std() < 4.0       # sigma = 2 DN in the scene


def test_blur_signature_disappears_without_blur():
    sharp = _sensor([])
    blurred = _sensor(["blur"])
    moving = RollerState(travel=0.012, depth=5e-4, speed=0.05)
    still = RollerState(travel=0.012, depth=5e-4, speed=0.0)
    assert np.array_equal(sharp.render(moving), sharp.render(still))       # speed does not matter
    assert not np.array_equal(blurred.render(moving), blurred.render(still))
    # blur lowers the relief's high-frequency energy along v
    b = blurred.render_layers(moving)["relief"]
    s = sharp.render_layers(moving)["relief"]
    assert np.abs(np.diff(b, axis=0)).sum() < 0.7 * np.abs(np.diff(s, axis=0)).sum()


def test_background_and_vignetting_signatures():
    plain = _sensor([]).render(RollerState(depth=-0.01))
    assert np.ptp(plain.reshape(-1, 3), axis=0).max() == 0          # a uniform membrane
    background = _sensor(["background"]).render(RollerState(depth=-0.01))
    assert np.ptp(background.reshape(-1, 3), axis=0).max() > 30      # uneven light and specks
    vignetted = _sensor(["vignetting"]).render(RollerState(depth=-0.01)).astype(float)
    assert vignetted[0, 0].sum() < 0.9 * vignetted[240, 320].sum()   # corners darker than the centre


def test_dropped_frames_are_skipped_and_counted():
    full = list(_sensor([]).frames())
    sensor = _sensor(["dropped_frames"], **{"effect_params.dropped_frames.probability": 0.3})
    kept = list(sensor.frames())
    assert 0 < len(kept) < len(full)
    assert sensor.counts["dropped_frames"] == len(full) - len(kept)
    assert {f.stamp_ns for f in kept} <= {f.stamp_ns for f in full}


def test_compression_changes_pixels_a_little():
    raw = _sensor([]).render(STATE).astype(int)
    jpeg = _sensor(["compression"]).render(STATE).astype(int)
    assert 0 < np.abs(raw - jpeg).mean() < 3


def test_capture_drops_like_a_camera():
    lossy = _sensor(["dropped_frames"], **{"effect_params.dropped_frames.probability": 0.5})
    results = [lossy.capture(STATE) for _ in range(40)]
    dropped = sum(r is None for r in results)
    assert 5 < dropped < 35 and lossy.counts["dropped_frames"] == dropped
    clean = _sensor([])
    assert all(clean.capture(STATE) is not None for _ in range(10))


def test_shot_noise_grows_with_signal():
    sensor = _sensor(["noise", "background"], **{"effect_params.noise.sigma": 1.0,
                                                 "effect_params.noise.shot": 0.5})
    clean = _sensor(["background"]).render(RollerState(depth=-0.01)).astype(float)
    noisy = np.stack([sensor.render(RollerState(depth=-0.01)).astype(float) for _ in range(6)])
    residual = (noisy - clean).reshape(6, -1)
    signal = clean.reshape(-1)
    dark, bright = signal < np.percentile(signal, 10), signal > np.percentile(signal, 90)
    var_dark, var_bright = residual[:, dark].var(), residual[:, bright].var()
    expected = lambda s: 1.0 + 0.5 * s  # noqa: E731 - variance model sigma^2 + g * signal
    assert var_bright > var_dark
    assert var_bright == pytest.approx(expected(signal[bright].mean()), rel=0.15)
