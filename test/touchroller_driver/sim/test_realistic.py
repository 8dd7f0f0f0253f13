"""The realistic appearance: fitted from presses, it reproduces them; fitted on real presses, it beats the ideal one."""
from __future__ import annotations

import numpy as np
import pytest

from touchroller_driver.sim.realistic import (
    IdealPressRenderer,
    PressShape,
    RealAppearance,
    RealisticPressRenderer,
    correlated_noise,
    fit_appearance,
)


def _synthetic(rng: np.random.Generator) -> tuple[RealAppearance, np.ndarray, np.ndarray, np.ndarray]:
    h, w = 160, 200
    background = np.full((h, w, 3), 100.0, np.float32) + np.linspace(0, 30, w, dtype=np.float32)[None, :, None]
    response = np.zeros((9, 3), np.float32)
    response[0], response[1], response[2] = (20, -10, 5), (5, 25, -15), (4, 0, 6)
    truth = RealAppearance(background, PressShape(1.6, 0.35), response, np.array([1.0, 1.5, 2.0], np.float32), 1.0, 0.0)
    centres = np.array([[60.0 + 20 * (i % 4), 60.0 + 10 * (i // 4)] for i in range(8)])
    radii = np.array([14.0 + i for i in range(8)])
    renderer = RealisticPressRenderer(truth)
    frames = np.stack([renderer.render([(u, v, r)], rng) for (u, v), r in zip(centres, radii, strict=True)])
    return truth, frames, centres, radii


def test_fit_recovers_a_known_appearance():
    rng = np.random.default_rng(0)
    truth, frames, centres, radii = _synthetic(rng)
    # the no-contact frame is a frame too, with its own noise (as a real one)
    no_contact = RealisticPressRenderer(truth).render([], rng)
    fitted = fit_appearance(no_contact, frames, centres, radii)
    assert fitted.shape == truth.shape
    assert fitted.fit_rms < 2.5                     # noise and rounding only
    np.testing.assert_allclose(fitted.response[:2], truth.response[:2], atol=1.5)
    np.testing.assert_allclose(fitted.noise_std, truth.noise_std, rtol=0.25)
    assert 0.5 < fitted.noise_correlation_px < 1.6


def test_correlated_noise_has_the_asked_std_and_correlation():
    noise = correlated_noise((200, 200, 3), np.array([1.0, 2.0, 3.0]), 1.0, np.random.default_rng(1))
    np.testing.assert_allclose(noise.std(axis=(0, 1)), [1.0, 2.0, 3.0], rtol=0.05)
    lag = np.mean(noise[:, :-1] * noise[:, 1:]) / np.mean(noise * noise)
    assert lag == pytest.approx(np.exp(-0.25), abs=0.05)


def test_on_real_presses_the_realistic_appearance_is_closer_than_the_ideal_one(real_presses):
    from bench.sim_to_real import realism

    presses = real_presses("gelsight")
    appearance = fit_appearance(presses.background, presses.presses, presses.centres, presses.radii,
                                presses.tuning[::2])
    held_out = presses.held_out[::3]
    realistic = realism(presses, RealisticPressRenderer(appearance), held_out)
    ideal = realism(presses, IdealPressRenderer(presses.background.shape[:2], appearance.shape), held_out)
    assert realistic["correlation"] > 0.8 > ideal["correlation"] + 0.3
    assert realistic["rms"] < 0.5 * ideal["rms"]
    frame = RealisticPressRenderer(appearance).render([(300.0, 200.0, 60.0)], np.random.default_rng(0))
    assert frame.shape == presses.background.shape and frame.dtype == np.uint8


def test_refined_fit_moves_hand_placed_centres_back_onto_the_presses():
    # labels a few pixels off, all to one side (as the GelSight Mini's hand labels are): a response fitted
    # around them absorbs the offset; refining the centres finds the presses' own centres again
    rng = np.random.default_rng(3)
    truth, frames, centres, radii = _synthetic(rng)
    no_contact = RealisticPressRenderer(truth).render([], rng)
    labels = centres + np.array([3.0, -2.0]) + rng.uniform(-1.5, 1.5, centres.shape)
    at_labels = fit_appearance(no_contact, frames, labels, radii)
    refined = fit_appearance(no_contact, frames, labels, radii, refine_rounds=6)
    assert at_labels.centres is None and refined.centres is not None
    error_before = np.hypot(*(labels - centres).T)
    error_after = np.hypot(*(refined.centres - centres).T)
    assert np.median(error_before) > 3.0
    assert np.median(error_after) < 1.0
    assert refined.fit_rms < at_labels.fit_rms
