"""Calibration of the TouchRoller camera: intrinsics (Zhang) and the paper's extrinsics theta and d.

Two steps, as in the paper (section III-C):

1. Intrinsics and the 5-coefficient distortion from chessboard views (`calibrate_intrinsics`),
   with per-view reprojection errors, rejection of bad views and blurred frames.
2. theta and d from images of the roller pressed on a flat frame of hemispheres
   (`calibrate_extrinsics`): subpixel imprint centres, a per-image pose solve, the mean and
   spread over the images, and outlier rejection.

What is the "reference coordinate"? The frame lies flat under the roller, centred below the
axis, its rows parallel to it; the contact line of a flat surface is z = +r. A hemisphere at
frame position (x, y) therefore presses the membrane at the cylinder point above it,
(x, y, sqrt(r^2 - y^2)), so the frame's reference coordinates ARE the cylinder frame and a
pose solve of these points gives the camera pose in `touchroller_cylinder` directly.

Two solves per image:
* the paper's two-parameter model (rotation theta about x, offset d along z; the other four
  degrees of freedom fixed at zero), by least squares on the reprojection error through
  `CameraModel.project`; this is what we report as theta and d.
* the full six-degree pose by `cv2.solvePnP(SOLVEPNP_ITERATIVE)`, written as
  R = Rx(theta) Ry(beta) Rz(gamma) (camera orientation in the cylinder frame, the paper's sign
  for theta) and t = (tx, ty, tz): beta, gamma, tx and ty are what the paper neglects. They
  include the frame's placement (an axial shift looks like tx, a yaw like gamma), and for a
  narrow frame a rotation about x and a shift along y look almost alike (theta vs ty), so the
  full pose is noisier than the two-parameter one. `ExtrinsicsResult.model_error_mm` turns them
  into what matters: how far apart the two models put back-projected points on the membrane.

Nothing here imports rclpy. Degenerate input raises `CalibrationError` with one line naming what
is missing, never a silently wrong result.
"""
from __future__ import annotations

import dataclasses
import math
from collections.abc import Iterable, Mapping, Sequence
from typing import Any

import cv2
import numpy as np
from numpy.typing import NDArray
from scipy.optimize import least_squares
from scipy.spatial.transform import Rotation

from touchroller_perception.geometry import CameraModel
from touchroller_perception.images import to_grey

FloatArray = NDArray[np.float64]

DISTORTION_NAMES = ("k1", "k2", "p1", "p2", "k3")
#: `calibrate_intrinsics(distortion=...)` -> cv2.calibrateCamera flags
DISTORTION_MODELS = {"full": 0, "radial": cv2.CALIB_ZERO_TANGENT_DIST}


class CalibrationError(ValueError):
    """Calibration input that cannot give a trustworthy result; the message is one line."""


# =========================================================================== images
def _image_size(images: Sequence[np.ndarray]) -> tuple[int, int]:
    sizes = {(int(img.shape[1]), int(img.shape[0])) for img in images}
    if len(sizes) != 1:
        raise CalibrationError(f"calibration images differ in size: {sorted(sizes)}")
    return sizes.pop()


# =========================================================================== intrinsics
@dataclasses.dataclass(frozen=True)
class Chessboard:
    """A planar chessboard: `columns` x `rows` INNER corners (OpenCV's convention), square side in m.
    Defaults: the simulator's `calibration_chessboard` (7x7 inner corners, 12 mm squares)."""

    columns: int = 7
    rows: int = 7
    square: float = 0.012

    def __post_init__(self) -> None:
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
    """cornerSubPix on a lightly smoothed image (a symmetric blur keeps an X-corner in place and
    halves the noise-driven error: 0.09 -> 0.06 px on the simulator's boards), with a window of
    ~45% of the smallest corner spacing (a window over two corners would pull them together)."""
    grid = corners.reshape(board.rows, board.columns, 2)
    spacing = min(np.linalg.norm(np.diff(grid, axis=0), axis=-1).min(),
                  np.linalg.norm(np.diff(grid, axis=1), axis=-1).min())
    half = int(np.clip(0.45 * spacing, 2, 10))
    smooth = cv2.GaussianBlur(gray, (0, 0), float(np.clip(0.1 * spacing, 0.5, 1.5)))
    criteria = (cv2.TERM_CRITERIA_EPS + cv2.TERM_CRITERIA_COUNT, 100, 1e-6)
    refined = cv2.cornerSubPix(smooth, corners.astype(np.float32).reshape(-1, 1, 2), (half, half), (-1, -1), criteria)
    return refined.reshape(-1, 2)


def _laplacian_sharpness(gray: np.ndarray) -> float:
    return float(cv2.Laplacian(gray, cv2.CV_64F).var())


@dataclasses.dataclass
class IntrinsicsResult:
    camera: CameraModel                  # the prior with fx, fy, cx, cy, distortion, size replaced
    rms: float                           # px, over the used views
    per_view_rms: dict[int, float]       # image index -> px, used views only
    rejected: dict[int, str]             # image index -> reason
    sigma: dict[str, float]              # one-sigma of fx, fy, cx, cy (px) and k1..k3 from OpenCV
    image_count: int

    def summary(self) -> str:
        c = self.camera
        return (f"intrinsics from {len(self.per_view_rms)}/{self.image_count} views: "
                f"fx={c.fx:.2f}±{self.sigma['fx']:.2f} fy={c.fy:.2f}±{self.sigma['fy']:.2f} "
                f"cx={c.cx:.2f}±{self.sigma['cx']:.2f} cy={c.cy:.2f}±{self.sigma['cy']:.2f} px, "
                f"distortion=[{', '.join(f'{k:.4g}' for k in c.distortion)}], RMS {self.rms:.3f} px, "
                f"{len(self.rejected)} rejected")

    def to_dict(self) -> dict[str, Any]:
        return {
            "rms_px": self.rms,
            "views_used": len(self.per_view_rms),
            "images": self.image_count,
            "per_view_rms_px": {int(k): float(v) for k, v in self.per_view_rms.items()},
            "rejected": {int(k): v for k, v in self.rejected.items()},
            "sigma": {k: float(v) for k, v in self.sigma.items()},
            "camera": self.camera.to_params(),
        }


