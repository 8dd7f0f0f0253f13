"""Height from real GelSight presses: k-fold photometric calibration and sphere fits on taxim's data.

The `gelsight` set (48 presses of a 2.0 mm ball, 0.0295 mm per pixel, hand-labelled circles) is split
6-fold by index (press i in fold i mod 6): each fold's presses are measured with a model calibrated on
the other 40 (`touchroller_perception.height`: circles refined from the images, sphere slopes as
targets, compiled lookup, exact Poisson integration), against the reference that calibration chose
(`PressCalibrationConfig.reference = "auto"`: one built from its presses' far fields when they match it
better than the given no-contact frame; the trade-off table keeps a row with the frame as given). The
measurements are this bench's own:

* normal-angle error: the model's normals against the 2.0 mm sphere's, inside the contact circle
  (less 2 px), with the circle the calibration's edge fit finds in the held-out image, and with the
  hand label as given;
* sphere fit (scipy least squares, written here): the height within 0.7 label radii of the label's
  centre against z0 + sqrt(R^2 - (x-x0)^2 - (y-y0)^2), centre and R free (and with R fixed at 2 mm);
  RMS residual and fitted R. The model was trained assuming R = 2.0 mm, so the fitted R is partly
  circular: `circularity` calibrates with R assumed 1.9 and 2.2 mm and shows how far the fitted R follows;
* rim-relative cap depth: the height at the fitted centre minus the median height on the contact
  circle, over the geometric cap R - sqrt(R^2 - a^2) (a the refined circle's radius, and the label's);
* no contact: the taxim sets hold one no-contact frame (the reference itself), so the no-contact figure
  is, per held-out press, the 128 x 128 px window nearest the image centre that lies beyond 3 contact
  radii of the ball, its slopes made a
  height as a frame of its own is (`slopes_to_height`, the estimator's levelling): RMS about 0;
  where it comes from (`no_contact_views`): the same beyond 4.5 contact radii, and the frames whose colour
  drifted against the reference by more than 2 % in a channel apart from the others. The estimator reads
  with the zero-slope prior its model carries (`HeightConfig.still_slope` None: the threshold each fold's
  calibration measured on its own presses' far fields, `PressCalibrationConfig.still_quantile`); the
  trade-off table keeps a row without it. `--choose-prior` shows how the quantile was chosen: inside each
  fold, on its calibration presses alone (a quarter of them measured with a model calibrated on the
  rest), never on the presses the fold measures;
* speed: CPU time (one thread) of slopes + integration per 640x480 frame and per roller band (the
  rows `contact_band` gives for the default camera, 0.5 mm deep), best of several;
* what accuracy costs in time: lookup resolution, position cells, position term, smoothing, exact
  polynomial, downsampled integration, whole frame vs band (on the even/odd split, to keep it short).

`gelsight_mini` (24 presses, ball radius unknown) is the development set: calibrated (assuming 2.0 mm)
3-fold, its fitted radii must agree with each other.
"""
from __future__ import annotations

import argparse
import dataclasses
import json
import math
import sys
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import cv2
import numpy as np
from scipy.optimize import least_squares

from bench._common import Provenance, provenance, provenance_markdown, results_path, to_json
from bench.real_presses import PressSet, available, load_presses
from touchroller_perception.files import atomic_write_text
from touchroller_perception.geometry import CameraModel
from touchroller_perception.height import (
    BallPress,
    HeightConfig,
    HeightEstimator,
    PhotometricCalibration,
    PhotometricConfig,
    PressCalibrationConfig,
    calibrate_photometric,
    change_magnitude,
    contact_band,
    normal_angles_deg,
    refine_circle,
    slopes_to_height,
    sphere_slopes,
)
from touchroller_perception.height.photometric import frame_gain
from touchroller_perception.height.presses import fit_still_prior

