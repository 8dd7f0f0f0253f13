"""Calibration accuracy against effort on the simulator, and checked on a second renderer.

Scenes: `calibration_chessboard` (intrinsics) and `calibration_hemispheres` (theta, d), whose truth
camera is the one of `contact_localisation` (fx = fy = 380 px, theta = 2 deg, d = 1.5 mm, barrel
distortion). Each seed renders its own views and presses (the frame's pose jitters between presses:
+-1.5 mm in x and y, +-2 deg yaw; the first press is centred).

Tables:
A. intrinsics against the number of chessboard views (errors vs truth, reprojection RMS, solve time);
B. theta and d against the number of presses, with the true intrinsics (ours, and the paper's
   plain mean of theta);
C. the whole calibration: 20 chessboard views + 10 presses per seed (goals: theta within 0.1 deg,
   d within 0.05 mm, reprojection RMS <= 0.2 px, the whole solve < 2 s);
D. end to end: contacts of the `contact_localisation` scene located with that calibration (exact
   sensor, and the paper variant's sensor flaws with a calibration made on the same flawed sensor);
E. robustness of theta and d to the paper's sensor flaws (noise, uneven elastomer);
F. the terms the paper's model neglects, as reported by one calibration;
G, H, I. the same calibration on data it was not tuned on (`bench.calib_crosscheck`: a second
   renderer with its own imprint model and a lens seen only in the middle; the sigmas checked).

`run(quick)` returns a `CalibBenchResult`; `python -m bench.calib_bench [--quick]` also writes
bench/results/calib_bench.md (and .json) and the figures beside them.
"""
from __future__ import annotations

import argparse
import dataclasses
import math
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np

from bench import calib_crosscheck as crosscheck
from bench._common import Provenance, load_json, provenance, provenance_markdown, results_path, save_figure, to_json
from bench.calib_crosscheck import Stats
from touchroller_perception import calibration as cal
from touchroller_perception.files import atomic_write_text
from touchroller_perception.geometry import CameraModel


@dataclasses.dataclass(frozen=True)
class Goals:
    theta_deg: float = 0.1
    d_mm: float = 0.05
    rms_px: float = 0.2
    solve_s: float = 2.0


#: the contact_localisation scene's `paper` variant sensor flaws, applied to the calibration scenes
SENSOR_FLAWS = {
    "noise sigma 3": {"effect_params.noise.sigma": 3.0},
    "elastomer thickness ±0.3 mm": {"sensor.thickness_variation": 3.0e-4},
    "both (the paper variant)": {"effect_params.noise.sigma": 3.0, "sensor.thickness_variation": 3.0e-4},
}


@dataclasses.dataclass(frozen=True)
class IntrinsicsRow:
    views: int
    distortion: str
    fx_err_px: Stats
    cx_err_px: Stats
    cy_err_px: Stats
    reprojection_rms_px: float
    solve_s_median: float
    rejected_views: int


@dataclasses.dataclass(frozen=True)
class PressesRow:
    presses: int
    theta_err_deg: Stats
    paper_plain_mean_theta_err_deg: Stats
    d_err_mm: Stats
    reprojection_rms_px: float
    solve_s_median: float


@dataclasses.dataclass(frozen=True)
class SeedRun:
    seed: int
    theta_err_deg: float
    paper_plain_mean_theta_err_deg: float
    d_err_mm: float
    fx_err_px: float
    intrinsics_rms_px: float
    extrinsics_rms_px: float
    seconds: float
    rejected: int
    #: CPU seconds of the same solve (this process, all its threads): what the solve costs, which the
    #: wall-clock seconds show only on an idle machine
    cpu_seconds: float = math.nan


@dataclasses.dataclass(frozen=True)
class FullCalibration:
    runs: tuple[SeedRun, ...]
    theta_err_deg: Stats
    paper_plain_mean_theta_err_deg: Stats
    d_err_mm: Stats
    intrinsics_rms_px: Stats
    extrinsics_rms_px: Stats
    solve_s_median: float
    solve_s_max: float
    within_goals: int
    solve_cpu_s_median: float = math.nan
    solve_cpu_s_max: float = math.nan