def calibrate_intrinsics(
    images: Iterable[np.ndarray],
    board: Chessboard | None = None,
    *,
    prior: CameraModel | None = None,
    min_views: int = 3,
    max_view_rms: float = 1.0,
    outlier_factor: float = 3.0,
    max_edge_width: float = 4.0,
    max_relative_focal_sigma: float = 0.005,
    min_tilt_spread_deg: float = 10.0,
    distortion: str = "full",
) -> IntrinsicsResult:
    """Zhang's calibration (cv2.calibrateCameraExtended) with view rejection.

    A view is rejected when the board is not found, the frame is blurred (edge width above
    `max_edge_width` px), or after a solve its reprojection RMS exceeds both `max_view_rms` and
    `outlier_factor` times the median view, judged leave-one-out (worst first, one at a time).
    Raises `CalibrationError` with fewer than `min_views` usable views, or when the views do not
    fix the focal length (board normals all within `min_tilt_spread_deg`, or sigma_f/f above
    `max_relative_focal_sigma`). `distortion`: ``"full"`` fits all 5 coefficients (the default);
    ``"radial"`` holds the tangential p1 = p2 = 0, which roughly halves the principal point's error
    when the lens has no measurable tangential distortion (check `sigma` of p1, p2 in a full fit).
    """
    board = board or Chessboard()
    prior = prior or CameraModel()
    if distortion not in DISTORTION_MODELS:
        raise CalibrationError(f"distortion must be one of {', '.join(DISTORTION_MODELS)}, got {distortion!r}")
    flags = DISTORTION_MODELS[distortion]
    images = list(images)
    if not images:
        raise CalibrationError("no chessboard images given")
    width, height = _image_size(images)
    rejected: dict[int, str] = {}
    corners: dict[int, FloatArray] = {}
    for index, image in enumerate(images):
        found = find_chessboard(image, board, max_edge_width)
        if found.corners is None:
            rejected[index] = str(found.reason)
        else:
            corners[index] = found.corners
    _require_views(len(corners), min_views, len(images), rejected, "chessboard")

    object_points = board.object_points()
    fit = _zhang(object_points, [corners[i] for i in sorted(corners)], (width, height), flags)
    while len(corners) > min_views:
        # leave-one-out on the worst view: a bad view drags the joint fit towards itself, so judge
        # it by how well the model fitted WITHOUT it predicts it
        indices = sorted(corners)
        worst = indices[int(np.argmax(fit["per_view"]))]
        rest = [i for i in indices if i != worst]
        refit = _zhang(object_points, [corners[i] for i in rest], (width, height), flags)
        predicted = _view_rms(object_points, corners[worst], refit["K"], refit["dist"])
        limit = max(max_view_rms, outlier_factor * float(np.median(refit["per_view"])))
        if predicted <= limit:
            break
        rejected[worst] = f"reprojection RMS {predicted:.2f} px when left out (limit {limit:.2f})"
        del corners[worst]
        fit = refit
    indices = sorted(corners)
    per_view = dict(zip(indices, (float(e) for e in fit["per_view"]), strict=True))
    k_matrix, dist, sigma = fit["K"], fit["dist"], fit["sigma"]
    for name, focal in (("fx", k_matrix[0, 0]), ("fy", k_matrix[1, 1])):
        if not sigma[name] / focal <= max_relative_focal_sigma:
            raise CalibrationError(
                f"the chessboard views do not fix the focal length (sigma_{name} = {sigma[name]:.1f} px): "
                "tilt the board in different directions between views")
    spread = _normal_spread_deg(fit["rvecs"])
    if spread < min_tilt_spread_deg:
        raise CalibrationError(
            f"the chessboard views are nearly parallel (board normals within {spread:.1f}° of each other, "
            f"need {min_tilt_spread_deg:.0f}°): the focal length is undetermined; tilt the board between views")
    try:
        camera = prior.replace(fx=k_matrix[0, 0], fy=k_matrix[1, 1], cx=k_matrix[0, 2], cy=k_matrix[1, 2],
                               distortion=tuple(float(k) for k in dist), width=width, height=height)
    except ValueError as exc:
        raise CalibrationError(f"the intrinsics found are not a valid camera model: {exc}") from None
    return IntrinsicsResult(camera=camera, rms=fit["rms"], per_view_rms=per_view, rejected=rejected,
                            sigma=sigma, image_count=len(images))


def _zhang(object_points: np.ndarray, image_points: list[FloatArray], size: tuple[int, int],
           flags: int = 0) -> dict[str, Any]:
    criteria = (cv2.TERM_CRITERIA_COUNT + cv2.TERM_CRITERIA_EPS, 100, 1e-12)
    try:
        rms, k_matrix, dist, rvecs, _, std_intr, _, per_view = cv2.calibrateCameraExtended(
            [object_points] * len(image_points), [p.astype(np.float32).reshape(-1, 1, 2) for p in image_points],
            size, None, None, flags=flags, criteria=criteria)
    except cv2.error as exc:
        message = str(exc).strip().splitlines()[-1] if str(exc).strip() else "OpenCV error"
        raise CalibrationError(f"Zhang's solve failed on these views: {message}") from None
    if not (math.isfinite(rms) and np.all(np.isfinite(k_matrix)) and np.all(np.isfinite(dist))):
        raise CalibrationError("Zhang's solve did not converge on these views (non-finite result)")
    std = np.asarray(std_intr, dtype=np.float64).ravel()
    names = ("fx", "fy", "cx", "cy", *DISTORTION_NAMES)
    sigma = {name: (float(std[i]) if i < std.size and math.isfinite(std[i]) else math.inf)
             for i, name in enumerate(names)}
    return {"rms": float(rms), "K": np.asarray(k_matrix, dtype=np.float64),
            "dist": np.asarray(dist, dtype=np.float64).ravel()[:5], "sigma": sigma,
            "per_view": np.asarray(per_view, dtype=np.float64).ravel(), "rvecs": rvecs}


