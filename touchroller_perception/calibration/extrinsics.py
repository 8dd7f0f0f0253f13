"""theta and d, the paper's extrinsics, from images of the roller pressed on a flat frame of
hemispheres (paper, section III-C): subpixel imprint centres (`imprints`), a per-image pose
solve, the frame's placement along y taken out by the row balance, the mean and its uncertainty
over the images, and outlier rejection.

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
"""
from __future__ import annotations

import dataclasses
import math
from collections.abc import Callable, Iterable, Mapping, Sequence
from typing import Any

import cv2
import numpy as np
from numpy.typing import NDArray
from scipy.optimize import least_squares
from scipy.spatial.transform import Rotation

from touchroller_perception.calibration.common import (
    CalibrationError,
    FloatArray,
    image_size,
    inliers,
    require_views,
)
from touchroller_perception.calibration.imprints import HemisphereFrame, ImprintDetectorConfig, find_imprints
from touchroller_perception.calibration.plausibility import Plausibility, check_plausible
from touchroller_perception.calibration.selection import (
    TermChoice,
    choose_term,
    gate_by_rms,
    not_judged,
    rms_warning,
)
from touchroller_perception.calibration.uncertainty import INTRINSIC_NAMES, jackknife_std
from touchroller_perception.geometry import PARAMETER_RANGES, CameraModel

_THETA_LIMIT = PARAMETER_RANGES["extrinsics.theta"][1]


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
    #: the rows' strengths by the detector's other measure (`ImprintDetection.other_strengths`), NaN without one
    other_row_strengths: tuple[float, float] = (math.nan, math.nan)
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


def _triple(values: np.ndarray) -> tuple[float, float, float]:
    flat = np.asarray(values, dtype=np.float64).ravel()
    return float(flat[0]), float(flat[1]), float(flat[2])


def _pose_residual(camera: CameraModel, frame: HemisphereFrame, image_points: FloatArray,
                   solve_placement: bool) -> Callable[[FloatArray], FloatArray]:
    """Reprojection residuals (px, flattened) of the two-parameter pose (theta, d[, shift_x, yaw])."""
    def residual(params: FloatArray) -> FloatArray:
        theta, d, shift_x, yaw = params if solve_placement else (*params, 0.0, 0.0)
        if abs(d) >= 0.99 * camera.radius or abs(theta) > _THETA_LIMIT:   # outside what a CameraModel takes
            return np.full(image_points.size, 1e6)
        points = frame.reference_points(camera.radius, shift_x, 0.0, yaw)
        uv, valid = camera.replace(theta=theta, d=d).project(points)
        return np.where(valid[:, None], uv - image_points, 1e6).ravel()
    return residual


def _two_parameter_pose(camera: CameraModel, frame: HemisphereFrame, image_points: FloatArray,
                        start: tuple[float, float],
                        solve_placement: bool = True) -> tuple[float, float, float, float, float]:
    """(theta, d, shift_x, yaw, RMS px): the paper's two-parameter pose of one image by
    Levenberg-Marquardt on the reprojection error, from `start` (theta, d)."""
    residual = _pose_residual(camera, frame, image_points, solve_placement)
    initial = np.array([*start, 0.0, 0.0] if solve_placement else list(start))
    scale = np.array([1e-2, 1e-3, 1e-3, 1e-2][:initial.size])
    fit = least_squares(residual, initial, method="lm", x_scale=scale, xtol=1e-14, ftol=1e-14)
    shift_x, yaw = (float(fit.x[2]), float(fit.x[3])) if solve_placement else (0.0, 0.0)
    rms = float(np.sqrt(np.mean(np.sum(fit.fun.reshape(-1, 2) ** 2, axis=1))))
    return float(fit.x[0]), float(fit.x[1]), shift_x, yaw, rms


def solve_view(camera: CameraModel, frame: HemisphereFrame, image_points: FloatArray, index: int = 0,
               solve_placement: bool = True) -> ViewPose:
    """One image: the paper's (theta, d) by least squares on the reprojection error, with the
    frame's axial shift and yaw as nuisance unknowns (a frame is never placed exactly; both are
    separable from theta and d, unlike a shift along y, which looks like theta), and the full
    iterative PnP pose of the nominal frame for the terms the paper neglects."""
    image_points = np.asarray(image_points, dtype=np.float64)
    theta, d, shift_x, yaw, rms = _two_parameter_pose(camera, frame, image_points, (camera.theta, camera.d),
                                                      solve_placement)
    object_points = frame.reference_points(camera.radius)
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
                    gamma=float(gamma), t=_triple(tvec), full_rms=full_rms, rvec=_triple(rvec))