@dataclasses.dataclass(frozen=True)
class ContactRow:
    condition: str
    camera: str
    mean_mm: float
    std_mm: float
    max_mm: float
    n: int


@dataclasses.dataclass(frozen=True)
class RobustnessRow:
    sensor: str
    theta_err_deg: Stats
    paper_plain_mean_theta_err_deg: Stats
    d_err_mm: Stats
    extrinsics_rms_px: Stats


@dataclasses.dataclass(frozen=True)
class CalibBenchResult:
    quick: bool
    seeds: int
    provenance: Provenance
    goals: Goals
    intrinsics_vs_views: tuple[IntrinsicsRow, ...]
    extrinsics_vs_presses: tuple[PressesRow, ...]
    full: FullCalibration
    neglected_example: cal.NeglectedTerms
    contacts: tuple[ContactRow, ...]
    robustness: tuple[RobustnessRow, ...]
    crosscheck: crosscheck.CrosscheckResult

    def contact(self, condition: str, camera: str) -> ContactRow:
        return next(r for r in self.contacts if r.condition == condition and r.camera == camera)


EXACT = "exact sensor"
FLAWED = "paper's sensor flaws (thickness ±0.3 mm, noise 3)"


# --------------------------------------------------------------------------- rendering
def chessboard_views(seed: int, views: int, sensor_overrides: dict[str, Any]) -> tuple[list[np.ndarray], CameraModel]:
    from touchroller_driver.sim import SimulatedSensor, load_scene

    sensor = SimulatedSensor(load_scene("calibration_chessboard", **{"motion.views": views, **sensor_overrides}),
                             seed=seed)
    return [f.image for f in sensor.frames()], sensor.camera


def hemisphere_presses(seed: int, presses: int, sensor_overrides: dict[str, Any]):
    """(reference image, press images, true camera)."""
    from touchroller_driver.sim import SimulatedSensor, load_scene

    sensor = SimulatedSensor(load_scene("calibration_hemispheres", **{"motion.presses": presses, **sensor_overrides}),
                             seed=1000 + seed)
    frames = list(sensor.frames())
    references = [f.image for f in frames if f.truth.get("phase") == "reference"]
    pressed = [f.image for f in frames if f.truth.get("phase") == "press"]
    return np.median(np.stack(references), axis=0).astype(np.uint8), pressed, sensor.camera


# --------------------------------------------------------------------------- measurements
def timed(function, *args, **kwargs):
    start = time.perf_counter()
    result = function(*args, **kwargs)
    return result, time.perf_counter() - start


def intrinsics_vs_views(seeds: list[int], counts: list[int]) -> list[IntrinsicsRow]:
    rows = []
    rendered = {s: chessboard_views(s, max(counts), {}) for s in seeds}
    for n, model in [(n, "auto") for n in counts] + [(20, "full"), (20, "radial")]:
        errors: dict[str, list[float]] = {k: [] for k in ("fx", "cx", "cy")}
        rms, seconds, rejected = [], [], 0
        for s in seeds:
            images, truth = rendered[s]
            result, dt = timed(cal.calibrate_intrinsics, images[:n], cal.IntrinsicsConfig(distortion=model))
            for k in errors:
                errors[k].append(getattr(result.camera, k) - getattr(truth, k))
            rms.append(result.rms)
            seconds.append(dt)
            rejected += len(result.rejected)
        rows.append(IntrinsicsRow(n, model, Stats.of(errors["fx"]), Stats.of(errors["cx"]), Stats.of(errors["cy"]),
                                  float(np.mean(rms)), float(np.median(seconds)), rejected))
    return rows


def extrinsics_vs_presses(seeds: list[int], counts: list[int]) -> list[PressesRow]:
    rows = []
    rendered = {s: hemisphere_presses(s, max(counts), {}) for s in seeds}
    for m in counts:
        theta, plain, d, rms, seconds = [], [], [], [], []
        for s in seeds:
            reference, presses, truth = rendered[s]
            start = truth.replace(theta=0.0, d=0.0)
            result, dt = timed(cal.calibrate_extrinsics, presses[:m], start, reference=reference)
            theta.append(math.degrees(result.theta - truth.theta))
            plain.append(math.degrees(result.theta_plain_mean - truth.theta))
            d.append(1e3 * (result.d - truth.d))
            rms.append(result.rms)
            seconds.append(dt)
        rows.append(PressesRow(m, Stats.of(theta), Stats.of(plain), Stats.of(d), float(np.mean(rms)),
                               float(np.median(seconds))))
    return rows


