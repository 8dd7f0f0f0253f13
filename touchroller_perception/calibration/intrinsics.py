"""Intrinsics and lens distortion from chessboard views (Zhang's method, OpenCV), with view
rejection, a distortion model chosen by held-out views, and what the views cover.

Why choose the distortion model: boards seen only in the middle of the image pin down the lens
there and nowhere else, and OpenCV's 5 coefficients (k1, k2, p1, p2, k3) then fit the corners'
noise with large k2 and k3 that extrapolate to many pixels of invented distortion in the image
corners. `distortion="auto"` (the default) starts from k1, k2 and adds k3 only when the held-out
views (k-fold: each view predicted by a fit without it) improve by more than one standard error
of the paired difference, and only when the views reach the image corners (k3 acts there). The
tangential p1, p2 are a different case: over a small part of the image they look like a shift
of the centre of distortion, so held-out views predict equally well with or without them and
cannot choose. Left out when the lens has them, the fit moves the principal point to the
centre of distortion instead (about p / k1 away: p ~ 4e-4 under k1 = -0.16 is 0.7 px at
f = 380 px), and every ray with it. Kept when the lens has none, they trade with the principal
point and add to its noise. The question is which model predicts the rays better, so they are
kept when the fit's own evidence for them pays for their two parameters by Akaike's criterion:
their Wald statistic (p / sigma_p, squared and summed) reaches 2 per parameter, 4. (A
significance test at the 99 % point, 9.21, asks whether the lens has them at all, and leaves
weak but real terms out.)
"""
from __future__ import annotations

import dataclasses
import math
from collections.abc import Callable, Iterable, Sequence
from typing import Any

import cv2
import numpy as np
from numpy.typing import NDArray

from touchroller_perception.calibration.common import (
    CalibrationError,
    FloatArray,
    image_size,
    require_views,
)
from touchroller_perception.calibration.coverage import BoardCoverage, board_coverage
from touchroller_perception.calibration.uncertainty import INTRINSIC_NAMES, view_clustered_covariance
from touchroller_perception.geometry import CameraModel
from touchroller_perception.images import to_grey

DISTORTION_NAMES = ("k1", "k2", "p1", "p2", "k3")
#: distortion models by name -> cv2.calibrateCamera flags (fixed terms stay 0)
DISTORTION_MODELS: dict[str, int] = {
    "k1": cv2.CALIB_FIX_K2 | cv2.CALIB_FIX_K3 | cv2.CALIB_ZERO_TANGENT_DIST,
    "k1k2": cv2.CALIB_FIX_K3 | cv2.CALIB_ZERO_TANGENT_DIST,
    "radial": cv2.CALIB_ZERO_TANGENT_DIST,          # k1, k2, k3
    "k1k2p": cv2.CALIB_FIX_K3,                      # k1, k2, p1, p2
    "full": 0,                                      # k1, k2, p1, p2, k3
}
#: what `distortion="auto"` chooses between, simplest first
AUTO_CANDIDATES = ("k1k2p", "full")


#: how `IntrinsicsConfig.corners` places the corners: in the image, or refined on the board's plane
CORNER_METHODS = ("image", "fronto_parallel")

#: Most inner corners along a chessboard side (printed boards have a dozen or two).
MAX_BOARD_SIDE = 100


@dataclasses.dataclass(frozen=True)
class Chessboard:
    """A planar chessboard: `columns` x `rows` INNER corners (OpenCV's convention), square side in m.
    Defaults: the simulator's `calibration_chessboard` (7x7 inner corners, 12 mm squares)."""

    columns: int = 7
    rows: int = 7
    square: float = 0.012

    def __post_init__(self) -> None:
        if self.columns > MAX_BOARD_SIDE or self.rows > MAX_BOARD_SIDE:
            raise CalibrationError(f"a chessboard has at most {MAX_BOARD_SIDE}x{MAX_BOARD_SIDE} inner corners, got "
                                   f"{self.columns}x{self.rows}")
        if self.columns < 2 or self.rows < 2:
            raise CalibrationError(f"a chessboard needs at least 2x2 inner corners, got {self.columns}x{self.rows}")
        if not (self.square > 0 and math.isfinite(self.square)):
            raise CalibrationError(f"chessboard square size must be positive, got {self.square}")

    @property
    def pattern_size(self) -> tuple[int, int]:
        return (self.columns, self.rows)

    def object_points(self) -> NDArray[np.float32]:
        """Corner coordinates on the board plane (z = 0), in OpenCV's detection order (row-major)."""
        grid = np.mgrid[0:self.columns, 0:self.rows].T.reshape(-1, 2) * self.square
        return np.hstack([grid, np.zeros((grid.shape[0], 1))]).astype(np.float32)


@dataclasses.dataclass(frozen=True)
class ChessboardDetection:
    corners: FloatArray | None      # (N, 2) subpixel corners, None if not found
    edge_width: float               # px, OpenCV's chessboard sharpness (NaN if no board)
    reason: str | None              # why the view is unusable, None if usable


