"""Photometric calibration from presses of a ball of known radius.

Each press is an image with a loosely labelled contact circle (centre and radius in pixels, as hand
labelling gives them). The circle is refined from the image: the colour change against the reference
is strongest where the membrane is steepest, at the contact's edge, so along rays from the labelled
centre the edge is the peak of the smoothed change magnitude (sub-pixel), and a robust algebraic
circle fit to those peaks is the new circle (twice, from the new centre). Inside the refined circle
the membrane wraps the ball, so its slopes are the sphere's: with the contact centre (u0, v0), pixel
size (su, sv) and ball radius R, dx = (u - u0) su, dy = (v - v0) sv, rho^2 = dx^2 + dy^2,

    gx = -dx / sqrt(R^2 - rho^2),   gy = -dy / sqrt(R^2 - rho^2)

(indentation positive into the gel, deepest at the centre). On a roller the membrane is a cylinder of
radius r curved along the image rows (v), and the indentation is measured from it: away from the press's
centre the tube recedes from the ball by r - sqrt(r^2 - dy^2), so the indentation's slope along v is
the sphere's plus the tube's, gy = -dy / sqrt(R^2 - rho^2) - dy / sqrt(r^2 - dy^2) (`membrane_radius`;
a flat sensor's is infinite). Leaving it out teaches the model a slope along v too gentle by about
r / (R + r). Those are the targets, together with a
sparse sample of the far field (beyond `far_factor` radii, where the gel is undeformed: slope 0).
The ring between is left out: there the gel sinks around the ball with slopes nobody knows.
"""
from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, field, replace

import cv2
import numpy as np

from touchroller_perception.calibration.common import CalibrationError
from touchroller_perception.height.photometric import (
    MAP_PHOTOMETRIC,
    PhotometricConfig,
    PhotometricModel,
    colour_features,
    fit_model,
    model_terms,
)
from touchroller_perception.height.reference import ReferenceChoice, choose_reference, far_masks


@dataclass(frozen=True)
class BallPress:
    """One press: the image, the labelled circle (px) and the pixel size there (m, along u and v).
    `membrane_radius`: the membrane's radius of curvature along the image rows (v) there, m: the
    roller's radius (`CameraModel.radius`); infinite for a flat sensor."""

    image: np.ndarray
    u: float
    v: float
    radius_px: float
    pixel_size: tuple[float, float]
    name: str = ""
    membrane_radius: float = math.inf

    def __post_init__(self) -> None:
        if not (self.membrane_radius > 0 and not math.isnan(self.membrane_radius)):
            raise CalibrationError(f"press {self.name or '?'}: membrane radius must be positive metres (inf: flat), "
                                   f"got {self.membrane_radius}")


#: `PressCalibrationConfig.still_quantile`'s default (see docs/height.md, "Zero-slope prior")
STILL_QUANTILE = 0.9