@dataclasses.dataclass(frozen=True)
class _Calibrated:
    run: SeedRun
    camera: CameraModel
    truth: CameraModel
    neglected: cal.NeglectedTerms


def full_calibration(seed: int, views: int, presses: int, sensor_overrides: dict[str, Any]) -> _Calibrated:
    images, truth = chessboard_views(seed, views, sensor_overrides)
    reference, pressed, _ = hemisphere_presses(seed, presses, sensor_overrides)
    start, cpu = time.perf_counter(), time.process_time()
    intrinsics = cal.calibrate_intrinsics(images)
    extrinsics = cal.calibrate_extrinsics(pressed, intrinsics.camera.replace(theta=0.0, d=0.0), reference=reference,
                                          intrinsics_covariance=intrinsics.covariance)
    seconds, cpu_seconds = time.perf_counter() - start, time.process_time() - cpu
    run = SeedRun(seed=seed, theta_err_deg=math.degrees(extrinsics.theta - truth.theta),
                  paper_plain_mean_theta_err_deg=math.degrees(extrinsics.theta_plain_mean - truth.theta),
                  d_err_mm=1e3 * (extrinsics.d - truth.d), fx_err_px=intrinsics.camera.fx - truth.fx,
                  intrinsics_rms_px=intrinsics.rms, extrinsics_rms_px=extrinsics.rms, seconds=seconds,
                  cpu_seconds=cpu_seconds,
                  rejected=len(intrinsics.rejected) + len(extrinsics.rejected))
    return _Calibrated(run, extrinsics.camera, truth, extrinsics.neglected)


def solve_met(full: FullCalibration, goals: Goals) -> bool:
    """The whole solve's goal, judged on its CPU time (every seed): on a machine other jobs share, the
    wall-clock time is the solve's and theirs. A result without CPU times is judged on the wall clock."""
    worst = full.solve_cpu_s_max if math.isfinite(full.solve_cpu_s_max) else full.solve_s_max
    return worst < goals.solve_s


def summarise(runs: list[SeedRun], goals: Goals) -> FullCalibration:
    return FullCalibration(
        runs=tuple(runs), theta_err_deg=Stats.of([r.theta_err_deg for r in runs]),
        paper_plain_mean_theta_err_deg=Stats.of([r.paper_plain_mean_theta_err_deg for r in runs]),
        d_err_mm=Stats.of([r.d_err_mm for r in runs]), intrinsics_rms_px=Stats.of([r.intrinsics_rms_px for r in runs]),
        extrinsics_rms_px=Stats.of([r.extrinsics_rms_px for r in runs]),
        solve_s_median=float(np.median([r.seconds for r in runs])),
        solve_s_max=float(np.max([r.seconds for r in runs])),
        solve_cpu_s_median=float(np.median([r.cpu_seconds for r in runs])),
        solve_cpu_s_max=float(np.max([r.cpu_seconds for r in runs])),
        within_goals=sum(abs(r.theta_err_deg) <= goals.theta_deg and abs(r.d_err_mm) <= goals.d_mm for r in runs))