def find_chessboard(image: np.ndarray, board: Chessboard, max_edge_width: float = 4.0) -> ChessboardDetection:
    """Subpixel inner corners of `board` in `image` (findChessboardCornersSB), with a blur check."""
    try:
        gray = to_grey(image)
    except ValueError as exc:
        raise CalibrationError(str(exc)) from None
    # the classic detector + cornerSubPix takes ~1 ms a view; the sector-based one (~30-90 ms) is the fallback
    found, corners = cv2.findChessboardCorners(
        gray, board.pattern_size,
        flags=cv2.CALIB_CB_ADAPTIVE_THRESH | cv2.CALIB_CB_NORMALIZE_IMAGE | cv2.CALIB_CB_FAST_CHECK)
    if found and corners is not None:
        corners = _refine_corners(gray, corners.reshape(-1, 2), board)
    else:
        found, corners = cv2.findChessboardCornersSB(gray, board.pattern_size,
                                                     flags=cv2.CALIB_CB_NORMALIZE_IMAGE | cv2.CALIB_CB_ACCURACY)
        if found and corners is not None:     # its corners are 4-8x noisier than the saddle points
            corners = saddle_points(gray, corners.reshape(-1, 2).astype(np.float64),
                                    _corner_spacing(corners, board))
    if not found or corners is None:
        blur = _laplacian_sharpness(gray)
        hint = " (the image looks blurred)" if blur < 20.0 else ""
        return ChessboardDetection(None, math.nan, f"no {board.columns}x{board.rows} chessboard found{hint}")
    corners = corners.reshape(-1, 2).astype(np.float64)
    edge_width = float(cv2.estimateChessboardSharpness(gray, board.pattern_size, corners.astype(np.float32))[0][0])
    if edge_width > max_edge_width:
        return ChessboardDetection(None, edge_width,
                                   f"blurred: chessboard edges {edge_width:.1f} px wide (> {max_edge_width:.1f})")
    return ChessboardDetection(corners, edge_width, None)


def _refine_corners(gray: np.ndarray, corners: np.ndarray, board: Chessboard) -> np.ndarray:
    """cornerSubPix (to within a fraction of a pixel), then a saddle-point fit (`saddle_points`):
    against the true corners the saddle point's error is about half cornerSubPix's, on the
    simulator's boards and on independently rendered ones (blur, perspective, a distorting lens).
    cornerSubPix runs on a lightly smoothed image with a window of ~45% of the smallest corner
    spacing (a window over two corners would pull them together)."""
    spacing = _corner_spacing(corners, board)
    half = int(np.clip(0.45 * spacing, 2, 10))
    smooth = cv2.GaussianBlur(gray, (0, 0), float(np.clip(0.1 * spacing, 0.5, 1.5)))
    criteria = (cv2.TERM_CRITERIA_EPS + cv2.TERM_CRITERIA_COUNT, 100, 1e-6)
    refined = cv2.cornerSubPix(smooth, corners.astype(np.float32).reshape(-1, 1, 2), (half, half), (-1, -1), criteria)
    return saddle_points(gray, refined.reshape(-1, 2).astype(np.float64), spacing)


def _corner_spacing(corners: np.ndarray, board: Chessboard) -> float:
    """Smallest distance (px) between neighbouring corners of the grid."""
    grid = np.asarray(corners, dtype=np.float64).reshape(board.rows, board.columns, 2)
    return float(min(np.linalg.norm(np.diff(grid, axis=0), axis=-1).min(),
                     np.linalg.norm(np.diff(grid, axis=1), axis=-1).min()))


#: saddle-point fit: Gaussian smoothing and window half-size as shares of the corner spacing
SADDLE_BLUR_SHARE = 0.15
SADDLE_WINDOW_SHARE = 0.3


def saddle_points(gray: np.ndarray, corners: np.ndarray, spacing: float, iterations: int = 5,
                  blur_share: float = SADDLE_BLUR_SHARE, window_share: float = SADDLE_WINDOW_SHARE) -> np.ndarray:
    """Each X-corner moved to the saddle point of a quadratic surface fitted (Gaussian-weighted
    least squares) to the smoothed image around it, iterated on the moved window.

    Why it is unbiased: an ideal X-junction (two straight edges crossing) is point-symmetric about
    the corner, so after any symmetric blur the intensity's gradient vanishes there, and a window
    centred on the corner fits no linear term. It uses the intensity of the whole window, not only
    its gradients as cornerSubPix does, which halves the noise-driven error. The smoothing (a share
    of the corner spacing, at least 0.7 px) makes the quadratic fit the blurred junction; the window
    stays well inside the neighbouring corners. A corner whose fit is no saddle (both curvatures of
    one sign: not an X-junction) or that would move by more than the window is left where it was."""
    half = int(round(np.clip(window_share * spacing, 2, 15)))
    smooth = cv2.GaussianBlur(np.asarray(gray, dtype=np.float32), (0, 0), max(blur_share * spacing, 0.7))
    ys, xs = np.mgrid[-half:half + 1, -half:half + 1].astype(np.float64)
    x, y = xs.ravel(), ys.ravel()
    weight = np.exp(-(x * x + y * y) / (2.0 * (half / 2.0) ** 2))
    design = np.stack([x * x, x * y, y * y, x, y, np.ones_like(x)], axis=1) * weight[:, None]
    solve = np.linalg.pinv(design)                         # (6, window) weighted least squares
    # all corners at once, each iterated until its step is below 1e-4 px (or it is given up)
    start = np.asarray(corners, dtype=np.float64).reshape(-1, 2)
    point = start.copy()
    active = np.ones(len(point), dtype=bool)
    for _ in range(iterations):
        if not active.any():
            break
        patches = _bilinear_patches(smooth, point[active], half).reshape(int(active.sum()), -1)
        a, b, c, d, e, _ = ((patches * weight) @ solve.T).T
        det = 4.0 * a * c - b * b                   # of the Hessian [[2a, b], [b, 2c]]
        saddle = det < 0                            # else not a saddle: left where it was
        safe = np.where(saddle, det, -1.0)
        step = np.stack([-(2.0 * c * d - b * e) / safe, -(2.0 * a * e - b * d) / safe], axis=1)
        moved = point[active] + step
        far = np.linalg.norm(moved - start[active], axis=1) > half
        index = np.flatnonzero(active)
        given_up = ~saddle | far
        point[index] = np.where(given_up[:, None], start[index], moved)
        active[index] = ~given_up & (np.linalg.norm(step, axis=1) >= 1e-4)
    return point