@dataclass(frozen=True)
class PressCalibrationConfig:
    model: PhotometricConfig = field(default_factory=PhotometricConfig)
    refine: bool = True                  # refine the labelled circles from the images
    refine_iterations: int = 2
    search: tuple[float, float] = (0.75, 1.2)   # edge search, in label radii
    max_shift: float = 0.35              # a refined circle further than this (label radii) is refused
    edge_margin_px: float = 1.0          # samples from inside radius - margin
    max_slope_angle_deg: float = 75.0    # targets steeper than this (close to the ball's equator) are left out
    inside_fraction: float = 0.5         # fraction of the inside pixels used (deterministic subsample)
    far_factor: float = 2.2              # far field: beyond this many contact radii ...
    far_fraction: float = 0.01           # ... this fraction of its pixels, slope 0 (0.05: see docs/height.md)
    seed: int = 0
    # candidate position degrees, the one whose slopes hold their gain best on held-out presses is used
    # (`choose_position_degree`); empty: the model's own `position_degree`
    position_degrees: tuple[int, ...] = ()
    # candidate degrees of the colour monomials that get position factors (`PhotometricConfig.position_colour_degree`),
    # the one whose held-out presses read their normals best is used (`choose_position_colour_degree`, after the
    # position degree); empty: the model's own
    position_colour_degrees: tuple[int, ...] = ()
    selection_folds: int = 4             # presses split this many ways (press i in fold i mod folds) to choose
    # the reference the model reads colour changes against (`reference.choose_reference`): "given" the no-contact
    # frame given, "presses" one built from the presses' far fields (beyond `reference_factor` label radii),
    # "auto" the one of the two the presses' far fields match better
    reference: str = "given"
    reference_factor: float = 3.0
    # the zero-slope prior's threshold (`PhotometricModel.still_slope`): this quantile of the slope's magnitude
    # the fitted model reads on the presses beyond `reference_factor` label radii, the undeformed gel (0: none)
    still_quantile: float = STILL_QUANTILE
    # ... that length measured in the ellipse of those slopes' covariance (unit area; `PhotometricModel.still_shape`);
    # False: round (the plain length)
    still_ellipse: bool = True

    def __post_init__(self) -> None:
        if not (0.0 < self.search[0] < 1.0 < self.search[1] <= 2.0):
            raise ValueError(f"search must be (lo < 1 < hi <= 2) label radii, got {self.search}")
        if not 0.0 < self.inside_fraction <= 1.0 or not 0.0 <= self.far_fraction <= 1.0:
            raise ValueError("inside_fraction must be in (0, 1] and far_fraction in [0, 1]")
        if not self.far_factor > 1.0:
            raise ValueError(f"far_factor must be > 1, got {self.far_factor}")
        if not 0 < self.max_slope_angle_deg < 90:
            raise ValueError("max_slope_angle_deg must be in (0, 90)")
        if not all(0 <= int(d) <= 6 for d in self.position_degrees):
            raise ValueError(f"position_degrees must be 0..6 each, got {self.position_degrees}")
        if not all(0 <= int(d) <= self.model.colour_degree for d in self.position_colour_degrees):
            raise ValueError(f"position_colour_degrees must be 0..colour_degree ({self.model.colour_degree}) each, "
                             f"got {self.position_colour_degrees}")
        if not 2 <= self.selection_folds <= 20:
            raise ValueError(f"selection_folds must be 2..20, got {self.selection_folds}")
        if self.reference not in ("given", "presses", "auto"):
            raise ValueError(f"reference must be 'given', 'presses' or 'auto', got {self.reference!r}")
        if not (math.isfinite(self.reference_factor) and self.reference_factor > 1.0):
            raise ValueError(f"reference_factor must be > 1, got {self.reference_factor}")
        if not (math.isfinite(self.still_quantile) and 0.0 <= self.still_quantile < 1.0):
            raise ValueError(f"still_quantile must be in [0, 1) (0: no zero-slope prior), got {self.still_quantile}")


#: a world height map's calibration: the map's model (`MAP_PHOTOMETRIC`), its position degree chosen from 0..3
#: by held-out presses (`choose_position_degree`): the map integrates slopes across its band, and a gain that
#: wanders along the roller's axis is a relief that is not there
MAP_CALIBRATION = PressCalibrationConfig(model=MAP_PHOTOMETRIC, position_degrees=(0, 1, 2, 3))


@dataclass(frozen=True)
class FittedCircle:
    u: float
    v: float
    radius_px: float
    edge_rms_px: float       # RMS distance of the kept edge points from the circle
    edge_points: int         # edge points kept (of the rays cast)
    refined: bool            # False: the label was kept (refinement refused)

    def shift_from(self, u: float, v: float) -> float:
        return math.hypot(self.u - u, self.v - v)


@dataclass(frozen=True)
class PressFit:
    """How the model fits one press (its own, in-sample)."""

    name: str
    circle: FittedCircle
    label: tuple[float, float, float]      # u, v, radius_px as labelled
    normal_error_deg: float                # median angle between model and sphere normals in the circle
    normal_error_p90_deg: float
    samples: int


@dataclass(frozen=True)
class DegreeScore:
    """How a candidate position degree holds the slopes' gain on held-out presses (`choose_position_degree`)."""

    degree: int
    gain_deviation: float     # RMS over held-out presses and both slopes of (read / true gain - 1)
    normal_error_deg: float   # median over held-out presses of each press's median normal-angle error


