"""Height per frame: a calibrated model plus the integrator give a press's depth in metres; no contact
gives zero; a band gives NaN outside; the model file round-trips and refuses what it is not."""
from __future__ import annotations

import json

import cv2
import numpy as np
import pytest

from touchroller_perception.geometry import CameraModel
from touchroller_perception.height import (
    BallPress,
    HeightConfig,
    HeightEstimator,
    PhotometricConfig,
    PhotometricModel,
    PressCalibrationConfig,
    band_height,
    calibrate_photometric,
    contact_band,
)

from .conftest import BALL, PIXEL

CONFIG = PressCalibrationConfig(model=PhotometricConfig(colour_degree=3, position_degree=1, smoothing=0.7,
                                                        lookup_cells=(4, 3)), far_fraction=0.05)


@pytest.fixture(scope="module")
def calibrated(synthetic_presses):
    reference, presses = synthetic_presses
    items = [BallPress(img, cu, cv, contact, (PIXEL, PIXEL), str(k))
             for k, (img, cu, cv, contact, *_rest) in enumerate(presses[:10])]
    return calibrate_photometric(items, reference, BALL, CONFIG).model


def test_held_out_press_depth(synthetic_presses, calibrated):
    reference, presses = synthetic_presses
    estimator = HeightEstimator(calibrated, reference, PIXEL)
    for img, cu, cv, _contact, _gx, _gy, z in presses[10:]:
        got = estimator.height(img)
        assert got.dtype == np.float32 and got.shape == img.shape[:2] and np.isfinite(got).all()
        centre = got[int(round(cv)), int(round(cu))]
        truth = z[int(round(cv)), int(round(cu))]
        assert centre == pytest.approx(truth, rel=0.1)
        assert abs(np.median(got[:, :5])) < 0.05 * truth     # far from the ball: undeformed


def test_no_contact_reads_zero(synthetic_presses, calibrated):
    reference, _ = synthetic_presses
    got = HeightEstimator(calibrated, reference, PIXEL).height(reference)
    assert np.sqrt(np.mean(got**2)) < 1e-6


def test_band_rows_and_band_height(synthetic_presses, calibrated):
    reference, presses = synthetic_presses
    img = presses[10][0]
    est = HeightEstimator(calibrated, reference, PIXEL, rows=(30, 90), config=HeightConfig())
    full = est.height(img)
    assert np.isnan(full[:30]).all() and np.isnan(full[90:]).all() and np.isfinite(full[30:90]).all()
    np.testing.assert_array_equal(est.band(img), full[30:90])
    np.testing.assert_array_equal(est.band(img[30:90]), full[30:90])
    exact = band_height(img[30:90], reference[30:90], calibrated, PIXEL, first_row=30)
    assert exact.shape == (60, img.shape[1])
    assert np.abs(exact - full[30:90]).max() < 0.1 * np.nanmax(full)
    with pytest.raises(ValueError):
        HeightEstimator(calibrated, reference, PIXEL, rows=(90, 30))
    with pytest.raises(ValueError):
        HeightEstimator(calibrated, reference[:50], PIXEL)
    with pytest.raises(ValueError):
        HeightEstimator(calibrated, reference, -1.0)


def test_downsampled_integration_is_close(synthetic_presses, calibrated):
    reference, presses = synthetic_presses
    img = presses[11][0]
    a = HeightEstimator(calibrated, reference, PIXEL).height(img)
    b = HeightEstimator(calibrated, reference, PIXEL, config=HeightConfig(downsample=2)).height(img)
    assert b.shape == a.shape and np.abs(a - b).max() < 0.1 * a.max()


def test_model_file_round_trip(tmp_path, calibrated):
    path = tmp_path / "p.npz"
    calibrated.save(path)
    loaded = PhotometricModel.load(path)
    np.testing.assert_array_equal(loaded.coefficients, calibrated.coefficients)
    assert loaded.config == calibrated.config and (loaded.width, loaded.height) == (calibrated.width, calibrated.height)
    bad = tmp_path / "bad.npz"
    bad.write_bytes(b"not a zip")
    with pytest.raises(ValueError, match="not a photometric model"):
        PhotometricModel.load(bad)
    np.savez(tmp_path / "other.npz", x=np.zeros(3))
    with pytest.raises(ValueError, match="not a photometric model"):
        PhotometricModel.load(tmp_path / "other.npz")


def test_contact_band_of_the_default_camera():
    camera = CameraModel()
    band = contact_band(camera, max_depth=1e-3)
    v0, v1 = band.rows
    assert v0 < band.contact_row < v1 and v1 - v0 < camera.height / 2
    assert all(1e-6 < s < 1e-3 for s in band.pixel_size)
    deeper = contact_band(camera, max_depth=2e-3)
    assert deeper.rows[1] - deeper.rows[0] > v1 - v0
    with pytest.raises(ValueError):
        contact_band(camera, max_depth=0.0)