def _bilinear_patches(image: np.ndarray, centres: np.ndarray, half: int) -> np.ndarray:
    """(N, 2 half + 1, 2 half + 1) windows of `image` centred on each (x, y) of `centres`, bilinearly
    interpolated with the border replicated: cv2.getRectSubPix for many centres in one go."""
    offsets = np.arange(-half, half + 1, dtype=np.float64)
    x = centres[:, 0, None, None] + offsets[None, None, :]
    y = centres[:, 1, None, None] + offsets[None, :, None]
    x0, y0 = np.floor(x), np.floor(y)
    fx, fy = x - x0, y - y0
    height, width = image.shape[:2]
    xa, xb = np.clip(x0, 0, width - 1).astype(np.intp), np.clip(x0 + 1, 0, width - 1).astype(np.intp)
    ya, yb = np.clip(y0, 0, height - 1).astype(np.intp), np.clip(y0 + 1, 0, height - 1).astype(np.intp)
    pixels = np.asarray(image)   # gathered values meet float64 weights: interpolated in float64
    top = pixels[ya, xa] * (1.0 - fx) + pixels[ya, xb] * fx
    bottom = pixels[yb, xa] * (1.0 - fx) + pixels[yb, xb] * fx
    return top * (1.0 - fy) + bottom * fy


#: fronto-parallel refinement: canonical image pixels per board square, the saddle fit's smoothing and
#: window as shares of a square, the order of the illumination's polynomial and the share of each
#: square's middle it is fitted to
FRONTO_PIXELS_PER_SQUARE = 32
FRONTO_BLUR_SHARE = 0.2
FRONTO_WINDOW_SHARE = 0.45
FRONTO_LIGHT_ORDER = 3
FRONTO_LIGHT_CORE = 0.5


def fronto_parallel_corners(gray: np.ndarray, corners: FloatArray, k_matrix: FloatArray, distortion: FloatArray,
                            board: Chessboard) -> FloatArray:
    """The inner corners of one view refined in the board's own plane (Datta, Kim and Kanade,
    "Accurate camera calibration using iterative refinement of control points", 2009): the view
    is posed with the lens (k_matrix, distortion) of a first calibration, resampled onto the board
    plane (a fronto-parallel image with `FRONTO_PIXELS_PER_SQUARE` per square, the squares and one
    square of margin), each corner is found there by the saddle-point fit (`saddle_points`), and
    the found positions are mapped back into the image through the same pose and lens.

    Why: in the image, perspective and the lens make the board's squares unequal around a corner,
    so only a small window around it is point-symmetric and the saddle fit must stay small (0.3 of
    the smallest spacing): it averages few pixels. On the board plane every interior corner is a
    centre of symmetry of the whole pattern to the next corners, so the window can span almost half
    a square in every view, tilted or not. The mapping back uses the same pose and lens as the
    resampling, so an error of the first calibration moves the resampled pattern and the found
    corner together and cancels to first order; the search starts from the grid's ideal positions,
    so a corner the detector put between the true ones is found again.

    A larger window also sees more of the illumination's gradient, which adds a linear term to the
    fit and moves the saddle point: the view is divided by the light, estimated on the board plane
    from the middles of the dark and of the light squares separately (`_divide_by_light`), before
    the fit."""
    square = board.square
    objects = board.object_points().astype(np.float64)
    ok, rvec, tvec = cv2.solvePnP(objects, np.asarray(corners, np.float64).reshape(-1, 1, 2), k_matrix, distortion,
                                  flags=cv2.SOLVEPNP_ITERATIVE)
    if not ok:
        return np.asarray(corners, dtype=np.float64)
    pps = FRONTO_PIXELS_PER_SQUARE
    low = -2.0                                  # the squares start one square before the first corner
    width, height = (board.columns + 3) * pps, (board.rows + 3) * pps
    bx, by = np.meshgrid((np.arange(width) + 0.5) / pps + low, (np.arange(height) + 0.5) / pps + low)
    u, v = _project_plane(bx * square, by * square, rvec, tvec, k_matrix, distortion)
    canonical = cv2.remap(np.asarray(gray, dtype=np.float32), u.astype(np.float32), v.astype(np.float32),
                          cv2.INTER_CUBIC, borderMode=cv2.BORDER_REPLICATE)
    canonical = _divide_by_light(canonical, bx, by, board)
    ideal = (objects[:, :2] / square - low) * pps - 0.5
    found = saddle_points(canonical, ideal, float(pps), blur_share=FRONTO_BLUR_SHARE,
                          window_share=FRONTO_WINDOW_SHARE)
    on_board = (found + 0.5) / pps + low
    back, _ = cv2.projectPoints(np.column_stack([on_board * square, np.zeros(len(on_board))]), rvec, tvec, k_matrix,
                                distortion)
    return np.asarray(back.reshape(-1, 2), dtype=np.float64)


def _project_plane(x: np.ndarray, y: np.ndarray, rvec: np.ndarray, tvec: np.ndarray, k_matrix: FloatArray,
                   distortion: FloatArray) -> tuple[np.ndarray, np.ndarray]:
    """Pixels of the board-plane points (x, y, 0) (m): OpenCV's projection with k1, k2, p1, p2, k3,
    written out (cv2.projectPoints is several times slower on a whole image of points)."""
    rotation = cv2.Rodrigues(np.asarray(rvec, dtype=np.float64))[0]
    t = np.asarray(tvec, dtype=np.float64).ravel()
    cx = rotation[0, 0] * x + rotation[0, 1] * y + t[0]
    cy = rotation[1, 0] * x + rotation[1, 1] * y + t[1]
    cz = rotation[2, 0] * x + rotation[2, 1] * y + t[2]
    xn, yn = cx / cz, cy / cz
    k1, k2, p1, p2, k3 = (float(k) for k in np.r_[np.asarray(distortion, dtype=np.float64).ravel(), np.zeros(5)][:5])
    r2 = xn * xn + yn * yn
    radial = 1.0 + r2 * (k1 + r2 * (k2 + r2 * k3))
    xd = xn * radial + 2.0 * p1 * xn * yn + p2 * (r2 + 2.0 * xn * xn)
    yd = yn * radial + p1 * (r2 + 2.0 * yn * yn) + 2.0 * p2 * xn * yn
    return k_matrix[0, 0] * xd + k_matrix[0, 1] * yd + k_matrix[0, 2], k_matrix[1, 1] * yd + k_matrix[1, 2]