def _view_rms(object_points: np.ndarray, corners: FloatArray, k_matrix: FloatArray, dist: FloatArray) -> float:
    ok, rvec, tvec = cv2.solvePnP(object_points, corners, k_matrix, dist, flags=cv2.SOLVEPNP_ITERATIVE)
    if not ok:
        return math.inf
    projected, _ = cv2.projectPoints(object_points, rvec, tvec, k_matrix, dist)
    return float(np.sqrt(np.mean(np.sum((projected.reshape(-1, 2) - corners) ** 2, axis=1))))


def _normal_spread_deg(rvecs: Sequence[np.ndarray]) -> float:
    """Largest angle between two views' board normals."""
    normals = np.array([cv2.Rodrigues(np.asarray(r, dtype=np.float64))[0][:, 2] for r in rvecs])
    cosines = np.clip(np.abs(normals @ normals.T), -1.0, 1.0)
    return float(np.degrees(np.arccos(cosines.min())))


def _require_views(usable: int, needed: int, total: int, rejected: Mapping[int, str], what: str) -> None:
    if total == 1 and needed > 1:
        raise CalibrationError(f"a single {what} image cannot be calibrated; capture at least {needed} views")
    if usable < needed:
        reasons: dict[str, int] = {}
        for reason in rejected.values():
            reasons[reason] = reasons.get(reason, 0) + 1
        listing = "; ".join(f"{n}x {r}" for r, n in sorted(reasons.items(), key=lambda kv: -kv[1])[:3])
        raise CalibrationError(f"only {usable} of {total} {what} images are usable, need {needed}"
                               + (f" ({listing})" if listing else ""))


# =========================================================================== hemisphere frame
@dataclasses.dataclass(frozen=True)
class HemisphereFrame:
    """The paper's 3D-printed frame: `rows` x `columns` hemispheres on a flat plate.

    Columns run along the roller axis (x), rows across it (y, the rolling direction); `pitch_x`
    and `pitch_y` are centre distances in metres. The plate lies under the roller, the hemispheres
    pressed `press_depth` into the membrane at y = 0. Defaults match the simulator's
    `calibration_hemispheres` scene: 2 rows x 5 columns, 10 mm x 8 mm pitch, 1 mm hemispheres
    (the paper gives the layout and the radius, not the pitch).
    """

    rows: int = 2
    columns: int = 5
    pitch_x: float = 0.010
    pitch_y: float = 0.008
    hemisphere_radius: float = 0.001
    press_depth: float = 0.0005

    def __post_init__(self) -> None:
        if self.rows < 1 or self.columns < 1 or self.rows * self.columns < 4:
            raise CalibrationError(f"a hemisphere frame needs at least 4 hemispheres, got {self.rows}x{self.columns}")
        if self.rows < 2 or self.columns < 2:
            raise CalibrationError(f"the frame's {self.rows}x{self.columns} hemispheres are collinear: "
                                   "the pose solve needs at least 2 rows and 2 columns")
        if not (self.pitch_x > 0 and self.pitch_y > 0 and self.hemisphere_radius > 0):
            raise CalibrationError(f"frame pitches and hemisphere radius must be positive, got "
                                   f"{self.pitch_x}, {self.pitch_y}, {self.hemisphere_radius}")

    @property
    def count(self) -> int:
        return self.rows * self.columns

    def layout(self) -> FloatArray:
        """Hemisphere centres (rows*columns, 2) on the plate, row-major: rows by increasing y,
        columns by increasing x, centred on the frame's middle."""
        x = (np.arange(self.columns) - 0.5 * (self.columns - 1)) * self.pitch_x
        y = (np.arange(self.rows) - 0.5 * (self.rows - 1)) * self.pitch_y
        yy, xx = np.meshgrid(y, x, indexing="ij")
        return np.stack([xx.ravel(), yy.ravel()], axis=-1)

    def reference_points(self, radius: float, shift_x: float = 0.0, shift_y: float = 0.0,
                         yaw: float = 0.0) -> FloatArray:
        """Imprint centres (rows*columns, 3) in the cylinder frame for the frame placed at
        (shift_x, shift_y) with `yaw` (rad, about z) relative to the centre below the axis.

        A sphere pressed into a cylinder touches it on the line from the axis to the sphere's
        centre, so the imprint centre is the membrane point at alpha = atan2(y, plate_z)."""
        layout = self.layout()
        c, s = math.cos(yaw), math.sin(yaw)
        x = shift_x + c * layout[:, 0] - s * layout[:, 1]
        y = shift_y + s * layout[:, 0] + c * layout[:, 1]
        plate_z = radius + self.hemisphere_radius - self.press_depth
        if np.max(np.abs(y)) >= 0.5 * radius:
            raise CalibrationError(f"frame rows at |y| = {np.max(np.abs(y)) * 1e3:.1f} mm do not fit under a "
                                   f"roller of radius {radius * 1e3:.1f} mm")
        alpha = np.arctan2(y, plate_z)
        return np.stack([x, radius * np.sin(alpha), radius * np.cos(alpha)], axis=-1)


@dataclasses.dataclass(frozen=True)
class ImprintDetection:
    centres: FloatArray | None       # (rows*columns, 2) in frame order, None if unusable
    elongation: float                # median ratio of the blobs' principal axes (1 = round)
    found: int                       # blobs found
    reason: str | None
    strengths: FloatArray | None = None   # integrated change of each imprint, frame order


