"""Ball-press calibration on presses from the test's own three-light renderer: circles refined from loose
labels, slopes recovered on held-out presses, refusals in one line."""
from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from touchroller_perception.calibration import CalibrationError
from touchroller_perception.height import (
    BallPress,
    PhotometricConfig,
    PressCalibrationConfig,
    calibrate_photometric,
    change_magnitude,
    normal_angles_deg,
    refine_circle,
)
from touchroller_perception.height.presses import fit_still_prior

from .conftest import BALL, PIXEL, SHAPE, cap_slopes, press_image, shade

CONFIG = PressCalibrationConfig(model=PhotometricConfig(colour_degree=3, position_degree=1, smoothing=0.7,
                                                        lookup_cells=(4, 3)), far_fraction=0.05)


def _presses(presses, shift=0.0, grow=0.0):
    return [BallPress(img, cu + shift, cv - shift, contact + grow, (PIXEL, PIXEL), str(k))
            for k, (img, cu, cv, contact, *_rest) in enumerate(presses)]


def test_refine_circle_recovers_the_contact_from_a_loose_label(synthetic_presses):
    reference, presses = synthetic_presses
    img, cu, cv, contact, *_ = presses[0]
    circle = refine_circle(change_magnitude(img, reference), cu + 3.0, cv - 2.0, contact + 3.0)
    assert circle.refined
    assert np.hypot(circle.u - cu, circle.v - cv) < 1.0
    assert abs(circle.radius_px - contact) < 1.5


def test_calibration_recovers_slopes_on_held_out_presses(synthetic_presses):
    reference, presses = synthetic_presses
    result = calibrate_photometric(_presses(presses[:10], shift=2.0, grow=2.0), reference, BALL, CONFIG)
    assert len(result.presses) == 10 and result.normal_error_deg < 3.0
    lookup = result.model.compile(reference)
    for img, cu, cv, contact, gx, gy, _z in presses[10:]:
        inside = np.hypot(*np.mgrid[0:img.shape[0], 0:img.shape[1]][::-1] - np.array([cu, cv])[:, None, None]) \
            < contact - 2
        px, py = result.model.slopes(img, reference)
        assert np.median(normal_angles_deg(px[inside], py[inside], gx[inside], gy[inside])) < 3.0
        lx, ly = lookup.slopes(img)
        assert np.median(normal_angles_deg(lx[inside], ly[inside], gx[inside], gy[inside])) < 4.0


def test_refusals(synthetic_presses):
    reference, presses = synthetic_presses
    ok = _presses(presses[:3])
    with pytest.raises(CalibrationError, match="not smaller than the ball"):
        calibrate_photometric(ok, reference, 0.5e-3, CONFIG)
    with pytest.raises(CalibrationError, match="one light"):
        calibrate_photometric(ok, reference[..., 0], BALL, CONFIG)
    with pytest.raises(CalibrationError, match="no ball presses"):
        calibrate_photometric([], reference, BALL, CONFIG)
    with pytest.raises(CalibrationError, match="positive"):
        calibrate_photometric(ok, reference, float("nan"), CONFIG)
    small = BallPress(presses[0][0][:50], 1, 1, 5, (PIXEL, PIXEL), "x")
    with pytest.raises(CalibrationError, match="does not match"):
        calibrate_photometric([small], reference, BALL, CONFIG)


def test_label_far_off_is_kept_not_moved(synthetic_presses):
    reference, presses = synthetic_presses
    flat = reference.copy()
    circle = refine_circle(change_magnitude(flat, reference), 80.0, 60.0, 18.0)
    assert circle.u == 80.0 and circle.v == 60.0 and circle.radius_px == 18.0  # nothing to see: the label stays
    img, *_ = press_image(80.0, 60.0, 18.0)
    assert refine_circle(change_magnitude(img, reference), 80.0, 60.0, 18.0).refined


def test_find_press_labels_the_one_press(synthetic_presses):
    from touchroller_perception.height import find_press

    reference, presses = synthetic_presses
    img, cu, cv, contact, *_ = presses[3]
    u, v, r = find_press(img, reference)
    assert np.hypot(u - cu, v - cv) < 3.0 and 0.5 * contact < r < 1.6 * contact
    with pytest.raises(CalibrationError, match="no press found"):
        find_press(reference, reference)