# =========================================================================== extrinsics
@dataclasses.dataclass(frozen=True)
class ExtrinsicsConfig:
    """How `calibrate_extrinsics` judges presses and combines them.

    A view is unusable when its imprints are not all found, are collinear or smeared, or its
    reprojection RMS exceeds `max_view_rms` px (an optional hard limit, off by default). Among
    the usable views, an outlier is one whose RMS lies above the set's median by more than
    `view_rms_k` robust standard deviations (`selection.gate_by_rms`), or whose theta or d lies
    more than `outlier_sigma` robust standard deviations from the others (or from the row-balance
    line). `balance_rows` allows the row balance. The row balance and the rejection of outliers
    are each kept only when, with each press left out in turn, they predict its imprint
    positions better by more than `term_margin` standard errors (`selection.choose_term`). Fewer
    than `min_views` views after that falls back to the paper's plain method (every usable view,
    the plain mean), which needs `min_views` usable views. `solve_placement` solves the frame's
    axial shift and yaw per image. Images without any imprint (between presses) are skipped
    when `skip_empty`. `plausibility`: the limits a result must meet to be returned at all.
    """

    frame: HemisphereFrame = HemisphereFrame()
    detector: ImprintDetectorConfig = ImprintDetectorConfig()
    min_views: int = 2
    max_view_rms: float = math.inf
    view_rms_k: float = 4.0
    outlier_sigma: float = 4.0
    solve_placement: bool = True
    balance_rows: bool = True
    term_margin: float = 2.0
    skip_empty: bool = True
    plausibility: Plausibility = Plausibility()

    def __post_init__(self) -> None:
        if self.min_views < 1:
            raise CalibrationError(f"min_views must be at least 1, got {self.min_views}")
        if not (self.max_view_rms > 0 and self.outlier_sigma > 0 and self.view_rms_k > 0 and self.term_margin >= 0):
            raise CalibrationError("max_view_rms, view_rms_k and outlier_sigma must be positive, term_margin >= 0")


@dataclasses.dataclass(frozen=True)
class NeglectedTerms:
    """Mean and spread over the presses of the full pose's terms the paper's model neglects, and
    how far apart the two models put back-projected points on the membrane."""

    full_theta_deg: float
    full_theta_std_deg: float
    beta_deg: float
    beta_std_deg: float
    gamma_deg: float
    gamma_std_deg: float
    tx_mm: float
    tx_std_mm: float
    ty_mm: float
    ty_std_mm: float
    tz_mm: float
    tz_std_mm: float
    full_rms_px: float
    model_error_centre_mm: float     # mean over the central contact band
    model_error_max_mm: float        # max over the image


@dataclasses.dataclass(frozen=True)
class RowBalance:
    """Whether theta was corrected for the frame's placement along y, and the evidence."""

    applied: bool
    reason: str              # one line: why it was (not) applied
    slope_deg: float         # d(theta)/d(row asymmetry) taken out, degrees (NaN when not fitted)
    significance: float      # the fitted slope in standard errors (NaN when not fitted)
    margin_px: float = math.nan   # held-out margin (`selection.TermChoice`), px
    spread_px: float = math.nan   # its standard error