def _divide_by_light(canonical: np.ndarray, bx: np.ndarray, by: np.ndarray, board: Chessboard) -> np.ndarray:
    """The fronto-parallel image (board coordinates bx, by in squares per pixel) rescaled so that the
    dark squares read 0 and the light ones 1 everywhere. The light under each kind of square is a
    polynomial of order `FRONTO_LIGHT_ORDER` in the board's coordinates, fitted (least squares) to the
    middles of that kind of square only: a smooth light needs few terms over one board, and a fit,
    unlike a local average, does not lean towards the side with more squares at the board's edge."""
    column, row = np.floor(bx), np.floor(by)
    middle = (np.abs(bx - column - 0.5) < FRONTO_LIGHT_CORE / 2) & (np.abs(by - row - 0.5) < FRONTO_LIGHT_CORE / 2)
    middle &= (column >= -1) & (column < board.columns) & (row >= -1) & (row < board.rows)
    even = (column + row) % 2 == 0
    if not (middle & even).any() or not (middle & ~even).any():
        return canonical
    dark_is_even = float(canonical[middle & even].mean()) < float(canonical[middle & ~even].mean())
    # coordinates scaled to about [-1, 1] over the board, for a well-conditioned fit; the fit sees
    # every 4th pixel of the middles in each direction (plenty for a few smooth terms)
    x = (bx[0] - (board.columns - 1) / 2) / ((board.columns + 1) / 2)
    y = (by[:, 0] - (board.rows - 1) / 2) / ((board.rows + 1) / 2)
    powers = [(i, j) for i in range(FRONTO_LIGHT_ORDER + 1) for j in range(FRONTO_LIGHT_ORDER + 1 - i)]
    xs, ys = np.meshgrid(x[::4], y[::4])
    terms = np.stack([xs**i * ys**j for i, j in powers], axis=-1)
    sampled = canonical[::4, ::4].astype(np.float64)

    def light(mask: np.ndarray) -> np.ndarray:
        fit = np.linalg.lstsq(terms[mask[::4, ::4]], sampled[mask[::4, ::4]], rcond=None)[0]
        coefficients = np.zeros((FRONTO_LIGHT_ORDER + 1, FRONTO_LIGHT_ORDER + 1))
        for (i, j), value in zip(powers, fit, strict=True):
            coefficients[i, j] = value
        return np.asarray(np.polynomial.polynomial.polygrid2d(x, y, coefficients).T, dtype=np.float32)

    dark = light(middle & (even == dark_is_even))
    bright = light(middle & (even != dark_is_even))
    return np.asarray((canonical - dark) / np.maximum(bright - dark, 1e-3), dtype=np.float32)


def _laplacian_sharpness(gray: np.ndarray) -> float:
    return float(cv2.Laplacian(gray, cv2.CV_64F).var())


@dataclasses.dataclass(frozen=True)
class IntrinsicsConfig:
    """How `calibrate_intrinsics` judges views and chooses the distortion model.

    A view is rejected when the board is not found, the frame is blurred (edge width above
    `max_edge_width` px), or, judged leave-one-out, its reprojection RMS exceeds both
    `max_view_rms` and `outlier_factor` times the median view. The solve fails with fewer than
    `min_views` usable views, or when the views do not fix the focal length (board normals all
    within `min_tilt_spread_deg`, or sigma_f / f above `max_relative_focal_sigma`).
    `distortion`: "auto" (the data choose, see the module), or one of DISTORTION_MODELS; "auto" keeps
    the tangential p1, p2 when their Wald statistic (p1/sigma)^2 + (p2/sigma)^2 reaches
    `tangential_chi2` (Akaike's penalty for their 2 parameters: 2 x 2).
    `folds`: how many groups of views the held-out test leaves out in turn. A view is also
    rejected when, left out, one of its corners lies more than `corner_outlier_sigma` robust
    standard deviations of all corners' residuals (and at least `min_corner_outlier` px) from the
    fit: a single misdetected corner.
    `corners`: "fronto_parallel" (the default) refines every view's corners on the board's plane
    with the lens of a first calibration (`fronto_parallel_corners`); "image" keeps the corners
    found in the image (findChessboardCorners, cornerSubPix, `saddle_points`).
    """

    board: Chessboard = Chessboard()
    distortion: str = "auto"
    corners: str = "fronto_parallel"
    min_views: int = 3
    max_view_rms: float = 1.0
    outlier_factor: float = 3.0
    max_edge_width: float = 4.0
    max_relative_focal_sigma: float = 0.005
    min_tilt_spread_deg: float = 10.0
    folds: int = 5
    corner_outlier_sigma: float = 8.0
    min_corner_outlier: float = 1.0
    tangential_chi2: float = 4.0

    def __post_init__(self) -> None:
        if self.distortion != "auto" and self.distortion not in DISTORTION_MODELS:
            raise CalibrationError(f"distortion must be auto or one of {', '.join(DISTORTION_MODELS)}, "
                                   f"got {self.distortion!r}")
        if self.corners not in CORNER_METHODS:
            raise CalibrationError(f"corners must be one of {', '.join(CORNER_METHODS)}, got {self.corners!r}")
        if self.min_views < 3:
            raise CalibrationError(f"min_views must be at least 3 (Zhang's method), got {self.min_views}")
        if self.folds < 2:
            raise CalibrationError(f"folds must be at least 2, got {self.folds}")
        for name in ("max_view_rms", "outlier_factor", "max_edge_width", "max_relative_focal_sigma",
                     "corner_outlier_sigma", "min_corner_outlier"):
            if not getattr(self, name) > 0:
                raise CalibrationError(f"{name} must be positive, got {getattr(self, name)}")

    @property
    def screening_model(self) -> str:
        """The distortion model of the fits that screen the views and place the board-plane refinement:
        the given one, or for "auto" the smallest candidate (k1, k2, p1, p2)."""
        return AUTO_CANDIDATES[0] if self.distortion == "auto" else self.distortion