@dataclass(frozen=True)
class PhotometricCalibration:
    model: PhotometricModel
    presses: tuple[PressFit, ...]
    ball_radius: float
    degree_scores: tuple[DegreeScore, ...] = ()   # the candidates weighed (empty: none were)
    # the reference the model was calibrated against (give this one to `HeightEstimator`), and how it was chosen
    reference: np.ndarray | None = None
    reference_choice: ReferenceChoice | None = None
    # the position-colour degrees weighed (`DegreeScore.degree` is the position-colour degree; empty: none were)
    colour_degree_scores: tuple[DegreeScore, ...] = ()
    # with position-colour candidates: the fraction of the image beyond `reference_factor` contact radii of at
    # least 3 presses (below 1: the presses keep to a part of the image, the model's own degree is kept; nan: none)
    press_spread: float = math.nan

    @property
    def normal_error_deg(self) -> float:
        """Median over the presses of each press's median normal-angle residual."""
        return float(np.median([p.normal_error_deg for p in self.presses]))

    def summary(self) -> str:
        refined = sum(p.circle.refined for p in self.presses)
        shifts = [p.circle.shift_from(p.label[0], p.label[1]) for p in self.presses]
        dr = [p.circle.radius_px - p.label[2] for p in self.presses]
        return (f"photometric calibration: {len(self.presses)} presses, ball radius {self.ball_radius * 1e3:.3f} mm, "
                f"{len(self.model.coefficients)} terms; normal-angle residual median {self.normal_error_deg:.2f} deg "
                f"(in-sample); {refined} circles refined from the images (centre moved {np.median(shifts):.1f} px, "
                f"radius {np.median(dr):+.1f} px, medians)" + self._degree_summary() + self._colour_degree_summary()
                + self._reference_summary() + self._prior_summary())

    def _prior_summary(self) -> str:
        if self.model.still_slope <= 0:
            return ""
        shape = "round" if self.model.still_shape == (1.0, 0.0, 0.0, 1.0) else "in the far-field slopes' ellipse"
        return (f"; zero-slope prior: slopes shorter than {self.model.still_slope:.4f} ({shape}) read 0, what the "
                "presses' undeformed gel reads")

    def _colour_degree_summary(self) -> str:
        if math.isfinite(self.press_spread) and self.press_spread < 1.0:
            return (f"; position terms on colour terms up to degree {self.model.config.position_colour_degree}, the "
                    f"model's own (the presses leave {100 * (1 - self.press_spread):.0f} % of the image near all but "
                    "a few of them: too few places to choose from)")
        if not self.colour_degree_scores:
            return ""
        weighed = ", ".join(f"{s.degree}: {s.normal_error_deg:.2f} deg" for s in self.colour_degree_scores)
        return (f"; position terms on colour terms up to degree {self.model.config.position_colour_degree} "
                f"(held-out normal-angle error by degree: {weighed})")

    def _reference_summary(self) -> str:
        choice = self.reference_choice
        if choice is None:
            return ""
        if choice.coverage < 1.0:
            return (f"; reference as given (the presses leave {100 * (1 - choice.coverage):.0f} % of the image "
                    "near all but a few of them: too few far fields there to build one)")
        if choice.source == "given" and not math.isfinite(choice.given_change):
            return ""
        made = "built from the presses' far fields" if choice.source == "presses" else "as given"
        text = f"; reference: {made}"
        if math.isfinite(choice.given_change):
            text += (f" (far-field colour change {100 * choice.given_change:.2f} % against the given one, "
                     f"{100 * choice.presses_change:.2f} % against one from the other presses)")
        return text

    def _degree_summary(self) -> str:
        if not self.degree_scores:
            return ""
        weighed = ", ".join(f"{s.degree}: {100 * s.gain_deviation:.2f} %" for s in self.degree_scores)
        return (f"; position degree {self.model.config.position_degree} (held-out slope gain deviation by degree: "
                f"{weighed})")


def change_magnitude(image: np.ndarray, reference: np.ndarray, sigma: float = 1.5) -> np.ndarray:
    """float32 H x W: the length of the smoothed colour change against the reference (DN)."""
    a = cv2.GaussianBlur(np.asarray(image, np.float32), (0, 0), sigma)
    b = cv2.GaussianBlur(np.asarray(reference, np.float32), (0, 0), sigma)
    d = a - b
    mag: np.ndarray = np.sqrt((d * d).sum(axis=2)).astype(np.float32)
    return mag