@dataclasses.dataclass(frozen=True)
class ExtrinsicsResult:
    camera: CameraModel               # the input intrinsics with theta and d replaced by the result
    theta: float                      # rad
    d: float                          # m
    theta_std: float                  # rad, spread (sample std) of the views' corrected theta
    d_std: float                      # m
    theta_sigma: float                # rad, one-sigma uncertainty of theta (views + intrinsics)
    d_sigma: float                    # m
    theta_plain_mean: float           # rad, the paper's plain mean over the same views
    row_balance: RowBalance
    views: list[ViewPose]             # used views
    rejected: dict[int, str]          # image index -> reason
    image_count: int
    neglected: NeglectedTerms
    theta_press_sigma: float = math.nan   # rad, the presses' share of theta_sigma (jackknife over presses)
    d_press_sigma: float = math.nan       # m
    #: rad, m: the model error's share of the sigmas, which every press shares: the pull a shadow leaves on
    #: the imprint centres (`imprints.shadow_pull`, moved through the pose solves) and, for theta with the row
    #: balance, how far the rows' other strength measure moves it (`_strength_model_error`)
    theta_model_sigma: float = 0.0
    d_model_sigma: float = 0.0
    #: the optional terms and the held-out evidence for each (row balance, view rejection)
    choices: tuple[TermChoice, ...] = ()
    #: "terms chosen by held-out prediction", or the paper's plain method when that left too few views
    method: str = "terms chosen by held-out prediction"
    warnings: tuple[str, ...] = ()
    #: d(theta, d) / d(intrinsic) over `uncertainty.INTRINSIC_NAMES`, (9, 2): propagates an intrinsics covariance
    intrinsics_gradient: FloatArray = dataclasses.field(default_factory=lambda: np.zeros((9, 2)), compare=False)

    @property
    def rms(self) -> float:
        return float(np.sqrt(np.mean([v.rms**2 for v in self.views])))

    def summary(self) -> str:
        n = self.neglected
        return (f"extrinsics from {len(self.views)}/{self.image_count} images: "
                f"theta = {math.degrees(self.theta):.4f}° ± {math.degrees(self.theta_sigma):.4f}°, "
                f"d = {self.d * 1e3:.4f} ± {self.d_sigma * 1e3:.4f} mm (one sigma, with a model error every press "
                f"shares of {math.degrees(self.theta_model_sigma):.4f}° and {self.d_model_sigma * 1e3:.4f} mm), "
                f"RMS {self.rms:.3f} px "
                f"(full pose {n.full_rms_px:.3f} px); neglected: beta {n.beta_deg:.3f}°, "
                f"gamma {n.gamma_deg:.3f}°, tx {n.tx_mm:.3f} mm, ty {n.ty_mm:.3f} mm; "
                f"two-parameter model differs from the full pose by {n.model_error_centre_mm:.3f} mm "
                f"in the contact band (max {n.model_error_max_mm:.3f} mm over the image); "
                + ("row balance applied" if self.row_balance.applied else "paper's plain mean")
                + f" ({self.row_balance.reason}); {self.method}"
                + "".join(f"; {c.line()}" for c in self.choices)
                + "".join(f"; warning: {w}" for w in self.warnings))

    def to_dict(self) -> dict[str, Any]:
        """The result as plain data, for the report file the CLI writes."""
        return {
            "theta_rad": self.theta, "theta_deg": math.degrees(self.theta),
            "theta_std_deg": math.degrees(self.theta_std), "theta_sigma_deg": math.degrees(self.theta_sigma),
            "theta_plain_mean_deg": math.degrees(self.theta_plain_mean),
            "d_m": self.d, "d_mm": self.d * 1e3, "d_std_mm": self.d_std * 1e3, "d_sigma_mm": self.d_sigma * 1e3,
            "theta_model_sigma_deg": math.degrees(self.theta_model_sigma), "d_model_sigma_mm": self.d_model_sigma * 1e3,
            "rms_px": self.rms, "views_used": len(self.views), "images": self.image_count,
            "row_balance": dataclasses.asdict(self.row_balance),
            "method": self.method, "choices": [dataclasses.asdict(c) | {"line": c.line()} for c in self.choices],
            "warnings": list(self.warnings),
            "rejected": {int(k): v for k, v in self.rejected.items()},
            "neglected": dataclasses.asdict(self.neglected),
            "views": [v.as_dict() for v in self.views],
        }


def calibrate_extrinsics(images: Iterable[np.ndarray], camera: CameraModel,
                         config: ExtrinsicsConfig = ExtrinsicsConfig(), reference: np.ndarray | None = None,
                         intrinsics_sigma: Mapping[str, float] | None = None,
                         intrinsics_covariance: FloatArray | None = None,
                         dark: np.ndarray | None = None) -> ExtrinsicsResult:
    """theta and d from hemisphere-frame images (the paper's averaging, with outlier rejection and
    the row balance; see `ExtrinsicsConfig`).

    `camera` carries the intrinsics and the prior theta, d that start the solves; `reference` is a
    no-contact frame, `dark` one with the sensor's lights off (it lets the row balance tell the
    light from a background the light does not make: `imprints._light`). The intrinsics'
    uncertainty is propagated into theta_sigma and d_sigma (d scales with the focal length and
    theta moves with cy, so the intrinsics often dominate it):
    `intrinsics_covariance` (as `IntrinsicsResult.covariance`, with its correlations), else
    `intrinsics_sigma` (one-sigma values by name, as a parameters file keeps them); neither: the
    presses' share alone.
    """
    frame = config.frame
    images = list(images)
    if not images:
        raise CalibrationError("no hemisphere-frame images given")
    width, height = image_size(images)
    if (width, height) != (camera.width, camera.height):
        raise CalibrationError(f"the intrinsics are for {camera.width}x{camera.height} images, the presses are "
                               f"{width}x{height}: calibrate the intrinsics on this camera first")
    frame.reference_points(camera.radius)       # fails early if the frame does not fit the roller
    solved, points, pulls, rejected, total = _solve_views(images, camera, config, reference, dark)
    solved = _with_row_asymmetry(solved)
    held_out = _HeldOut(camera, frame, points, config.solve_placement)
    views, balance, choices, fit, rejected = _choose_terms(solved, config, held_out, rejected)
    method = "terms chosen by held-out prediction"
    if len(views) < config.min_views:
        # the paper's plain method: every view that solved, the plain mean; never nothing when it solves
        method = (f"the paper's plain method (every usable view, the plain mean): only {len(views)} view(s) were "
                  f"left after the rejections, need {config.min_views}")
        views, fit = solved, None
        balance = RowBalance(False, "not used: fell back to the paper's plain method", math.nan, math.nan)
        used = {view.index for view in solved}
        rejected = {index: why for index, why in rejected.items() if index not in used}
    require_views(len(views), config.min_views, total, rejected, "hemisphere-frame")
    slope = fit.slope if (fit is not None and balance.applied) else 0.0
    shifts = np.array([slope * v.row_asymmetry for v in views])
    if balance.applied:
        plate_z = camera.radius + frame.hemisphere_radius - frame.press_depth
        views = [dataclasses.replace(v, frame_shift_y=-shift * plate_z) for v, shift in zip(views, shifts, strict=True)]
    # each view's theta with its frame shift along y taken out (that shift turns the picture like theta does)
    thetas = np.array([v.theta for v in views]) + shifts
    ds = np.array([v.d for v in views])
    theta, d = float(thetas.mean()), float(ds.mean())
    theta_se, d_se = _standard_errors(views, thetas, ds, fit if balance.applied else None)
    gradient, pull_shift = _pose_sensitivities(camera, frame, views, points, pulls, config.solve_placement)
    theta_strength = _strength_model_error(views) if balance.applied else 0.0
    theta_model = math.hypot(float(pull_shift[0]), theta_strength)
    d_model = abs(float(pull_shift[1]))
    covariance = intrinsics_covariance if intrinsics_covariance is not None else \
        intrinsics_covariance_from_sigma(intrinsics_sigma)
    theta_intr, d_intr = _intrinsics_effect(gradient, covariance)
    result_camera = camera.replace(theta=theta, d=d)
    ddof = 1 if len(views) > 1 else 0
    median_rms = float(np.median([v.rms for v in views]))
    warning = rms_warning(median_rms, math.degrees(theta_se), d_se * 1e3)
    warnings = ([method] if method != "terms chosen by held-out prediction" else []) + ([warning] if warning else [])
    result = ExtrinsicsResult(
        camera=result_camera, theta=theta, d=d,
        theta_std=float(thetas.std(ddof=ddof)), d_std=float(ds.std(ddof=ddof)),
        theta_sigma=math.sqrt(theta_se**2 + theta_intr**2 + theta_model**2),
        d_sigma=math.sqrt(d_se**2 + d_intr**2 + d_model**2),
        theta_plain_mean=float(np.mean([v.theta for v in views])), row_balance=balance,
        views=views, rejected=rejected, image_count=total,
        neglected=_neglected_terms(result_camera, views, shifts),
        theta_press_sigma=theta_se, d_press_sigma=d_se, intrinsics_gradient=gradient,
        theta_model_sigma=theta_model, d_model_sigma=d_model,
        choices=choices, method=method, warnings=tuple(warnings))
    check_plausible(result, camera, config.plausibility)
    return result


