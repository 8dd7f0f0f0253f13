"""The compiled lookup: its smoothing is OpenCV's Gaussian, and its slopes are the model's polynomial up to
the colour quantisation (also for a band of rows and with the frame's gain divided out)."""
from __future__ import annotations

import dataclasses

import cv2
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from touchroller_perception.height import BallPress, PhotometricConfig, PressCalibrationConfig, calibrate_photometric
from touchroller_perception.height.photometric import SLOPE_UNIT, smooth, still_prior

from .conftest import BALL, PIXEL


@pytest.mark.parametrize("dtype", [np.uint8, np.uint16, np.float32, np.float64])
@pytest.mark.parametrize("sigma", [0.0, 0.7, 2.0])
def test_smooth_is_opencvs_gaussian_of_the_float_image(dtype, sigma):
    rng = np.random.default_rng(1)
    img = (rng.random((37, 53, 3)) * 200).astype(dtype)
    want = cv2.GaussianBlur(img.astype(np.float32), (0, 0), sigma) if sigma > 0 else img.astype(np.float32)
    got = smooth(img, sigma)
    assert got.dtype == np.float32 and got.shape == img.shape
    np.testing.assert_allclose(got, want, rtol=1e-5, atol=1e-3)


@pytest.fixture(scope="module")
def model(synthetic_presses):
    reference, presses = synthetic_presses
    items = [BallPress(img, cu, cv, contact, (PIXEL, PIXEL), str(k))
             for k, (img, cu, cv, contact, *_rest) in enumerate(presses[:10])]
    config = PressCalibrationConfig(model=PhotometricConfig(position_degree=1, smoothing=0.7, lookup_cells=(4, 3),
                                                            lookup_bins=65), far_fraction=0.05)
    return calibrate_photometric(items, reference, BALL, config).model


@pytest.mark.parametrize("drift", [1.0, 1.08])
def test_lookup_slopes_follow_the_polynomial(synthetic_presses, model, drift):
    """A held-out press (its light drifted by `drift`): the lookup's slopes against the exact polynomial's."""
    reference, presses = synthetic_presses
    img = np.clip(presses[11][0].astype(np.float64) * drift, 0, 255).astype(np.uint8)
    lookup = model.compile(reference)
    gx, gy = lookup.slopes(img)
    ex, ey = model.slopes(img, reference)
    assert gx.dtype == np.float32 and gx.shape == img.shape[:2] and gx.flags.c_contiguous
    steep = np.hypot(ex, ey) > 0.05
    assert np.median(np.abs(gx - ex)[steep]) < 0.02 and np.median(np.abs(gy - ey)[steep]) < 0.02
    assert np.corrcoef(gx[steep], ex[steep])[0, 1] > 0.98
    # the fixed-point step is far finer than the colour quantisation
    assert SLOPE_UNIT < 1e-3
    band_x, band_y = lookup.slopes(img[40:80], rows=slice(40, 80))
    np.testing.assert_array_equal(band_x, lookup.slopes(img, rows=slice(40, 80))[0])
    assert band_x.shape == (40, img.shape[1]) and band_y.shape == (40, img.shape[1])


def test_lookup_reads_the_reference_as_flat(synthetic_presses, model):
    reference, _ = synthetic_presses
    gx, gy = model.compile(reference).slopes(reference)
    assert np.abs(gx).max() == 0.0 and np.abs(gy).max() == 0.0


@settings(max_examples=200, deadline=None)
@given(st.floats(-0.5, 0.5), st.floats(-0.5, 0.5), st.floats(0.001, 0.2))
def test_still_prior_is_a_firm_threshold_on_the_slopes_magnitude(gx, gy, threshold):
    """Below the threshold 0, beyond twice it as given, in between shorter, never longer, direction kept;
    monotone in the magnitude."""
    slopes = np.array([[gx, gy], [2 * gx, 2 * gy]])
    out = still_prior(slopes, threshold)
    m, shrunk = np.hypot(*slopes.T), np.hypot(*out.T)
    for k in range(2):
        if m[k] < threshold:
            assert shrunk[k] == 0.0
        elif m[k] >= 2 * threshold:
            np.testing.assert_allclose(out[k], slopes[k], rtol=1e-12)
        else:
            assert shrunk[k] == pytest.approx(2 * (m[k] - threshold), rel=1e-9, abs=1e-15)
            assert float(out[k] @ slopes[k]) >= 0.0          # same direction
        assert shrunk[k] <= m[k] + 1e-15
    assert shrunk[1] >= shrunk[0]


def test_still_prior_keeps_non_finite_slopes_and_is_off_at_zero():
    slopes = np.array([[np.nan, 0.01], [0.001, 0.0], [0.3, 0.4]], np.float32)
    out = still_prior(slopes, 0.05)
    assert out.dtype == np.float32 and np.isnan(out[0, 0]) and (out[1] == 0).all()
    np.testing.assert_array_equal(out[2], slopes[2])
    np.testing.assert_array_equal(still_prior(slopes[1:], 0.0), slopes[1:])


def test_still_prior_measures_the_length_in_its_shape():
    """With a shape W the length is |W g|: a slope along the stretched axis is kept, one as long along the
    squeezed axis is taken as the gel's wander."""
    shape = (2.0, 0.0, 0.0, 0.5)
    out = still_prior(np.array([[0.03, 0.0], [0.0, 0.06], [0.0, 0.2]]), 0.04, shape)
    np.testing.assert_allclose(out[0], [0.03 * 2 * (0.06 - 0.04) / 0.06, 0.0])
    np.testing.assert_array_equal(out[1], [0.0, 0.0])
    np.testing.assert_array_equal(out[2], [0.0, 0.2])
    rotated = (0.0, 1.0, -1.0, 0.0)     # a rotation keeps the plain length
    slopes = np.array([[0.01, 0.05], [0.05, 0.06]])
    np.testing.assert_allclose(still_prior(slopes, 0.04, rotated), still_prior(slopes, 0.04))


def test_the_lookup_bakes_the_prior_in(synthetic_presses, model):
    """The compiled table with the prior reads what the prior makes of the table without it (to the
    fixed-point step), and the exact polynomial with it what the prior makes of the polynomial."""
    reference, presses = synthetic_presses
    img = presses[11][0]
    threshold = 0.04
    shape = (1.2, 0.3, 0.0, 1.0 / 1.2)
    model = dataclasses.replace(model, still_shape=shape)
    gx, gy = model.compile(reference).slopes(img)
    px, py = model.compile(reference, still_slope=threshold).slopes(img)
    want = still_prior(np.stack([gx, gy], -1), threshold, shape)
    np.testing.assert_allclose(np.stack([px, py], -1), want, atol=3 * SLOPE_UNIT)
    assert np.count_nonzero(np.hypot(gx, gy) > 0) > np.count_nonzero(np.hypot(px, py) > 0)
    ex, ey = model.slopes(img, reference)
    qx, qy = model.slopes(img, reference, still_slope=threshold)
    np.testing.assert_allclose(np.stack([qx, qy], -1), still_prior(np.stack([ex, ey], -1), threshold, shape),
                               atol=1e-6)
    with pytest.raises(ValueError, match="still_slope"):
        model.compile(reference, still_slope=-0.1)