def find_imprints(
    image: np.ndarray,
    frame: HemisphereFrame,
    *,
    reference: np.ndarray | None = None,
    min_area: float = 12.0,
    max_area: float = 8000.0,
    max_elongation: float = 1.8,
    min_spread: float = 0.08,
) -> ImprintDetection:
    """Subpixel imprint centres, ordered as `frame.reference_points`.

    The change image is |image - reference| summed over colour channels (without a reference, a
    large median filter estimates the static background). Shading lights one side of an imprint
    and darkens the other, so the magnitude of the change is symmetric about the centre while the
    signed brightness is not. Binarise at a noise-adapted threshold, open/close, fill, keep the
    strongest `frame.count` components and take their change-weighted centroids.
    """
    change = _change_magnitude(image, reference)
    change = cv2.GaussianBlur(change, (0, 0), 1.0)
    sample = change[::3, ::3]        # statistics of a subsample: a full-image median costs ~10 ms
    median = float(np.median(sample))
    noise = 1.4826 * float(np.median(np.abs(sample - median))) + 1e-6
    peak = float(np.percentile(sample, 99.95))
    threshold = max(median + 6.0 * noise, median + 0.2 * (peak - median))
    mask = (change > threshold).astype(np.uint8)
    mask = cv2.morphologyEx(mask, cv2.MORPH_OPEN, cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (3, 3)))
    mask = cv2.morphologyEx(mask, cv2.MORPH_CLOSE, cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (7, 7)))
    contours, _ = cv2.findContours(mask, cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_SIMPLE)
    filled = np.zeros_like(mask)
    cv2.drawContours(filled, contours, -1, 1, thickness=cv2.FILLED)
    count, labels, stats, _ = cv2.connectedComponentsWithStats(filled, connectivity=8)

    weight = np.maximum(change - median, 0.0)
    blobs = []
    for label in range(1, count):
        area = stats[label, cv2.CC_STAT_AREA]
        if not (min_area <= area <= max_area):
            continue
        x0, y0, w, h = (stats[label, k] for k in (cv2.CC_STAT_LEFT, cv2.CC_STAT_TOP,
                                                  cv2.CC_STAT_WIDTH, cv2.CC_STAT_HEIGHT))
        w_roi = weight[y0:y0 + h, x0:x0 + w] * (labels[y0:y0 + h, x0:x0 + w] == label)
        total = float(w_roi.sum())
        if total <= 0:
            continue
        vs, us = np.mgrid[y0:y0 + h, x0:x0 + w]
        cu, cv_ = float((w_roi * us).sum() / total), float((w_roi * vs).sum() / total)
        cov = np.cov(np.stack([us.ravel() - cu, vs.ravel() - cv_]), aweights=w_roi.ravel() + 1e-12, bias=True)
        eig = np.linalg.eigvalsh(cov)
        blobs.append((total, cu, cv_, math.sqrt(max(eig[1], 1e-12) / max(eig[0], 1e-12))))
    found = len(blobs)
    if found < frame.count:
        return ImprintDetection(None, math.nan, found,
                                f"too few imprints: found {found}, the {frame.rows}x{frame.columns} frame has "
                                f"{frame.count}")
    blobs.sort(key=lambda b: -b[0])
    blobs = blobs[:frame.count]
    elongation = float(np.median([b[3] for b in blobs]))
    if elongation > max_elongation:
        return ImprintDetection(None, elongation, found,
                                f"blurred: imprints smeared {elongation:.1f}:1 (> {max_elongation:.1f}:1); "
                                "hold the roller still")
    centres = np.array([[b[1], b[2]] for b in blobs])
    order, reason = _order_grid(centres, frame.rows, frame.columns, min_spread)
    if order is None:
        return ImprintDetection(None, elongation, found, reason)
    strengths = np.array([b[0] for b in blobs])[order]
    return ImprintDetection(centres[order], elongation, found, None, strengths)


def _change_magnitude(image: np.ndarray, reference: np.ndarray | None) -> NDArray[np.float32]:
    array = np.asarray(image)
    if array.ndim == 2:
        array = array[..., None]
    array = array.astype(np.float32)
    if reference is not None:
        ref = np.asarray(reference)
        if ref.shape[:2] != array.shape[:2]:
            raise CalibrationError(f"reference frame is {ref.shape[1]}x{ref.shape[0]}, "
                                   f"images are {array.shape[1]}x{array.shape[0]}")
        ref = ref[..., None] if ref.ndim == 2 else ref
        background = ref.astype(np.float32)
    else:
        # a median over ~5 imprint diameters, on a half-size image (cheap, and still far larger than an imprint)
        small = cv2.resize(np.clip(array, 0, 255).astype(np.uint8), None, fx=0.5, fy=0.5,
                           interpolation=cv2.INTER_AREA)
        small = small[..., None] if small.ndim == 2 else small
        planes = [cv2.medianBlur(np.ascontiguousarray(small[..., c]), 31) for c in range(small.shape[2])]
        background = np.stack([cv2.resize(p, (array.shape[1], array.shape[0]), interpolation=cv2.INTER_LINEAR)
                               for p in planes], axis=-1).astype(np.float32)
    return np.abs(array - background).sum(axis=2)


def _order_grid(centres: FloatArray, rows: int, columns: int,
                min_spread: float) -> tuple[NDArray[np.intp] | None, str | None]:
    """The permutation ordering blob centres row-major (rows by increasing v, columns by increasing u) using the
    cloud's principal axes, so a tilted frame still sorts correctly."""
    mean = centres.mean(axis=0)
    _, singular, vt = np.linalg.svd(centres - mean, full_matrices=False)
    if singular[1] < min_spread * singular[0]:
        return None, (f"imprint centres are collinear (spread ratio {singular[1] / singular[0]:.3f} "
                      f"< {min_spread}): the pose is undetermined")
    long_axis = vt[0] if columns >= rows else vt[1]
    if long_axis[0] < 0:
        long_axis = -long_axis
    across = np.array([-long_axis[1], long_axis[0]])   # +v for an axis along +u
    along_c = (centres - mean) @ long_axis
    across_c = (centres - mean) @ across
    by_row = np.argsort(across_c, kind="stable")
    ordered = []
    for r in range(rows):
        members = by_row[r * columns:(r + 1) * columns]
        ordered.extend(members[np.argsort(along_c[members], kind="stable")])
    # the rows must separate: the gap between rows larger than the scatter within a row
    row_values = across_c[by_row].reshape(rows, columns)
    if rows > 1:
        gap = np.min(row_values[1:].min(axis=1) - row_values[:-1].max(axis=1))
        if gap <= 0:
            return None, "imprints do not form the frame's grid (rows overlap)"
    return np.asarray(ordered), None


