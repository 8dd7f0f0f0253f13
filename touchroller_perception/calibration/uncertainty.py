"""Uncertainties a calibration can stand behind: covariances robust to errors that are correlated
within a view, and jackknife spreads over presses.

Why not OpenCV's standard deviations: `cv2.calibrateCameraExtended` scales (J^T J)^-1 by the
residual variance, which is right when every corner's error is independent noise and the model is
right. Neither holds: a detector's corner error has a pattern that repeats along a board's edges,
and a distortion model with fewer terms than the lens (or one fitted only in the middle of the
image) leaves a smooth residual over each view. Errors then add up within a view instead of
averaging out, and OpenCV's sigmas come out too small (bench `calib_crosscheck`, table I).

`view_clustered_covariance` treats each view as one independent sample instead of each corner:
the cluster-robust (sandwich) covariance, built from each view's score J_v^T r_v, the sum of what
its corners' residuals say about the intrinsics. Correlations inside a view, of any form, are
carried by that sum; only independence between views is assumed. A fit pulls towards every view, so
a view's residuals are smaller than its errors; each view's residual is scaled up by its leverage
first ((I - H_v)^-1/2, Bell and McCaffrey's bias-reduced form, CR2), which makes the covariance
exactly OpenCV's on average when corner noise is independent and the model right. It is close to
the jackknife over views (CR3, slightly larger) at the cost of one Jacobian instead of a refit
per view.
"""
from __future__ import annotations

import math
from collections.abc import Sequence

import cv2
import numpy as np

from touchroller_perception.calibration.common import FloatArray

#: the intrinsic parameters in the order of the covariance `view_clustered_covariance` returns
INTRINSIC_NAMES = ("fx", "fy", "cx", "cy", "k1", "k2", "p1", "p2", "k3")


def view_clustered_covariance(object_points: np.ndarray, image_points: Sequence[np.ndarray],
                              rvecs: Sequence[np.ndarray], tvecs: Sequence[np.ndarray], k_matrix: FloatArray,
                              distortion: FloatArray, free: Sequence[bool]) -> FloatArray:
    """Covariance (9 x 9, `INTRINSIC_NAMES` order) of the intrinsics of a Zhang fit, clustered by
    view: the sandwich S^-1 (sum over views of u_v u_v^T) S^-1, S the intrinsics' normal matrix with
    the poses profiled out, u_v a view's score with its leverage taken out (CR2).

    `free` (9 flags) marks the parameters the fit solved for; the others were held and get zero
    rows and columns. Every view's pose (6 parameters) is profiled out. Returns NaN when the views
    do not determine the parameters.
    """
    free_mask = np.asarray(free, dtype=bool)
    if free_mask.size != len(INTRINSIC_NAMES):
        raise ValueError(f"free needs {len(INTRINSIC_NAMES)} flags, got {free_mask.size}")
    views = len(image_points)
    n_intrinsic = int(free_mask.sum())
    n_params = n_intrinsic + 6 * views
    dist = np.zeros(5)
    dist[:min(5, np.asarray(distortion).size)] = np.asarray(distortion, dtype=np.float64).ravel()[:5]
    object_points = np.asarray(object_points, dtype=np.float64).reshape(-1, 1, 3)
    blocks, residuals = [], []
    for points, rvec, tvec in zip(image_points, rvecs, tvecs, strict=True):
        projected, jacobian = cv2.projectPoints(object_points, np.asarray(rvec, dtype=np.float64),
                                                np.asarray(tvec, dtype=np.float64), k_matrix, dist)
        # columns: rvec (3), tvec (3), fx, fy, cx, cy, k1, k2, p1, p2, k3
        blocks.append((np.asarray(jacobian[:, 6:15])[:, free_mask], np.asarray(jacobian[:, :6])))
        residuals.append((np.asarray(points, dtype=np.float64).reshape(-1, 2) - projected.reshape(-1, 2)).ravel())
    rows = sum(r.size for r in residuals)
    if views < 2 or rows <= n_params:
        return np.full((len(INTRINSIC_NAMES), len(INTRINSIC_NAMES)), math.nan)
    # A is block-arrow shaped (intrinsics x everything, one 6 x 6 block per view's pose): profile
    # the poses out view by view (Schur complement) instead of inverting A whole
    schur = np.zeros((n_intrinsic, n_intrinsic))
    profiled = []
    for intrinsic, pose in blocks:
        try:
            within = intrinsic - pose @ np.linalg.solve(pose.T @ pose, pose.T @ intrinsic)
        except np.linalg.LinAlgError:
            return np.full((len(INTRINSIC_NAMES), len(INTRINSIC_NAMES)), math.nan)
        schur += within.T @ within
        profiled.append(within)
    try:
        inverse = np.linalg.inv(schur)
    except np.linalg.LinAlgError:
        return np.full((len(INTRINSIC_NAMES), len(INTRINSIC_NAMES)), math.nan)
    # each view's score J_v^T r_v, its residual first scaled by (I - H_v)^-1/2, H_v = J_v S^-1 J_v^T
    # the view's leverage on the intrinsics: a fit pulls towards every view, so a view's residual
    # is smaller than its error, by just that much for independent noise (bias-reduced, CR2)
    # H_v = (W_v M)(W_v M)^T with S^-1 = M M^T has rank <= the intrinsics' count: its eigenvectors
    # and eigenvalues are the thin SVD's of W_v M (rows x 9), not those of the rows x rows H_v
    # (an eigendecomposition of 98 x 98 per view cost most of the whole covariance)
    try:
        root = np.linalg.cholesky(inverse)
    except np.linalg.LinAlgError:
        return np.full((len(INTRINSIC_NAMES), len(INTRINSIC_NAMES)), math.nan)
    scores = np.zeros((views, n_intrinsic))
    for v, (within, residual) in enumerate(zip(profiled, residuals, strict=True)):
        vectors, singular, _ = np.linalg.svd(within @ root, full_matrices=False)
        shrink = 1.0 / np.sqrt(np.clip(1.0 - singular**2, 1e-6, None)) - 1.0
        scaled = residual + vectors @ (shrink * (vectors.T @ residual))
        scores[v] = within.T @ scaled
    clustered = inverse @ (scores.T @ scores) @ inverse
    out = np.zeros((len(INTRINSIC_NAMES), len(INTRINSIC_NAMES)))
    out[np.ix_(free_mask, free_mask)] = clustered
    return out


def jackknife_std(leave_one_out: FloatArray) -> float:
    """Standard error of an estimate from its values with each sample left out in turn:
    sqrt((n - 1) / n * sum (x_i - mean)^2). NaN for fewer than 2 values."""
    values = np.asarray(leave_one_out, dtype=np.float64)
    n = values.size
    if n < 2:
        return math.nan
    return math.sqrt((n - 1) / n * float(((values - values.mean()) ** 2).sum()))
