"""The paper's Table II (contact localisation error) in simulation: the evaluation harness.

`table_ii(quick)` reproduces the paper's contact-localisation protocol (Sec. IV-B, Table II): a
tip tapped at central angles -pi/6, -pi/12, 0, pi/12, pi/6 x axial positions 1/4, 1/2, 3/4 of the
length, each tap rendered, detected and localised, under several error conditions:

* ``exact``: true calibration, sensor noise only (the detector's own error);
* ``paper_detector``: true calibration, the paper's grey/threshold/moments pipeline;
* ``error_sources``: the three sources the paper names, at stated sizes: calibration error
  (theta, d offsets), uneven elastomer thickness (radius varying along x and alpha), detection
  noise; with our detector (and with the paper's);
* in the full run, each source alone (``theta_only``, ``d_only``, ``thickness_only``, ``noise_only``);
* with the simulator, ``our_calibration``: no injected calibration error; per seed, our calibration
  (`touchroller_perception.calibration`) runs on simulated chessboard and hemisphere images of a
  sensor with the ``paper`` variant's other flaws (uneven elastomer, noise), and that sensor's taps
  are located with the camera it found (full run: also ``our_calibration_no_row_balance``).

`explain_paper_table` fits the calibration offsets that would reproduce the paper's own numbers.

It also gives, per cell, the sensitivity of the localisation to each source (mm per degree of
theta error, per mm of d error, per pixel along u and v, per mm of radius error), computed by
finite differences through the camera model. Frames come from the simulator's
``contact_localisation`` scene, or (``source="synthetic"``) from `touchroller_driver.sim.taps.TapRenderer`.
"""
from __future__ import annotations

import dataclasses
import math
import time
from collections.abc import Callable, Mapping, Sequence
from typing import Any

import numpy as np

from touchroller_driver.sim import SimulatedSensor, load_scene
from touchroller_driver.sim.taps import TapRenderer
from touchroller_perception.contacts import Contact, ContactDetector, DetectorConfig
from touchroller_perception.geometry import CameraModel

#: The paper's Table II (mm): rows = central angle, columns = 1/4, 1/2, 3/4 of the length.
TABLE_II_ALPHAS = (-math.pi / 6, -math.pi / 12, 0.0, math.pi / 12, math.pi / 6)
TABLE_II_ALPHA_LABELS = ("-pi/6", "-pi/12", "0", "pi/12", "pi/6")
TABLE_II_FRACTIONS = (0.25, 0.5, 0.75)
PAPER_TABLE_II_MEAN = np.array([
    [9.64, 11.13, 13.75],
    [7.53, 4.50, 8.26],
    [5.00, 2.63, 6.89],
    [6.42, 4.06, 6.66],
    [8.83, 8.58, 12.34],
])
PAPER_TABLE_II_STD = np.array([
    [0.09, 0.06, 1.89],
    [0.19, 0.08, 1.46],
    [0.59, 0.74, 0.79],
    [0.32, 0.26, 0.53],
    [0.10, 0.19, 0.21],
])

#: Camera for the fallback renderer: the 640x480 webcam behind a 2.8 mm wide-angle lens. With the
#: pinhole-only default (fx = 500) the +-pi/6 taps fall outside the image, so the table uses a
#: shorter focal length with barrel distortion, which sees all 15 cells.
TABLE_II_CAMERA = CameraModel(fx=400.0, fy=400.0, distortion=(-0.2, 0.0, 0.0, 0.0, 0.0))


# --------------------------------------------------------------------------- error sources
@dataclasses.dataclass(frozen=True)
class ErrorSources:
    """Sizes of the error sources the paper names (all zero = exact calibration)."""

    theta_error: float = 0.0         # rad, calibrated minus true
    d_error: float = 0.0             # m, calibrated minus true
    thickness_amplitude: float = 0.0  # m, peak deviation of the membrane radius from nominal
    detector: str = "colour"


def membrane_radius(camera: CameraModel, x: np.ndarray, alpha: np.ndarray, amplitude: float) -> np.ndarray:
    """Uneven elastomer: radius = r + amplitude * (a smooth pattern in [-1, 1] along x and alpha)."""
    half = 0.5 * camera.length
    pattern = 0.6 * np.cos(math.pi * x / half) * np.cos(3.0 * alpha) + 0.4 * np.sin(math.pi * x / half + alpha)
    return camera.radius + amplitude * pattern


def true_tap_point(camera: CameraModel, x: float, alpha: float, thickness_amplitude: float) -> np.ndarray:
    radius = float(membrane_radius(camera, np.float64(x), np.float64(alpha), thickness_amplitude))
    return np.array([x, radius * math.sin(alpha), radius * math.cos(alpha)])