class _HeldOut:
    """Held-out prediction of one press's imprint positions: given (theta, d) from the other
    presses, its own frame placement (axial shift, yaw: nuisances no other press can know) is
    refitted and the reprojection RMS (px) of its imprints is what the prediction scores."""

    def __init__(self, camera: CameraModel, frame: HemisphereFrame, points: Mapping[int, FloatArray],
                 solve_placement: bool) -> None:
        self.camera, self.frame, self.points, self.solve_placement = camera, frame, points, solve_placement

    def rms(self, view: ViewPose, theta: float, d: float) -> float:
        residual = _pose_residual(self.camera, self.frame, self.points[view.index], self.solve_placement)
        if not self.solve_placement:
            fun = residual(np.array([theta, d]))
        else:
            start = np.array([view.shift_x, view.yaw])
            fit = least_squares(lambda p: residual(np.array([theta, d, p[0], p[1]])), start, method="lm",
                                x_scale=np.array([1e-3, 1e-2]), xtol=1e-12, ftol=1e-12)
            fun = fit.fun
        return float(np.sqrt(np.mean(np.sum(fun.reshape(-1, 2) ** 2, axis=1))))

    def errors(self, views: Sequence[ViewPose], use: NDArray[np.bool_], balanced: bool) -> FloatArray:
        """Each view's held-out RMS, (theta, d) estimated from the other views in `use`: their plain
        means, or (`balanced`) theta from their row-balance line at the view's own asymmetry."""
        raw = np.array([v.theta for v in views])
        a = np.array([v.row_asymmetry for v in views])
        ds = np.array([v.d for v in views])
        out = np.full(len(views), np.nan)
        for i, view in enumerate(views):
            others = use.copy()
            others[i] = False
            if others.sum() < (3 if balanced else 1):
                continue
            if balanced:
                if np.ptp(a[others]) <= 0:
                    continue
                slope, intercept = np.polyfit(a[others], raw[others], 1)
                theta = float(intercept + slope * a[i])
            else:
                theta = float(raw[others].mean())
            out[i] = self.rms(view, theta, float(ds[others].mean()))
        return out