def _haloed_presses(n, seed):
    """Presses with a halo: about 3 contact radii below the press the colour changes as a slope of 0.08 would
    change it, with the gel flat there (light the press redirects, as on taxim's real GelSight presses, where
    such a zone lies 3-4.5 radii below a press), so the only slope there is 0."""
    rng = np.random.default_rng(seed)
    shape = (150, 190)
    out = []
    for _ in range(n):
        cu, cv, contact = rng.uniform(70, 120), rng.uniform(55, 95), rng.uniform(13, 16)
        gx, gy, _z = cap_slopes(shape, cu, cv, contact, skirt=0.15)
        vv, uu = np.mgrid[0:shape[0], 0:shape[1]]
        rho = np.hypot(uu - cu, vv - cv) / contact
        # the halo shades like a slope of 0.08 facing away from one side of the press, the gel flat
        halo = 0.08 * np.exp(-(((rho - 3.2) / 0.6) ** 2)) * (vv > cv)
        img = shade(gx, gy + halo)
        img = np.clip(np.rint(img + rng.normal(0, 0.8, img.shape)), 0, 255).astype(np.uint8)
        out.append((img, cu, cv, contact, halo > 0.04))
    reference = np.clip(np.rint(shade(np.zeros(shape), np.zeros(shape))), 0, 255).astype(np.uint8)
    return reference, out


def test_far_field_targets_teach_a_halo_to_read_flat():
    """With the far field sampled 5x denser than the default 1 %, the halo reads flatter."""
    reference, presses = _haloed_presses(12, 5)
    items = [BallPress(img, cu, cv, c, (PIXEL, PIXEL), str(k)) for k, (img, cu, cv, c, _) in enumerate(presses[:9])]
    model_cfg = PhotometricConfig(position_degree=1, smoothing=0.7, lookup_cells=(4, 3))
    halo_slope = {}
    for fraction in (PressCalibrationConfig().far_fraction, 0.05):
        model = calibrate_photometric(items, reference, BALL, PressCalibrationConfig(model=model_cfg,
                                                                                      far_fraction=fraction)).model
        lookup = model.compile(reference)
        values = []
        for img, _cu, _cv, _c, zone in presses[9:]:
            gx, gy = lookup.slopes(img)
            values.append(np.hypot(gx, gy)[zone])
        halo_slope[fraction] = float(np.median(np.concatenate(values)))
    assert halo_slope[0.05] < 0.85 * halo_slope[PressCalibrationConfig().far_fraction]


def test_a_rollers_curvature_along_v_is_in_the_targets():
    """Presses into a membrane curved along v (a roller): the indentation's slope along v is the sphere's
    plus the tube's. Calibrated with the membrane's radius, the model reads a held-out press's slopes
    at their size; calibrated as if flat, it reads gy too gentle by about r / (R + r)."""
    rng = np.random.default_rng(11)
    tube = 6e-3
    presses = []
    for _ in range(11):
        cu, cv, contact = rng.uniform(45, 115), rng.uniform(40, 80), rng.uniform(16, 22)
        gx, gy, _z = cap_slopes(SHAPE, cu, cv, contact)
        vv, uu = np.mgrid[0:SHAPE[0], 0:SHAPE[1]]
        dy = (vv - cv) * PIXEL
        # where the membrane wraps the ball, the tube recedes from it along v (the far field is undeformed)
        gy = gy - np.where(np.hypot(uu - cu, vv - cv) < contact, dy / np.sqrt(tube**2 - dy**2), 0.0)
        img = np.clip(np.rint(shade(gx, gy) + rng.normal(0, 0.8, SHAPE + (3,))), 0, 255).astype(np.uint8)
        presses.append((img, cu, cv, contact, gx, gy))
    reference = np.clip(np.rint(shade(np.zeros(SHAPE), np.zeros(SHAPE))), 0, 255).astype(np.uint8)
    gains = {}
    for radius in (tube, np.inf):
        items = [BallPress(img, cu, cv, c, (PIXEL, PIXEL), str(k), membrane_radius=radius)
                 for k, (img, cu, cv, c, *_) in enumerate(presses[:9])]
        model = calibrate_photometric(items, reference, BALL, CONFIG).model
        read, true = [], []
        for img, cu, cv, contact, _gx, gy in presses[9:]:
            vv, uu = np.mgrid[0:SHAPE[0], 0:SHAPE[1]]
            inside = np.hypot(uu - cu, vv - cv) < contact - 3
            read.append(model.slopes(img, reference)[1][inside])
            true.append(gy[inside])
        a, b = np.concatenate(read), np.concatenate(true)
        gains[radius] = float(a @ b / (b @ b))
    assert abs(gains[tube] - 1.0) < 0.04
    assert gains[np.inf] < 0.85
    with pytest.raises(CalibrationError, match="membrane radius"):
        BallPress(presses[0][0], 1.0, 1.0, 5.0, (PIXEL, PIXEL), "x", membrane_radius=0.0)