def fit_circle(x: np.ndarray, y: np.ndarray, iterations: int = 3) -> tuple[float, float, float, np.ndarray]:
    """Robust algebraic (Kasa) circle fit: centre, radius and the inlier mask."""
    keep = np.isfinite(x) & np.isfinite(y)
    cu = cv = r = math.nan
    for _ in range(iterations):
        if keep.sum() < 5:
            raise CalibrationError("too few edge points for a circle")
        A = np.c_[2 * x[keep], 2 * y[keep], np.ones(int(keep.sum()))]
        b = x[keep] ** 2 + y[keep] ** 2
        (cu, cv, c), *_ = np.linalg.lstsq(A, b, rcond=None)
        r = math.sqrt(max(c + cu * cu + cv * cv, 0.0))
        res = np.abs(np.hypot(x - cu, y - cv) - r)
        scale = 1.4826 * float(np.median(res[keep]))
        keep = np.isfinite(res) & (res <= max(3.0 * scale, 1.0))
    return float(cu), float(cv), float(r), keep


def refine_circle(magnitude: np.ndarray, u: float, v: float, radius: float,
                  config: PressCalibrationConfig | None = None) -> FittedCircle:
    """The contact circle from the change magnitude, starting at a label (u, v, radius px)."""
    config = config or PressCalibrationConfig()
    label = FittedCircle(float(u), float(v), float(radius), math.nan, 0, False)
    if not (math.isfinite(u) and math.isfinite(v) and math.isfinite(radius) and radius > 2):
        raise CalibrationError(f"label circle ({u}, {v}, r={radius}) is not a usable circle")
    if not config.refine:
        return label
    cu, cv, r = float(u), float(v), float(radius)
    angles = np.linspace(0.0, 2 * math.pi, 180, endpoint=False)
    rms, kept = math.nan, 0
    for _ in range(config.refine_iterations):
        rho = np.arange(config.search[0] * r, config.search[1] * r, 0.5)
        X = (cu + rho[None, :] * np.cos(angles)[:, None]).astype(np.float32)
        Y = (cv + rho[None, :] * np.sin(angles)[:, None]).astype(np.float32)
        profile = cv2.remap(magnitude, X, Y, cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT, borderValue=np.nan)
        inside = np.isfinite(profile).all(axis=1)
        profile = np.nan_to_num(profile)
        k = np.clip(np.argmax(profile, axis=1), 1, len(rho) - 2)
        rows = np.arange(len(k))
        a, b, c = profile[rows, k - 1], profile[rows, k], profile[rows, k + 1]
        den = a - 2 * b + c
        off = np.where(den < 0, 0.5 * (a - c) / np.where(den < 0, den, -1.0), 0.0)
        edge = rho[k] + 0.5 * np.clip(off, -1.0, 1.0)
        interior = (k > 1) & (k < len(rho) - 2) & inside
        px = np.where(interior, cu + edge * np.cos(angles), np.nan)
        py = np.where(interior, cv + edge * np.sin(angles), np.nan)
        try:
            nu, nv, nr, keep = fit_circle(px, py)
        except CalibrationError:
            return label
        kept = int(keep.sum())
        rms = float(np.sqrt(np.mean((np.hypot(px[keep] - nu, py[keep] - nv) - nr) ** 2)))
        cu, cv, r = nu, nv, nr
    if (math.hypot(cu - u, cv - v) > config.max_shift * radius or not 0.6 * radius <= r <= 1.4 * radius
            or kept < 60):
        return label
    return FittedCircle(cu, cv, r, rms, kept, True)


def find_press(image: np.ndarray, reference: np.ndarray, min_area_px: int = 30) -> tuple[float, float, float]:
    """A rough label (u, v, radius px) of the one press in an image, when nobody labelled it: the largest
    connected region whose change magnitude stands out (median + the larger of 6 robust sigmas and a
    quarter of the peak), its centroid and the radius of a disc of its area. `refine_circle` then
    finds the contact's edge."""
    mag = change_magnitude(image, reference)
    base = float(np.median(mag))
    sigma = 1.4826 * float(np.median(np.abs(mag - base))) + 1e-6
    threshold = base + max(6.0 * sigma, 0.25 * (float(mag.max()) - base))
    mask = (mag > threshold).astype(np.uint8)
    count, _labels, stats, centroids = cv2.connectedComponentsWithStats(mask, connectivity=8)
    if count < 2:
        raise CalibrationError("no press found: the image does not differ from the reference")
    best = 1 + int(np.argmax(stats[1:, cv2.CC_STAT_AREA]))
    area = int(stats[best, cv2.CC_STAT_AREA])
    if area < min_area_px:
        raise CalibrationError(f"no press found: the largest change covers {area} px (< {min_area_px})")
    u, v = (float(c) for c in centroids[best])
    return u, v, math.sqrt(area / math.pi)