#: What the `error_sources` condition assumes (stated, not fitted): a calibration good to ~1 degree
#: and ~1 mm, and an elastomer whose thickness varies by +-0.5 mm.
PAPER_LIKE_ERRORS = ErrorSources(theta_error=math.radians(1.0), d_error=1.0e-3, thickness_amplitude=0.5e-3)

CONDITIONS: dict[str, ErrorSources] = {
    "exact": ErrorSources(),
    "paper_detector": ErrorSources(detector="paper"),
    "error_sources": PAPER_LIKE_ERRORS,
}


def sensitivities(camera: CameraModel, point: np.ndarray) -> dict[str, float]:
    """|d point| per unit error of each source at the pixel where `point` is seen (mm per unit)."""
    uv, ok = camera.project(point)
    if not ok:
        return dict.fromkeys(("mm_per_deg_theta", "mm_per_mm_d", "mm_per_px_u", "mm_per_px_v",
                              "mm_per_mm_radius"), float("nan"))
    base = camera.back_project(uv)[0]

    def moved(model: CameraModel, pixel: np.ndarray, step: float) -> float:
        return float(np.linalg.norm(model.back_project(pixel)[0] - base)) * 1e3 / step

    h_theta = math.radians(0.01)
    return {
        "mm_per_deg_theta": moved(camera.replace(theta=camera.theta + h_theta), uv, 0.01),
        "mm_per_mm_d": moved(camera.replace(d=camera.d + 1e-5), uv, 1e-2),
        "mm_per_px_u": moved(camera, uv + np.array([0.01, 0.0]), 0.01),
        "mm_per_px_v": moved(camera, uv + np.array([0.0, 0.01]), 0.01),
        "mm_per_mm_radius": moved(camera.replace(radius=camera.radius + 1e-5), uv, 1e-2),
    }


# --------------------------------------------------------------------------- Table II
def _detector_for(errors: ErrorSources, references: list[np.ndarray]) -> ContactDetector:
    config = DetectorConfig(method="paper") if errors.detector == "paper" else DetectorConfig()
    detector = ContactDetector(config)
    detector.set_reference(references)
    return detector


def _pick(contacts: list[Contact], expected_uv: np.ndarray, gate_px: float) -> Contact | None:
    """The detection nearest the expected pixel, within a gate (a tap has one contact)."""
    best = min(contacts, key=lambda c: math.hypot(c.u - expected_uv[0], c.v - expected_uv[1]), default=None)
    if best is None or math.hypot(best.u - expected_uv[0], best.v - expected_uv[1]) > gate_px:
        return None
    return best


def table_ii(quick: bool = True, taps: int | None = None, seed: int = 0, source: str = "auto",
             camera: CameraModel | None = None,
             conditions: Mapping[str, ErrorSources] | None = None,
             sim_conditions: Sequence[str] | None = None,
             calibrations: Mapping[str, CalibrateFn] | None = None,
             calibration_seeds: int | None = None) -> dict[str, Any]:
    """Reproduce Table II in simulation; returns a JSON-friendly dict (see `table_ii_markdown`).

    `source`: ``"sim"`` renders the simulator's ``contact_localisation`` scene (its ``exact`` and
    ``paper`` variants carry the error sources), ``"synthetic"`` the fallback `TapRenderer`, and
    ``"auto"`` the simulator. `quick` uses 3 taps per cell and the four main
    conditions, else 10 taps and also each error source alone.

    With the simulator, the ``our_calibration`` condition(s) (`calibrations`, default
    `OUR_CALIBRATIONS`, the first only when `quick`) calibrate a sensor with the `paper` variant's
    flaws on its simulated calibration images, per seed (`calibration_seeds`: 3 quick, 10 full),
    and locate that sensor's taps with the camera found. `sim_conditions` overrides the list of
    `SIM_CONDITIONS` to run.
    """
    if source not in ("auto", "sim", "synthetic"):
        raise ValueError(f"source must be auto, sim or synthetic, got {source!r}")
    taps = taps or (3 if quick else 10)
    if source != "synthetic" and camera is None and conditions is None:
        names = tuple(sim_conditions) if sim_conditions is not None else (
            QUICK_SIM_CONDITIONS if quick else tuple(SIM_CONDITIONS))
        if calibrations is None:
            calibrations = {n: f for n, f in OUR_CALIBRATIONS.items() if not quick or n in QUICK_OUR_CALIBRATIONS}
        seeds = calibration_seeds or (3 if quick else 10)
        if not names and not calibrations:
            raise ValueError("no condition to run")
        return _table_ii_sim(taps, seed, names, calibrations, seeds)
    return _table_ii_synthetic(taps, seed, camera, conditions)