def _choose_terms(views: list[ViewPose], config: ExtrinsicsConfig, held_out: _HeldOut, rejected: dict[int, str]
                  ) -> tuple[list[ViewPose], RowBalance, tuple[TermChoice, ...], _BalanceFit | None, dict[int, str]]:
    """The row balance and the rejection of outliers, each kept only when it predicts left-out
    presses better (`selection.choose_term`). Returns the views used, the row balance's verdict,
    the choices, the row-balance fit and the rejected views."""
    rejected = dict(rejected)
    gate = gate_by_rms([v.rms for v in views], config.view_rms_k)
    gated = [v for v, ok in zip(views, gate, strict=True) if ok]
    fit = _row_balance(gated, config) if config.balance_rows else None
    balance = _balance_verdict(fit, config, len(gated))
    balance_choice = not_judged("row balance", balance.reason)
    if balance.applied and fit is not None:
        use = fit.inliers.copy()
        balance_choice = choose_term("row balance", held_out.errors(gated, use, False),
                                     held_out.errors(gated, use, True), config.term_margin)
        balance = dataclasses.replace(
            balance, applied=balance_choice.kept, margin_px=balance_choice.margin_px,
            spread_px=balance_choice.spread_px,
            reason=(f"{balance.reason}; " if balance_choice.kept else
                    f"does not predict left-out presses better ({balance.reason}); ") + balance_choice.line())
    kept, outlier_reasons = _drop_outliers(gated, fit if balance.applied else None, config, {})
    for view, ok in zip(views, gate, strict=True):
        if not ok:
            outlier_reasons[view.index] = (f"outlier: reprojection RMS {view.rms:.2f} px, far above the other views' "
                                           f"(median {np.median([v.rms for v in views]):.2f} px)")
    if outlier_reasons:
        keep = np.array([v.index not in outlier_reasons for v in views])
        everything = np.ones(len(views), dtype=bool)
        rejection = choose_term("view rejection", held_out.errors(views, everything, balance.applied),
                                held_out.errors(views, keep, balance.applied), config.term_margin,
                                f"{len(outlier_reasons)} outlier(s)")
        if rejection.kept:
            rejected.update(outlier_reasons)
            used = kept
        else:
            used = list(views)
            if balance.applied and fit is not None:
                fit = dataclasses.replace(fit, inliers=np.ones(len(views), dtype=bool))
    else:
        rejection = not_judged("view rejection", "no view stands out")
        used = kept
    if balance.applied and fit is not None and len(used) != len(gated):
        fit = _refit_balance(used, fit)
    return used, balance, (balance_choice, rejection), fit, rejected


def _refit_balance(views: Sequence[ViewPose], fit: _BalanceFit) -> _BalanceFit:
    """The row-balance line on `views` (least squares, every view an inlier)."""
    a = np.array([v.row_asymmetry for v in views])
    theta = np.array([v.theta for v in views])
    if len(views) < 3 or np.ptp(a) <= 0:
        return fit
    slope, _ = (float(c) for c in np.polyfit(a, theta, 1))
    return dataclasses.replace(fit, slope=-slope, inliers=np.ones(len(views), dtype=bool))


def _solve_views(images: Sequence[np.ndarray], camera: CameraModel, config: ExtrinsicsConfig,
                 reference: np.ndarray | None,
                 dark: np.ndarray | None = None
                 ) -> tuple[list[ViewPose], dict[int, FloatArray], dict[int, FloatArray], dict[int, str], int]:
    """Per image: imprints, the pose solve and the rows' strengths; (views, imprint centres by
    image index, the centres' shadow pulls by image index (`imprints.shadow_pull`; only for the
    images whose detector measured them), rejected, number of press images)."""
    frame = config.frame
    rejected: dict[int, str] = {}
    views: list[ViewPose] = []
    points: dict[int, FloatArray] = {}
    pulls: dict[int, FloatArray] = {}
    empty = 0
    for index, image in enumerate(images):
        detection = find_imprints(image, frame, config.detector, reference, dark)
        if detection.found == 0 and config.skip_empty:
            empty += 1          # a frame between presses, not a view
            continue
        if detection.centres is None:
            rejected[index] = str(detection.reason)
            continue
        try:
            view = solve_view(camera, frame, detection.centres, index, config.solve_placement)
        except CalibrationError as exc:
            rejected[index] = str(exc)
            continue
        if not view.rms <= config.max_view_rms:
            rejected[index] = f"reprojection RMS {view.rms:.2f} px (hard limit {config.max_view_rms:.2f})"
            continue
        strengths = _per_membrane_area(detection.strengths, camera.replace(theta=view.theta, d=view.d),
                                       frame.reference_points(camera.radius, view.shift_x, 0.0, view.yaw))
        other = _per_membrane_area(detection.other_strengths, camera.replace(theta=view.theta, d=view.d),
                                   frame.reference_points(camera.radius, view.shift_x, 0.0, view.yaw))
        views.append(dataclasses.replace(view, row_strengths=_row_strengths(strengths, frame),
                                         other_row_strengths=_row_strengths(other, frame)))
        points[index] = detection.centres
        if detection.pull is not None:
            pulls[index] = detection.pull
    total = len(images) - empty
    if total == 0:
        raise CalibrationError(f"no imprints found in any of the {len(images)} hemisphere-frame images")
    require_views(len(views), config.min_views, total, rejected, "hemisphere-frame")
    return views, points, pulls, rejected, total