def sphere_slopes(shape: tuple[int, int], circle: FittedCircle, pixel_size: tuple[float, float],
                  ball_radius: float, membrane_radius: float = math.inf
                  ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """(gx, gy, rho in contact radii, slope angle deg) of the ball's cap over the whole image: the
    indentation's slopes, measured from a membrane curved with `membrane_radius` along v (inf: flat)."""
    h, w = shape
    vv, uu = np.mgrid[0:h, 0:w].astype(np.float64)
    dx = (uu - circle.u) * pixel_size[0]
    dy = (vv - circle.v) * pixel_size[1]
    rho2 = dx * dx + dy * dy
    s = np.sqrt(np.maximum(ball_radius**2 - rho2, (1e-3 * ball_radius) ** 2))
    rho_rel = np.hypot(uu - circle.u, vv - circle.v) / circle.radius_px
    angle = np.degrees(np.arctan(np.sqrt(rho2) / s))
    gy = -dy / s
    if math.isfinite(membrane_radius):   # the tube recedes from the ball along v: its slope adds
        gy -= dy / np.sqrt(np.maximum(membrane_radius**2 - dy * dy, (1e-3 * membrane_radius) ** 2))
    return -dx / s, gy, rho_rel, angle


def normal_angles_deg(gx: np.ndarray, gy: np.ndarray, tx: np.ndarray, ty: np.ndarray) -> np.ndarray:
    """Angles between the normals (-gx, -gy, 1) and (-tx, -ty, 1), degrees."""
    dot = gx * tx + gy * ty + 1.0
    norm = np.sqrt((gx * gx + gy * gy + 1.0) * (tx * tx + ty * ty + 1.0))
    result: np.ndarray = np.degrees(np.arccos(np.clip(dot / norm, -1.0, 1.0)))
    return result


def press_samples(press: BallPress, circle: FittedCircle, reference: np.ndarray, ball_radius: float,
                  config: PressCalibrationConfig, rng: np.random.Generator
                  ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """(features N x 3, u N, v N, target slopes N x 2) of one press: inside the circle and the far field."""
    feats = colour_features(press.image, reference, config.model.smoothing, config.model.gain)
    h, w = feats.shape[:2]
    gx, gy, rho, angle = sphere_slopes((h, w), circle, press.pixel_size, ball_radius, press.membrane_radius)
    inside = (rho * circle.radius_px < circle.radius_px - config.edge_margin_px) & (angle <= config.max_slope_angle_deg)
    inside &= rng.random((h, w)) < config.inside_fraction
    far = (rho > config.far_factor) & (rng.random((h, w)) < config.far_fraction)
    vv, uu = np.mgrid[0:h, 0:w]
    mask = inside | far
    targets = np.stack([np.where(far, 0.0, gx)[mask], np.where(far, 0.0, gy)[mask]], axis=1)
    return feats[mask].astype(np.float64), uu[mask], vv[mask], targets


def calibrate_photometric(presses: Sequence[BallPress], reference: np.ndarray, ball_radius: float,
                          config: PressCalibrationConfig | None = None) -> PhotometricCalibration:
    """The colour (+ position) -> slope model from ball presses, and how it fits each press."""
    config = config or PressCalibrationConfig()
    if not (math.isfinite(ball_radius) and ball_radius > 0):
        raise CalibrationError(f"ball radius must be a positive number of metres, got {ball_radius}")
    if not presses:
        raise CalibrationError("no ball presses to calibrate from")
    reference = np.asarray(reference)
    if reference.ndim != 3 or reference.shape[2] != 3:
        raise CalibrationError(f"the reference must be a colour image (H x W x 3), got shape {reference.shape}; "
                               "one light (grey) cannot give slopes")
    h, w = reference.shape[:2]
    for press in presses:
        if press.image.shape != reference.shape:
            raise CalibrationError(f"press {press.name or '?'}: image {press.image.shape} does not match the "
                                   f"reference {reference.shape}")
        if not all(math.isfinite(s) and s > 0 for s in press.pixel_size):
            raise CalibrationError(f"press {press.name or '?'}: pixel size must be positive, got {press.pixel_size}")
    choice = choose_reference([p.image for p in presses], [(p.u, p.v, p.radius_px) for p in presses], reference,
                              config.reference, config.reference_factor)
    reference = choice.reference
    circles = [refine_circle(change_magnitude(p.image, reference), p.u, p.v, p.radius_px, config) for p in presses]
    for press, circle in zip(presses, circles, strict=True):
        contact = circle.radius_px * max(press.pixel_size)
        if contact >= ball_radius:
            raise CalibrationError(f"press {press.name or '?'}: contact radius {contact * 1e3:.3f} mm is not "
                                   f"smaller than the ball's {ball_radius * 1e3:.3f} mm (wrong --ball-radius or "
                                   f"pixel size?)")
    rng = np.random.default_rng(config.seed)
    parts = [press_samples(p, c, reference, ball_radius, config, rng) for p, c in zip(presses, circles, strict=True)]
    feats = np.concatenate([p[0] for p in parts])
    us = np.concatenate([p[1] for p in parts])
    vs = np.concatenate([p[2] for p in parts])
    targets = np.concatenate([p[3] for p in parts])
    pixel = float(np.median([np.mean(p.pixel_size) for p in presses]))
    model_config = config.model
    scores: tuple[DegreeScore, ...] = ()
    if config.position_degrees:
        scores = choose_position_degree(parts, config, w, h)
        best = min(scores, key=lambda sc: (sc.gain_deviation, sc.degree))
        model_config = replace(config.model, position_degree=best.degree)
    colour_scores: tuple[DegreeScore, ...] = ()
    spread = math.nan
    if config.position_colour_degrees:
        spread = float(np.mean(far_masks((h, w), [(p.u, p.v, p.radius_px) for p in presses],
                                         config.reference_factor).sum(axis=0) >= 3))
    if config.position_colour_degrees and spread >= 1.0:
        colour_scores = choose_position_colour_degree(parts, config, model_config, w, h)
        pick = min(colour_scores, key=lambda sc: (sc.normal_error_deg, sc.degree))
        model_config = replace(model_config, position_colour_degree=pick.degree)
    try:
        model = fit_model(model_config, feats, us, vs, targets, w, h, pixel_size=pixel, ball_radius=ball_radius)
    except ValueError as exc:
        raise CalibrationError(str(exc)) from None
    if config.still_quantile > 0:
        threshold, shape = fit_still_prior(model, presses, reference, config.reference_factor, config.still_quantile,
                                           config.still_ellipse)
        model = replace(model, still_slope=threshold, still_shape=shape)
    fits = tuple(press_fit(model, p, c, reference, ball_radius, config) for p, c in zip(presses, circles, strict=True))
    return PhotometricCalibration(model, fits, float(ball_radius), scores, reference, choice, colour_scores, spread)


def fit_still_prior(model: PhotometricModel, presses: Sequence[BallPress], reference: np.ndarray, factor: float,
                    quantile: float, ellipse: bool = True, step: int = 4
                    ) -> tuple[float, tuple[float, float, float, float]]:
    """The zero-slope prior the undeformed gel asks for: (threshold, shape) of `photometric.still_prior`. The
    model's slopes (its exact polynomial, on a 1-in-`step` grid) over the presses' pixels beyond `factor` label
    radii of their contact, where the calibration takes the membrane to be flat; with `ellipse` the shape
    whitens them (their covariance's ellipse, scaled to unit area), else it is round; the threshold is the
    `quantile` of their length in that shape ((0, round) when there are none)."""
    samples = []
    for press in presses:
        feats = colour_features(press.image, reference, model.config.smoothing, model.config.gain)[::step, ::step]
        h, w = feats.shape[:2]
        vv, uu = np.mgrid[0:h, 0:w] * step
        far = np.hypot(uu - press.u, vv - press.v) > factor * press.radius_px
        if far.any():
            samples.append(model.slopes_at(feats[far].astype(np.float64), uu[far], vv[far]))
    g = np.concatenate(samples) if samples else np.zeros((0, 2))
    g = g[np.isfinite(g).all(axis=1)]
    shape: tuple[float, float, float, float] = (1.0, 0.0, 0.0, 1.0)
    if len(g) == 0:
        return 0.0, shape
    if ellipse and len(g) >= 10:
        values, vectors = np.linalg.eigh(np.cov(g.T))
        if values[0] > 1e-12 * max(values[1], 1e-300):
            whiten = (vectors / np.sqrt(values)).T * math.sqrt(math.sqrt(values[0] * values[1]))   # |det| 1
            if np.linalg.det(whiten) < 0:
                whiten[1] *= -1.0
            shape = tuple(float(x) for x in whiten.ravel())  # type: ignore[assignment]
    a, b, c, d = shape
    length = np.hypot(a * g[:, 0] + b * g[:, 1], c * g[:, 0] + d * g[:, 1])
    return float(np.quantile(length, quantile)), shape


def choose_position_degree(parts: Sequence[tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]],
                           config: PressCalibrationConfig, width: int, height: int) -> tuple[DegreeScore, ...]:
    """Each candidate of `config.position_degrees` weighed on held-out presses: the presses (their samples,
    `press_samples`) split `selection_folds` ways, each part's presses read by a model fitted on the others.
    The score is how far a held-out press's slopes read from their true size (per press and slope, the
    least-squares gain of read on true over its contact): a height map integrates slopes across its band,
    so a gain that wanders from place to place is a relief that is not there, while the normal-angle
    residual (also reported) is led by a ball's steep slopes. Position terms of a high degree fit the
    presses' own patches and wander between them; how high the presses' coverage carries is what this finds."""
    candidates = {int(d): replace(config.model, position_degree=int(d)) for d in config.position_degrees}
    return held_out_scores(parts, config, candidates, width, height)


def choose_position_colour_degree(parts: Sequence[tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]],
                                  config: PressCalibrationConfig, model: PhotometricConfig, width: int,
                                  height: int) -> tuple[DegreeScore, ...]:
    """Each candidate of `config.position_colour_degrees` (the colour terms up to which position factors
    multiply, on `model`) weighed on held-out presses as `choose_position_degree` does; the score the
    calibration picks by is the held-out normal-angle error (`DegreeScore.normal_error_deg`): how the
    light's unevenness bends a slope's colour is what these terms take. Presses that keep to one place
    cannot teach it, and their held-out presses, at the same place, cannot tell: `calibrate_photometric`
    weighs the candidates only when every pixel lies beyond `reference_factor` contact radii of at least 3
    presses (the presses move about, as `choose_reference` asks), and keeps the model's own degree otherwise."""
    candidates = {int(d): replace(model, position_colour_degree=int(d)) for d in config.position_colour_degrees}
    return nested_held_out_scores(parts, config, candidates, width, height)