@dataclasses.dataclass(frozen=True)
class ModelScore:
    """One candidate distortion model, judged by views it was not fitted on."""

    model: str
    held_out_rms: float      # px, RMS over the held-out views' corners
    excess_se: float         # its mean squared error above the best candidate's, in standard errors
    chosen: bool


@dataclasses.dataclass(frozen=True)
class IntrinsicsResult:
    camera: CameraModel                  # the prior with fx, fy, cx, cy, distortion, size replaced
    rms: float                           # px, over the used views
    per_view_rms: dict[int, float]       # image index -> px, used views only
    rejected: dict[int, str]             # image index -> reason
    sigma: dict[str, float]              # one-sigma of fx, fy, cx, cy (px) and k1..k3 (`intrinsics_uncertainty`)
    image_count: int
    distortion_model: str                # the model fitted (a DISTORTION_MODELS name)
    model_scores: tuple[ModelScore, ...]  # the held-out comparison ("auto"); empty when the model was given
    coverage: BoardCoverage              # what the used views cover
    tangential_chi2: float = math.nan    # "auto": evidence for p1, p2 (Wald statistic); NaN when the model was given
    #: covariance of (fx, fy, cx, cy, k1, k2, p1, p2, k3), `intrinsics_uncertainty`
    covariance: FloatArray = dataclasses.field(default_factory=lambda: np.full((9, 9), math.nan), compare=False)

    def summary(self) -> str:
        c, s = self.camera, self.sigma
        return (f"intrinsics from {len(self.per_view_rms)}/{self.image_count} views: "
                f"fx={c.fx:.2f}±{s['fx']:.2f} fy={c.fy:.2f}±{s['fy']:.2f} "
                f"cx={c.cx:.2f}±{s['cx']:.2f} cy={c.cy:.2f}±{s['cy']:.2f} px, "
                f"distortion model {self.distortion_model} [{', '.join(f'{k:.4g}' for k in c.distortion)}], "
                f"RMS {self.rms:.3f} px, {len(self.rejected)} rejected; {self.coverage.one_line()}")

    def warnings(self) -> list[str]:
        return self.coverage.warnings()

    def to_dict(self) -> dict[str, Any]:
        """The result as plain data, for the report file the CLI writes."""
        return {
            "rms_px": self.rms,
            "views_used": len(self.per_view_rms),
            "images": self.image_count,
            "per_view_rms_px": {int(k): float(v) for k, v in self.per_view_rms.items()},
            "rejected": {int(k): v for k, v in self.rejected.items()},
            "sigma": {k: float(v) for k, v in self.sigma.items()},
            "distortion_model": self.distortion_model,
            "model_scores": [dataclasses.asdict(score) for score in self.model_scores],
            "tangential_chi2": self.tangential_chi2,
            "coverage": {"bars": {bar.name: round(bar.progress, 3) for bar in self.coverage.bars},
                         "corners_seen": list(self.coverage.corners_seen), "reach": self.coverage.reach,
                         "warnings": self.coverage.warnings()},
            "camera": self.camera.to_params(),
        }


#: called after each view is examined: (image index, its detection, what the views found so far cover)
ViewCallback = Callable[[int, ChessboardDetection, BoardCoverage], None]


def detect_chessboards(images: Sequence[np.ndarray], config: IntrinsicsConfig,
                       on_view: ViewCallback | None = None) -> tuple[dict[int, FloatArray], dict[int, str]]:
    """Corners of every view where the board is found sharp, and why the others were not.
    `on_view` sees each view as it is examined, with the coverage so far (for progress output)."""
    corners: dict[int, FloatArray] = {}
    rejected: dict[int, str] = {}
    for index, image in enumerate(images):
        found = find_chessboard(image, config.board, config.max_edge_width)
        if found.corners is None:
            rejected[index] = str(found.reason)
        else:
            corners[index] = found.corners
        if on_view is not None:
            size = (int(image.shape[1]), int(image.shape[0]))
            on_view(index, found, board_coverage(list(corners.values()), config.board.columns, config.board.rows,
                                                 size))
    return corners, rejected


def refine_on_the_board(images: Sequence[np.ndarray], corners: dict[int, FloatArray], size: tuple[int, int],
                        config: IntrinsicsConfig) -> dict[int, FloatArray]:
    """Every view's corners refined on the board's plane (`fronto_parallel_corners`) with the lens of
    a first calibration on the image corners (the distortion model that screens the views: k1, k2,
    p1, p2 for "auto"). The first calibration only places the resampling; where it fails the image
    corners are kept."""
    if len(corners) < config.min_views:
        return dict(corners)
    try:
        first = _zhang(config.board.object_points(), [corners[i] for i in sorted(corners)], size,
                       DISTORTION_MODELS[config.screening_model])
    except CalibrationError:
        return dict(corners)
    return {i: fronto_parallel_corners(to_grey(images[i]), found, first.k_matrix, first.distortion, config.board)
            for i, found in corners.items()}