def _empty_rows(truth_camera: CameraModel) -> list[dict[str, Any]]:
    rows = []
    for i, alpha in enumerate(TABLE_II_ALPHAS):
        for j, fraction in enumerate(TABLE_II_FRACTIONS):
            x = (fraction - 0.5) * truth_camera.length
            nominal = true_tap_point(truth_camera, x, alpha, 0.0)
            rows.append({"alpha": TABLE_II_ALPHA_LABELS[i], "alpha_rad": alpha, "fraction": fraction,
                         "paper_mean_mm": float(PAPER_TABLE_II_MEAN[i, j]),
                         "paper_std_mm": float(PAPER_TABLE_II_STD[i, j]),
                         "sensitivity": sensitivities(truth_camera, nominal)})
    return rows


def _cell_index(alpha: float, fraction: float) -> tuple[int, int]:
    i = int(np.argmin([abs(alpha - a) for a in TABLE_II_ALPHAS]))
    j = int(np.argmin([abs(fraction - f) for f in TABLE_II_FRACTIONS]))
    return i, j


def _summarise(rows: list[dict[str, Any]], errors: Mapping[str, list[list[list[float]]]],
               expected: Mapping[str, int], described: Mapping[str, dict[str, Any]]) -> dict[str, Any]:
    summary: dict[str, Any] = {}
    for name, cells in errors.items():
        means = np.full((5, 3), np.nan)
        everything: list[float] = []
        for r, row in enumerate(rows):
            i, j = divmod(r, 3)
            cell = np.asarray(cells[i][j], dtype=np.float64)
            row[name] = {"mean_mm": float(cell.mean()) if cell.size else float("nan"),
                         "std_mm": float(cell.std()) if cell.size else float("nan"), "n": int(cell.size)}
            if cell.size:
                means[i, j] = cell.mean()
                everything.extend(cell.tolist())
        summary[name] = {
            "mean_mm": float(np.mean(everything)) if everything else float("nan"),
            "max_cell_mean_mm": float(np.nanmax(means)) if np.isfinite(means).any() else float("nan"),
            "centre_mean_mm": float(means[2, 1]), "detected": len(everything), "taps": int(expected[name]),
            "max_tap_mm": float(np.max(everything)) if everything else float("nan"),
            "errors": described[name],
        }
    summary["paper"] = {"mean_mm": float(PAPER_TABLE_II_MEAN.mean()), "centre_mean_mm": 2.63}
    return summary


def _new_cells() -> list[list[list[float]]]:
    return [[[] for _ in TABLE_II_FRACTIONS] for _ in TABLE_II_ALPHAS]


#: Simulator conditions: name -> (scene variant, scene overrides, detector). The `paper` variant's
#: error sizes are the scene's (1 deg, 0.5 mm, +-0.3 mm thickness, noise 3); the single-source rows
#: apply one of them at a time to the exact variant, to split the error budget.
SIM_CONDITIONS: dict[str, tuple[str, dict[str, Any], str]] = {
    "exact": ("exact", {}, "colour"),
    "paper_detector": ("exact", {}, "paper"),
    "theta_only": ("exact", {"calibration_error.theta": math.radians(1.0)}, "colour"),
    "d_only": ("exact", {"calibration_error.d": 0.5e-3}, "colour"),
    "thickness_only": ("exact", {"sensor.thickness_variation": 0.3e-3}, "colour"),
    "noise_only": ("exact", {"effect_params.noise.sigma": 3.0}, "colour"),
    "error_sources": ("paper", {}, "colour"),
    "error_sources_paper_detector": ("paper", {}, "paper"),
}
QUICK_SIM_CONDITIONS = ("exact", "paper_detector", "error_sources", "error_sources_paper_detector")


