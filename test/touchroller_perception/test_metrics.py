"""Map quality metrics: the paper's SSIM / PSNR / MAE(%) and alignment, and the like-for-like comparison."""
from __future__ import annotations

import math

import cv2
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from touchroller_perception.metrics import (
    align_affine_3pt,
    compare_to_truth,
    drift_percent,
    length_error_percent,
    mae_percent,
    psnr,
    ssim,
    standardise,
)


def texture(shape=(300, 200), seed=0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    t = cv2.GaussianBlur(rng.normal(size=shape).astype(np.float32), (0, 0), 2.0)
    return np.clip(128 + 60 * t / t.std(), 0, 255).astype(np.float32)


def test_scores_of_identical_and_opposite_images():
    a = texture()
    assert ssim(a, a) == pytest.approx(1.0)
    assert psnr(a, a) == math.inf
    assert mae_percent(a, a) == 0.0
    black, white = np.zeros((20, 20)), np.full((20, 20), 255.0)
    assert mae_percent(black, white) == pytest.approx(100.0)
    assert psnr(black, white) == pytest.approx(0.0)


def test_scores_fall_with_noise():
    a = texture()
    rng = np.random.default_rng(1)
    small = a + rng.normal(0, 5, a.shape)
    large = a + rng.normal(0, 30, a.shape)
    assert ssim(a, small) > ssim(a, large)
    assert psnr(a, small) > psnr(a, large)
    assert mae_percent(a, small) < mae_percent(a, large)


def test_bad_inputs_are_rejected():
    with pytest.raises(ValueError, match="same shape"):
        ssim(np.zeros((10, 10)), np.zeros((10, 11)))
    with pytest.raises(ValueError, match="non-finite"):
        psnr(np.full((10, 10), np.nan), np.zeros((10, 10)))
    with pytest.raises(ValueError, match="2-D"):
        mae_percent(np.zeros((3, 3)), np.zeros((3, 3)))


def test_align_affine_3pt_undoes_a_similarity_and_stays_one():
    ref = texture((200, 200))
    # the map: the reference shrunk to 80 % and shifted by (7, 11)
    m = np.float32([[0.8, 0, 7], [0, 0.8, 11]])
    small = cv2.warpAffine(ref, m, (180, 180))
    pts_map = [(7 + 0.8 * 20, 11 + 0.8 * 20), (7 + 0.8 * 20, 11 + 0.8 * 180)]
    pts_ref = [(20, 20), (20, 180)]
    warped, valid, matrix = align_affine_3pt(small, ref, pts_map, pts_ref)
    a, b = matrix[0, :2], matrix[1, :2]
    assert a[0] == pytest.approx(b[1]) and a[1] == pytest.approx(-b[0])  # similarity: no shear
    assert a[0] == pytest.approx(1 / 0.8, rel=1e-6)
    core = np.zeros_like(valid)
    core[30:170, 30:170] = True
    assert ssim(warped[30:170, 30:170], ref[30:170, 30:170]) > 0.9
    assert valid[core].all()


def test_align_affine_3pt_rejects_degenerate_points():
    with pytest.raises(ValueError, match="distinct"):
        align_affine_3pt(texture(), texture(), [(1, 1), (1, 1)], [(0, 0), (0, 5)])


@settings(max_examples=10, deadline=None)
@given(dy=st.floats(-20, 20), dx=st.floats(-10, 10))
def test_compare_to_truth_finds_a_subpixel_offset(dy, dx):
    truth = texture((300, 200))
    m = np.float32([[1, 0, -40 - dx], [0, 1, -50 - dy]])
    crop = cv2.warpAffine(truth, m, (120, 200))  # map(y, x) = truth(y + 50 + dy, x + 40 + dx)
    res = compare_to_truth(crop, truth, normalise=False)
    assert res["offset_rows"] == pytest.approx(50 + dy, abs=0.2)
    assert res["offset_cols"] == pytest.approx(40 + dx, abs=0.2)
    assert res["ssim"] > 0.95


def test_compare_to_truth_does_not_hide_a_stretch():
    truth = texture((400, 200))
    exact = truth[50:350, 20:180]
    stretched = cv2.resize(exact, (160, 315), interpolation=cv2.INTER_LINEAR)  # 5 % too long
    good, bad = compare_to_truth(exact, truth), compare_to_truth(stretched, truth)
    assert good["ssim"] > 0.95
    assert bad["ssim"] < good["ssim"] - 0.2


def test_compare_to_truth_normalises_contrast_and_masks_invalid_pixels():
    truth = texture((300, 200))
    faint = truth[40:240, 10:190] * 0.1 + 100  # same structure, a tenth of the contrast
    valid = np.ones(faint.shape, bool)
    valid[:, :5] = False
    faint[:, :5] = 0  # columns no frame reached
    res = compare_to_truth(faint, truth, valid=valid)
    assert res["ssim"] > 0.95
    assert res["overlap_cols"] <= 175
    with pytest.raises(ValueError, match="no valid"):
        compare_to_truth(faint, truth, valid=np.zeros(faint.shape, bool))


def test_standardise_and_length_errors():
    a = standardise(texture())
    assert a.mean() == pytest.approx(127.5, abs=1.0)
    assert np.all(standardise(np.full((5, 5), 3.0)) == 127.5)
    assert length_error_percent(101.0, 100.0) == pytest.approx(1.0)
    assert length_error_percent(-99.0, -100.0) == pytest.approx(-1.0)
    with pytest.raises(ValueError):
        length_error_percent(1.0, 0.0)
    true = np.linspace(0, 100, 11)
    assert drift_percent(true * 1.02, true) == pytest.approx(2.0)
    assert drift_percent(true + 5.0, true) == pytest.approx(0.0)