def chessboard_corners(images: Sequence[np.ndarray], config: IntrinsicsConfig = IntrinsicsConfig()
                       ) -> tuple[dict[int, FloatArray], dict[int, str]]:
    """The corners `calibrate_intrinsics` calibrates from (per `config.corners`), before any view is
    rejected by the fit, and why the other views were not used."""
    images = list(images)
    corners, rejected = detect_chessboards(images, config)
    if config.corners == "fronto_parallel":
        corners = refine_on_the_board(images, corners, image_size(images), config)
    return corners, rejected


def calibrate_intrinsics(images: Iterable[np.ndarray], config: IntrinsicsConfig = IntrinsicsConfig(),
                         prior: CameraModel | None = None, on_view: ViewCallback | None = None) -> IntrinsicsResult:
    """Zhang's calibration (cv2.calibrateCameraExtended) with view rejection and model choice
    (see `IntrinsicsConfig` and the module). `prior` supplies everything but the intrinsics;
    `on_view` is told of each view as it is examined, with the coverage so far."""
    prior = prior or CameraModel()
    images = list(images)
    if not images:
        raise CalibrationError("no chessboard images given")
    size = image_size(images)
    corners, rejected = detect_chessboards(images, config, on_view)
    require_views(len(corners), config.min_views, len(images), rejected, "chessboard")
    object_points = config.board.object_points()
    if config.corners == "fronto_parallel":
        corners = refine_on_the_board(images, corners, size, config)
    corners = _reject_outlier_views(object_points, corners, size, DISTORTION_MODELS[config.screening_model],
                                    config, rejected)
    views = [corners[i] for i in sorted(corners)]
    choice = choose_distortion_model(object_points, views, size, config)
    model = choice.model
    fit = _zhang(object_points, views, size, DISTORTION_MODELS[model])
    _require_fixed_focal_length(fit, config)
    k_matrix = fit.k_matrix
    try:
        camera = prior.replace(fx=k_matrix[0, 0], fy=k_matrix[1, 1], cx=k_matrix[0, 2], cy=k_matrix[1, 2],
                               distortion=tuple(float(k) for k in fit.distortion), width=size[0], height=size[1])
    except ValueError as exc:
        raise CalibrationError(f"the intrinsics found are not a valid camera model: {exc}") from None
    per_view = dict(zip(sorted(corners), (float(e) for e in fit.per_view), strict=True))
    board = config.board
    covariance, sigma = intrinsics_uncertainty(object_points, views, size, fit, model)
    return IntrinsicsResult(camera=camera, rms=fit.rms, per_view_rms=per_view, rejected=rejected, sigma=sigma,
                            image_count=len(images), distortion_model=model, model_scores=choice.scores,
                            coverage=board_coverage(views, board.columns, board.rows, size),
                            tangential_chi2=choice.tangential_chi2, covariance=covariance)


@dataclasses.dataclass(frozen=True)
class ModelChoice:
    model: str                           # a DISTORTION_MODELS name
    scores: tuple[ModelScore, ...]       # the held-out comparison; empty when the model was given
    tangential_chi2: float               # Wald statistic of p1, p2; NaN when the model was given


def choose_distortion_model(object_points: NDArray[np.float32], views: Sequence[FloatArray], size: tuple[int, int],
                            config: IntrinsicsConfig) -> ModelChoice:
    """The distortion model `config.distortion` names, or for "auto" the one the views choose: p1, p2
    when their Wald statistic reaches `config.tangential_chi2`, then k3 by held-out views, but only
    when the views cover the image corners. k3 (r^6) acts mostly far from the centre: boards that
    never reach the corners cannot pin it where it acts, and within the area they cover k1, k2
    absorb it, so the held-out views can only buy it by a chance fraction of a standard error, and
    it then extrapolates to pixels of invented distortion beyond the boards (where a calibration's
    other measurements, the hemisphere imprints, may well lie). The coverage warns there."""
    if config.distortion != "auto":
        return ModelChoice(config.distortion, (), math.nan)
    tangential = _tangential_evidence(object_points, views, size)
    candidates: tuple[str, ...] = AUTO_CANDIDATES if tangential >= config.tangential_chi2 else ("k1k2", "radial")
    board = config.board
    if not board_coverage(views, board.columns, board.rows, size).corners_covered:
        candidates = candidates[:1]
    scores = select_distortion_model(object_points, views, size, config.folds, candidates)
    return ModelChoice(next(score.model for score in scores if score.chosen), scores, tangential)


def free_intrinsics(flags: int) -> tuple[bool, ...]:
    """Which of `uncertainty.INTRINSIC_NAMES` a Zhang fit with these flags solves for."""
    return (True, True, True, True, True, not flags & cv2.CALIB_FIX_K2, not flags & cv2.CALIB_ZERO_TANGENT_DIST,
            not flags & cv2.CALIB_ZERO_TANGENT_DIST, not flags & cv2.CALIB_FIX_K3)


#: the next larger distortion models, one term group more each: what a model may have left out
#: (see `intrinsics_uncertainty`)
LARGER_MODELS: dict[str, tuple[str, ...]] = {"k1": ("k1k2",), "k1k2": ("k1k2p", "radial"), "radial": ("full",),
                                             "k1k2p": ("full",), "full": ()}