def _drop_outliers(views: list[ViewPose], fit: _BalanceFit | None, config: ExtrinsicsConfig,
                   rejected: dict[int, str]) -> tuple[list[ViewPose], dict[int, str]]:
    """Views whose d, or whose theta (against the others, or against the row-balance line), is an outlier."""
    d_ok = inliers(np.array([v.d for v in views]), config.outlier_sigma, 5e-6)
    if fit is None:     # the paper's plain mean: theta outliers against the other views
        keep = d_ok & inliers(np.array([v.theta for v in views]), config.outlier_sigma, math.radians(0.01))
        why = "far from the other views"
    else:
        keep = d_ok & fit.inliers
        why = "off the row-balance fit"
    rejected = dict(rejected)
    for view, ok in zip(views, keep, strict=True):
        if not ok:
            rejected[view.index] = f"outlier: theta {math.degrees(view.theta):.3f}°, d {view.d * 1e3:.3f} mm {why}"
    return [v for v, ok in zip(views, keep, strict=True) if ok], rejected


def _strength_model_error(views: Sequence[ViewPose]) -> float:
    """How far the row balance's theta moves (rad) when the rows' strengths are measured the
    detector's other way (`ViewPose.other_row_strengths`): the line theta_i = theta + s a_i refitted
    on the same views with the other asymmetry. Both measures follow the press depth and both are
    light-independent in principle (energy relative to the light of a lights-off frame, and the
    imprints' extent); where a low light or shadows make them disagree, the zero of the row
    asymmetry is uncertain by as much, for every press alike. 0 when there is no other measure."""
    other = [dataclasses.replace(v, row_strengths=v.other_row_strengths) for v in views]
    if len(views) < 3 or not np.all(np.isfinite([s for v in other for s in v.row_strengths])):
        return 0.0
    raw = np.array([v.theta for v in views])
    a = np.array([v.row_asymmetry for v in views])
    b = np.array([v.row_asymmetry for v in _with_row_asymmetry(other)])
    if np.ptp(a) <= 0 or np.ptp(b) <= 0 or not np.all(np.isfinite(b)):
        return 0.0
    return abs(float(np.polyfit(a, raw, 1)[1]) - float(np.polyfit(b, raw, 1)[1]))


def _standard_errors(views: Sequence[ViewPose], thetas: FloatArray, ds: FloatArray,
                     fit: _BalanceFit | None) -> tuple[float, float]:
    """Standard errors of theta and d from the presses, by the jackknife over presses: the
    estimate redone with each press left out (with the row balance, its slope refitted too, so a
    press that leans on the slope counts as much as it moves the result; the analytic standard
    error of an intercept assumes every press scatters alike). For d, and for theta's plain mean,
    this is the usual standard error of a mean."""
    n = len(views)
    if n < 2:
        return math.nan, math.nan
    keep = np.ones(n, dtype=bool)
    theta_out, d_out = [], []
    raw = np.array([v.theta for v in views])
    a = np.array([v.row_asymmetry for v in views])
    for i in range(n):
        keep[:] = True
        keep[i] = False
        d_out.append(float(ds[keep].mean()))
        if fit is None:
            theta_out.append(float(thetas[keep].mean()))
        elif np.ptp(a[keep]) > 0 and keep.sum() >= 2:
            slope, intercept = np.polyfit(a[keep], raw[keep], 1)
            theta_out.append(float(intercept))
    theta_se = jackknife_std(np.array(theta_out)) if len(theta_out) == n else math.nan
    return theta_se, jackknife_std(np.array(d_out))


#: finite-difference steps of the intrinsics (`uncertainty.INTRINSIC_NAMES`) for the pose sensitivities
_INTRINSIC_STEPS = (0.1, 0.1, 0.1, 0.1, 1e-3, 1e-3, 1e-4, 1e-4, 1e-3)


def _pose_sensitivities(camera: CameraModel, frame: HemisphereFrame, views: Sequence[ViewPose],
                        points: Mapping[int, FloatArray], pulls: Mapping[int, FloatArray],
                        solve_placement: bool) -> tuple[FloatArray, FloatArray]:
    """(d(mean theta, mean d) / d(intrinsic), (9, 2) over `uncertainty.INTRINSIC_NAMES`; how far the
    mean theta and d move, (2,), when each view's imprint centres move by its `pulls`). Each view's
    pose sensitivity comes from its least-squares solve linearised at the solution (Gauss-Newton:
    d(pose) = -(J^T J)^-1 J^T d(residual)), with each intrinsic parameter moved in turn; moving the
    imprint centres by p moves the residual by -p. Views without a pull count as moving by 0."""
    gradient = np.zeros((len(INTRINSIC_NAMES), 2))
    pull_shift = np.zeros(2)
    for view in views:
        pose = np.array([view.theta, view.d, view.shift_x, view.yaw][:4 if solve_placement else 2])
        residual = _pose_residual(camera, frame, points[view.index], solve_placement)
        jacobian = _numeric_jacobian(residual, pose, np.array([1e-5, 1e-6, 1e-6, 1e-5])[:pose.size])
        normal = np.linalg.pinv(jacobian.T @ jacobian) @ jacobian.T
        base = residual(pose)
        pull = pulls.get(view.index)
        if pull is not None and np.all(np.isfinite(pull)):
            pull_shift += (normal @ np.asarray(pull, dtype=np.float64).ravel())[:2] / len(views)
        for k, (name, step) in enumerate(zip(INTRINSIC_NAMES, _INTRINSIC_STEPS, strict=True)):
            moved = _pose_residual(_moved_intrinsic(camera, name, step), frame, points[view.index],
                                   solve_placement)(pose)
            gradient[k] += -(normal @ (moved - base))[:2] / len(views) / step
    return gradient, pull_shift


