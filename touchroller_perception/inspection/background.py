"""The local surface under a map and the residual's robust noise.

The local surface is a normalised Gaussian convolution (sum of weight x value over sum of weight) whose
weights leave out the pixels that lie far off the previous round's surface: defects, NaNs and the user's
mask do not pull it. Large Gaussians run on a grid reduced by area averaging, then are brought back by
bilinear interpolation: the cost is a few passes over the map whatever the scale.
"""
from __future__ import annotations

import math

import cv2
import numpy as np


def gaussian_mean(values: np.ndarray, weights: np.ndarray, sigma_px: float) -> np.ndarray:
    """sum(w v) / sum(w) under a Gaussian of `sigma_px`; NaN where no weight reaches. float32 arrays;
    `values` finite wherever the weight is not 0."""
    rows, cols = values.shape
    factor = max(1.0, sigma_px / 3.0)
    small = (max(1, round(cols / factor)), max(1, round(rows / factor)))
    w = weights if weights.dtype == np.float32 else weights.astype(np.float32)
    wv = cv2.multiply(values, w) if values.dtype == np.float32 else (values * w).astype(np.float32)
    if small != (cols, rows):
        wv = cv2.resize(wv, small, interpolation=cv2.INTER_AREA)
        w = cv2.resize(w, small, interpolation=cv2.INTER_AREA)
    sigma_small = sigma_px * small[0] / cols
    wv = cv2.GaussianBlur(wv, (0, 0), sigma_small, borderType=cv2.BORDER_REFLECT)
    w = cv2.GaussianBlur(w, (0, 0), sigma_small, borderType=cv2.BORDER_REFLECT)
    reached = w > 1e-4
    with np.errstate(divide="ignore", invalid="ignore"):
        mean = np.where(reached, wv / np.where(reached, w, 1), 0).astype(np.float32)   # on the small grid: cheap
    if small != (cols, rows):
        mean = cv2.resize(mean, (cols, rows), interpolation=cv2.INTER_LINEAR).reshape(rows, cols)
        reached = cv2.resize(reached.astype(np.float32), (cols, rows), interpolation=cv2.INTER_LINEAR) >= 0.999
        reached = reached.reshape(rows, cols)
    mean[~reached] = np.nan
    return mean


def robust_sigma(residual: np.ndarray, valid: np.ndarray, sample: int) -> float:
    """1.4826 x the median absolute deviation of the residual over (a regular sample of) the valid pixels;
    0 when nothing is valid."""
    values = residual[valid]
    if values.size == 0:
        return 0.0
    if values.size > sample:
        values = values[:: math.ceil(values.size / sample)]
    centre = np.median(values)
    return float(1.4826 * np.median(np.abs(values - centre)))


def texture_peak(residual: np.ndarray, valid: np.ndarray, block_px: int, quantile: float = 99.0,
                 max_blocks: int = 256) -> float:
    """The texture's own peaks: the median over blocks of about `block_px` (those at least 90 % valid, at most
    `max_blocks` of them spread over the map, every second pixel) of each block's `quantile` percentile of
    |residual|. A defect raises its own blocks' peaks only, so the median over blocks is the texture's;
    0 when no block is valid enough."""
    r, v = residual[::2, ::2], valid[::2, ::2]
    rows, cols = r.shape
    b = max(4, block_px // 2)
    nr, nc = rows // b, cols // b
    if nr == 0 or nc == 0:
        return 0.0
    blocks = np.abs(r[: nr * b, : nc * b]).reshape(nr, b, nc, b).transpose(0, 2, 1, 3).reshape(nr * nc, b * b)
    ok = v[: nr * b, : nc * b].reshape(nr, b, nc, b).transpose(0, 2, 1, 3).reshape(nr * nc, b * b)
    full = np.flatnonzero(ok.mean(axis=1) >= 0.9)
    if full.size == 0:
        return 0.0
    full = full[:: math.ceil(full.size / max_blocks)]
    values = np.where(ok[full], np.nan_to_num(blocks[full]), 0.0)
    return float(np.median(np.percentile(values, quantile, axis=1)))


def local_surface(values: np.ndarray, usable: np.ndarray, sigma_px: float, iterations: int, reject: float,
                  sample: int, reject_floor: float = 0.0) -> tuple[np.ndarray, float]:
    """(local surface, robust sigma of values - surface over the usable pixels). Each round leaves out the
    pixels more than max(`reject` sigmas, `reject_floor`) off the previous round's surface: the floor keeps
    a broad gentle undulation (a few sigmas high but shallower than any defect) in the surface."""
    weights = usable.astype(np.float32)
    surface = gaussian_mean(values, weights, sigma_px)
    sigma = robust_sigma(values - surface, usable, sample)
    grow = np.ones((3, 3), np.uint8)
    outliers = np.zeros(values.shape, np.uint8)
    for _ in range(iterations):
        residual = np.abs(values - surface)
        if sigma > 0 or reject_floor > 0:   # (a noise-free rest, sigma 0, keeps what the last round left out)
            outliers = np.zeros(values.shape, np.uint8)
            outliers[usable & (residual > max(reject * sigma, reject_floor))] = 1
            outliers = cv2.dilate(outliers, grow)   # the defect's flanks, below the cut, go with it
        weights = (usable & (outliers == 0)).astype(np.float32)
        surface = gaussian_mean(values, weights, sigma_px)
        sigma = robust_sigma(values - surface, usable & (outliers == 0), sample) if weights.any() else sigma
    return surface, sigma