def contact_errors(cameras: dict[str, CameraModel], variant: str, seed: int, repeats: int,
                   condition: str) -> list[ContactRow]:
    """Locate the contact_localisation taps (colour detector of touchroller_perception.contacts)
    through each camera model; errors in mm against the true membrane points."""
    from touchroller_driver.sim import SimulatedSensor, load_scene
    from touchroller_perception.contacts import ContactDetector

    scene = load_scene("contact_localisation", variant=variant, **{"motion.repeats": repeats})
    sensor = SimulatedSensor(scene, seed=seed)
    detector = ContactDetector(reference_frames=int(scene.motion.get("reference_frames", 5)))
    errors: dict[str, list[float]] = {name: [] for name in cameras}
    for frame in sensor.frames():
        found = detector.process(frame.image) or []
        if frame.truth.get("phase") != "tap":
            continue
        for truth in frame.truth["contacts"]:
            pixel = np.asarray(truth["pixel"], dtype=np.float64)
            if not np.isfinite(pixel).all() or not sensor.camera.in_image(pixel, margin=5):
                continue
            best = min(found, key=lambda c: math.hypot(c.u - pixel[0], c.v - pixel[1]), default=None)
            if best is None or math.hypot(best.u - pixel[0], best.v - pixel[1]) > 25.0:
                continue
            for name, camera in cameras.items():
                point, valid = camera.back_project(np.array([best.u, best.v]))
                if valid:
                    errors[name].append(1e3 * float(np.linalg.norm(point - np.asarray(truth["point"]))))
    return [ContactRow(condition, name, float(np.mean(v)), float(np.std(v)), float(np.max(v)), len(v))
            for name, v in errors.items()]


def run(quick: bool = False) -> CalibBenchResult:
    goals = Goals()
    seeds = list(range(2 if quick else 10))
    stamp = provenance("calib_bench", quick)
    by_views = intrinsics_vs_views(seeds, [5, 10, 20] if quick else [5, 10, 20, 40])
    by_presses = extrinsics_vs_presses(seeds, [2, 5, 10] if quick else [2, 3, 5, 10, 20])
    calibrated = [full_calibration(s, 20, 10, {}) for s in seeds]
    truth = calibrated[0].truth
    paper_sized = truth.replace(theta=truth.theta + math.radians(1.0), d=truth.d + 0.5e-3)
    cameras = {"truth": truth, "ours (seed 0)": calibrated[0].camera,
               "uncalibrated (theta = d = 0)": truth.replace(theta=0.0, d=0.0),
               "paper-sized error (1 deg, 0.5 mm)": paper_sized}
    repeats = 1 if quick else 3
    contacts = contact_errors(cameras, "exact", 0, repeats, EXACT)
    robustness, flawed_camera = [], truth
    for name, overrides in SENSOR_FLAWS.items():
        flawed = [full_calibration(s, 20, 10, overrides) for s in seeds[:2 if quick else 5]]
        runs = [f.run for f in flawed]
        robustness.append(RobustnessRow(name, Stats.of([r.theta_err_deg for r in runs]),
                                        Stats.of([r.paper_plain_mean_theta_err_deg for r in runs]),
                                        Stats.of([r.d_err_mm for r in runs]),
                                        Stats.of([r.extrinsics_rms_px for r in runs])))
        flawed_camera = flawed[0].camera
    contacts += contact_errors({"truth": truth, "ours, calibrated on the same flawed sensor (seed 0)": flawed_camera,
                                "paper-sized error (1 deg, 0.5 mm)": paper_sized}, "paper", 0, repeats, FLAWED)
    return CalibBenchResult(quick=quick, seeds=len(seeds), provenance=stamp, goals=goals,
                            intrinsics_vs_views=tuple(by_views), extrinsics_vs_presses=tuple(by_presses),
                            full=summarise([c.run for c in calibrated], goals),
                            neglected_example=calibrated[0].neglected, contacts=tuple(contacts),
                            robustness=tuple(robustness), crosscheck=crosscheck.run(quick))


# --------------------------------------------------------------------------- report
def _met(ok: bool) -> str:
    return "yes" if ok else "no"


