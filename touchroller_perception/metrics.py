"""Map quality metrics: the paper's SSIM / PSNR / MAE(%) after its 3-point affine alignment, and a
like-for-like comparison against a simulator's ground-truth surface (issue 5). No rclpy here.

The paper (section IV-A) compares the tactile map with a grey top-down photo: two pairs of points are
picked on corresponding vertical lines, a third pair completes a right isosceles triangle in each image,
and `cv2.getAffineTransform` + `cv2.warpAffine` align the map to the photo. Such a transform is a
similarity (uniform scale, no shear), so a map stretched along the roll by drift stays stretched.
"""
from __future__ import annotations

import math
from collections.abc import Sequence
from typing import Any

import cv2
import numpy as np
from numpy.typing import ArrayLike
from skimage.metrics import peak_signal_noise_ratio, structural_similarity

DATA_RANGE = 255.0


def _pair(a: ArrayLike, b: ArrayLike) -> tuple[np.ndarray, np.ndarray]:
    a = np.asarray(a, dtype=np.float64)
    b = np.asarray(b, dtype=np.float64)
    if a.shape != b.shape:
        raise ValueError(f"images must have the same shape, got {a.shape} and {b.shape}")
    if a.ndim != 2 or min(a.shape) < 7:
        raise ValueError(f"expected 2-D grey images of at least 7x7 pixels, got shape {a.shape}")
    if not (np.isfinite(a).all() and np.isfinite(b).all()):
        raise ValueError("images contain non-finite values; crop or mask them first")
    return a, b


def ssim(a: ArrayLike, b: ArrayLike) -> float:
    """Structural similarity (Wang et al. 2004, 7x7 windows) of two grey images on a 0..255 scale."""
    a, b = _pair(a, b)
    return float(structural_similarity(a, b, data_range=DATA_RANGE))


def psnr(a: ArrayLike, b: ArrayLike) -> float:
    """Peak signal-to-noise ratio in dB for 0..255 images (inf when identical)."""
    a, b = _pair(a, b)
    if np.array_equal(a, b):
        return math.inf
    return float(peak_signal_noise_ratio(a, b, data_range=DATA_RANGE))


def mae_percent(a: ArrayLike, b: ArrayLike) -> float:
    """Mean absolute error as a percentage of the 0..255 range (the paper's MAE column)."""
    a, b = _pair(a, b)
    return float(np.mean(np.abs(a - b)) / DATA_RANGE * 100.0)


def _third_point(p1: np.ndarray, p2: np.ndarray) -> np.ndarray:
    """Completes a right isosceles triangle with the right angle at p1 (p2 - p1 turned by 90 degrees)."""
    d = p2 - p1
    return p1 + np.array([-d[1], d[0]])