# =========================================================================== pose per view
@dataclasses.dataclass(frozen=True)
class ViewPose:
    index: int
    theta: float            # rad, two-parameter model
    d: float                # m, two-parameter model
    rms: float              # px, two-parameter model
    shift_x: float          # m, the frame's placement along the axis (nuisance, solved per image)
    yaw: float              # rad, the frame's yaw about z (nuisance, solved per image)
    full_theta: float       # rad, full pose R = Rx(theta) Ry(beta) Rz(gamma) of the nominal frame
    beta: float             # rad
    gamma: float            # rad
    t: tuple[float, float, float]   # m, full pose translation (tx, ty, tz)
    full_rms: float         # px
    rvec: tuple[float, float, float]
    row_strengths: tuple[float, float] = (math.nan, math.nan)   # summed imprint strength of the -y, +y rows
    row_asymmetry: float = math.nan     # (S+ - S-) / median over the views of (S+ + S-); 0 when centred
    frame_shift_y: float = math.nan     # m, the frame's shift along y implied by the row balance

    def as_dict(self) -> dict[str, float]:
        return {"index": self.index, "theta_deg": math.degrees(self.theta), "d_mm": self.d * 1e3,
                "rms_px": self.rms, "frame_shift_x_mm": self.shift_x * 1e3, "frame_yaw_deg": math.degrees(self.yaw),
                "full_theta_deg": math.degrees(self.full_theta),
                "beta_deg": math.degrees(self.beta), "gamma_deg": math.degrees(self.gamma),
                "tx_mm": self.t[0] * 1e3, "ty_mm": self.t[1] * 1e3, "tz_mm": self.t[2] * 1e3,
                "full_rms_px": self.full_rms, "row_asymmetry": self.row_asymmetry,
                "frame_shift_y_mm": self.frame_shift_y * 1e3}


def full_pose_rotation(theta: float, beta: float, gamma: float) -> FloatArray:
    """Cylinder -> camera rotation for the camera orientation Rx(theta) Ry(beta) Rz(gamma)."""
    return Rotation.from_euler("XYZ", [theta, beta, gamma]).as_matrix().T


def solve_view(camera: CameraModel, frame: HemisphereFrame, image_points: FloatArray, index: int = 0,
               solve_placement: bool = True) -> ViewPose:
    """One image: the paper's (theta, d) by least squares on the reprojection error, with the
    frame's axial shift and yaw as nuisance unknowns (a frame is never placed exactly; both are
    separable from theta and d, unlike a shift along y, which looks like theta), and the full
    iterative PnP pose of the nominal frame for the terms the paper neglects."""
    image_points = np.asarray(image_points, dtype=np.float64)
    nominal = frame.reference_points(camera.radius)

    def residual(params: FloatArray) -> FloatArray:
        theta, d, shift_x, yaw = params if solve_placement else (*params, 0.0, 0.0)
        if abs(d) >= 0.99 * camera.radius:
            return np.full(image_points.size, 1e6)
        points = frame.reference_points(camera.radius, shift_x, 0.0, yaw)
        uv, valid = camera.replace(theta=theta, d=d).project(points)
        return np.where(valid[:, None], uv - image_points, 1e6).ravel()

    start = np.array([camera.theta, camera.d, 0.0, 0.0] if solve_placement else [camera.theta, camera.d])
    scale = np.array([1e-2, 1e-3, 1e-3, 1e-2][:start.size])
    fit = least_squares(residual, start, method="lm", x_scale=scale, xtol=1e-14, ftol=1e-14)
    theta, d = float(fit.x[0]), float(fit.x[1])
    shift_x, yaw = (float(fit.x[2]), float(fit.x[3])) if solve_placement else (0.0, 0.0)
    rms = float(np.sqrt(np.mean(np.sum(fit.fun.reshape(-1, 2) ** 2, axis=1))))
    object_points = nominal
    fitted = camera.replace(theta=theta, d=d)
    rvec0, _ = cv2.Rodrigues(fitted.R)
    tvec0 = fitted.t.reshape(3, 1).copy()
    # start the full pose from the two-parameter one (planar PnP has a mirror solution)
    dist = np.asarray(camera.distortion, dtype=np.float64)
    ok, rvec, tvec = cv2.solvePnP(object_points, image_points, camera.K, dist, rvec0.copy(), tvec0,
                                  useExtrinsicGuess=True, flags=cv2.SOLVEPNP_ITERATIVE)
    if not ok or not np.all(np.isfinite(rvec)) or not np.all(np.isfinite(tvec)):
        raise CalibrationError(f"image {index}: the pose solve did not converge")
    # theta and ty nearly trade off for a narrow frame: polish to a tight tolerance
    rvec, tvec = cv2.solvePnPRefineLM(object_points, image_points, camera.K, dist, rvec, tvec,
                                      criteria=(cv2.TERM_CRITERIA_EPS + cv2.TERM_CRITERIA_COUNT, 200, 1e-15))
    projected, _ = cv2.projectPoints(object_points, rvec, tvec, camera.K, dist)
    full_rms = float(np.sqrt(np.mean(np.sum((projected.reshape(-1, 2) - image_points) ** 2, axis=1))))
    rotation = cv2.Rodrigues(rvec)[0]
    full_theta, beta, gamma = Rotation.from_matrix(rotation.T).as_euler("XYZ")
    return ViewPose(index=index, theta=theta, d=d, rms=rms, shift_x=shift_x, yaw=yaw,
                    full_theta=float(full_theta), beta=float(beta),
                    gamma=float(gamma), t=tuple(float(v) for v in tvec.ravel()), full_rms=full_rms,
                    rvec=tuple(float(v) for v in rvec.ravel()))