BALL = 2.0e-3
BAND_DEPTH = 5.0e-4     # the roller's band: rows a 0.5 mm press reaches (the scenes' press depth)
FOLDS = 6
# HeightConfig.still_change for the trade-off row: on gelsight_mini (even presses calibrate, odd measured) the
# largest relative colour change that left the sphere-fit RMS unchanged (0.03: 35.04 -> 35.07 um; 0.04: 35.23)
STILL_CHANGE = 0.03
# PressCalibrationConfig.far_fraction for the trade-off row: chosen on the even presses alone (0 mod 4 calibrate,
# 2 mod 4 measured), where 0.01 -> 0.05 took the no-contact window 8.2 -> 3.5 um and the sphere-fit RMS 21.8 -> 18.2
FAR_DENSE = 0.05
# the no-contact diagnosis (`no_contact_views`): a window further from the press (taxim's GelSight changes colour
# up to ~4.5 contact radii from a press), and frames whose light drifted against the reference by more than this
FAR_WINDOW = 4.5
DRIFT = 0.02
# PressCalibrationConfig.reference: "auto" builds a reference from the calibration presses' far fields (beyond
# 3 label radii, the per-pixel median) and keeps it when those far fields match it better than the given
# no-contact frame (each press against one built without it): a rule on the calibration's own input, no truth
REFERENCE = "auto"
# PressCalibrationConfig.position_colour_degrees: the colour terms that get position factors, up to a degree chosen by
# the calibration on its own held-out presses (their normal-angle error); the trade-off table keeps the model's own 2
COLOUR_POSITION = (1, 2, 3)
# PressCalibrationConfig.still_quantile / still_ellipse: the zero-slope prior's threshold is this quantile of the length
# of the slopes the model reads on its calibration presses beyond 3 label radii, measured in their covariance's ellipse.
# Chosen with `--choose-prior` (inside each of the 6 folds, a quarter of its 40 calibration presses measured with a
# model calibrated on the other 30; the presses each fold measures never seen) as the least prior whose held-out
# calibration presses read the no-contact window within the goal: window median none 6.93, quantile 0.5 6.93, 0.75
# 6.80, 0.85 5.86, 0.9 4.25, 0.95 1.58 um (0.9 round: 4.51); normal-angle median 2.95 -> 2.96 (0.9), 2.97 deg (0.95),
# fitted R 2.047 -> 2.048 mm, depth ratio 0.981 -> 0.978 (0.9), 0.975 (0.95). At 0.9 on the same split a hard threshold
# read 6.47 um, a soft one 2.36 um with R 2.213 mm and depth 0.909 (the firm one: 4.52, round). Every bit of prior
# flattens gentle relief, which a ball's steep cap cannot show: the least that meets the goal, not the most the ball
# allows. The trade-off table shows the prior off, round, and at the neighbouring quantiles.
STILL_QUANTILES = (0.5, 0.75, 0.85, 0.9, 0.95)
BASELINE = {"angle_deg": 6.2, "rms_um": 25.0, "radius_mm": 1.89, "depth_ratio": 0.96, "ms": 40.0}
GOALS = {"angle_deg": 4.0, "rms_um": 15.0, "radius_rel": 0.03, "depth_lo": 0.9, "depth_hi": 1.1, "flat_um": 5.0,
         "frame_ms": 10.0, "band_ms": 2.0}


@dataclasses.dataclass(frozen=True)
class PressMeasure:
    index: int
    angle_deg: float            # median normal-angle error, refined circle
    angle_label_deg: float      # the same with the hand label's circle
    rms_um: float               # sphere fit, centre and R free
    radius_mm: float            # fitted R
    rms_fixed_um: float         # sphere fit with R = 2 mm
    depth_ratio: float          # rim-relative cap depth / geometric cap (refined circle radius)
    depth_ratio_label: float    # ... geometric cap from the label's radius
    flat_um: float              # RMS of a no-contact window (nan when none fits)
    circle: tuple[float, float, float]
    label: tuple[float, float, float]
    flat_far_um: float = math.nan   # the same window beyond FAR_WINDOW contact radii (nan when none fits)
    drift: float = math.nan         # the frame's largest per-channel colour drift against the reference, |gain - 1|


@dataclasses.dataclass(frozen=True)
class Summary:
    presses: int
    angle_deg: float
    angle_p90_deg: float
    angle_label_deg: float
    rms_um: float
    radius_mm: float
    radius_p10_mm: float
    radius_p90_mm: float
    rms_fixed_um: float
    depth_ratio: float
    depth_p10: float
    depth_p90: float
    depth_ratio_label: float
    depth_label_p10: float
    depth_label_p90: float
    flat_um: float
    flat_max_um: float


@dataclasses.dataclass(frozen=True)
class TradeoffRow:
    setting: str
    angle_deg: float
    ms: float
    rows: str
    flat_um: float = math.nan     # median no-contact window RMS (whole-frame lookup rows only)


@dataclasses.dataclass(frozen=True)
class HeightRealResult:
    provenance: Provenance
    config: dict[str, Any]
    folds: int
    gelsight: Summary
    per_press: tuple[PressMeasure, ...]
    frame_ms: float
    band_ms: float
    band_rows: tuple[int, int]
    exact_frame_ms: float
    calibrate_s: float
    circularity: dict[str, float]       # assumed R (mm) -> median fitted R (mm)
    mini: Summary | None
    tradeoffs: tuple[TradeoffRow, ...]
    baseline: dict[str, float]
    goals: dict[str, float]
    reference_choices: tuple[str, ...] = ()   # per fold: the reference its calibration chose (cfg.reference)


# --------------------------------------------------------------------------- measurement (this bench's own)

def sphere_fit(z: np.ndarray, cu: float, cv: float, radius_px: float, pixel: float, fixed_radius: float | None = None
               ) -> tuple[float, float, tuple[float, float, float]]:
    """(RMS residual m, R m, (x0, y0, z0) px, px, m) of a sphere fitted to the height near (cu, cv)."""
    h, w = z.shape
    vv, uu = np.mgrid[0:h, 0:w]
    near = np.hypot(uu - cu, vv - cv) < 0.7 * radius_px
    x, y, zz = uu[near] * pixel, vv[near] * pixel, z[near].astype(np.float64)
    keep = np.isfinite(zz)
    x, y, zz = x[keep], y[keep], zz[keep]

    def residual(p: np.ndarray) -> np.ndarray:
        x0, y0, z0 = p[:3]
        r = fixed_radius if fixed_radius is not None else p[3]
        return z0 + np.sqrt(np.maximum(r * r - (x - x0) ** 2 - (y - y0) ** 2, 0.0)) - zz

    start = [cu * pixel, cv * pixel, float(zz.max()) - BALL] + ([] if fixed_radius is not None else [BALL])
    fit = least_squares(residual, np.array(start), x_scale=1e-4)
    rms = float(np.sqrt(np.mean(fit.fun**2)))
    radius = float(fixed_radius if fixed_radius is not None else fit.x[3])
    return rms, radius, (fit.x[0] / pixel, fit.x[1] / pixel, fit.x[2])


