"""Sigmas that hold when corner errors are correlated within a view (synthetic corners: fast)."""
from __future__ import annotations

import math

import cv2
import numpy as np
import pytest

from touchroller_perception import calibration as cal
from touchroller_perception.calibration.intrinsics import DISTORTION_MODELS, _zhang, free_intrinsics
from touchroller_perception.calibration.uncertainty import (
    INTRINSIC_NAMES,
    jackknife_std,
    view_clustered_covariance,
)
from touchroller_perception.geometry import CameraModel

LENS = CameraModel(fx=380.0, fy=380.0, cx=320.0, cy=240.0, distortion=(-0.2, 0.05, 0.0, 0.0, 0.0))
BOARD = cal.Chessboard()
FLAGS = DISTORTION_MODELS["k1k2"]


def views(seed: int, count: int = 12, noise: float = 0.03, view_shift: float = 0.0) -> list[np.ndarray]:
    """Corners of `count` tilted board poses with independent noise and, per view, a smooth
    error field over the board (`view_shift` px per coefficient): errors correlated within a view."""
    rng = np.random.default_rng(seed)
    objects = BOARD.object_points().astype(np.float64)
    centre = np.array([(BOARD.columns - 1) / 2, (BOARD.rows - 1) / 2, 0.0]) * BOARD.square
    out = []
    while len(out) < count:
        rotation = cv2.Rodrigues(np.radians(rng.uniform(-35, 35, 3) * np.array([1, 1, 0.5])))[0]
        distance = rng.uniform(0.15, 0.3)
        tvec = np.array([*rng.uniform(-0.4, 0.4, 2) * distance, distance]) - rotation @ centre
        uv, _ = cv2.projectPoints(objects, cv2.Rodrigues(rotation)[0], tvec, LENS.K, np.array(LENS.distortion))
        uv = uv.reshape(-1, 2)
        if np.all(uv > 20) and np.all(uv < [620, 460]):
            # a smooth error over the board, its own in each view (a pose cannot absorb a quadratic)
            x, y = (objects[:, 0] / centre[0] - 1.0), (objects[:, 1] / centre[1] - 1.0)
            pattern = np.stack([x * x - 0.4, y * y - 0.4, x * y], axis=1) @ rng.normal(0.0, view_shift, (3, 2))
            out.append(uv + rng.normal(0.0, noise, uv.shape) + pattern)
    return out


def principal_point_z(seed: int, view_shift: float) -> tuple[float, float]:
    """|cx error| / sigma for OpenCV's sigma and for the view-clustered one."""
    corners = views(seed, view_shift=view_shift)
    fit = _zhang(BOARD.object_points(), corners, (640, 480), FLAGS)
    covariance = view_clustered_covariance(BOARD.object_points(), corners, fit.rvecs, fit.tvecs, fit.k_matrix,
                                           fit.distortion, free_intrinsics(FLAGS))
    error = abs(fit.k_matrix[0, 2] - LENS.cx)
    return error / fit.sigma["cx"], error / math.sqrt(covariance[2, 2])


def test_clustered_covariance_agrees_with_opencv_for_independent_noise():
    """Independent corner noise and the right model: OpenCV's sigma is right, and the clustered
    one agrees with it on average over trials (each trial's is noisier: it has fewer samples)."""
    opencv, clustered = [], []
    for seed in range(10):
        corners = views(seed, count=20)
        fit = _zhang(BOARD.object_points(), corners, (640, 480), FLAGS)
        covariance = view_clustered_covariance(BOARD.object_points(), corners, fit.rvecs, fit.tvecs, fit.k_matrix,
                                               fit.distortion, free_intrinsics(FLAGS))
        opencv.append([fit.sigma[name] for name in INTRINSIC_NAMES[:6]])
        clustered.append(np.sqrt(np.diag(covariance)[:6]))
        # held terms (p1, p2, k3) have none
        assert np.all(covariance[6:] == 0) and np.all(covariance[:, 6:] == 0)
    ratio = np.sqrt(np.mean(np.square(clustered), axis=0) / np.mean(np.square(opencv), axis=0))
    assert np.all((ratio > 0.75) & (ratio < 1.25)), ratio


def test_clustered_sigma_covers_errors_correlated_within_a_view():
    """Each view's corners carry a smooth error of their own: OpenCV's sigma, which counts every
    corner as independent, leaves the true principal point outside 2 sigma in about half of the
    trials; the view-clustered sigma in about 5 % of them."""
    z = np.array([principal_point_z(seed, view_shift=0.1) for seed in range(40)])
    opencv, clustered = z[:, 0], z[:, 1]
    assert np.mean(opencv <= 2.0) < 0.6
    assert np.mean(clustered <= 2.0) >= 0.85
    assert 0.4 < np.median(clustered) < 1.0


def test_intrinsics_result_carries_the_clustered_sigma_and_covariance():
    """calibrate_intrinsics reports the clustered sigma (larger than OpenCV's here) and its covariance."""
    from touchroller_perception.calibration.intrinsics import intrinsics_uncertainty

    corners = views(5, view_shift=0.1)
    fit = _zhang(BOARD.object_points(), corners, (640, 480), FLAGS)
    covariance, sigma = intrinsics_uncertainty(BOARD.object_points(), corners, (640, 480), fit, "k1k2")
    assert sigma["cx"] == pytest.approx(math.sqrt(covariance[2, 2]))
    assert sigma["cx"] > 1.5 * fit.sigma["cx"] and sigma["cy"] > 1.5 * fit.sigma["cy"]
    assert np.allclose(covariance, covariance.T)


def test_jackknife_of_a_mean_is_its_standard_error():
    values = np.array([1.0, 2.0, 4.0, 7.0, 11.0])
    leave_one_out = np.array([np.delete(values, i).mean() for i in range(values.size)])
    assert jackknife_std(leave_one_out) == pytest.approx(values.std(ddof=1) / math.sqrt(values.size))
    assert math.isnan(jackknife_std(np.array([1.0])))


def test_covariance_needs_one_flag_per_parameter():
    with pytest.raises(ValueError, match="9 flags"):
        view_clustered_covariance(BOARD.object_points(), [], [], [], LENS.K, np.zeros(5), [True] * 4)