def test_the_position_degree_is_chosen_by_held_out_presses(synthetic_presses):
    # the renderer's uneven light is a gain the colour ratios divide out: position terms have nothing to learn,
    # and a cubic one, fitted on ten presses, reads held-out presses with a wandering gain; the choice weighs each
    # candidate on presses it was not fitted on and takes the steadiest
    from touchroller_perception.height import DegreeScore

    reference, presses = synthetic_presses
    items = _presses(presses[:10])
    config = dataclasses.replace(CONFIG, position_degrees=(3, 1, 0), selection_folds=5)
    result = calibrate_photometric(items, reference, BALL, config)
    scores = {s.degree: s for s in result.degree_scores}
    assert set(scores) == {0, 1, 3} and all(isinstance(s, DegreeScore) for s in scores.values())
    assert scores[3].gain_deviation > 1.5 * min(scores[0].gain_deviation, scores[1].gain_deviation)
    assert result.model.config.position_degree == min(scores.values(), key=lambda s: s.gain_deviation).degree != 3
    assert "position degree" in result.summary()
    # the chosen model reads the presses it never saw at their size; the cubic one less so
    cubic = calibrate_photometric(items, reference, BALL, dataclasses.replace(
        CONFIG, model=dataclasses.replace(CONFIG.model, position_degree=3)))

    def gain_error(model):
        errors = []
        for img, cu, cv, contact, gx, gy, _z in presses[10:]:
            vv, uu = np.mgrid[0:img.shape[0], 0:img.shape[1]]
            inside = np.hypot(uu - cu, vv - cv) < contact - 2
            px, py = model.slopes(img, reference)
            errors += [abs(float(px[inside] @ gx[inside] / (gx[inside] @ gx[inside])) - 1),
                       abs(float(py[inside] @ gy[inside] / (gy[inside] @ gy[inside])) - 1)]
        return max(errors)

    assert gain_error(result.model) < gain_error(cubic.model)


def test_position_degree_choice_needs_presses_and_valid_candidates(synthetic_presses):
    reference, presses = synthetic_presses
    with pytest.raises(ValueError, match="position_degrees"):
        PressCalibrationConfig(position_degrees=(7,))
    with pytest.raises(CalibrationError, match="at least 4 presses"):
        calibrate_photometric(_presses(presses[:3]), reference, BALL,
                              dataclasses.replace(CONFIG, position_degrees=(0, 1)))


def _shade_turning(gx, gy, turn_deg=40.0):
    """The renderer's three lights, their azimuths turning by `turn_deg` from the left edge to the right: how a
    slope colours a pixel then depends on where it is, beyond a gain the colour ratios divide out."""
    h, w = gx.shape
    vv, uu = np.mgrid[0:h, 0:w]
    n = np.stack([-gx, -gy, np.ones_like(gx)], -1)
    n /= np.linalg.norm(n, axis=-1, keepdims=True)
    el = np.radians(35.0)
    turn = np.radians(turn_deg) * (uu / w - 0.5)
    channels = []
    for az in (0.0, 120.0, 240.0):
        a = np.radians(az) + turn
        lvec = np.stack([np.cos(el) * np.cos(a), np.cos(el) * np.sin(a), np.full_like(a, np.sin(el))], -1)
        channels.append(40 + 150 * np.clip((n * lvec).sum(-1), 0, None))
    return np.clip(np.rint(np.stack(channels, -1)), 0, 255).astype(np.uint8)