def _detected_taps(scene: Any, seed: int, method: str) -> tuple[list[tuple[int, int, np.ndarray, np.ndarray]], int]:
    """Render a `contact_localisation` scene and detect its taps: [(cell row, cell column, detected
    pixel, true membrane point)] for the taps found near their true pixel, and how many taps were visible."""

    sensor = SimulatedSensor(scene, seed=seed)
    truth_camera = scene.camera
    config = DetectorConfig(method="paper") if method == "paper" else DetectorConfig()
    detector = ContactDetector(config, reference_frames=int(scene.motion.get("reference_frames", 5)))
    found_taps: list[tuple[int, int, np.ndarray, np.ndarray]] = []
    count = 0
    for frame in sensor.frames():
        found = detector.process(frame.image)
        if frame.truth.get("phase") != "tap":
            continue
        for truth in frame.truth["contacts"]:
            pixel = np.asarray(truth["pixel"], dtype=np.float64)
            if not np.isfinite(pixel).all() or not truth_camera.in_image(pixel, margin=5):
                continue
            count += 1
            contact = _pick(found or [], pixel, gate_px=25.0)
            if contact is not None:
                i, j = _cell_index(truth["alpha"], truth["position_fraction"])
                point = np.asarray(truth["point"], dtype=np.float64)
                found_taps.append((i, j, np.array([contact.u, contact.v]), point))
    return found_taps, count


def _tap_errors(taps: Sequence[tuple[int, int, np.ndarray, np.ndarray]], camera: CameraModel,
                cells: list[list[list[float]]] | None = None) -> list[list[list[float]]]:
    """Back-project the detected taps through `camera`; errors (mm) appended to `cells` per cell."""
    cells = cells if cells is not None else _new_cells()
    for i, j, uv, truth_point in taps:
        point, valid = camera.back_project(uv)
        if valid:
            cells[i][j].append(1e3 * float(np.linalg.norm(point - truth_point)))
    return cells


def _table_ii_sim(taps: int, seed: int, names: Sequence[str],
                  calibrations: Mapping[str, CalibrateFn] | None = None, calibration_seeds: int = 3) -> dict[str, Any]:

    start = time.perf_counter()
    errors: dict[str, list[list[list[float]]]] = {}
    expected: dict[str, int] = {}
    described: dict[str, dict[str, Any]] = {}
    rows: list[dict[str, Any]] | None = None
    scene_info: dict[str, Any] = {}
    detections: dict[tuple[str, str, int], tuple[list, int]] = {}     # (variant, detector, seed) -> taps
    for name in names:
        variant, overrides, method = SIM_CONDITIONS[name]
        scene = load_scene("contact_localisation", variant=variant, **{"motion.repeats": taps, **overrides})
        truth_camera, calibrated = scene.camera, scene.paper_camera
        if rows is None:
            rows = _empty_rows(truth_camera)
        found, count = _detected_taps(scene, seed, method)
        if not overrides:
            detections[(variant, method, seed)] = (found, count)
        errors[name], expected[name] = _tap_errors(found, calibrated), count
        described[name] = {"detector": method, "variant": variant + (" + " + ", ".join(
                               f"{k}={v:g}" for k, v in overrides.items()) if overrides else ""),
                           **_scene_errors(scene)}
        scene_info = {"camera": truth_camera.to_params(), "effects": list(scene.effects)}
    if calibrations:
        scene = load_scene("contact_localisation", variant=OUR_CALIBRATION_VARIANT, **{"motion.repeats": taps})
        if rows is None:
            rows = _empty_rows(scene.camera)
            scene_info = {"camera": scene.camera.to_params(), "effects": list(scene.effects)}
        for name, calibrated_errors in _our_calibration(scene, taps, seed, calibration_seeds, calibrations,
                                                        detections).items():
            errors[name], expected[name], described[name] = calibrated_errors
    assert rows is not None
    summary = _summarise(rows, errors, expected, described)
    for name in calibrations or {}:
        per_seed = described[name]["calibration"]["per_seed"]
        summary[name]["worst_seed_max_cell_mean_mm"] = max(s["max_cell_mean_mm"] for s in per_seed)
    return {"rows": rows, "summary": summary, "taps_per_cell": taps, "seed": seed,
            "source": "touchroller_driver.sim scene contact_localisation (variants exact, paper)",
            "camera": scene_info["camera"], "effects": scene_info["effects"],
            "seconds": time.perf_counter() - start}


def _scene_errors(scene: Any) -> dict[str, float]:
    """The error sources a `contact_localisation` scene carries (what its `paper_camera` gets wrong,
    its elastomer's thickness variation and its sensor noise)."""
    cal_err = scene.data.get("calibration_error") or {}
    return {"theta_error": float(cal_err.get("theta", 0.0)), "d_error": float(cal_err.get("d", 0.0)),
            "thickness_amplitude": float(scene.sensor.get("thickness_variation", 0.0)),
            "noise_sigma": float(scene.effect_params("noise").get("sigma", 0.0)) if "noise" in scene.effects else 0.0}