def intrinsics_uncertainty(object_points: NDArray[np.float32], views: Sequence[FloatArray], size: tuple[int, int],
                           fit: _ZhangFit, model: str) -> tuple[FloatArray, dict[str, float]]:
    """The covariance of (fx, fy, cx, cy, k1, k2, p1, p2, k3) that `IntrinsicsResult` reports, and
    the one-sigma it gives each term (OpenCV's where the covariance cannot be computed).

    Two parts. The spread: the fit's covariance clustered by view (`uncertainty`), which holds
    when corner errors are correlated within a view. The model: a distortion model that leaves out
    a term the lens has is biased, most in the principal point (the tangential terms trade with
    it, the radial terms with the focal length), and no spread within the data shows that. The
    difference delta between the fit and each next larger model's fit (`LARGER_MODELS`: the tangential
    terms or k3 added) measures it, and delta delta^T is added: when the
    smaller model is right, delta is noise whose expected square is the larger model's extra
    variance, so the sigma becomes about the larger model's; when it is wrong, delta carries the
    bias. The largest model gets no such term."""
    flags = DISTORTION_MODELS[model]
    free = free_intrinsics(flags)
    covariance = view_clustered_covariance(object_points, views, fit.rvecs, fit.tvecs, fit.k_matrix,
                                           fit.distortion, free)
    for larger in LARGER_MODELS.get(model, ()):
        try:
            other = _zhang(object_points, views, size, DISTORTION_MODELS[larger])
        except CalibrationError:
            continue
        delta = _parameter_vector(other) - _parameter_vector(fit)
        covariance = covariance + np.outer(delta, delta)
    sigma = dict(fit.sigma)
    for i, name in enumerate(INTRINSIC_NAMES):
        variance = float(covariance[i, i])
        if (free[i] or variance > 0) and math.isfinite(variance) and variance > 0:
            sigma[name] = math.sqrt(variance)
    return covariance, sigma


def _parameter_vector(fit: _ZhangFit) -> FloatArray:
    """(fx, fy, cx, cy, k1, k2, p1, p2, k3) of a fit."""
    k = fit.k_matrix
    return np.r_[k[0, 0], k[1, 1], k[0, 2], k[1, 2], fit.distortion[:5]]


def _tangential_evidence(object_points: NDArray[np.float32], views: Sequence[FloatArray],
                         size: tuple[int, int]) -> float:
    """Wald statistic of the tangential terms in a k1, k2, p1, p2 fit: (p1/sigma_p1)^2 + (p2/sigma_p2)^2."""
    fit = _zhang(object_points, views, size, DISTORTION_MODELS["k1k2p"])
    statistic = 0.0
    for index, name in ((2, "p1"), (3, "p2")):
        sigma = fit.sigma[name]
        if not (math.isfinite(sigma) and sigma > 0):
            return math.nan          # not measurable: no evidence for the terms
        statistic += (float(fit.distortion[index]) / sigma) ** 2
    return statistic


def _reject_outlier_views(object_points: NDArray[np.float32], corners: dict[int, FloatArray], size: tuple[int, int],
                          flags: int, config: IntrinsicsConfig, rejected: dict[int, str]) -> dict[int, FloatArray]:
    """Leave-one-out on the worst view, one at a time: a bad view drags the joint fit towards
    itself, so judge it by how well the model fitted WITHOUT it predicts it. A view is bad when
    its RMS is (a blurred or warped view), or when one of its corners is (a corner the detector
    put between the true ones: a few px off in a view whose RMS stays under a pixel, but enough to
    move the principal point by a pixel). The worst view is the one with the largest corner
    residual measured in robust standard deviations of all corners' residuals."""
    corners = dict(corners)
    fit = _zhang(object_points, [corners[i] for i in sorted(corners)], size, flags)
    while len(corners) > config.min_views:
        indices = sorted(corners)
        worst_corner = [float(r.max()) for r in fit.residuals]
        worst = indices[int(np.argmax(worst_corner))] if max(worst_corner) > _corner_limit(fit, config) \
            else indices[int(np.argmax(fit.per_view))]
        rest = [i for i in indices if i != worst]
        refit = _zhang(object_points, [corners[i] for i in rest], size, flags)
        errors = _view_errors(object_points, corners[worst], refit.k_matrix, refit.distortion)
        predicted = float(np.sqrt(np.mean(errors**2)))
        limit = max(config.max_view_rms, config.outlier_factor * float(np.median(refit.per_view)))
        corner_limit = _corner_limit(refit, config)
        if predicted > limit:
            rejected[worst] = f"reprojection RMS {predicted:.2f} px when left out (limit {limit:.2f})"
        elif float(errors.max()) > corner_limit:
            rejected[worst] = (f"corner {int(np.argmax(errors))} is {float(errors.max()):.2f} px off when the view "
                               f"is left out (limit {corner_limit:.2f} px): a misdetected corner")
        else:
            break
        del corners[worst]
        fit = refit
    return corners


def _corner_limit(fit: _ZhangFit, config: IntrinsicsConfig) -> float:
    """How far a corner may lie from the fit: `corner_outlier_sigma` robust standard deviations of
    the corner residuals (the median 2D residual is 1.18 sigma for Gaussian noise), at least
    `min_corner_outlier` px."""
    residuals = np.concatenate(fit.residuals) if fit.residuals else np.zeros(1)
    sigma = float(np.median(residuals)) / 1.1774
    return max(config.corner_outlier_sigma * sigma, config.min_corner_outlier)