def rim_depth(z: np.ndarray, cu: float, cv: float, a_px: float) -> float:
    """Height at (cu, cv) (mean within 2 px) minus the median height on the circle of radius a_px."""
    h, w = z.shape
    vv, uu = np.mgrid[0:h, 0:w]
    rho = np.hypot(uu - cu, vv - cv)
    return float(np.nanmean(z[rho <= 2.0]) - np.nanmedian(z[np.abs(rho - a_px) <= 1.0]))


def geometric_cap(a_px: float, pixel: float, radius: float = BALL) -> float:
    a = a_px * pixel
    return radius - math.sqrt(max(radius * radius - a * a, 0.0))


def flat_window(shape: tuple[int, int], cu: float, cv: float, r: float, size: int = 128,
                factor: float = 3.0) -> tuple[slice, slice] | None:
    """The size x size window (on a 16-px grid) nearest the image centre whose every pixel is beyond `factor`
    r of the contact (the sensor's field, not the gel's border in the corners)."""
    h, w = shape
    best, best_d = None, math.inf
    for v0 in range(0, h - size + 1, 16):
        for u0 in range(0, w - size + 1, 16):
            du = max(u0 - cu, 0.0, cu - (u0 + size))
            dv = max(v0 - cv, 0.0, cv - (v0 + size))
            d = math.hypot(du, dv)
            centre = math.hypot(u0 + size / 2 - w / 2, v0 + size / 2 - h / 2)
            if d >= factor * r and centre < best_d:
                best, best_d = (slice(v0, v0 + size), slice(u0, u0 + size)), centre
    return best


def measure_press(index: int, est: HeightEstimator, image: np.ndarray, reference: np.ndarray, label: Sequence[float],
                  pixel: float, cfg: PressCalibrationConfig) -> PressMeasure:
    cu, cv, r = (float(x) for x in label)
    circle = refine_circle(change_magnitude(image, reference), cu, cv, r, cfg)
    gx, gy = est.slopes(image)
    angles = []
    for c in (circle, dataclasses.replace(circle, u=cu, v=cv, radius_px=r)):
        tx, ty, rho, _ = sphere_slopes(image.shape[:2], c, (pixel, pixel), BALL)
        inside = rho * c.radius_px < c.radius_px - 2.0
        angles.append(float(np.median(normal_angles_deg(gx[inside], gy[inside], tx[inside], ty[inside]))))
    z = est.height(image)
    rms, radius, (x0, y0, _) = sphere_fit(z, cu, cv, r, pixel)
    rms_fixed, _, _ = sphere_fit(z, cu, cv, r, pixel, fixed_radius=BALL)
    depth = rim_depth(z, circle.u, circle.v, circle.radius_px)
    window = flat_window(image.shape[:2], circle.u, circle.v, circle.radius_px)
    flats = []
    for win in (window, flat_window(image.shape[:2], circle.u, circle.v, circle.radius_px, factor=FAR_WINDOW)):
        wz = slopes_to_height(gx[win], gy[win], pixel, est.config) if win is not None else None   # a frame of its own
        flats.append(float(np.sqrt(np.mean(wz**2))) if wz is not None else math.nan)
    drift = float(np.max(np.abs(frame_gain(image, reference) - 1.0)))
    return PressMeasure(index, angles[0], angles[1], rms * 1e6, radius * 1e3, rms_fixed * 1e6,
                        depth / geometric_cap(circle.radius_px, pixel), depth / geometric_cap(r, pixel),
                        flats[0] * 1e6, (circle.u, circle.v, circle.radius_px), (cu, cv, r), flats[1] * 1e6, drift)


def no_contact_views(measures: Sequence[PressMeasure]) -> dict[str, tuple[float, int]]:
    """Where the no-contact windows' height comes from: (median window RMS um, windows) beyond 3 and beyond
    FAR_WINDOW contact radii, and beyond 3 radii in the frames whose colour drifted against the reference by
    more than DRIFT in a channel and in the others."""
    def median(values: list[float]) -> tuple[float, int]:
        kept = [v for v in values if math.isfinite(v)]
        return (float(np.median(kept)) if kept else math.nan, len(kept))

    return {"beyond 3 radii": median([m.flat_um for m in measures]),
            f"beyond {FAR_WINDOW:g} radii": median([m.flat_far_um for m in measures]),
            f"frames drifted > {DRIFT:.0%}": median([m.flat_um for m in measures if m.drift > DRIFT]),
            f"frames drifted <= {DRIFT:.0%}": median([m.flat_um for m in measures if m.drift <= DRIFT])}