def _turning_presses(places, shape=(120, 320), seed=5):
    rng = np.random.default_rng(seed)
    presses = []
    for cu, cv in places:
        cu, cv, contact = cu + rng.uniform(-4, 4), cv + rng.uniform(-10, 10), rng.uniform(16, 22)
        gx, gy, _z = cap_slopes(shape, cu, cv, contact)
        presses.append((_shade_turning(gx, gy), cu, cv, contact, gx, gy))
    return _shade_turning(np.zeros(shape), np.zeros(shape)), presses


def _items(presses):
    return [BallPress(img, cu, cv, contact, (PIXEL, PIXEL), str(k))
            for k, (img, cu, cv, contact, *_rest) in enumerate(presses)]


TURNING = dataclasses.replace(CONFIG, model=dataclasses.replace(CONFIG.model, position_colour_degree=0),
                              position_colour_degrees=(0, 2), selection_folds=5)


def test_the_position_colour_degree_is_chosen_by_held_out_presses():
    # lights whose direction turns across the image: a slope's colour means another slope elsewhere, which a model
    # without position factors on its colour terms cannot follow; the choice weighs each candidate on presses it was
    # not fitted on, takes the one that reads their normals best, and that one reads unseen presses better
    reference, presses = _turning_presses([(20 + 280 * (k % 7) / 6, 60) for k in range(14)])
    items = _items(presses[:10])
    result = calibrate_photometric(items, reference, BALL, TURNING)
    scores = {s.degree: s for s in result.colour_degree_scores}
    assert set(scores) == {0, 2} and result.press_spread == 1.0
    assert result.model.config.position_colour_degree == min(scores.values(), key=lambda s: s.normal_error_deg).degree
    assert result.model.config.position_colour_degree == 2 and "held-out normal-angle error" in result.summary()
    own = calibrate_photometric(items, reference, BALL, dataclasses.replace(TURNING, position_colour_degrees=()))
    assert own.model.config.position_colour_degree == 0 and not own.colour_degree_scores

    def angle(model):
        errors = []
        for img, cu, cv, contact, gx, gy in presses[10:]:
            vv, uu = np.mgrid[0:img.shape[0], 0:img.shape[1]]
            inside = np.hypot(uu - cu, vv - cv) < contact - 2
            px, py = model.slopes(img, reference)
            errors.append(float(np.median(normal_angles_deg(px[inside], py[inside], gx[inside], gy[inside]))))
        return float(np.median(errors))

    assert angle(result.model) < 0.5 * angle(own.model)


def test_presses_at_one_place_keep_the_models_own_position_colour_degree():
    # presses that keep to one place cannot say how a slope's colour changes elsewhere, and held-out presses at
    # the same place cannot tell: the candidates are not weighed, the model's own degree is kept, and said
    reference, presses = _turning_presses([(160, 60)] * 10)
    result = calibrate_photometric(_items(presses), reference, BALL, TURNING)
    assert not result.colour_degree_scores and result.press_spread < 1.0
    assert result.model.config.position_colour_degree == 0 and "the model's own" in result.summary()


def test_position_colour_degree_candidates_must_fit_the_colour_degree():
    with pytest.raises(ValueError, match="position_colour_degrees"):
        PressCalibrationConfig(position_colour_degrees=(4,))
    assert PressCalibrationConfig(position_colour_degrees=(0, 3)).position_colour_degrees == (0, 3)