# --------------------------------------------------------------------------- our calibration in the loop
#: Calibration images per seed: as `bench/calib_bench.py` table C (20 chessboard views, 10 presses).
OUR_CALIBRATION_VIEWS = 20
OUR_CALIBRATION_PRESSES = 10
#: The scene variant whose sensor flaws (uneven elastomer, noise) stay on; its injected calibration
#: error is NOT used: the taps are back-projected with the camera our calibration found.
OUR_CALIBRATION_VARIANT = "paper"

#: (chessboard images, hemisphere reference image, hemisphere press images) -> calibrated camera
CalibrateFn = Callable[[list[np.ndarray], np.ndarray, list[np.ndarray]], CameraModel]


def calibrate_with_ours(chessboard: list[np.ndarray], reference: np.ndarray, presses: list[np.ndarray],
                        balance_rows: bool = True) -> CameraModel:
    """`touchroller_perception.calibration` as `touchroller calibrate` runs it: intrinsics from the
    chessboard, then theta and d from the hemisphere presses (started at theta = d = 0)."""
    from touchroller_perception import calibration as cal

    intrinsics = cal.calibrate_intrinsics(chessboard)
    start = intrinsics.camera.replace(theta=0.0, d=0.0)
    config = cal.ExtrinsicsConfig(balance_rows=balance_rows)
    return cal.calibrate_extrinsics(presses, start, config, reference=reference,
                                    intrinsics_covariance=intrinsics.covariance).camera


def _without_row_balance(chessboard: list[np.ndarray], reference: np.ndarray, presses: list[np.ndarray]) -> CameraModel:
    return calibrate_with_ours(chessboard, reference, presses, balance_rows=False)


#: name -> calibration. The quick run has the default (row balance on) only.
OUR_CALIBRATIONS: dict[str, CalibrateFn] = {"our_calibration": calibrate_with_ours,
                                            "our_calibration_no_row_balance": _without_row_balance}
QUICK_OUR_CALIBRATIONS = ("our_calibration",)


def render_calibration_images(
        seed: int, sensor_overrides: Mapping[str, Any], views: int = OUR_CALIBRATION_VIEWS,
        presses: int = OUR_CALIBRATION_PRESSES) -> tuple[list[np.ndarray], np.ndarray, list[np.ndarray], CameraModel]:
    """The simulator's calibration scenes for one sensor: (chessboard views, median hemisphere
    reference, hemisphere presses, true camera). Both scenes use `seed`, which also draws the
    elastomer's thickness pattern, so a tap scene rendered with the same seed has the same membrane."""

    board_scene = load_scene("calibration_chessboard", **{"motion.views": views, **sensor_overrides})
    board = SimulatedSensor(board_scene, seed=seed)
    chessboard = [f.image for f in board.frames()]
    frame = SimulatedSensor(load_scene("calibration_hemispheres", **{"motion.presses": presses, **sensor_overrides}),
                            seed=seed)
    frames = list(frame.frames())
    references = [f.image for f in frames if f.truth.get("phase") == "reference"]
    pressed = [f.image for f in frames if f.truth.get("phase") == "press"]
    if board.camera != frame.camera:
        raise ValueError("the calibration scenes disagree on the true camera")
    return chessboard, np.median(np.stack(references), axis=0).astype(np.uint8), pressed, frame.camera