def summarise(measures: Sequence[PressMeasure]) -> Summary:
    def col(name: str) -> np.ndarray:
        return np.array([getattr(m, name) for m in measures], np.float64)

    def pct(name: str, q: float) -> float:
        values = col(name)
        values = values[np.isfinite(values)]
        return float(np.percentile(values, q)) if values.size else math.nan

    return Summary(len(measures), pct("angle_deg", 50), pct("angle_deg", 90), pct("angle_label_deg", 50),
                   pct("rms_um", 50), pct("radius_mm", 50), pct("radius_mm", 10), pct("radius_mm", 90),
                   pct("rms_fixed_um", 50), pct("depth_ratio", 50), pct("depth_ratio", 10), pct("depth_ratio", 90),
                   pct("depth_ratio_label", 50), pct("depth_ratio_label", 10), pct("depth_ratio_label", 90),
                   pct("flat_um", 50), float(np.nanmax(col("flat_um"))) if np.isfinite(col("flat_um")).any()
                   else math.nan)


# --------------------------------------------------------------------------- calibration and folds

def presses_of(data: PressSet, indices: Sequence[int]) -> list[BallPress]:
    s = data.mm_per_pixel * 1e-3
    return [BallPress(data.presses[i], float(data.centres[i][0]), float(data.centres[i][1]), float(data.radii[i]),
                      (s, s), str(i)) for i in indices]


def kfold(data: PressSet, folds: int, cfg: PressCalibrationConfig, ball: float = BALL,
          height: HeightConfig | None = None) -> tuple[list[PressMeasure], float, list[str]]:
    """Each press measured with a model calibrated on the other folds, against the reference that calibration
    chose (cfg.reference); also the median calibration seconds and each fold's reference choice."""
    pixel = data.mm_per_pixel * 1e-3
    measures: list[PressMeasure] = []
    seconds = []
    choices = []
    for k in range(folds):
        test = [i for i in range(len(data)) if i % folds == k]
        train = [i for i in range(len(data)) if i % folds != k]
        start = time.perf_counter()
        cal = calibrate_photometric(presses_of(data, train), data.background, ball, cfg)
        seconds.append(time.perf_counter() - start)
        reference = calibrated_reference(cal, data)
        choices.append(reference_text(cal) + colour_degree_text(cal)
                       + f", still slope {cal.model.still_slope:.4f}")
        est = HeightEstimator(cal.model, reference, pixel, config=height)
        for i in test:
            measures.append(measure_press(i, est, data.presses[i], reference, (*data.centres[i], data.radii[i]),
                                          pixel, cfg))
    return sorted(measures, key=lambda m: m.index), float(np.median(seconds)), choices


def choose_prior(data: PressSet, cfg: PressCalibrationConfig, quantiles: Sequence[float] = STILL_QUANTILES,
                 folds: int = FOLDS) -> dict[str, Summary]:
    """How `PressCalibrationConfig.still_quantile` is chosen, on calibration presses alone: inside each fold's
    calibration presses (those the fold does not measure), every fourth (from the fold's index) is measured with a
    model calibrated on the others, its prior's threshold that quantile of those others' far-field slopes (none: the
    prior off), its shape the configuration's (`still_ellipse`; the default quantile also with the other shape).
    The summaries pool the folds' held-out calibration presses per candidate."""
    pixel = data.mm_per_pixel * 1e-3
    candidates = {"none": (0.0, False), **{f"{q:g}": (q, cfg.still_ellipse) for q in quantiles},
                  **{f"{q:g} {'round' if cfg.still_ellipse else 'ellipse'}": (q, not cfg.still_ellipse)
                     for q in quantiles if q == cfg.still_quantile}}
    pooled: dict[str, list[PressMeasure]] = {name: [] for name in candidates}
    for k in range(folds):
        train = [i for i in range(len(data)) if i % folds != k]
        inner_test = train[k % 4::4]
        inner_cal = [i for i in train if i not in inner_test]
        cal = calibrate_photometric(presses_of(data, inner_cal), data.background, BALL,
                                    dataclasses.replace(cfg, still_quantile=0.0))
        reference = calibrated_reference(cal, data)
        for name, (q, ellipse) in candidates.items():
            slope, shape = (fit_still_prior(cal.model, presses_of(data, inner_cal), reference, cfg.reference_factor, q,
                                            ellipse) if q > 0 else (0.0, (1.0, 0.0, 0.0, 1.0)))
            model = dataclasses.replace(cal.model, still_slope=slope, still_shape=shape)
            est = HeightEstimator(model, reference, pixel)
            pooled[name] += [measure_press(i, est, data.presses[i], reference, (*data.centres[i], data.radii[i]),
                                           pixel, cfg) for i in inner_test]
    return {name: summarise(measures) for name, measures in pooled.items()}


def prior_markdown(summaries: dict[str, Summary]) -> str:
    lines = ["| still quantile | normal-angle error | sphere-fit RMS | fitted R | depth ratio | no-contact window "
             "(worst) |", "|---|---|---|---|---|---|"]
    lines += [f"| {name} | {g.angle_deg:.2f} deg | {g.rms_um:.1f} um | {g.radius_mm:.3f} mm | {g.depth_ratio:.3f} | "
              f"{g.flat_um:.2f} um ({g.flat_max_um:.1f}) |" for name, g in summaries.items()]
    return "\n".join(lines) + "\n"


def calibrated_reference(cal: PhotometricCalibration, data: PressSet) -> np.ndarray:
    """The reference the calibration read the presses against (the product's: give it to the estimator)."""
    return cal.reference if cal.reference is not None else data.background