def test_still_change_reads_a_frame_that_matches_the_reference_as_flat(synthetic_presses, calibrated):
    """A no-contact frame whose colour wanders by up to 2 % against the reference (light that changed
    unevenly: no gain takes it out) integrates into a bowl without the zero-slope prior, and to 0 with
    it; a press still reads its depth."""
    reference, presses = synthetic_presses
    h, w = reference.shape[:2]
    vv, uu = np.mgrid[0:h, 0:w]
    wander = 1.0 + 0.02 * np.stack([np.cos(np.pi * uu / w), np.sin(np.pi * vv / h), np.cos(np.pi * (uu + vv) / w)],
                                   axis=-1)
    frame = np.clip(reference.astype(np.float64) * wander, 0, 255).astype(np.uint8)
    plain = HeightEstimator(calibrated, reference, PIXEL).height(frame)
    still = HeightEstimator(calibrated, reference, PIXEL, config=HeightConfig(still_change=0.05))
    assert np.sqrt(np.mean(plain**2)) > 1e-6
    assert np.sqrt(np.mean(still.height(frame) ** 2)) < 1e-9
    img, cu, cv, _contact, _gx, _gy, z = presses[10]
    got = still.height(img)
    assert got[int(round(cv)), int(round(cu))] == pytest.approx(z[int(round(cv)), int(round(cu))], rel=0.1)
    exact = band_height(frame[30:90], reference[30:90], calibrated, PIXEL, first_row=30,
                        config=HeightConfig(still_change=0.05))
    assert np.abs(exact).max() < 1e-9
    with pytest.raises(ValueError):
        HeightConfig(still_change=-0.1)


def _wander(shape, rng, amplitude=0.01, sigma=3.0):
    """1 + a colour wander per channel in patches a few pixels across (a gel's creases, uneven light)."""
    field = cv2.GaussianBlur(rng.normal(0.0, 1.0, shape), (0, 0), sigma)
    return 1.0 + field * (amplitude / field.std())


def test_the_models_zero_slope_prior_reads_a_wandering_no_contact_frame_flatter(synthetic_presses):
    """Presses whose colour wanders in patches a few pixels across teach the calibration what the undeformed
    gel reads (`still_slope`); a no-contact frame that wanders alike then reads less relief with the prior
    (the default) than without it (`still_slope` 0, the old behaviour), and a held-out press keeps its depth."""
    reference, presses = synthetic_presses
    rng = np.random.default_rng(5)
    items = [BallPress(np.clip(np.rint(img * _wander(img.shape, rng)), 0, 255).astype(np.uint8), cu, cv, contact,
                       (PIXEL, PIXEL), str(k)) for k, (img, cu, cv, contact, *_rest) in enumerate(presses[:10])]
    model = calibrate_photometric(items, reference, BALL, CONFIG).model
    assert model.still_slope > 0
    frame = np.clip(np.rint(reference * _wander(reference.shape, rng)), 0, 255).astype(np.uint8)
    off = HeightEstimator(model, reference, PIXEL, config=HeightConfig(still_slope=0.0)).height(frame)
    default = HeightEstimator(model, reference, PIXEL)
    on = default.height(frame)
    assert np.sqrt(np.mean(on**2)) < 0.7 * np.sqrt(np.mean(off**2))
    img, cu, cv, _contact, _gx, _gy, z = presses[10]
    got = default.height(img)
    assert got[int(round(cv)), int(round(cu))] == pytest.approx(z[int(round(cv)), int(round(cu))], rel=0.1)
    exact_on = band_height(frame[30:90], reference[30:90], model, PIXEL, first_row=30)
    exact_off = band_height(frame[30:90], reference[30:90], model, PIXEL, first_row=30,
                            config=HeightConfig(still_slope=0.0))
    assert np.sqrt(np.mean(exact_on**2)) < 0.7 * np.sqrt(np.mean(exact_off**2))
    assert HeightConfig(still_slope=0.02).prior_slope(model) == 0.02
    for bad in (-0.01, float("nan"), 2.0):
        with pytest.raises(ValueError, match="still_slope"):
            HeightConfig(still_slope=bad)


def test_the_prior_threshold_round_trips_and_old_files_have_none(tmp_path, calibrated):
    path = tmp_path / "m.npz"
    calibrated.save(path)
    loaded = PhotometricModel.load(path)
    assert loaded.still_slope == calibrated.still_slope > 0 and loaded.still_shape == calibrated.still_shape
    assert calibrated.still_shape != (1.0, 0.0, 0.0, 1.0)
    with np.load(path) as data:
        arrays = dict(data)
    meta = json.loads(str(arrays["meta"]))
    skewed = dict(meta, still_shape=[2.0, 0.0, 0.0, 1.0])     # not of unit determinant
    arrays["meta"] = np.array(json.dumps(skewed))
    np.savez(tmp_path / "skewed.npz", **arrays)
    with pytest.raises(ValueError, match="still_shape is not of determinant 1"):
        PhotometricModel.load(tmp_path / "skewed.npz")
    del meta["still_slope"], meta["still_shape"]     # a model file made before the prior
    arrays["meta"] = np.array(json.dumps(meta))
    np.savez(tmp_path / "old.npz", **arrays)
    old = PhotometricModel.load(tmp_path / "old.npz")
    assert old.still_slope == 0.0 and old.still_shape == (1.0, 0.0, 0.0, 1.0)
    meta["still_slope"] = -1.0
    arrays["meta"] = np.array(json.dumps(meta))
    np.savez(tmp_path / "bad.npz", **arrays)
    with pytest.raises(ValueError, match="non-finite or non-positive"):
        PhotometricModel.load(tmp_path / "bad.npz")