def intrinsics_covariance_from_sigma(sigma: Mapping[str, float] | None) -> FloatArray:
    """A covariance over `uncertainty.INTRINSIC_NAMES` from one-sigma values alone (what a
    parameters file keeps): fx and fy come from the same views and move together (correlation 1),
    the other terms independent; missing or non-finite sigmas count as 0."""
    values = np.array([float((sigma or {}).get(name, 0.0)) for name in INTRINSIC_NAMES])
    values = np.where(np.isfinite(values) & (values > 0), values, 0.0)
    covariance = np.diag(values**2)
    covariance[0, 1] = covariance[1, 0] = values[0] * values[1]
    return covariance


def _intrinsics_effect(gradient: FloatArray, covariance: FloatArray) -> tuple[float, float]:
    """One sigma of (theta, d) from the intrinsics: sqrt of the diagonal of g^T C g."""
    variance = np.diag(gradient.T @ np.nan_to_num(np.asarray(covariance, dtype=np.float64)) @ gradient)
    return math.sqrt(max(float(variance[0]), 0.0)), math.sqrt(max(float(variance[1]), 0.0))


def _moved_intrinsic(camera: CameraModel, name: str, step: float) -> CameraModel:
    """`camera` with one of `uncertainty.INTRINSIC_NAMES` moved by `step`."""
    if name in ("fx", "fy", "cx", "cy"):
        return camera.replace(**{name: getattr(camera, name) + step})
    distortion = list(camera.distortion) + [0.0] * (5 - len(camera.distortion))
    distortion[INTRINSIC_NAMES.index(name) - 4] += step
    return camera.replace(distortion=tuple(distortion))


def _numeric_jacobian(function: Callable[[FloatArray], FloatArray], x: FloatArray, steps: FloatArray) -> FloatArray:
    columns = []
    for k, step in enumerate(steps):
        delta = np.zeros_like(x)
        delta[k] = step
        columns.append((function(x + delta) - function(x - delta)) / (2 * step))
    return np.stack(columns, axis=1)


def _per_membrane_area(strengths: FloatArray | None, camera: CameraModel, points: FloatArray) -> FloatArray | None:
    """Strengths summed over pixels, divided by the pixels one mm^2 of membrane covers at each
    imprint: the rows lie at different angles to the optical axis, so one row's imprints cover
    ~1 % more pixels than the other's, which would read as a deeper press."""
    if strengths is None:
        return None
    step = 1e-4
    x, alpha = CameraModel.surface_coords(points)
    arc = step / camera.radius
    def pixels(x_at: FloatArray, alpha_at: FloatArray) -> FloatArray:
        return camera.project(camera.surface_point(x_at, alpha_at))[0]

    du = pixels(x + step, alpha) - pixels(x - step, alpha)
    dv = pixels(x, alpha + arc) - pixels(x, alpha - arc)
    pixels_per_m2 = np.abs(du[:, 0] * dv[:, 1] - du[:, 1] * dv[:, 0]) / (2 * step) ** 2
    return np.where(np.isfinite(pixels_per_m2) & (pixels_per_m2 > 0), strengths / pixels_per_m2 * 1e-6, np.nan)


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


@dataclasses.dataclass(frozen=True)
class _BalanceFit:
    slope: float                  # -d(theta)/d(asymmetry), rad; positive for a physical fit
    slope_se: float               # its standard error
    residual_std: float           # rad, scatter of theta about the line
    inliers: NDArray[np.bool_]