def markdown(result: CalibBenchResult) -> str:
    g, full = result.goals, result.full
    worst_rms = max(full.intrinsics_rms_px.max, full.extrinsics_rms_px.max)
    lines = [
        "# Calibration benchmark", "",
        provenance_markdown(result.provenance) + "  ",
        f"Seeds: {result.seeds} (each renders its own chessboard views and hemisphere presses).", "",
        "Scenes: `calibration_chessboard` (7x7 inner corners, 12 mm squares, 14-26 cm, tilts to 35°) and "
        "`calibration_hemispheres` (2x5 hemispheres, 1 mm radius, 10 x 8 mm pitch, frame jittered ±1.5 mm in x "
        "and y and ±2° in yaw between presses); truth camera fx = fy = 380 px, theta = 2°, d = 1.5 mm.", "",
        "## C. The whole calibration: 20 chessboard views + 10 presses", "",
        "| goal | measured (RMS over seeds) | worst seed | met |", "|---|---|---|---|",
        f"| theta within {g.theta_deg}° | {full.theta_err_deg.rms:.3f}° | {full.theta_err_deg.max:.3f}° "
        f"| {_met(full.theta_err_deg.max <= g.theta_deg)} |",
        f"| d within {g.d_mm} mm | {full.d_err_mm.rms:.3f} mm | {full.d_err_mm.max:.3f} mm "
        f"| {_met(full.d_err_mm.max <= g.d_mm)} |",
        f"| reprojection RMS ≤ {g.rms_px} px (intrinsics / extrinsics) | {full.intrinsics_rms_px.rms:.3f} / "
        f"{full.extrinsics_rms_px.rms:.3f} px | {full.intrinsics_rms_px.max:.3f} / {full.extrinsics_rms_px.max:.3f} px "
        f"| {_met(worst_rms <= g.rms_px)} |",
        f"| whole solve < {g.solve_s} s (CPU time) | median {full.solve_cpu_s_median:.2f} s "
        f"(wall {full.solve_s_median:.2f} s) | {full.solve_cpu_s_max:.2f} s (wall {full.solve_s_max:.2f} s) "
        f"| {_met(solve_met(full, g))} |",
        "",
        f"Seeds with both theta and d within the goals: {full.within_goals} of {result.seeds}. "
        f"The paper's plain mean of theta (no row balance) is off by {full.paper_plain_mean_theta_err_deg.rms:.3f}° "
        f"RMS (worst {full.paper_plain_mean_theta_err_deg.max:.3f}°): a frame shifted by e along y turns the "
        "picture exactly like theta does (e / 50.5 mm rad), which no pose solve can separate; the row balance "
        "measures the shift from the two rows' imprint strengths.", "",
        "| seed | theta err (°) | plain-mean theta err (°) | d err (mm) | fx err (px) | RMS intr / extr (px) "
        "| solve CPU / wall (s) |",
        "|---|---|---|---|---|---|---|",
    ]
    for r in full.runs:
        lines.append(f"| {r.seed} | {r.theta_err_deg:+.4f} | {r.paper_plain_mean_theta_err_deg:+.4f} | "
                     f"{r.d_err_mm:+.4f} | {r.fx_err_px:+.3f} | {r.intrinsics_rms_px:.3f} / "
                     f"{r.extrinsics_rms_px:.3f} | {r.cpu_seconds:.2f} / {r.seconds:.2f} |")
    lines += ["", "## A. Intrinsics against the number of chessboard views", "",
              "| views (distortion model) | fx err RMS / max (px) | cx err RMS / max (px) | cy err RMS / max (px) "
              "| reprojection RMS (px) | solve median (s) |", "|---|---|---|---|---|---|"]
    for r in result.intrinsics_vs_views:
        lines.append(f"| {r.views} ({r.distortion}) | {r.fx_err_px.rms:.3f} / {r.fx_err_px.max:.3f} | "
                     f"{r.cx_err_px.rms:.3f} / {r.cx_err_px.max:.3f} | {r.cy_err_px.rms:.3f} / {r.cy_err_px.max:.3f} | "
                     f"{r.reprojection_rms_px:.3f} | {r.solve_s_median:.3f} |")
    lines += ["", "`auto` (the default) fits k1, k2, adds p1, p2 when the fit's evidence for them pays for their two "
              "parameters (Wald statistic >= 4, Akaike's criterion) and k3 only when held-out views need it; `full` "
              "always fits all 5 coefficients, `radial` holds p1 = p2 = 0. The solve time of `auto` includes its "
              "k-fold comparison.", "",
              "d scales with the focal length (d + r = f x pitch / pixel pitch): 1 px of fx error at 380 px is "
              "0.14 mm of d, so d's accuracy is bought with chessboard views.", "",
              "## B. theta and d against the number of presses (true intrinsics)", "",
              "| presses | theta err RMS / max (°) | paper's plain mean: theta err RMS / max (°) "
              "| d err RMS / max (mm) | reprojection RMS (px) | solve median (s) |", "|---|---|---|---|---|---|"]
    for r in result.extrinsics_vs_presses:
        lines.append(f"| {r.presses} | {r.theta_err_deg.rms:.3f} / {r.theta_err_deg.max:.3f} | "
                     f"{r.paper_plain_mean_theta_err_deg.rms:.3f} / {r.paper_plain_mean_theta_err_deg.max:.3f} | "
                     f"{r.d_err_mm.rms:.4f} / {r.d_err_mm.max:.4f} | {r.reprojection_rms_px:.3f} | "
                     f"{r.solve_s_median:.3f} |")
    lines += ["", "With 2 presses the row balance cannot be fitted and the result is the plain mean (the first press "
              "is the scene's centred one); from 3 presses on it is applied when its slope is 3 standard errors "
              "from zero.", "",
              "## D. End to end: contacts located with the calibration", "",
              "`contact_localisation` (exact sensor), colour detector of `touchroller_perception.contacts`, "
              "back-projected through each camera model; error = distance to the true membrane point. "
              "The paper reports 2.63 mm at the centre and 7.66 mm on average.", "",
              "| camera model | mean (mm) | std (mm) | max (mm) | contacts |", "|---|---|---|---|---|"]
    for c in result.contacts:
        lines.append(f"| {c.camera} ({c.condition}) | {c.mean_mm:.3f} | {c.std_mm:.3f} | {c.max_mm:.3f} | {c.n} |")
    lines += ["", "## E. Robustness: the paper's sensor flaws in the calibration scenes", "",
              f"20 views + 10 presses, {result.robustness[0].theta_err_deg.n} seeds each.", "",
              "| sensor | theta err RMS / max (°) | paper's plain mean theta err RMS / max (°) | d err RMS / max (mm) "
              "| extrinsics RMS (px) |", "|---|---|---|---|---|"]
    for r in result.robustness:
        lines.append(f"| {r.sensor} | {r.theta_err_deg.rms:.3f} / {r.theta_err_deg.max:.3f} | "
                     f"{r.paper_plain_mean_theta_err_deg.rms:.3f} / {r.paper_plain_mean_theta_err_deg.max:.3f} | "
                     f"{r.d_err_mm.rms:.3f} / {r.d_err_mm.max:.3f} | {r.extrinsics_rms_px.rms:.3f} |")
    lines += ["", "A membrane whose thickness varies around the roller makes one row of hemispheres press deeper "
              "than the other even with a centred frame; the row balance reads that as a frame shift and biases "
              "theta. Nothing in the images separates the two: use a jig that centres the frame and "
              "`--no-row-balance` when the membrane is uneven.", ""]
    n = result.neglected_example
    lines += ["## F. What the paper's two-parameter model neglects (seed 0)", "",
              "Full iterative PnP pose of the nominal frame, R = Rx(theta) Ry(beta) Rz(gamma), t = (tx, ty, tz); "
              "mean ± std over the presses. gamma and tx include the frame's yaw and axial placement, which vary "
              "between presses; for a narrow frame theta and ty, and beta and tx, nearly trade off.", "",
              "| term | mean | std |", "|---|---|---|",
              f"| theta (full pose) | {n.full_theta_deg:.3f}° | {n.full_theta_std_deg:.3f}° |",
              f"| beta (about y) | {n.beta_deg:.3f}° | {n.beta_std_deg:.3f}° |",
              f"| gamma (about z) | {n.gamma_deg:.3f}° | {n.gamma_std_deg:.3f}° |",
              f"| tx | {n.tx_mm:.3f} mm | {n.tx_std_mm:.3f} mm |",
              f"| ty | {n.ty_mm:.3f} mm | {n.ty_std_mm:.3f} mm |",
              f"| tz (d) | {n.tz_mm:.3f} mm | {n.tz_std_mm:.3f} mm |", "",
              f"Reprojection RMS: full pose {n.full_rms_px:.3f} px. The two models' back-projections differ by "
              f"{n.model_error_centre_mm:.3f} mm on average in the central contact band and by at most "
              f"{n.model_error_max_mm:.3f} mm over the image: for this build the two-parameter model is good "
              "enough when that is below the contact error you need.", ""]
    lines += crosscheck.markdown(result.crosscheck)
    return "\n".join(lines)