def _our_calibration(
        scene: Any, taps: int, seed: int, seeds: int, calibrations: Mapping[str, CalibrateFn],
        detections: dict[tuple[str, str, int], tuple[list, int]]) -> dict[str, tuple[Any, int, dict[str, Any]]]:
    """Per seed: calibrate on the simulated calibration images of a sensor with the scene's flaws,
    then locate that sensor's taps (same seed, same membrane) with the camera each calibration found."""
    flaws = _scene_errors(scene)
    overrides = {"sensor.thickness_variation": flaws["thickness_amplitude"]}
    if "noise" in scene.effects:
        overrides["effect_params.noise.sigma"] = flaws["noise_sigma"]
    cells = {name: _new_cells() for name in calibrations}
    runs: dict[str, list[dict[str, Any]]] = {name: [] for name in calibrations}
    count = 0
    for k in range(seeds):
        chessboard, reference, presses, truth = render_calibration_images(seed + k, overrides)
        if truth != scene.camera:
            raise ValueError("the calibration scenes' true camera is not the contact scene's")
        key = (OUR_CALIBRATION_VARIANT, "colour", seed + k)
        found, seen = detections.get(key) or _detected_taps(scene, seed + k, "colour")
        count += seen
        for name, calibrate in calibrations.items():
            camera = calibrate(chessboard, reference, presses)
            seed_cells = _tap_errors(found, camera)
            means = np.array([[np.mean(c) if c else np.nan for c in row] for row in seed_cells])
            for i, row in enumerate(seed_cells):
                for j, cell in enumerate(row):
                    cells[name][i][j].extend(cell)
            runs[name].append({
                "seed": seed + k, "theta_err_deg": math.degrees(camera.theta - truth.theta),
                "d_err_mm": 1e3 * (camera.d - truth.d), "fx_err_px": camera.fx - truth.fx,
                "cx_err_px": camera.cx - truth.cx, "cy_err_px": camera.cy - truth.cy,
                "mean_mm": float(np.mean([e for row in seed_cells for c in row for e in c])),
                "max_cell_mean_mm": float(np.nanmax(means)) if np.isfinite(means).any() else float("nan")})
    out = {}
    for name in calibrations:
        theta = np.array([r["theta_err_deg"] for r in runs[name]])
        d = np.array([r["d_err_mm"] for r in runs[name]])
        described = {"detector": "colour", "variant": OUR_CALIBRATION_VARIANT + " (its calibration error not used)",
                     **flaws, "theta_error": 0.0, "d_error": 0.0,
                     "calibration": {
                         "method": name, "views": OUR_CALIBRATION_VIEWS, "presses": OUR_CALIBRATION_PRESSES,
                         "seeds": seeds, "per_seed": runs[name],
                         "theta_err_deg": {"rms": float(np.sqrt(np.mean(theta**2))), "max": float(np.abs(theta).max())},
                         "d_err_mm": {"rms": float(np.sqrt(np.mean(d**2))), "max": float(np.abs(d).max())}}}
        out[name] = (cells[name], count, described)
    return out


def _table_ii_synthetic(taps: int, seed: int, camera: CameraModel | None,
                        conditions: Mapping[str, ErrorSources] | None) -> dict[str, Any]:
    start = time.perf_counter()
    truth_camera = camera or TABLE_II_CAMERA
    conditions = dict(conditions or CONDITIONS)
    renderer = TapRenderer(truth_camera, seed=seed)
    rng = np.random.default_rng(seed)
    references = [renderer.render([], rng) for _ in range(5)]
    rows = _empty_rows(truth_camera)
    errors: dict[str, list[list[list[float]]]] = {}
    expected: dict[str, int] = {}
    for name, sources in conditions.items():
        calibrated = truth_camera.replace(theta=truth_camera.theta + sources.theta_error,
                                          d=truth_camera.d + sources.d_error)
        detector = _detector_for(sources, references)
        cells, count = _new_cells(), 0
        for i, alpha in enumerate(TABLE_II_ALPHAS):
            for j, fraction in enumerate(TABLE_II_FRACTIONS):
                x = (fraction - 0.5) * truth_camera.length
                truth = true_tap_point(truth_camera, x, alpha, sources.thickness_amplitude)
                uv, ok = truth_camera.project(truth)
                if not ok or not truth_camera.in_image(uv, margin=10):
                    continue
                for _ in range(taps):
                    count += 1
                    contact = _pick(detector.detect(renderer.render([uv], rng)), uv, gate_px=40.0)
                    if contact is None:
                        continue
                    point, valid = calibrated.back_project(np.array([contact.u, contact.v]))
                    if valid:
                        cells[i][j].append(1e3 * float(np.linalg.norm(point - truth)))
        errors[name], expected[name] = cells, count
    described = {name: dataclasses.asdict(sources) for name, sources in conditions.items()}
    summary = _summarise(rows, errors, expected, described)
    return {"rows": rows, "summary": summary, "taps_per_cell": taps, "seed": seed,
            "source": "touchroller_driver.sim.taps.TapRenderer",
            "camera": truth_camera.to_params(), "rendering": dataclasses.asdict(renderer.settings),
            "seconds": time.perf_counter() - start}


