"""Ball-press calibration on presses from the test's own three-light renderer: circles refined from loose
labels, slopes recovered on held-out presses, refusals in one line."""
from __future__ import annotations

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

from .conftest import BALL, PIXEL, press_image

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
