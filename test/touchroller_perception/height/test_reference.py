"""The no-contact reference built from the presses' own far fields: frames in a light that changed since
the given no-contact frame (the test's own three-light renderer, conftest)."""
from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from touchroller_perception.calibration import CalibrationError
from touchroller_perception.height import (
    BallPress,
    HeightConfig,
    HeightEstimator,
    PhotometricConfig,
    PressCalibrationConfig,
    calibrate_photometric,
)
from touchroller_perception.height.reference import choose_reference, far_field_reference, reference_change

from .conftest import BALL, PIXEL, SHAPE, shade

CONFIG = PressCalibrationConfig(model=PhotometricConfig(colour_degree=3, position_degree=1, smoothing=0.7,
                                                        lookup_cells=(4, 3)), far_fraction=0.05,
                                reference_factor=1.3)


def _drift() -> np.ndarray:
    """A change of light since the no-contact frame: a few per cent, different per channel and place."""
    h, w = SHAPE
    vv, uu = np.mgrid[0:h, 0:w]
    return np.stack([1 + 0.04 * np.sin(2 * np.pi * uu / 50), 1 - 0.03 * np.cos(2 * np.pi * vv / 40),
                     1 + 0.05 * np.sin(2 * np.pi * (uu + vv) / 70)], -1)


def _flat() -> np.ndarray:
    return shade(np.zeros(SHAPE), np.zeros(SHAPE))


def _discs(light: np.ndarray, places: list[tuple[float, float]], r: float) -> list[np.ndarray]:
    h, w = SHAPE
    vv, uu = np.mgrid[0:h, 0:w]
    return [np.where((np.hypot(uu - u, vv - v) <= r)[..., None], 0.0, light) for u, v in places]


def test_far_field_reference_is_the_frames_light_away_from_their_contacts():
    light = _flat() * _drift()
    places = [(u, v) for u in (30, 80, 130) for v in (30, 90)]
    frames = _discs(light, places, 10.0)
    given = _flat()
    built = far_field_reference(frames, [(u, v, 10.0) for u, v in places], given, factor=2.0, min_frames=6)
    h, w = SHAPE
    vv, uu = np.mgrid[0:h, 0:w]
    covered = sum((np.hypot(uu - u, vv - v) > 20.0).astype(int) for u, v in places) >= 6
    assert covered.any() and (~covered).any()
    np.testing.assert_allclose(built[covered], light[covered], rtol=1e-6)      # the contacts left out
    assert np.abs(built[covered] - given[covered]).max() > 3.0
    # too few frames: the given reference in the frames' light, carried in smoothly (no step at the edge)
    brighter = far_field_reference(_discs(given * 1.05, places, 10.0), [(u, v, 10.0) for u, v in places], given,
                                   factor=2.0, min_frames=6)
    np.testing.assert_allclose(brighter, given * 1.05, rtol=1e-3)


def test_choose_reference_keeps_the_one_the_far_fields_match():
    rng = np.random.default_rng(0)
    places = [(u, v) for u in (30, 80, 130) for v in (30, 90)]
    circles = [(u, v, 10.0) for u, v in places]
    given = _flat()
    drifted = [f + rng.normal(0, 0.5, f.shape) for f in _discs(given * _drift(), places, 10.0)]
    choice = choose_reference(drifted, circles, given, "auto", factor=2.0)
    assert choice.source == "presses" and choice.presses_change < 0.5 * choice.given_change
    steady = [f + rng.normal(0, 0.5, f.shape) for f in _discs(given, places, 10.0)]
    choice = choose_reference(steady, circles, given, "auto", factor=2.0)
    assert choice.source == "given" and choice.reference is given
    assert choose_reference(drifted, circles, given, "given").reference is given
    # presses that keep to one place: no far field is far from every press's influence, the given one is kept
    still = [f + rng.normal(0, 0.5, f.shape) for f in _discs(given * _drift(), [(80, 60)] * 6, 10.0)]
    choice = choose_reference(still, [(80, 60, 10.0)] * 6, given, "auto", factor=2.0)
    assert choice.source == "given" and choice.coverage < 1.0
    assert reference_change(drifted, circles, [given] * 6, 2.0) > 0.02
    with pytest.raises(ValueError, match="reference source"):
        choose_reference(drifted, circles, given, "median")
    with pytest.raises(CalibrationError, match="does not match"):
        far_field_reference([given[:50]], [(1.0, 1.0, 5.0)], given)


def test_a_reference_from_the_presses_reads_a_no_contact_frame_in_their_light_flat(synthetic_presses):
    reference, presses = synthetic_presses
    drift = _drift()
    items = [BallPress(np.clip(np.rint(img * drift), 0, 255).astype(np.uint8), cu, cv, contact, (PIXEL, PIXEL),
                       str(k)) for k, (img, cu, cv, contact, *_rest) in enumerate(presses)]
    no_contact = np.clip(np.rint(_flat() * drift), 0, 255).astype(np.uint8)
    rms = {}
    for source in ("given", "presses", "auto"):
        cal = calibrate_photometric(items, reference, BALL, dataclasses.replace(CONFIG, reference=source))
        assert cal.reference is not None and cal.reference_choice is not None
        # the reference alone: without the zero-slope prior (which the given one's drift would raise)
        z = HeightEstimator(cal.model, cal.reference, PIXEL, config=HeightConfig(still_slope=0.0)).height(no_contact)
        rms[source] = float(np.sqrt(np.mean(z**2)))
        if source == "auto":
            assert cal.reference_choice.source == "presses" and "built from the presses" in cal.summary()
    assert rms["presses"] < 0.5 * rms["given"]
    assert rms["auto"] == rms["presses"]


def test_reference_source_is_validated():
    with pytest.raises(ValueError, match="reference must be"):
        PressCalibrationConfig(reference="median")
    with pytest.raises(ValueError, match="reference_factor"):
        PressCalibrationConfig(reference_factor=1.0)