def align_affine_3pt(image: ArrayLike, reference: ArrayLike,
                     image_points: Sequence[Sequence[float]] | None = None,
                     reference_points: Sequence[Sequence[float]] | None = None,
                     ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The paper's constrained alignment of `image` (the map) onto `reference`.

    `image_points` and `reference_points` are two (x, y) points each, on a vertical line (same x) in
    their image; a third point per image completes a right isosceles triangle. Without points the
    left edges are matched top to bottom (the map spans the reference's height).
    Returns (warped image in the reference's frame, valid mask, 2x3 affine matrix).
    """
    img = np.asarray(image, dtype=np.float32)
    ref = np.asarray(reference)
    if img.ndim != 2 or ref.ndim != 2:
        raise ValueError("align_affine_3pt expects 2-D grey images")
    if image_points is None:
        image_points = ((0.0, 0.0), (0.0, img.shape[0] - 1.0))
    if reference_points is None:
        reference_points = ((0.0, 0.0), (0.0, ref.shape[0] - 1.0))
    src = np.asarray(image_points, np.float64).reshape(2, 2)
    dst = np.asarray(reference_points, np.float64).reshape(2, 2)
    for name, pts in (("image_points", src), ("reference_points", dst)):
        if not np.isfinite(pts).all() or np.allclose(pts[0], pts[1]):
            raise ValueError(f"{name} must be two distinct finite points")
    src3 = np.vstack([src, _third_point(src[0], src[1])]).astype(np.float32)
    dst3 = np.vstack([dst, _third_point(dst[0], dst[1])]).astype(np.float32)
    matrix = cv2.getAffineTransform(src3, dst3)
    size = (ref.shape[1], ref.shape[0])
    warped = cv2.warpAffine(img, matrix, size, flags=cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT)
    valid = cv2.warpAffine(np.ones_like(img), matrix, size, flags=cv2.INTER_NEAREST,
                           borderMode=cv2.BORDER_CONSTANT) > 0.5
    return warped, valid, matrix


def valid_box(mask: np.ndarray) -> tuple[slice, slice] | None:
    """A large axis-aligned box of valid pixels: the bounding box, trimmed greedily at the edge with
    the largest share of invalid pixels until none is left."""
    rows, cols = np.flatnonzero(mask.any(axis=1)), np.flatnonzero(mask.any(axis=0))
    if rows.size == 0:
        return None
    r0, r1, c0, c1 = rows[0], rows[-1] + 1, cols[0], cols[-1] + 1
    while r1 - r0 > 0 and c1 - c0 > 0:
        box = mask[r0:r1, c0:c1]
        bad_rows = (~box).sum(axis=1) / box.shape[1]
        bad_cols = (~box).sum(axis=0) / box.shape[0]
        if not bad_rows.any():
            return slice(r0, r1), slice(c0, c1)
        edges = (bad_rows[0], bad_rows[-1], bad_cols[0], bad_cols[-1])
        worst = int(np.argmax(edges))
        if edges[worst] == 0:  # a hole inside: cut away the side nearer to it
            i, j = np.unravel_index(np.argmax(~box), box.shape)
            worst = int(np.argmin((i, box.shape[0] - i, j, box.shape[1] - j)))
        r0, r1, c0, c1 = (r0 + (worst == 0), r1 - (worst == 1), c0 + (worst == 2), c1 - (worst == 3))
    return None


def scores(a: ArrayLike, b: ArrayLike) -> dict[str, float]:
    """SSIM, PSNR (dB) and MAE (%) of two same-size grey images."""
    return {"ssim": ssim(a, b), "psnr": psnr(a, b), "mae_percent": mae_percent(a, b)}


def _locate(template: np.ndarray, image: np.ndarray) -> tuple[float, float, float]:
    """Subpixel (row, col) of `template` in `image` by normalised cross-correlation; and the peak score."""
    result = cv2.matchTemplate(image.astype(np.float32), template.astype(np.float32), cv2.TM_CCOEFF_NORMED)
    _, peak, _, (col, row) = cv2.minMaxLoc(result)

    def refine(values: np.ndarray, i: int) -> float:
        if 0 < i < len(values) - 1:
            a, b, c = values[i - 1], values[i], values[i + 1]
            den = a - 2 * b + c
            if den < -1e-12:
                return float(np.clip(0.5 * (a - c) / den, -0.5, 0.5))
        return 0.0

    return row + refine(result[:, col], row), col + refine(result[row, :], col), float(peak)


def compare_to_truth(map_image: ArrayLike, truth: ArrayLike, *, valid: ArrayLike | None = None,
                     normalise: bool = True, margin: float = 0.1) -> dict[str, Any]:
    """Like-for-like map quality against a ground-truth surface at the same (camera pixel) scale.

    The map is located in the truth by normalised cross-correlation (translation only, subpixel: no
    scale, so drift is not hidden), both are cropped to their overlap, and SSIM / PSNR / MAE(%) are
    computed. With `normalise` both are first `standardise`d (same mean and contrast), so the scores
    measure structure: a tactile map's contrast is arbitrary (exposure, LED power, grey conversion),
    and on low-contrast images SSIM's stabilising constants would otherwise dominate.
    `valid` masks map pixels that carry data (default: all). Returns the scores and the alignment.
    """
    m = np.asarray(map_image, dtype=np.float64)
    t = np.asarray(truth, dtype=np.float64)
    if m.ndim != 2 or t.ndim != 2:
        raise ValueError("compare_to_truth expects 2-D grey images")
    mask = np.ones(m.shape, bool) if valid is None else np.asarray(valid, bool)
    if mask.shape != m.shape:
        raise ValueError(f"valid mask shape {mask.shape} differs from the map's {m.shape}")
    mask &= np.isfinite(m)
    box = valid_box(mask)
    if box is None:
        raise ValueError("the map has no valid pixels")
    m = m[box]
    origin = (box[0].start, box[1].start)
    # The template: the map's core, smaller than the truth in both directions.
    mr = int(max(margin * m.shape[0], m.shape[0] - t.shape[0] + 2))
    mc = int(max(margin * m.shape[1], m.shape[1] - t.shape[1] + 2))
    r0, c0 = mr // 2, mc // 2
    core = m[r0:m.shape[0] - (mr - r0), c0:m.shape[1] - (mc - c0)]
    if min(core.shape) < 16:
        raise ValueError(f"map {m.shape} and truth {t.shape} overlap too little to compare")
    row, col, peak = _locate(core, t)
    # truth(y, x) ~ map(y - dy, x - dx)
    dy, dx = row - r0, col - c0
    shift = np.array([[1, 0, dx], [0, 1, dy]], dtype=np.float32)
    size = (t.shape[1], t.shape[0])
    warped = cv2.warpAffine(m.astype(np.float32), shift, size, flags=cv2.INTER_LINEAR)
    inside = cv2.warpAffine(np.ones(m.shape, np.float32), shift, size, flags=cv2.INTER_LINEAR) > 0.999
    box = valid_box(inside)
    if box is None:
        raise ValueError("map and truth do not overlap")
    a, b = warped[box].astype(np.float64), t[box]
    if normalise:
        a, b = standardise(a), standardise(b)
    out: dict[str, Any] = scores(a, b)
    out.update({
        "offset_rows": float(dy - origin[0]), "offset_cols": float(dx - origin[1]),
        "overlap_rows": int(a.shape[0]), "overlap_cols": int(a.shape[1]),
        "ncc_peak": peak, "normalised": bool(normalise),
    })
    return out


def standardise(image: ArrayLike, level: float = 127.5, spread: float = DATA_RANGE / 6.0) -> np.ndarray:
    """Grey levels shifted and scaled to mean `level` and standard deviation `spread`, clipped to 0..255."""
    a = np.asarray(image, dtype=np.float64)
    std = float(a.std())
    if not math.isfinite(std) or std < 1e-9:
        return np.full(a.shape, level)
    return np.clip((a - a.mean()) / std * spread + level, 0.0, DATA_RANGE)


def length_error_percent(estimated_px: float, true_px: float) -> float:
    """Signed error of a stitched length against the truth, % of the true length."""
    if not (math.isfinite(estimated_px) and math.isfinite(true_px)) or abs(true_px) < 1e-9:
        raise ValueError(f"need finite lengths and a non-zero true length, got {estimated_px}, {true_px}")
    return float((estimated_px - true_px) / true_px * 100.0)


def drift_percent(estimated_positions: ArrayLike, true_positions: ArrayLike) -> float:
    """Largest |position error| along the scan, % of the true travelled length (0 = no drift)."""
    est = np.asarray(estimated_positions, np.float64)
    true = np.asarray(true_positions, np.float64)
    if est.shape != true.shape or est.ndim != 1 or est.size < 2:
        raise ValueError("need two equally long 1-D position sequences")
    est, true = est - est[0], true - true[0]
    span = float(np.max(np.abs(true)))
    if span < 1e-9:
        raise ValueError("the true positions do not move")
    return float(np.max(np.abs(est - true)) / span * 100.0)