# =========================================================================== extrinsics
@dataclasses.dataclass
class ExtrinsicsResult:
    camera: CameraModel               # the input intrinsics with theta and d replaced by the means
    theta: float                      # rad, mean over the used views
    d: float                          # m
    theta_std: float                  # rad, spread (sample std) over the used views
    d_std: float                      # m
    views: list[ViewPose]             # used views
    rejected: dict[int, str]          # image index -> reason
    image_count: int
    neglected: dict[str, float]       # full-pose terms the paper neglects (mean and std), and model error

    @property
    def rms(self) -> float:
        return float(np.sqrt(np.mean([v.rms**2 for v in self.views])))

    def summary(self) -> str:
        n = self.neglected
        return (f"extrinsics from {len(self.views)}/{self.image_count} images: "
                f"theta = {math.degrees(self.theta):.4f}° ± {math.degrees(self.theta_std):.4f}°, "
                f"d = {self.d * 1e3:.4f} ± {self.d_std * 1e3:.4f} mm, RMS {self.rms:.3f} px "
                f"(full pose {n['full_rms_px']:.3f} px); neglected: beta {n['beta_deg']:.3f}°, "
                f"gamma {n['gamma_deg']:.3f}°, tx {n['tx_mm']:.3f} mm, ty {n['ty_mm']:.3f} mm; "
                f"two-parameter model differs from the full pose by {n['model_error_centre_mm']:.3f} mm "
                f"in the contact band (max {n['model_error_max_mm']:.3f} mm over the image)"
                + ("" if math.isfinite(n["row_balance_slope_deg"]) else
                   "; row balance NOT applied (presses too alike to fit it): theta includes the frame's "
                   "placement error along y (1 mm = 1.1°); move the frame between 5 or more presses"))

    def to_dict(self) -> dict[str, Any]:
        return {
            "theta_rad": self.theta, "theta_deg": math.degrees(self.theta),
            "theta_std_deg": math.degrees(self.theta_std),
            "d_m": self.d, "d_mm": self.d * 1e3, "d_std_mm": self.d_std * 1e3,
            "rms_px": self.rms, "views_used": len(self.views), "images": self.image_count,
            "rejected": {int(k): v for k, v in self.rejected.items()},
            "neglected": {k: float(v) for k, v in self.neglected.items()},
            "views": [v.as_dict() for v in self.views],
        }


def calibrate_extrinsics(
    images: Iterable[np.ndarray],
    camera: CameraModel,
    frame: HemisphereFrame | None = None,
    *,
    reference: np.ndarray | None = None,
    min_views: int = 2,
    max_view_rms: float = 1.0,
    outlier_sigma: float = 4.0,
    solve_placement: bool = True,
    balance_rows: bool = True,
    skip_empty: bool = True,
    **detect_options: Any,
) -> ExtrinsicsResult:
    """theta and d from hemisphere-frame images (the paper's averaging, with outlier rejection).

    `camera` carries the intrinsics (from `calibrate_intrinsics`) and the prior theta, d used to
    start the solves. A view is rejected when its imprints are not all found, are collinear or
    smeared, its reprojection RMS exceeds `max_view_rms` px, or its theta or d lies more than
    `outlier_sigma` robust standard deviations from the median of the views. Images without
    any imprint (between presses) are skipped when `skip_empty`. With `balance_rows`, each view's
    theta is corrected for the frame's shift along y measured by the rows' imprint strengths
    (see `_row_balance`); the paper's plain mean stays in `neglected["theta_plain_mean_deg"]`.
    """
    frame = frame or HemisphereFrame()
    images = list(images)
    if not images:
        raise CalibrationError("no hemisphere-frame images given")
    _image_size(images)
    frame.reference_points(camera.radius)       # fails early if the frame does not fit the roller
    rejected: dict[int, str] = {}
    views: list[ViewPose] = []
    empty = 0
    for index, image in enumerate(images):
        detection = find_imprints(image, frame, reference=reference, **detect_options)
        if detection.found == 0 and skip_empty:
            empty += 1          # a frame between presses, not a view
            continue
        if detection.centres is None:
            rejected[index] = str(detection.reason)
            continue
        try:
            view = solve_view(camera, frame, detection.centres, index, solve_placement)
            view = dataclasses.replace(view, row_strengths=_row_strengths(detection.strengths, frame))
        except CalibrationError as exc:
            rejected[index] = str(exc)
            continue
        if not view.rms <= max_view_rms:
            rejected[index] = f"reprojection RMS {view.rms:.2f} px (limit {max_view_rms:.2f})"
            continue
        views.append(view)
    total = len(images) - empty
    if total == 0:
        raise CalibrationError(f"no imprints found in any of the {len(images)} hemisphere-frame images")
    _require_views(len(views), min_views, total, rejected, "hemisphere-frame")
    views = _with_row_asymmetry(views)
    balance = _row_balance(views, outlier_sigma) if balance_rows else None
    d_ok = _inliers(np.array([v.d for v in views]), outlier_sigma, 5e-6)
    if balance is None:     # the paper's plain mean: theta outliers against the other views
        keep = d_ok & _inliers(np.array([v.theta for v in views]), outlier_sigma, math.radians(0.01))
        why = "far from the other views"
    else:                   # theta outliers against the row-balance line
        slope, theta_ok = balance
        keep = d_ok & theta_ok
        why = "off the row-balance fit"
    for view, ok in zip(views, keep, strict=True):
        if not ok:
            rejected[view.index] = f"outlier: theta {math.degrees(view.theta):.3f}°, d {view.d * 1e3:.3f} mm {why}"
    views = [v for v, ok in zip(views, keep, strict=True) if ok]
    _require_views(len(views), min_views, total, rejected, "hemisphere-frame")
    plain_theta = float(np.mean([v.theta for v in views]))
    if balance is not None:
        plate_z = camera.radius + frame.hemisphere_radius - frame.press_depth
        views = [dataclasses.replace(v, frame_shift_y=-slope * v.row_asymmetry * plate_z) for v in views]
    # theta of each view with its frame shift along y taken out (that shift turns the picture like theta does)
    shifts = [slope * v.row_asymmetry if balance is not None else 0.0 for v in views]
    thetas = np.array([v.theta for v in views]) + np.array(shifts)
    ds = np.array([v.d for v in views])
    theta, d = float(thetas.mean()), float(ds.mean())
    result_camera = camera.replace(theta=theta, d=d)
    neglected = _neglected_terms(result_camera, views, shifts)
    neglected["theta_plain_mean_deg"] = math.degrees(plain_theta)
    neglected["row_balance_slope_deg"] = math.degrees(slope) if balance is not None else math.nan
    return ExtrinsicsResult(
        camera=result_camera, theta=theta, d=d,
        theta_std=float(thetas.std(ddof=1)) if len(views) > 1 else math.nan,
        d_std=float(ds.std(ddof=1)) if len(views) > 1 else math.nan,
        views=views, rejected=rejected, image_count=total, neglected=neglected)