def _row_balance(views: Sequence[ViewPose], config: ExtrinsicsConfig,
                 min_asymmetry_spread: float = 0.05) -> _BalanceFit | None:
    """Fit theta_i = theta + s * a_i over the views (a_i: row asymmetry).

    A frame shifted by e along y turns the picture like a rotation theta of e / plate_z, and no
    pose solve can tell them apart. But the row nearer the contact line presses deeper and leaves
    the stronger imprint, so the rows' strength asymmetry a_i measures the shift: a_i = 0 for a
    centred frame (by symmetry, once the strengths are relative to the light each row gets and
    per mm^2 of membrane), and theta at a = 0 is the camera's. The slope comes from the views'
    own scatter (no model of imprint strength needed): a robust Theil-Sen line, outliers by their
    residual, then least squares on the inliers. Returns None when the views do not vary enough
    in a to fit a slope.
    """
    a = np.array([v.row_asymmetry for v in views])
    theta = np.array([v.theta for v in views])
    if len(views) < 3 or not np.all(np.isfinite(a)) or np.ptp(a) < min_asymmetry_spread:
        return None
    slope, intercept = _theil_sen(a, theta)
    residual = theta - (intercept + slope * a)
    scale = max(1.4826 * float(np.median(np.abs(residual))), math.radians(0.05))
    keep = np.abs(residual) <= config.outlier_sigma * scale
    if keep.sum() < 3 or np.ptp(a[keep]) < min_asymmetry_spread:
        return None
    slope, intercept = (float(c) for c in np.polyfit(a[keep], theta[keep], 1))
    spread = theta[keep] - (intercept + slope * a[keep])
    dof = int(keep.sum()) - 2
    residual_std = float(np.sqrt((spread**2).sum() / dof)) if dof > 0 else math.nan
    a_spread = float(((a[keep] - a[keep].mean()) ** 2).sum())
    return _BalanceFit(slope=-slope, slope_se=residual_std / math.sqrt(a_spread) if a_spread > 0 else math.inf,
                       residual_std=residual_std, inliers=keep)


def _balance_verdict(fit: _BalanceFit | None, config: ExtrinsicsConfig, views: int) -> RowBalance:
    """Whether the row balance can be put to the held-out test: allowed, fitted (the presses vary
    in row strength), and a slope of the physical sign. Its fit's significance is reported, not
    used: a slope can be many standard errors from zero and still be the light's asymmetry, not
    the frame's placement; only what it predicts decides (`_choose_terms`)."""
    if not config.balance_rows:
        return RowBalance(False, "switched off", math.nan, math.nan)
    if fit is None:
        return RowBalance(False, f"the {views} presses hardly differ in row strength: theta includes the frame's "
                          "placement error along y (1 mm = 1.1°); move the frame between 5 or more presses",
                          math.nan, math.nan)
    significance = fit.slope / fit.slope_se if fit.slope_se > 0 else math.inf
    if not math.isfinite(fit.residual_std):
        significance = math.nan
    degrees = math.degrees(fit.slope)
    if fit.slope <= 0:
        return RowBalance(False, f"rows' strengths do not follow the placement (slope of the wrong sign, "
                          f"{degrees:.2f}°)", degrees, significance)
    return RowBalance(True, f"slope {degrees:.2f}° per unit asymmetry, {significance:.1f} standard errors",
                      degrees, significance)


def _theil_sen(x: FloatArray, y: FloatArray) -> tuple[float, float]:
    """Median of the pairwise slopes and the median intercept (scipy.stats.theilslopes without the
    ~0.5 s import of scipy.stats)."""
    i, j = np.triu_indices(len(x), k=1)
    dx = x[j] - x[i]
    ok = dx != 0
    slope = float(np.median((y[j] - y[i])[ok] / dx[ok])) if ok.any() else 0.0
    return slope, float(np.median(y - slope * x))


def _neglected_terms(camera: CameraModel, views: Sequence[ViewPose], theta_shift: FloatArray) -> NeglectedTerms:
    """Mean and spread of the full poses. `theta_shift` (per view, rad) takes the frame's shift
    along y out of the full pose's theta as the row balance did for the two-parameter theta, so
    the comparison of the two models is about the camera, not the frame's placement."""
    beta = np.array([v.beta for v in views])
    gamma = np.array([v.gamma for v in views])
    t = np.array([v.t for v in views]) * 1e3
    full_theta = np.array([v.full_theta for v in views]) + np.asarray(theta_shift, dtype=np.float64)
    ddof = 1 if len(views) > 1 else 0
    rotation = full_pose_rotation(float(full_theta.mean()), float(beta.mean()), float(gamma.mean()))
    error_centre, error_max = model_error_mm(camera, rotation, t.mean(axis=0) * 1e-3)
    return NeglectedTerms(
        full_theta_deg=math.degrees(full_theta.mean()), full_theta_std_deg=math.degrees(full_theta.std(ddof=ddof)),
        beta_deg=math.degrees(beta.mean()), beta_std_deg=math.degrees(beta.std(ddof=ddof)),
        gamma_deg=math.degrees(gamma.mean()), gamma_std_deg=math.degrees(gamma.std(ddof=ddof)),
        tx_mm=float(t[:, 0].mean()), tx_std_mm=float(t[:, 0].std(ddof=ddof)),
        ty_mm=float(t[:, 1].mean()), ty_std_mm=float(t[:, 1].std(ddof=ddof)),
        tz_mm=float(t[:, 2].mean()), tz_std_mm=float(t[:, 2].std(ddof=ddof)),
        full_rms_px=float(np.sqrt(np.mean([v.full_rms**2 for v in views]))),
        model_error_centre_mm=error_centre, model_error_max_mm=error_max)


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