def nested_held_out_scores(parts: Sequence[tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]],
                           config: PressCalibrationConfig, candidates: dict[int, PhotometricConfig], width: int,
                           height: int) -> tuple[DegreeScore, ...]:
    """`held_out_scores` for candidates whose terms all lie among the largest one's (the position-colour
    degrees of one model), in one pass: each press's normal equations are formed once in the largest
    candidate's terms (the colour scaled by all the presses' features, not each fold's), and each fold and
    candidate solves the sum of its training presses' over its own terms (the column scaling and ridge of
    `fit_model`)."""
    n = len(parts)
    folds = min(config.selection_folds, n)
    if n < 4:
        raise CalibrationError(f"choosing a model degree needs at least 4 presses, got {n}")
    largest = max(candidates.values(), key=lambda c: len(model_terms(c)))
    index = {t: k for k, t in enumerate(model_terms(largest))}
    columns = {}
    for degree, candidate in candidates.items():
        terms = model_terms(candidate)
        if not all(t in index for t in terms):      # not nested: fit each candidate on its own
            return held_out_scores(parts, config, candidates, width, height)
        columns[degree] = np.array([index[t] for t in terms])
    feats = np.concatenate([p[0] for p in parts])
    feats = feats[np.isfinite(feats).all(axis=1)]
    if feats.shape[0] < 10 * len(index):
        raise CalibrationError(f"too few samples ({feats.shape[0]}) for {len(index)} model terms")
    scale = np.maximum(np.percentile(np.abs(feats), 99, axis=0), 1e-3)
    shell = PhotometricModel(largest, np.zeros((len(index), 2)), int(width), int(height), scale, scale)
    designs, grams, rights = [], [], []
    for f, us, vs, targets in parts:
        ok = np.isfinite(f).all(axis=1) & np.isfinite(targets).all(axis=1)
        x = shell.design(f[ok], us[ok], vs[ok])
        designs.append((x, targets[ok], np.abs(targets[ok]).sum(axis=1) > 0))
        grams.append(x.T @ x)
        rights.append(x.T @ targets[ok])
    scores = []
    for degree, candidate in candidates.items():
        cols = columns[degree]
        gains: list[float] = []
        angles: list[float] = []
        for k in range(folds):
            train = [i for i in range(n) if i % folds != k]
            gram = sum(grams[i] for i in train)[np.ix_(cols, cols)]
            right = sum(rights[i] for i in train)[cols]
            norms = np.sqrt(np.maximum(np.diag(gram), 1e-24))
            a = gram / np.outer(norms, norms) + candidate.ridge * np.eye(len(cols))
            coefficients = np.linalg.solve(a, right / norms[:, None]) / norms[:, None]
            for i in range(k, n, folds):
                x, targets, contact = designs[i]
                if contact.sum() < 10:
                    continue
                read = x[contact][:, cols] @ coefficients
                _score_held_out(read, targets[contact], gains, angles)
        scores.append(_degree_score(degree, gains, angles))
    return tuple(scores)