def select_distortion_model(object_points: NDArray[np.float32], views: Sequence[FloatArray], size: tuple[int, int],
                            folds: int = 5, candidates: Sequence[str] = AUTO_CANDIDATES) -> tuple[ModelScore, ...]:
    """Score each candidate by k-fold held-out views and choose the simplest whose mean squared
    error is within one standard error (of the paired per-view difference) of the best one's.
    With fewer than 2 views per fold there is nothing to hold out: the simplest is chosen."""
    folds = min(folds, len(views) // 2)
    if folds < 2:
        return tuple(ModelScore(m, math.nan, math.nan, i == 0) for i, m in enumerate(candidates))
    errors = {model: _held_out_errors(object_points, views, size, DISTORTION_MODELS[model], folds)
              for model in candidates}
    best = min(candidates, key=lambda m: float(errors[m].mean()))
    excess = {}
    for model in candidates:
        difference = errors[model] - errors[best]
        spread = float(difference.std(ddof=1)) / math.sqrt(difference.size) if difference.size > 1 else 0.0
        excess[model] = float(difference.mean()) / spread if spread > 0 else 0.0
    chosen = next(m for m in candidates if excess[m] <= 1.0)
    return tuple(ModelScore(m, math.sqrt(float(errors[m].mean())), excess[m], m == chosen) for m in candidates)


def _held_out_errors(object_points: NDArray[np.float32], views: Sequence[FloatArray], size: tuple[int, int],
                     flags: int, folds: int) -> FloatArray:
    """Per view: its mean squared corner error when predicted by a fit on the other folds."""
    errors = np.zeros(len(views))
    for fold in range(folds):
        held = list(range(fold, len(views), folds))
        fit = _zhang(object_points, [v for i, v in enumerate(views) if i not in held], size, flags)
        for i in held:
            errors[i] = min(_view_rms(object_points, views[i], fit.k_matrix, fit.distortion) ** 2, 1e6)
    return errors


def _require_fixed_focal_length(fit: _ZhangFit, config: IntrinsicsConfig) -> None:
    for name, focal in (("fx", fit.k_matrix[0, 0]), ("fy", fit.k_matrix[1, 1])):
        if not fit.sigma[name] / focal <= config.max_relative_focal_sigma:
            raise CalibrationError(
                f"the chessboard views do not fix the focal length (sigma_{name} = {fit.sigma[name]:.1f} px): "
                "tilt the board in different directions between views")
    spread = _normal_spread_deg(fit.rvecs)
    if spread < config.min_tilt_spread_deg:
        raise CalibrationError(
            f"the chessboard views are nearly parallel (board normals within {spread:.1f}° of each other, "
            f"need {config.min_tilt_spread_deg:.0f}°): the focal length is undetermined; tilt the board between views")


@dataclasses.dataclass(frozen=True)
class _ZhangFit:
    rms: float
    k_matrix: FloatArray
    distortion: FloatArray        # (5,)
    sigma: dict[str, float]
    per_view: FloatArray
    rvecs: tuple[FloatArray, ...]
    residuals: tuple[FloatArray, ...] = ()     # per view: each corner's reprojection error, px
    tvecs: tuple[FloatArray, ...] = ()


def _zhang(object_points: NDArray[np.float32], image_points: Sequence[FloatArray], size: tuple[int, int],
           flags: int = 0) -> _ZhangFit:
    criteria = (cv2.TERM_CRITERIA_COUNT + cv2.TERM_CRITERIA_EPS, 100, 1e-12)
    try:
        rms, k_matrix, dist, rvecs, tvecs, std_intr, _, per_view = cv2.calibrateCameraExtended(
            [object_points] * len(image_points), [p.astype(np.float32).reshape(-1, 1, 2) for p in image_points],
            size, None, np.zeros(5), flags=flags, criteria=criteria)
    except cv2.error as exc:
        message = str(exc).strip().splitlines()[-1] if str(exc).strip() else "OpenCV error"
        raise CalibrationError(f"Zhang's solve failed on these views: {message}") from None
    if not (math.isfinite(rms) and np.all(np.isfinite(k_matrix)) and np.all(np.isfinite(dist))):
        raise CalibrationError("Zhang's solve did not converge on these views (non-finite result)")
    std = np.asarray(std_intr, dtype=np.float64).ravel()
    names = ("fx", "fy", "cx", "cy", *DISTORTION_NAMES)
    sigma = {name: (float(std[i]) if i < std.size and math.isfinite(std[i]) else math.inf)
             for i, name in enumerate(names)}
    residuals = []
    for points, rvec, tvec in zip(image_points, rvecs, tvecs, strict=True):
        projected, _ = cv2.projectPoints(object_points, rvec, tvec, k_matrix, dist)
        residuals.append(np.linalg.norm(projected.reshape(-1, 2) - np.asarray(points).reshape(-1, 2), axis=1))
    return _ZhangFit(rms=float(rms), k_matrix=np.asarray(k_matrix, dtype=np.float64),
                     distortion=np.asarray(dist, dtype=np.float64).ravel()[:5], sigma=sigma,
                     per_view=np.asarray(per_view, dtype=np.float64).ravel(),
                     rvecs=tuple(np.asarray(r, dtype=np.float64) for r in rvecs), residuals=tuple(residuals),
                     tvecs=tuple(np.asarray(t, dtype=np.float64) for t in tvecs))


def _view_rms(object_points: np.ndarray, corners: FloatArray, k_matrix: FloatArray, dist: FloatArray) -> float:
    return float(np.sqrt(np.mean(_view_errors(object_points, corners, k_matrix, dist) ** 2)))


def _view_errors(object_points: np.ndarray, corners: FloatArray, k_matrix: FloatArray, dist: FloatArray) -> FloatArray:
    """Each corner's distance (px) from its prediction by the model (k_matrix, dist) posed by PnP."""
    ok, rvec, tvec = cv2.solvePnP(object_points, corners, k_matrix, dist, flags=cv2.SOLVEPNP_ITERATIVE)
    if not ok:
        return np.full(len(corners), math.inf)
    projected, _ = cv2.projectPoints(object_points, rvec, tvec, k_matrix, dist)
    return np.asarray(np.linalg.norm(projected.reshape(-1, 2) - corners, axis=1), dtype=np.float64)


def _normal_spread_deg(rvecs: Sequence[np.ndarray]) -> float:
    """Largest angle between two views' board normals."""
    normals = np.array([cv2.Rodrigues(np.asarray(r, dtype=np.float64))[0][:, 2] for r in rvecs])
    cosines = np.clip(np.abs(normals @ normals.T), -1.0, 1.0)
    return float(np.degrees(np.arccos(cosines.min())))