def test_nested_candidates_score_as_fitting_each_on_its_own(synthetic_presses):
    # the one-pass scoring of nested candidates (each press's normal equations formed once) gives the scores that
    # fitting every candidate on every fold gives (up to the colour scaling, all presses' rather than each fold's)
    from touchroller_perception.height.presses import held_out_scores, nested_held_out_scores, press_samples

    reference, presses = synthetic_presses
    items = _presses(presses[:8])
    rng = np.random.default_rng(0)
    parts = [press_samples(p, refine_circle(change_magnitude(p.image, reference), p.u, p.v, p.radius_px, CONFIG),
                           reference, BALL, CONFIG, rng) for p in items]
    candidates = {d: dataclasses.replace(CONFIG.model, position_colour_degree=d) for d in (0, 1, 2)}
    fast = nested_held_out_scores(parts, CONFIG, candidates, SHAPE[1], SHAPE[0])
    slow = held_out_scores(parts, CONFIG, candidates, SHAPE[1], SHAPE[0])
    assert [s.degree for s in fast] == [s.degree for s in slow] == [0, 1, 2]
    for a, b in zip(fast, slow, strict=True):
        assert a.normal_error_deg == pytest.approx(b.normal_error_deg, rel=0.02, abs=0.01)
        assert a.gain_deviation == pytest.approx(b.gain_deviation, rel=0.02, abs=1e-3)
    with pytest.raises(CalibrationError, match="at least 4 presses"):
        nested_held_out_scores(parts[:3], CONFIG, candidates, SHAPE[1], SHAPE[0])


def test_the_calibration_measures_what_the_undeformed_gel_reads(synthetic_presses):
    """`PhotometricModel.still_slope` is the quantile of the length of the slopes the model reads beyond
    `reference_factor` label radii of the presses, measured in their covariance's ellipse of unit area
    (`still_shape`; round with `still_ellipse` False): larger for a larger quantile, none with quantile 0."""
    reference, presses = synthetic_presses
    items = _presses(presses[:10])
    base = calibrate_photometric(items, reference, BALL, dataclasses.replace(CONFIG, still_quantile=0.0))
    assert base.model.still_slope == 0.0 and base.model.still_shape == (1.0, 0.0, 0.0, 1.0)
    low = calibrate_photometric(items, reference, BALL, dataclasses.replace(CONFIG, still_quantile=0.5))
    high = calibrate_photometric(items, reference, BALL, dataclasses.replace(CONFIG, still_quantile=0.95))
    np.testing.assert_array_equal(low.model.coefficients, base.model.coefficients)   # the fit is not touched
    assert 0.0 < low.model.still_slope < high.model.still_slope < 0.2
    want, shape = fit_still_prior(base.model, items, reference, CONFIG.reference_factor, 0.95)
    assert high.model.still_slope == pytest.approx(want) and high.model.still_shape == pytest.approx(shape)
    # by hand: the exact polynomial on the far pixels of a 1-in-4 grid
    samples = []
    for press in items:
        px, py = base.model.slopes(press.image, reference)
        vv, uu = np.mgrid[0:SHAPE[0]:4, 0:SHAPE[1]:4]
        far = np.hypot(uu - press.u, vv - press.v) > CONFIG.reference_factor * press.radius_px
        samples.append(np.stack([px[::4, ::4][far], py[::4, ::4][far]], axis=1).astype(np.float64))
    g = np.concatenate(samples)
    whiten = np.reshape(shape, (2, 2))
    assert np.linalg.det(whiten) == pytest.approx(1.0)
    covariance = whiten @ np.cov(g.T) @ whiten.T            # round: a multiple of the identity
    assert covariance[0, 1] == pytest.approx(0.0, abs=1e-3 * covariance[0, 0])
    assert covariance[0, 0] == pytest.approx(covariance[1, 1], rel=1e-3)
    assert want == pytest.approx(float(np.quantile(np.linalg.norm(g @ whiten.T, axis=1), 0.95)), rel=1e-3)
    round_ = calibrate_photometric(items, reference, BALL, dataclasses.replace(CONFIG, still_quantile=0.95,
                                                                               still_ellipse=False))
    assert round_.model.still_shape == (1.0, 0.0, 0.0, 1.0)
    assert round_.model.still_slope == pytest.approx(float(np.quantile(np.hypot(g[:, 0], g[:, 1]), 0.95)), rel=1e-3)
    for bad in (-0.1, 1.0, float("nan")):
        with pytest.raises(ValueError, match="still_quantile"):
            dataclasses.replace(CONFIG, still_quantile=bad)