def _row_strengths(strengths: FloatArray | None, frame: HemisphereFrame) -> tuple[float, float]:
    """Summed imprint strengths of the rows at -y and at +y."""
    if strengths is None:
        return (math.nan, math.nan)
    y = frame.layout()[:, 1]
    return float(strengths[y < -1e-12].sum()), float(strengths[y > 1e-12].sum())


def _with_row_asymmetry(views: Sequence[ViewPose]) -> list[ViewPose]:
    """The strength difference of the rows is close to linear in the frame's shift whatever the
    press depth (a ratio is not: it falls with depth), so normalise by one common scale only."""
    sums = [a + b for a, b in (v.row_strengths for v in views)]
    scale = float(np.median(sums)) if sums and np.all(np.isfinite(sums)) else math.nan
    return [dataclasses.replace(v, row_asymmetry=(v.row_strengths[1] - v.row_strengths[0]) / scale)
            for v in views]


def _row_balance(views: Sequence[ViewPose], outlier_sigma: float = 4.0,
                 min_asymmetry_spread: float = 0.05) -> tuple[float, NDArray[np.bool_]] | None:
    """Fit theta_i = theta + s * a_i over the views (a_i: row asymmetry); returns (-s, inliers).

    A frame shifted by e along y turns the picture like a rotation theta of e / plate_z, and no
    pose solve can tell them apart. But the row nearer the contact line presses deeper and leaves
    the stronger imprint, so the rows' strength asymmetry a_i measures the shift: a_i = 0 for a
    centred frame (by symmetry), and theta at a = 0 is the camera's. The slope comes from the
    views' own scatter (no model of imprint strength needed): a robust Theil-Sen line, outliers
    by their residual, then least squares on the inliers. It must be negative (the +y row is
    stronger when the frame moved towards -y, which lowers theta_i). Returns None, i.e. the
    paper's plain mean, when the views do not vary enough in a to fit a slope.
    """
    a = np.array([v.row_asymmetry for v in views])
    theta = np.array([v.theta for v in views])
    if len(views) < 3 or not np.all(np.isfinite(a)) or np.ptp(a) < min_asymmetry_spread:
        return None
    slope, intercept = _theil_sen(a, theta)
    residual = theta - (intercept + slope * a)
    scale = max(1.4826 * float(np.median(np.abs(residual))), math.radians(0.05))
    keep = np.abs(residual) <= outlier_sigma * scale
    if keep.sum() < 3 or np.ptp(a[keep]) < min_asymmetry_spread:
        return None
    slope = float(np.polyfit(a[keep], theta[keep], 1)[0])
    if slope >= 0:
        return None
    return -slope, keep


def _theil_sen(x: FloatArray, y: FloatArray) -> tuple[float, float]:
    """Median of the pairwise slopes and the median intercept (scipy.stats.theilslopes without the
    ~0.5 s import of scipy.stats)."""
    i, j = np.triu_indices(len(x), k=1)
    dx = x[j] - x[i]
    ok = dx != 0
    slope = float(np.median((y[j] - y[i])[ok] / dx[ok])) if ok.any() else 0.0
    return slope, float(np.median(y - slope * x))


def _inliers(values: FloatArray, k: float, floor: float) -> NDArray[np.bool_]:
    median = np.median(values)
    scale = max(1.4826 * float(np.median(np.abs(values - median))), floor)
    return np.abs(values - median) <= k * scale


def _neglected_terms(camera: CameraModel, views: Sequence[ViewPose], theta_shift: Sequence[float]) -> dict[str, float]:
    """Mean and spread of the full poses. `theta_shift` (per view, rad) takes the frame's shift
    along y out of the full pose's theta as the row balance did for the two-parameter theta, so
    the comparison of the two models is about the camera, not the frame's placement."""
    beta = np.array([v.beta for v in views])
    gamma = np.array([v.gamma for v in views])
    t = np.array([v.t for v in views])
    full_theta = np.array([v.full_theta for v in views]) + np.asarray(theta_shift, dtype=np.float64)
    ddof = 1 if len(views) > 1 else 0
    rotation = full_pose_rotation(float(full_theta.mean()), float(beta.mean()), float(gamma.mean()))
    error_centre, error_max = model_error_mm(camera, rotation, t.mean(axis=0))
    return {
        "full_theta_deg": math.degrees(full_theta.mean()),
        "full_theta_std_deg": math.degrees(full_theta.std(ddof=ddof)),
        "beta_deg": math.degrees(beta.mean()), "beta_std_deg": math.degrees(beta.std(ddof=ddof)),
        "gamma_deg": math.degrees(gamma.mean()), "gamma_std_deg": math.degrees(gamma.std(ddof=ddof)),
        "tx_mm": 1e3 * t[:, 0].mean(), "tx_std_mm": 1e3 * t[:, 0].std(ddof=ddof),
        "ty_mm": 1e3 * t[:, 1].mean(), "ty_std_mm": 1e3 * t[:, 1].std(ddof=ddof),
        "tz_mm": 1e3 * t[:, 2].mean(), "tz_std_mm": 1e3 * t[:, 2].std(ddof=ddof),
        "full_rms_px": float(np.sqrt(np.mean([v.full_rms**2 for v in views]))),
        "model_error_centre_mm": error_centre, "model_error_max_mm": error_max,
    }