def table_ii_markdown(result: Mapping[str, Any], command: str = "") -> str:
    """The Table II result as Markdown: per-cell mean +- std beside the paper, then sensitivities."""
    names = [n for n in result["summary"] if n != "paper"]
    lines = ["# Contact localisation: the paper's Table II in simulation", ""]
    if command:
        lines += [f"Command: `{command}`", ""]
    lines += [f"Frames: {result['source']}, {result['taps_per_cell']} taps per cell, seed {result['seed']}.",
              f"Camera: `{dict(result['camera'])}`.", ""]
    for name in names:
        lines.append(f"- **{name}**: {_describe(result['summary'][name]['errors'])}")
    lines += ["", "### Euclidean error, mm (mean ± std per cell)", "",
              "| angle | position | paper | " + " | ".join(names) + " |",
              "|---|---|---|" + "---|" * len(names)]
    for row in result["rows"]:
        cells = [f"{row[n]['mean_mm']:.3f} ± {row[n]['std_mm']:.3f}" if row[n]["n"] else "not seen"
                 for n in names]
        lines.append(f"| {row['alpha']} | {row['fraction']:g} L | {row['paper_mean_mm']:.2f} ± "
                     f"{row['paper_std_mm']:.2f} | " + " | ".join(cells) + " |")
    lines += ["", "| summary | paper | " + " | ".join(names) + " |", "|---|---|" + "---|" * len(names)]
    summary = result["summary"]
    means = " | ".join(f"{summary[n]['mean_mm']:.3f}" for n in names)
    lines.append(f"| mean over all taps, mm | 7.66 | {means} |")
    lines.append("| centre cell (0, 1/2 L), mm | 2.63 | "
                 + " | ".join(f"{summary[n]['centre_mean_mm']:.3f}" for n in names) + " |")
    lines.append("| worst cell mean, mm | 13.75 | "
                 + " | ".join(f"{summary[n]['max_cell_mean_mm']:.3f}" for n in names) + " |")
    lines.append("| worst single tap, mm | - | "
                 + " | ".join(f"{summary[n].get('max_tap_mm', float('nan')):.3f}" for n in names) + " |")
    lines.append("| taps detected | - | " + " | ".join(f"{summary[n]['detected']}/{summary[n]['taps']}"
                                                       for n in names) + " |")
    lines += _calibration_markdown(result)
    lines += ["", "### Sensitivity of the localised point to each error source", "",
              "| angle | position | mm per deg theta | mm per mm d | mm per px u | mm per px v | mm per mm radius |",
              "|---|---|---|---|---|---|---|"]
    for row in result["rows"]:
        s = row["sensitivity"]
        lines.append(f"| {row['alpha']} | {row['fraction']:g} L | {s['mm_per_deg_theta']:.3f} | {s['mm_per_mm_d']:.3f} "
                     f"| {s['mm_per_px_u']:.4f} | {s['mm_per_px_v']:.4f} | {s['mm_per_mm_radius']:.3f} |")
    return "\n".join(lines) + "\n"


def _calibration_markdown(result: Mapping[str, Any]) -> list[str]:
    """Per seed of each our-calibration condition: what the calibration got wrong and what it cost."""
    lines: list[str] = []
    for name, summary in result["summary"].items():
        calibration = summary.get("errors", {}).get("calibration") if name != "paper" else None
        if not calibration:
            continue
        lines += ["", f"### `{name}`: the calibration each seed found, and its Table II", "",
                  f"Worst cell over the pooled taps: **{summary['max_cell_mean_mm']:.3f} mm**; worst cell of any "
                  f"single seed: {summary['worst_seed_max_cell_mean_mm']:.3f} mm.", "",
                  "| seed | theta err (deg) | d err (mm) | fx err (px) | cx err (px) | cy err (px) | mean (mm) "
                  "| worst cell (mm) |", "|---|---|---|---|---|---|---|---|"]
        for r in calibration["per_seed"]:
            lines.append(f"| {r['seed']} | {r['theta_err_deg']:+.4f} | {r['d_err_mm']:+.4f} | {r['fx_err_px']:+.3f} "
                         f"| {r['cx_err_px']:+.3f} | {r['cy_err_px']:+.3f} | {r['mean_mm']:.3f} "
                         f"| {r['max_cell_mean_mm']:.3f} |")
    return lines


def _describe(errors: Mapping[str, Any]) -> str:
    parts = [f"detector `{errors['detector']}`"]
    if errors.get("variant"):
        parts.append(f"scene variant `{errors['variant']}`")
    calibration = errors.get("calibration")
    if calibration:
        parts.append(f"camera from our calibration ({calibration['views']} chessboard views + "
                     f"{calibration['presses']} hemisphere presses on the same flawed sensor, "
                     f"{'row balance off' if 'no_row_balance' in calibration['method'] else 'default settings'}), "
                     f"recalibrated for each of {calibration['seeds']} seeds: theta error "
                     f"{calibration['theta_err_deg']['rms']:.3f} deg RMS "
                     f"(worst {calibration['theta_err_deg']['max']:.3f}), "
                     f"d error {calibration['d_err_mm']['rms']:.3f} mm RMS "
                     f"(worst {calibration['d_err_mm']['max']:.3f})")
    if errors["theta_error"]:
        parts.append(f"theta error {math.degrees(errors['theta_error']):.2f} deg")
    if errors["d_error"]:
        parts.append(f"d error {errors['d_error'] * 1e3:.2f} mm")
    if errors["thickness_amplitude"]:
        parts.append(f"elastomer thickness ±{errors['thickness_amplitude'] * 1e3:.2f} mm")
    if errors.get("noise_sigma"):
        parts.append(f"sensor noise std {errors['noise_sigma']:g} grey levels")
    if not (errors["theta_error"] or errors["d_error"] or errors["thickness_amplitude"] or calibration):
        parts.append("exact calibration, uniform elastomer")
    return ", ".join(parts)