def to_markdown(result: CalibBenchResult) -> str:
    """The report's section: the results file without its title."""
    body = markdown(result).split("\n", 2)[2]
    return body.replace("\n## ", "\n### ")          # sub-sections of the report's section


def figures(result: CalibBenchResult, out_dir: Path) -> list[Path]:
    """Accuracy against solve time (points labelled with the number of images), contact error
    against calibration effort, and the cross-check on the second renderer."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    fig, axes = plt.subplots(1, 3, figsize=(16, 4.4))
    ax = axes[0]
    rows = [r for r in result.intrinsics_vs_views if r.distortion == "auto"]
    for key, label in (("fx_err_px", "fx"), ("cx_err_px", "cx"), ("cy_err_px", "cy")):
        ax.plot([r.solve_s_median for r in rows], [getattr(r, key).rms for r in rows], "o-", label=f"{label} error RMS")
    for r in rows:
        ax.annotate(f"{r.views} views", (r.solve_s_median, r.fx_err_px.rms), fontsize=8, xytext=(3, 3),
                    textcoords="offset points")
    ax.set_xlabel("intrinsics solve, median s")
    ax.set_ylabel("error, px")
    ax.set_title("Intrinsics against chessboard views", fontsize=10)
    ax.legend(fontsize=8)
    ax.grid(alpha=0.3)
    ax = axes[1]
    presses = result.extrinsics_vs_presses
    times = [r.solve_s_median for r in presses]
    ax.plot(times, [r.theta_err_deg.rms for r in presses], "o-", label="theta, ours (row balance)")
    ax.plot(times, [r.paper_plain_mean_theta_err_deg.rms for r in presses], "s--", label="theta, paper's plain mean")
    ax.axhline(result.goals.theta_deg, color="k", lw=0.8, ls="--", label=f"goal {result.goals.theta_deg}°")
    for r in presses:
        ax.annotate(f"{r.presses} presses", (r.solve_s_median, r.theta_err_deg.rms), fontsize=8, xytext=(3, 3),
                    textcoords="offset points")
    ax.set_yscale("log")
    ax.set_xlabel("theta and d solve, median s")
    ax.set_ylabel("theta error RMS, degrees")
    ax.set_title("theta against hemisphere presses (true intrinsics)", fontsize=10)
    ax.legend(fontsize=8)
    ax.grid(alpha=0.3)
    ax = axes[2]
    exact = [c for c in result.contacts if c.condition == EXACT]
    ax.barh(np.arange(len(exact)), [c.mean_mm for c in exact], xerr=[c.std_mm for c in exact], color="tab:blue")
    ax.set_yticks(np.arange(len(exact)), [c.camera for c in exact], fontsize=8)
    ax.set_xscale("log")
    ax.set_xlabel("contact error, mean mm (log)")
    ax.set_title("Contact error against calibration (exact sensor)", fontsize=10)
    fig.tight_layout()
    path = out_dir / "calib_bench.png"
    save_figure(fig, path, dpi=110)
    plt.close(fig)
    second = out_dir / "calib_crosscheck.png"
    crosscheck.figure(result.crosscheck, second)
    return [path, second]

def load(path: Path) -> CalibBenchResult:
    """A result this bench wrote (its JSON), for the report to render without running it again."""
    result: CalibBenchResult = load_json(CalibBenchResult, path)
    return result



def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="2 seeds and fewer image counts")
    args = parser.parse_args()
    result = run(quick=args.quick)
    out = results_path("calib_bench", args.quick)
    out.parent.mkdir(parents=True, exist_ok=True)
    atomic_write_text(out, markdown(result))
    atomic_write_text(out.with_suffix(".json"), to_json(result, indent=1))
    figures(result, out.parent)
    print(markdown(result))
    return 0


if __name__ == "__main__":
    sys.exit(main())