def back_project_pose(camera: CameraModel, rotation: FloatArray, translation: FloatArray,
                      uv: np.ndarray) -> FloatArray:
    """Back-project pixels onto the membrane for a general pose (x_c = R X + t); NaN where invalid."""
    xn, yn, valid = camera.undistort_normalised(uv)
    direction = np.stack([xn, yn, np.ones_like(xn)], axis=-1) @ rotation      # R^T (xn, yn, 1)
    origin = -rotation.T @ np.asarray(translation, dtype=np.float64)
    dy, dz = direction[..., 1], direction[..., 2]
    a = dy * dy + dz * dz
    b = 2.0 * (origin[1] * dy + origin[2] * dz)
    c0 = origin[1] ** 2 + origin[2] ** 2 - camera.radius**2
    with np.errstate(invalid="ignore", divide="ignore"):
        s = (-b + np.sqrt(b * b - 4.0 * a * c0)) / (2.0 * a)
    points = origin + s[..., None] * direction
    ok = valid & np.isfinite(s) & (s > 0) & (np.abs(points[..., 0]) <= 0.5 * camera.length)
    points[~ok] = np.nan
    return points


def model_error_mm(camera: CameraModel, rotation: FloatArray, translation: FloatArray,
                   band_px: float = 35.0, step: int = 8) -> tuple[float, float]:
    """How far the two-parameter model's back-projection lies from the full pose's, in mm:
    (mean in the central contact band |v - cy| <= band_px, max over the whole image)."""
    us, vs = np.meshgrid(np.arange(0, camera.width, step, dtype=np.float64),
                         np.arange(0, camera.height, step, dtype=np.float64))
    uv = np.stack([us, vs], axis=-1)
    two_param, _ = camera.back_project(uv)
    full = back_project_pose(camera, rotation, translation, uv)
    distance = 1e3 * np.linalg.norm(two_param - full, axis=-1)
    finite = np.isfinite(distance)
    if not finite.any():
        return math.nan, math.nan
    band = finite & (np.abs(vs - camera.cy) <= band_px)
    centre = float(distance[band].mean()) if band.any() else math.nan
    return centre, float(distance[finite].max())


def compare_cameras(a: CameraModel, b: CameraModel, band_px: float = 35.0, step: int = 4) -> dict[str, float]:
    """How two calibrations differ: parameter differences (b - a) and how far apart they put the
    back-projections of the same pixels on the membrane (mm): mean in the central contact band
    |v - cy| <= band_px, and mean and max over the pixels both models can map."""
    us, vs = np.meshgrid(np.arange(0, a.width, step, dtype=np.float64), np.arange(0, a.height, step, dtype=np.float64))
    uv = np.stack([us, vs], axis=-1)
    pa, va = a.back_project(uv)
    pb, vb = b.back_project(uv)
    both = va & vb
    distance = 1e3 * np.linalg.norm(pa - pb, axis=-1)
    band = both & (np.abs(vs - a.cy) <= band_px)
    out = {f"d{name}_px": getattr(b, name) - getattr(a, name) for name in ("fx", "fy", "cx", "cy")}
    out.update({"dtheta_deg": math.degrees(b.theta - a.theta), "dd_mm": 1e3 * (b.d - a.d),
                "dradius_mm": 1e3 * (b.radius - a.radius),
                "contact_band_mean_mm": float(distance[band].mean()) if band.any() else math.nan,
                "image_mean_mm": float(distance[both].mean()) if both.any() else math.nan,
                "image_max_mm": float(distance[both].max()) if both.any() else math.nan,
                "mapped_fraction": float(both.mean())})
    return out


# =========================================================================== outputs
def calibration_sigma(intrinsics: IntrinsicsResult | None, extrinsics: ExtrinsicsResult | None) -> dict[str, float]:
    """One-sigma uncertainties in `CameraModel.contact_covariance`'s names (theta in rad, d in m).
    For theta and d this is the standard error of the mean over the views."""
    sigma: dict[str, float] = {}
    if intrinsics is not None:
        sigma.update({k: v for k, v in intrinsics.sigma.items() if math.isfinite(v)})
    if extrinsics is not None and len(extrinsics.views) > 1:
        n = math.sqrt(len(extrinsics.views))
        sigma["theta"] = extrinsics.theta_std / n
        sigma["d"] = extrinsics.d_std / n
    return sigma


def write_calibration(path: str, camera: CameraModel, intrinsics: IntrinsicsResult | None = None,
                      extrinsics: ExtrinsicsResult | None = None, keep: Mapping[str, Any] | None = None) -> None:
    """The docs/design.md parameters file, plus `calibration.sigma.*` and RMS figures as extra parameters
    (`keep`: extra parameters of an earlier step to carry over, overridden by this step's)."""
    extra: dict[str, Any] = dict(keep or {})
    extra.update({f"calibration.sigma.{k}": float(v) for k, v in calibration_sigma(intrinsics, extrinsics).items()})
    if intrinsics is not None:
        extra["calibration.intrinsics_rms_px"] = float(intrinsics.rms)
    if extrinsics is not None:
        extra["calibration.extrinsics_rms_px"] = float(extrinsics.rms)
        extra["calibration.extrinsics_views"] = len(extrinsics.views)
    camera.to_yaml(path, extra=extra)


def read_calibration_extras(path: str) -> dict[str, Any]:
    """The `calibration.*` parameters of a parameters file (uncertainties and RMS of earlier steps)."""
    import yaml

    with open(path, encoding="utf-8") as stream:
        document = yaml.safe_load(stream) or {}
    for value in document.values() if isinstance(document, Mapping) else ():
        if isinstance(value, Mapping) and isinstance(value.get("ros__parameters"), Mapping):
            params = value["ros__parameters"]
            flat = {f"calibration.{k}": v for k, v in params.get("calibration", {}).items()} \
                if isinstance(params.get("calibration"), Mapping) else {}
            flat.update({k: v for k, v in params.items() if str(k).startswith("calibration.")})
            return flat
    return {}


def camera_info_fields(camera: CameraModel) -> dict[str, Any]:
    """sensor_msgs/CameraInfo fields (plumb_bob) for `camera`; R is identity, P = [K | 0]."""
    k_matrix = camera.K
    projection = np.hstack([k_matrix, np.zeros((3, 1))])
    return {"width": camera.width, "height": camera.height, "distortion_model": "plumb_bob",
            "d": [float(v) for v in camera.distortion], "k": [float(v) for v in k_matrix.ravel()],
            "r": [float(v) for v in np.eye(3).ravel()], "p": [float(v) for v in projection.ravel()]}