def reference_text(cal: PhotometricCalibration) -> str:
    c = cal.reference_choice
    if c is None:
        return "given"
    if c.coverage < 1.0:
        return f"given (the presses leave {100 * (1 - c.coverage):.0f} % of the image near all but a few of them)"
    if not math.isfinite(c.given_change):
        return c.source
    return f"{c.source} ({100 * c.given_change:.2f} % / {100 * c.presses_change:.2f} %)"


def colour_degree_text(cal: PhotometricCalibration) -> str:
    if not cal.colour_degree_scores:
        return ""
    weighed = ", ".join(f"{s.degree}: {s.normal_error_deg:.2f}" for s in cal.colour_degree_scores)
    return f", position-colour degree {cal.model.config.position_colour_degree} ({weighed} deg)"


def cpu_ms(fn: Any, repeats: int) -> float:
    fn()
    best = math.inf
    for _ in range(repeats):
        start = time.thread_time()
        fn()
        best = min(best, time.thread_time() - start)
    return best * 1e3


_SPLIT_CALIBRATIONS: dict[tuple[str, PressCalibrationConfig], PhotometricCalibration] = {}


def split_calibration(data: PressSet, cfg: PressCalibrationConfig) -> PhotometricCalibration:
    """The even presses' calibration for `cfg`, made once per sensor and fitting (the lookup's size is not part
    of the fit: rows that change only it reuse the fit, with the model's configuration replaced)."""
    lookup = {"lookup_bins": cfg.model.lookup_bins, "lookup_cells": cfg.model.lookup_cells}
    base = PhotometricConfig()
    key = (data.sensor, dataclasses.replace(cfg, model=dataclasses.replace(
        cfg.model, lookup_bins=base.lookup_bins, lookup_cells=base.lookup_cells)))
    if key not in _SPLIT_CALIBRATIONS:
        _SPLIT_CALIBRATIONS[key] = calibrate_photometric(presses_of(data, range(0, len(data), 2)), data.background,
                                                         BALL, key[1])
    cal = _SPLIT_CALIBRATIONS[key]
    model = dataclasses.replace(cal.model, config=dataclasses.replace(cal.model.config, **lookup))
    return dataclasses.replace(cal, model=model)