#: Calibration parameters `explain_paper_table` fits, with bounds (rad, m, px).
PAPER_FIT_BOUNDS = {"theta": (-0.5, 0.5), "d": (-0.03, 0.03), "cx": (-100.0, 100.0), "cy": (-100.0, 100.0)}


def explain_paper_table(camera: CameraModel, names: Sequence[str] = ("theta", "d", "cx", "cy"),
                        starts: int = 20, seed: int = 0) -> dict[str, Any]:
    """Which calibration errors would reproduce the paper's 15 cell means with a perfect detector?

    Least-squares fit (scipy, multi-start, bounded) of offsets of `names` between the true camera
    and the one used for back-projection, to the paper's Table II means. A diagnostic, not a claim:
    a few parameters fitted to 15 numbers; the residual says how much the pattern is left unexplained.
    """
    from scipy.optimize import least_squares

    points = np.array([camera.surface_point((f - 0.5) * camera.length, a)
                       for a in TABLE_II_ALPHAS for f in TABLE_II_FRACTIONS])
    pixels, seen = camera.project(points)
    if not seen.all():
        raise ValueError("the camera does not see all 15 Table II cells")
    target = PAPER_TABLE_II_MEAN.ravel()
    lower = np.array([PAPER_FIT_BOUNDS[n][0] for n in names])
    upper = np.array([PAPER_FIT_BOUNDS[n][1] for n in names])

    def errors_mm(offsets: np.ndarray) -> np.ndarray:
        model = camera.replace(**{n: getattr(camera, n) + float(v) for n, v in zip(names, offsets, strict=True)})
        located, ok = model.back_project(pixels)
        return np.where(ok, 1e3 * np.linalg.norm(located - points, axis=1), 100.0)

    rng = np.random.default_rng(seed)
    best = None
    for _ in range(starts):
        start = rng.uniform(lower, upper) * 0.2
        fit = least_squares(lambda p: errors_mm(p) - target, start, bounds=(lower, upper))
        if best is None or fit.cost < best.cost:
            best = fit
    predicted = errors_mm(best.x)
    return {"offsets": {n: float(v) for n, v in zip(names, best.x, strict=True)},
            "at_bound": [n for n, v, lo, hi in zip(names, best.x, lower, upper, strict=True)
                         if min(v - lo, hi - v) < 1e-3 * (hi - lo)],
            "predicted_mm": predicted.reshape(5, 3).tolist(),
            "rms_residual_mm": float(np.sqrt(np.mean((predicted - target) ** 2)))}


def explain_markdown(fit: Mapping[str, Any]) -> str:
    offsets = fit["offsets"]
    parts = []
    for name, value in offsets.items():
        parts.append(f"{name} {math.degrees(value):+.2f} deg" if name == "theta" else
                     f"{name} {value * 1e3:+.2f} mm" if name == "d" else f"{name} {value:+.1f} px")
    lines = ["### What would explain the paper's numbers", "",
             "Least-squares fit of calibration offsets (true camera vs the one used to back-project) to the "
             "paper's 15 cell means, with a perfect detector: " + ", ".join(parts)
             + f"; RMS residual {fit['rms_residual_mm']:.2f} mm"
             + (f" (at the fit's bound: {', '.join(fit['at_bound'])})" if fit["at_bound"] else "") + ".", "",
             "| angle | 1/4 L fit (paper) | 1/2 L fit (paper) | 3/4 L fit (paper) |", "|---|---|---|---|"]
    for i, label in enumerate(TABLE_II_ALPHA_LABELS):
        cells = [f"{fit['predicted_mm'][i][j]:.2f} ({PAPER_TABLE_II_MEAN[i, j]:.2f})" for j in range(3)]
        lines.append(f"| {label} | " + " | ".join(cells) + " |")
    return "\n".join(lines) + "\n"