def _score_held_out(read: np.ndarray, true: np.ndarray, gains: list[float], angles: list[float]) -> None:
    """One held-out press's slopes read against the true ones (contact pixels, 2 columns): each slope's
    least-squares gain of read on true into `gains`, the median normal-angle error into `angles`."""
    for j in range(2):
        gains.append(float(read[:, j] @ true[:, j]) / max(float(true[:, j] @ true[:, j]), 1e-12))
    angles.append(float(np.median(normal_angles_deg(read[:, 0], read[:, 1], true[:, 0], true[:, 1]))))


def _degree_score(degree: int, gains: list[float], angles: list[float]) -> DegreeScore:
    """RMS of (gain - 1) over the held-out presses' slopes and their median normal-angle error."""
    deviation = float(np.sqrt(np.mean((np.array(gains) - 1.0) ** 2))) if gains else math.inf
    return DegreeScore(degree, deviation, float(np.median(angles)) if angles else math.inf)


def held_out_scores(parts: Sequence[tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]],
                    config: PressCalibrationConfig, candidates: dict[int, PhotometricConfig], width: int,
                    height: int) -> tuple[DegreeScore, ...]:
    """Per candidate model (keyed by the degree weighed): the presses split `config.selection_folds` ways
    (press i in part i mod folds), each part's presses read by the candidate fitted on the others; the RMS
    over held-out presses and both slopes of (least-squares gain of read on true over the contact - 1),
    and the median over held-out presses of each one's median normal-angle error."""
    n = len(parts)
    folds = min(config.selection_folds, n)
    if n < 4:
        raise CalibrationError(f"choosing a model degree needs at least 4 presses, got {n}")
    scores = []
    for degree, model_config in candidates.items():
        gains: list[float] = []
        angles: list[float] = []
        for k in range(folds):
            train = [parts[i] for i in range(n) if i % folds != k]
            try:
                model = fit_model(model_config, np.concatenate([p[0] for p in train]),
                                  np.concatenate([p[1] for p in train]), np.concatenate([p[2] for p in train]),
                                  np.concatenate([p[3] for p in train]), width, height)
            except ValueError as exc:
                raise CalibrationError(str(exc)) from None
            for i in range(k, n, folds):
                feats, us, vs, targets = parts[i]
                contact = np.abs(targets).sum(axis=1) > 0     # the far field's targets are 0
                if contact.sum() < 10:
                    continue
                read = model.slopes_at(feats[contact], us[contact], vs[contact])
                _score_held_out(read, targets[contact], gains, angles)
        scores.append(_degree_score(degree, gains, angles))
    return tuple(scores)


def press_fit(model: PhotometricModel, press: BallPress, circle: FittedCircle, reference: np.ndarray,
              ball_radius: float, config: PressCalibrationConfig) -> PressFit:
    """The model's normal-angle residual inside one press's circle (radius - 2 px)."""
    feats = colour_features(press.image, reference, model.config.smoothing, model.config.gain)
    h, w = feats.shape[:2]
    gx, gy, rho, angle = sphere_slopes((h, w), circle, press.pixel_size, ball_radius, press.membrane_radius)
    mask = (rho * circle.radius_px < circle.radius_px - 2.0) & (angle <= config.max_slope_angle_deg)
    vv, uu = np.mgrid[0:h, 0:w]
    pred = model.slopes_at(feats[mask].astype(np.float64), uu[mask], vv[mask])
    err = normal_angles_deg(pred[:, 0], pred[:, 1], gx[mask], gy[mask])
    med = float(np.median(err)) if err.size else math.nan
    p90 = float(np.percentile(err, 90)) if err.size else math.nan
    return PressFit(press.name, circle, (press.u, press.v, press.radius_px), med, p90, int(err.size))