def split_angle(data: PressSet, cfg: PressCalibrationConfig, lookup: bool = True, rows: tuple[int, int] | None = None,
                height: HeightConfig | None = None, repeats: int = 10) -> tuple[float, float, float]:
    """(median normal-angle error on the odd presses calibrated on the even ones, CPU ms per frame, median
    no-contact window RMS in um: whole frames through the lookup only, else nan)."""
    pixel = data.mm_per_pixel * 1e-3
    cal = split_calibration(data, cfg)
    reference = calibrated_reference(cal, data)
    est = HeightEstimator(cal.model, reference, pixel, rows=rows, config=height)
    errors, flats = [], []
    for i in range(1, len(data), 2):
        image = data.presses[i]
        circle = refine_circle(change_magnitude(image, reference), *data.centres[i], data.radii[i], cfg)
        tx, ty, rho, _ = sphere_slopes(image.shape[:2], circle, (pixel, pixel), BALL)
        inside = rho * circle.radius_px < circle.radius_px - 2.0
        gx, gy = est.slopes(image) if lookup else cal.model.slopes(image, reference)
        window = flat_window(image.shape[:2], circle.u, circle.v, circle.radius_px)
        if lookup and rows is None and window is not None:     # as measure_press does
            flats.append(float(np.sqrt(np.mean(slopes_to_height(gx[window], gy[window], pixel, est.config) ** 2))))
        if rows is not None:
            full_x = np.full(image.shape[:2], np.nan, np.float32)
            full_y = full_x.copy()
            full_x[rows[0]:rows[1]], full_y[rows[0]:rows[1]] = gx, gy
            gx, gy = full_x, full_y
            inside &= np.isfinite(gx)
        if inside.any():
            errors.append(np.median(normal_angles_deg(gx[inside], gy[inside], tx[inside], ty[inside])))
    image = data.presses[1]
    if lookup:
        ms = cpu_ms(lambda: est.band(image), repeats)
    else:
        ms = cpu_ms(lambda: cal.model.slopes(image, reference), max(1, repeats // 5))
    return (float(np.median(errors)) if errors else math.nan, ms,
            float(np.median(flats)) * 1e6 if flats else math.nan)


def add_split(data: PressSet, cfg: PressCalibrationConfig, repeats: int) -> TradeoffRow:
    """The whole-frame default row for a calibration setting."""
    angle, ms, flat = split_angle(data, cfg, True, None, None, repeats)
    return TradeoffRow("", angle, ms, "frame", flat)


def tradeoffs(data: PressSet, base: PressCalibrationConfig, band: tuple[int, int], quick: bool) -> list[TradeoffRow]:
    m = base.model
    rows: list[TradeoffRow] = []
    reps = 5 if quick else 15

    def add(label: str, model: PhotometricConfig, lookup: bool = True, rows_: tuple[int, int] | None = None,
            height: HeightConfig | None = None) -> None:
        angle, ms, flat = split_angle(data, dataclasses.replace(base, model=model), lookup, rows_, height, reps)
        rows.append(TradeoffRow(label, angle, ms, "band" if rows_ else "frame", flat))

    add(f"default: lookup {m.lookup_bins}^3 x {m.lookup_cells[0]}x{m.lookup_cells[1]} cells, smoothing "
        f"{m.smoothing:g} px", m)
    add("band only (roller, default settings)", m, rows_=band)
    add("exact polynomial (no lookup), slopes only", m, lookup=False)
    add("integration on a 2x coarser grid", m, height=HeightConfig(downsample=2))
    add(f"zero-slope prior: colour change within {STILL_CHANGE:g} reads flat (chosen on gelsight_mini)", m,
        height=HeightConfig(still_change=STILL_CHANGE))
    add("zero-slope prior off (`HeightConfig.still_slope` 0: as before it)", m, height=HeightConfig(still_slope=0.0))
    cal = split_calibration(data, base)
    reference = calibrated_reference(cal, data)
    for q in (0.85, 0.95):
        if q != base.still_quantile:
            slope, _ = fit_still_prior(cal.model, presses_of(data, range(0, len(data), 2)), reference,
                                       base.reference_factor, q, base.still_ellipse)
            add(f"zero-slope prior at the {q:g} quantile of the far-field slopes ({slope:.4f}; default "
                f"{base.still_quantile:g}: {cal.model.still_slope:.4f})", m, height=HeightConfig(still_slope=slope))
    rows.append(dataclasses.replace(
        add_split(data, dataclasses.replace(base, still_ellipse=not base.still_ellipse), reps),
        setting="zero-slope prior " + ("round (the plain length)" if base.still_ellipse else
                                       "in the far-field slopes' ellipse") + f", {base.still_quantile:g} quantile"))
    if base.position_colour_degrees:
        rows.append(dataclasses.replace(
            add_split(data, dataclasses.replace(base, position_colour_degrees=()), reps),
            setting=f"position terms on colour terms up to degree {m.position_colour_degree} (the model's own, "
                    "not chosen on held-out presses)"))
    if base.reference != "given":
        rows.append(dataclasses.replace(add_split(data, dataclasses.replace(base, reference="given"), reps),
                                        setting="reference as given (the no-contact frame), not from the presses"))
    rows.append(dataclasses.replace(
        add_split(data, dataclasses.replace(base, far_fraction=FAR_DENSE), reps),
        setting=f"far-field targets {FAR_DENSE:.0%} of the far pixels (default {base.far_fraction:.0%})"))
    if not quick:
        add("lookup 17^3", dataclasses.replace(m, lookup_bins=17))
        add("lookup 49^3", dataclasses.replace(m, lookup_bins=49))
        add("position cells 4x3", dataclasses.replace(m, lookup_cells=(4, 3)))
        add("position cells 1x1 (position term averaged away)", dataclasses.replace(m, lookup_cells=(1, 1)))
        add("no position term (colour alone)", dataclasses.replace(m, position_degree=0))
        add("no smoothing", dataclasses.replace(m, smoothing=0.0))
        add("smoothing 2 px", dataclasses.replace(m, smoothing=2.0))
        add("offset term (position alone -> slope)", dataclasses.replace(m, offset=True))
        add("no frame gain (drift not divided out)", dataclasses.replace(m, gain=False))
        add("circles as labelled (no refinement)", m)   # replaced below
        unrefined = split_angle(data, dataclasses.replace(base, refine=False), True, None, None, reps)
        rows[-1] = TradeoffRow("circles as labelled (no refinement)", unrefined[0], rows[0].ms, "frame", unrefined[2])
    return rows


def run(quick: bool = False) -> HeightRealResult:
    if not available():
        raise SystemExit("the taxim wheel is not installed (pinned in requirements.txt): run `make setup`")
    cv2.setNumThreads(1)
    stamp = provenance("height_real", quick)
    cfg = PressCalibrationConfig(reference=REFERENCE, position_colour_degrees=COLOUR_POSITION)
    data = load_presses("gelsight")
    folds = 3 if quick else FOLDS
    measures, calibrate_s, choices = kfold(data, folds, cfg)
    pixel = data.mm_per_pixel * 1e-3
    cal = calibrate_photometric(presses_of(data, range(len(data))), data.background, BALL, cfg)
    reference = calibrated_reference(cal, data)
    band = contact_band(CameraModel(), max_depth=BAND_DEPTH)
    frame_est = HeightEstimator(cal.model, reference, pixel)
    band_est = HeightEstimator(cal.model, reference, band.pixel_size, rows=band.rows)
    image = data.presses[0]
    repeats = 5 if quick else 30
    frame_ms = cpu_ms(lambda: frame_est.height(image), repeats)
    band_ms = cpu_ms(lambda: band_est.band(image), repeats)
    exact_ms = cpu_ms(lambda: cal.model.slopes(image, reference), 2)
    circularity: dict[str, float] = {}
    for assumed in ((2.2e-3,) if quick else (1.9e-3, 2.2e-3)):   # above the largest contact radius, 1.84 mm
        train = [i for i in range(len(data)) if i % 2 == 0]
        c2 = calibrate_photometric(presses_of(data, train), data.background, assumed, cfg)
        est = HeightEstimator(c2.model, calibrated_reference(c2, data), pixel)
        radii = [sphere_fit(est.height(data.presses[i]), *data.centres[i], data.radii[i], pixel)[1]
                 for i in range(1, len(data), 2)]
        circularity[f"{assumed * 1e3:.1f}"] = float(np.median(radii)) * 1e3
    mini = None
    mini_data = load_presses("gelsight_mini")
    mini_measures, _, _ = kfold(mini_data, 3, cfg)
    mini = summarise(mini_measures)
    table = tradeoffs(data, cfg, band.rows, quick)
    return HeightRealResult(stamp, dataclasses.asdict(cfg), folds, summarise(measures), tuple(measures), frame_ms,
                            band_ms, band.rows, exact_ms, calibrate_s, circularity, mini, tuple(table), BASELINE,
                            GOALS, tuple(choices))


# --------------------------------------------------------------------------- output

def _met(ok: bool) -> str:
    return "met" if ok else "NOT met"


def goal_checks(r: HeightRealResult) -> list[tuple[str, str, bool]]:
    g = r.gelsight
    return [
        ("normal-angle error median <= 4 deg", f"{g.angle_deg:.2f} deg (p90 {g.angle_p90_deg:.2f}; against the hand "
         f"labels' circles {g.angle_label_deg:.2f})", g.angle_deg <= GOALS["angle_deg"]),
        ("sphere-fit RMS residual median <= 15 um", f"{g.rms_um:.1f} um (R fixed at 2 mm: {g.rms_fixed_um:.1f} um)",
         g.rms_um <= GOALS["rms_um"]),
        ("fitted radius within 3 % of 2.0 mm (median)", f"{g.radius_mm:.3f} mm (p10-p90 {g.radius_p10_mm:.3f}-"
         f"{g.radius_p90_mm:.3f}); circular: trained assuming "
         + ", ".join(f"{k} mm it fits {v:.3f} mm" for k, v in r.circularity.items()),
         abs(g.radius_mm / 2.0 - 1) <= GOALS["radius_rel"]),
        ("rim-relative cap depth / geometric cap median in 0.9-1.1", f"{g.depth_ratio:.3f} (p10-p90 {g.depth_p10:.2f}-"
         f"{g.depth_p90:.2f}; geometric cap from the labels' radii: {g.depth_ratio_label:.3f}, "
         f"{g.depth_label_p10:.2f}-{g.depth_label_p90:.2f})",
         GOALS["depth_lo"] <= g.depth_ratio <= GOALS["depth_hi"]),
        ("no-contact window <= 5 um RMS (median)", f"{g.flat_um:.2f} um (worst {g.flat_max_um:.2f})",
         g.flat_um <= GOALS["flat_um"]),
        ("slopes + integration <= 10 ms per 640x480 frame (one core)", f"{r.frame_ms:.2f} ms", r.frame_ms <= 10.0),
        ("roller band <= 2 ms", f"{r.band_ms:.2f} ms ({r.band_rows[1] - r.band_rows[0]} x 640 px)", r.band_ms <= 2.0),
    ]


def to_markdown(r: HeightRealResult) -> str:
    g = r.gelsight
    lines = [provenance_markdown(r.provenance), "",
             f"taxim `gelsight`: {g.presses} presses of a 2.0 mm ball, {r.folds}-fold (each press measured with a "
             f"model calibrated on the others; calibration {r.calibrate_s:.1f} s per fold). Real data: shares "
             "nothing with the simulator.", "",
             f"Reference: `PressCalibrationConfig.reference = {r.config.get('reference', 'given')!r}`, "
             f"`position_colour_degrees = {tuple(r.config.get('position_colour_degrees', ()))}`"
             + (" (each fold's calibration: " + "; ".join(r.reference_choices) + "; the median far-field colour "
                "change of its presses against the given no-contact frame / against one built from its other "
                "presses, the smaller kept; the position-colour degree chosen by its held-out presses' median "
                "normal-angle error)" if r.reference_choices else "") + ".", "",
             "| measure | ours | baseline (RGB LUT + DCT, 6-fold) | goal |", "|---|---|---|---|"]
    base = r.baseline
    rows = [("normal-angle error, median", f"{g.angle_deg:.2f} deg", f"{base['angle_deg']} deg", "<= 4 deg"),
            ("sphere-fit RMS residual, median (centre, R free)", f"{g.rms_um:.1f} um", f"{base['rms_um']} um",
             "<= 15 um"),
            ("fitted R, median", f"{g.radius_mm:.3f} mm", f"{base['radius_mm']} mm", "2.0 mm +- 3 %"),
            ("rim-relative depth / geometric cap", f"{g.depth_ratio:.3f} (p10-p90 {g.depth_p10:.2f}-{g.depth_p90:.2f})",
             f"{base['depth_ratio']} (0.69-1.09)", "0.9-1.1"),
            ("no-contact window RMS, median", f"{g.flat_um:.2f} um", "", "<= 5 um"),
            ("slopes + integration, 640x480, CPU ms", f"{r.frame_ms:.2f} ms", f"{base['ms']} ms", "<= 10 ms"),
            (f"roller band ({r.band_rows[1] - r.band_rows[0]} rows)", f"{r.band_ms:.2f} ms", "", "<= 2 ms")]
    lines += [f"| {a} | {b} | {c} | {d} |" for a, b, c, d in rows]
    lines += ["", "Goals:", ""]
    lines += [f"- {name}: {value} — **{_met(ok)}**" for name, value, ok in goal_checks(r)]
    lines += ["", "Other views of the same presses:", "",
              f"- normal-angle error against the hand labels' circles (not refined): {g.angle_label_deg:.2f} deg",
              f"- sphere fit with R fixed at 2.0 mm: RMS {g.rms_fixed_um:.1f} um",
              f"- depth ratio with the geometric cap from the labels' radii: {g.depth_ratio_label:.3f} "
              f"(p10-p90 {g.depth_label_p10:.2f}-{g.depth_label_p90:.2f})",
              f"- exact polynomial instead of the lookup: {r.exact_frame_ms:.1f} ms per frame (slopes only)",
              "- circularity of the fitted R (the model is trained assuming a radius; even presses calibrate, odd "
              "measured): " + ", ".join(f"assumed {k} mm -> fitted {v:.3f} mm" for k, v in r.circularity.items())
              + f"; assumed 2.0 mm -> fitted {g.radius_mm:.3f} mm (the k-fold above)"]
    if any(math.isfinite(m.drift) for m in r.per_press):
        lines += ["- where the no-contact windows' height comes from (median window RMS, windows): "
                  + ", ".join(f"{k}: {v:.2f} um ({n})" for k, (v, n) in no_contact_views(r.per_press).items())
                  + " (a frame's drift: its largest per-channel colour change against the reference, which the "
                  "frame gain divides out over the whole frame)"]
    if r.mini is not None:
        m = r.mini
        lines += [f"- `gelsight_mini` (development set, ball radius unknown, calibrated assuming 2.0 mm, 3-fold): "
                  f"fitted R median {m.radius_mm:.3f} mm, p10-p90 {m.radius_p10_mm:.3f}-{m.radius_p90_mm:.3f} mm "
                  f"(consistency: {100 * (m.radius_p90_mm - m.radius_p10_mm) / max(m.radius_mm, 1e-9):.1f} % of the "
                  f"median); normal-angle error {m.angle_deg:.2f} deg; sphere-fit RMS {m.rms_um:.1f} um"]
    lines += ["", "What accuracy costs in time (even presses calibrate, odd measured; CPU ms of slopes + integration "
              "per frame or band, one thread; the exact polynomial row is slopes only; no-contact: the median "
              "window RMS as above, whole-frame lookup rows; every row reads with the zero-slope prior its own "
              "calibration measured unless it says otherwise):", "",
              "| setting | normal-angle error, median | ms | region | no-contact window, median |",
              "|---|---|---|---|---|"]
    lines += [f"| {t.setting} | {t.angle_deg:.2f} deg | {t.ms:.2f} | {t.rows} | "
              + (f"{t.flat_um:.2f} um |" if math.isfinite(t.flat_um) else "|") for t in r.tradeoffs]
    lines += ["", "Per press (index: angle deg, RMS um, R mm, depth ratio, no-contact um):", ""]
    lines += ["; ".join(f"{m.index}: {m.angle_deg:.1f}, {m.rms_um:.0f}, {m.radius_mm:.2f}, {m.depth_ratio:.2f}, "
                        f"{m.flat_um:.1f}" for m in r.per_press)]
    return "\n".join(lines) + "\n"


def load(path: Path) -> HeightRealResult:
    raw = json.loads(Path(path).read_text())
    raw["provenance"] = Provenance(**raw["provenance"])
    raw["gelsight"] = Summary(**raw["gelsight"])
    raw["mini"] = Summary(**raw["mini"]) if raw.get("mini") else None
    raw["per_press"] = tuple(PressMeasure(**{**m, "circle": tuple(m["circle"]), "label": tuple(m["label"])})
                             for m in raw["per_press"])
    raw["tradeoffs"] = tuple(TradeoffRow(**t) for t in raw["tradeoffs"])
    raw["band_rows"] = tuple(raw["band_rows"])
    raw["reference_choices"] = tuple(raw.get("reference_choices", ()))
    return HeightRealResult(**raw)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="3 folds, fewer timing repeats, a short trade-off table")
    parser.add_argument("--choose-prior", action="store_true",
                        help="only show how the zero-slope prior's quantile is chosen on calibration presses (prints a "
                             "table, records nothing)")
    args = parser.parse_args(argv)
    if args.choose_prior:
        if not available():
            raise SystemExit("the taxim wheel is not installed (pinned in requirements.txt): run `make setup`")
        cv2.setNumThreads(1)
        print(prior_markdown(choose_prior(load_presses("gelsight"),
                                          PressCalibrationConfig(reference=REFERENCE,
                                                                 position_colour_degrees=COLOUR_POSITION))))
        return 0
    result = run(quick=args.quick)
    out = results_path("height_real", args.quick)
    out.parent.mkdir(parents=True, exist_ok=True)
    text = "# Height on real GelSight presses\n\n" + to_markdown(result)
    atomic_write_text(out, text)
    atomic_write_text(out.with_suffix(".json"), to_json(result, indent=1))
    print(text)
    return 0


if __name__ == "__main__":
    sys.exit(main())
