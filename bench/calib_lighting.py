"""The whole calibration under light from one side: both renderers x 4 light azimuths x seeds.

A GelSight-type membrane lit by directional LEDs shades every imprint bright on one side and dark on
the other, and its light falls off across the membrane. Each trial is the whole calibration with
its defaults, as a user runs it: intrinsics from chessboard views (boards in the central half of
the image), then theta and d from 10 presses lit by one LED from the azimuth of the row (0: from +u
along the roller axis, 90: from +v around it), with a no-contact reference and a frame with the
sensor's light off (the documented capture, as in `bench.calib_crosscheck`). The same presses are
also solved without the lights-off frame, as a user without one runs it: the rows' strengths are then
the imprints' extent (`ImprintDetectorConfig.strength` "auto"), which a background the light does not
make (the second renderer's uneven gel and ambient light) cannot reach, where the energy relative to
the whole reference would have that background divided into it.

Press sets:
* simulator: `calibration_hemispheres` with `sensor.directional_light_deg` (one white LED at 25 deg
  elevation, frame moved up to 1.5 mm between presses);
* second renderer: `bench.second_renderer` with `Look.light_azimuth_deg` (its own code: Hertzian
  imprints, LED at 35 deg, frame placed by hand within +-1 mm);
* second renderer, frame centred: the frame within +-0.2 mm and pressed +-0.15 mm deeper or
  shallower, the LED low at 15 deg (the issue's case: the rows' strengths follow the depth and the
  light, not the placement, so a row balance fitted on them moves theta away from the truth).

Per trial: theta's and d's errors, whether the calibration refused (and whether the paper's plain
method solves the same set), the terms held-out prediction chose and their margins, and whether the
truth lies within 2 sigma. `python -m bench.calib_lighting [--quick]` writes
bench/results/calib_lighting.{md,json}.
"""
from __future__ import annotations

import argparse
import dataclasses
import json
import math
import sys
from collections.abc import Callable, Sequence
from pathlib import Path

import numpy as np

from bench import calib_crosscheck as crosscheck
from bench import second_renderer as second
from bench._common import Provenance, provenance, provenance_markdown, results_path, write_results
from touchroller_perception import calibration as cal

TITLE = "Calibration under light from one side"
AZIMUTHS = (0.0, 90.0, 180.0, 270.0)
SIMULATOR, SECOND, CENTRED = "simulator", "second renderer", "second renderer, frame centred, LED at 15°"
RENDERERS = (SIMULATOR, SECOND, CENTRED)
#: the chessboard views of each press set's renderer
BOARD_RENDERER = {SIMULATOR: "simulator", SECOND: "second renderer", CENTRED: "second renderer"}
GOALS = {"theta_deg": 0.1, "d_mm": 0.05, "within_2_sigma": 0.95}


@dataclasses.dataclass(frozen=True)
class Trial:
    renderer: str
    azimuth_deg: float
    seed: int
    refused: str                  # the one-line reason, "" when it calibrated
    plain_solves: bool            # the paper's plain method solves the same set
    theta_err_deg: float          # NaN when refused
    d_err_mm: float
    theta_sigma_deg: float
    d_sigma_mm: float
    plain_theta_err_deg: float    # the paper's plain mean over the same views
    theta_err_no_dark_deg: float  # the same presses without the lights-off frame (NaN when refused)
    d_err_no_dark_mm: float
    method: str
    row_balance_kept: bool
    balance_margin_px: float
    balance_spread_px: float
    rejection_kept: bool
    choices: tuple[str, ...]
    theta_sigma_no_dark_deg: float = math.nan   # the sigmas the calibration gives without the lights-off frame
    d_sigma_no_dark_mm: float = math.nan


@dataclasses.dataclass(frozen=True)
class Cell:
    renderer: str
    azimuth_deg: float
    trials: int
    refused: int
    theta_worst_deg: float
    d_worst_mm: float
    plain_theta_worst_deg: float
    theta_worst_no_dark_deg: float
    balance_kept: int
    margin_median_px: float
    spread_median_px: float
    within_2_sigma: float         # share of theta and d errors within 2 sigma
    within_2_sigma_no_dark: float  # the same without the lights-off frame


@dataclasses.dataclass(frozen=True)
class LightingResult:
    provenance: Provenance
    quick: bool
    seeds: int
    views: int
    trials: tuple[Trial, ...]

    def cells(self) -> list[Cell]:
        out = []
        for renderer in RENDERERS:
            for azimuth in AZIMUTHS:
                rows = [t for t in self.trials if t.renderer == renderer and t.azimuth_deg == azimuth]
                if rows:
                    out.append(_cell(renderer, azimuth, rows))
        return out

    def solved(self, renderers: Sequence[str] = RENDERERS) -> list[Trial]:
        return [t for t in self.trials if not t.refused and t.renderer in renderers]

    def theta_worst(self, renderers: Sequence[str] = RENDERERS) -> float:
        return max((abs(t.theta_err_deg) for t in self.solved(renderers)), default=math.inf)

    def d_worst(self, renderers: Sequence[str] = RENDERERS) -> float:
        return max((abs(t.d_err_mm) for t in self.solved(renderers)), default=math.inf)

    def theta_worst_no_dark(self, renderers: Sequence[str] = RENDERERS) -> float:
        """The same presses without the lights-off frame (a set that then refuses counts as infinitely off)."""
        return max((abs(t.theta_err_no_dark_deg) if math.isfinite(t.theta_err_no_dark_deg) else math.inf
                    for t in self.solved(renderers)), default=math.inf)

    def d_worst_no_dark(self, renderers: Sequence[str] = RENDERERS) -> float:
        return max((abs(t.d_err_no_dark_mm) if math.isfinite(t.d_err_no_dark_mm) else math.inf
                    for t in self.solved(renderers)), default=math.inf)

    def refusals_where_plain_solves(self) -> int:
        return sum(1 for t in self.trials if t.refused and t.plain_solves)

    def within_2_sigma(self, no_dark: bool = False) -> tuple[float, int]:
        """The share of theta and d errors within 2 of the sigmas the calibration gives, and how many."""
        hits = [abs(e) <= 2 * s for t in self.solved() for e, s in _errors_and_sigmas(t, no_dark)
                if math.isfinite(e) and math.isfinite(s)]
        return (float(np.mean(hits)) if hits else math.nan), len(hits)

    def met(self) -> bool:
        return (self.theta_worst() <= GOALS["theta_deg"] and self.d_worst() <= GOALS["d_mm"]
                and self.theta_worst_no_dark() <= GOALS["theta_deg"] and self.d_worst_no_dark() <= GOALS["d_mm"]
                and self.refusals_where_plain_solves() == 0 and not any(t.refused for t in self.trials))


def _cell(renderer: str, azimuth: float, rows: list[Trial]) -> Cell:
    solved = [t for t in rows if not t.refused]
    hits = [abs(e) <= 2 * s for t in solved for e, s in _errors_and_sigmas(t, False)]
    hits_no_dark = [abs(e) <= 2 * s for t in solved for e, s in _errors_and_sigmas(t, True)
                    if math.isfinite(e) and math.isfinite(s)]
    margins = [t.balance_margin_px for t in solved if math.isfinite(t.balance_margin_px)]
    spreads = [t.balance_spread_px for t in solved if math.isfinite(t.balance_spread_px)]
    return Cell(renderer, azimuth, len(rows), len(rows) - len(solved),
                max((abs(t.theta_err_deg) for t in solved), default=math.nan),
                max((abs(t.d_err_mm) for t in solved), default=math.nan),
                max((abs(t.plain_theta_err_deg) for t in solved), default=math.nan),
                max((abs(t.theta_err_no_dark_deg) for t in solved), default=math.nan),
                sum(t.row_balance_kept for t in solved),
                float(np.median(margins)) if margins else math.nan, float(np.median(spreads)) if spreads else math.nan,
                float(np.mean(hits)) if hits else math.nan,
                float(np.mean(hits_no_dark)) if hits_no_dark else math.nan)


def _errors_and_sigmas(t: Trial, no_dark: bool) -> tuple[tuple[float, float], tuple[float, float]]:
    if no_dark:
        return (t.theta_err_no_dark_deg, t.theta_sigma_no_dark_deg), (t.d_err_no_dark_mm, t.d_sigma_no_dark_mm)
    return (t.theta_err_deg, t.theta_sigma_deg), (t.d_err_mm, t.d_sigma_mm)


def simulator_presses(seed: int, azimuth: float, presses: int = 10) -> crosscheck.Presses:
    from touchroller_driver.sim import SimulatedSensor, load_scene

    def references(**overrides: float) -> tuple[SimulatedSensor, list, np.ndarray]:
        scene = load_scene("calibration_hemispheres", **{"motion.presses": presses,
                                                         "sensor.directional_light_deg": azimuth, **overrides})
        sensor = SimulatedSensor(scene, seed=seed)
        frames = list(sensor.frames())
        reference = np.median(np.stack([f.image for f in frames if f.truth.get("phase") == "reference"]), axis=0)
        return sensor, frames, reference.astype(np.uint8)

    sensor, frames, reference = references()
    # the LED off: its light and the gel's glow it makes are gone, the gel's own background stays
    _, _, dark = references(**{"sensor.light_gain": 0.0, "sensor.ambient": 0.0, "motion.presses": 0})
    pressed = [f for f in frames if f.truth.get("phase") == "press"]
    return crosscheck.Presses(reference, [f.image for f in pressed],
                              [np.array([c["pixel"] for c in f.truth["contacts"]]) for f in pressed], sensor.camera,
                              dark)


def second_presses(seed: int, azimuth: float, presses: int = 10, centred: bool = False) -> crosscheck.Presses:
    look = dataclasses.replace(second.Look(), light_azimuth_deg=azimuth,
                               **({"light_elevation_deg": 15.0} if centred else {}))
    placement = second.Placement(shift=2e-4, depth_jitter=1.5e-4) if centred else second.Placement()
    rendered = second.render_presses(seed, presses, look=look, placement=placement)
    return crosscheck.Presses(rendered.reference, rendered.images, [t.centres_px for t in rendered.truth],
                              rendered.camera, rendered.dark)


PRESSES: dict[str, Callable[[int, float], crosscheck.Presses]] = {
    SIMULATOR: simulator_presses, SECOND: second_presses,
    CENTRED: lambda seed, azimuth: second_presses(seed, azimuth, centred=True)}


def trial(renderer: str, azimuth: float, seed: int, presses: crosscheck.Presses,
          intrinsics: cal.IntrinsicsResult) -> Trial:
    """The extrinsics with their defaults after `intrinsics`, against the truth."""
    start = intrinsics.camera.replace(theta=0.0, d=0.0)
    truth = presses.camera
    try:
        result = cal.calibrate_extrinsics(presses.images, start, reference=presses.reference, dark=presses.dark,
                                          intrinsics_covariance=intrinsics.covariance)
    except cal.CalibrationError as exc:
        plain = cal.ExtrinsicsConfig(balance_rows=False, view_rms_k=1e9, outlier_sigma=1e9,
                                     plausibility=cal.Plausibility(1.0, math.pi / 2, 1e9))
        try:
            cal.calibrate_extrinsics(presses.images, start, plain, reference=presses.reference)
            plain_solves = True
        except cal.CalibrationError:
            plain_solves = False
        nan = math.nan
        return Trial(renderer, azimuth, seed, str(exc), plain_solves, nan, nan, nan, nan, nan, nan, nan, "", False,
                     nan, nan, False, ())
    try:
        no_dark = cal.calibrate_extrinsics(presses.images, start, reference=presses.reference,
                                           intrinsics_covariance=intrinsics.covariance)
        theta_no_dark, d_no_dark = math.degrees(no_dark.theta - truth.theta), 1e3 * (no_dark.d - truth.d)
        sigmas_no_dark = math.degrees(no_dark.theta_sigma), 1e3 * no_dark.d_sigma
    except cal.CalibrationError:
        theta_no_dark = d_no_dark = math.nan
        sigmas_no_dark = math.nan, math.nan
    balance = next(c for c in result.choices if c.term == "row balance")
    rejection = next(c for c in result.choices if c.term == "view rejection")
    return Trial(renderer, azimuth, seed, "", True,
                 math.degrees(result.theta - truth.theta), 1e3 * (result.d - truth.d),
                 math.degrees(result.theta_sigma), 1e3 * result.d_sigma,
                 math.degrees(result.theta_plain_mean - truth.theta), theta_no_dark, d_no_dark, result.method,
                 balance.kept,
                 balance.margin_px, balance.spread_px, rejection.kept, tuple(c.line() for c in result.choices),
                 *sigmas_no_dark)


def _intrinsics_job(board: str, seed: int, views: int) -> cal.IntrinsicsResult:
    return cal.calibrate_intrinsics(crosscheck.BOARDS[board](seed, views).images)


def _trial_job(renderer: str, azimuth: float, seed: int, intrinsics: cal.IntrinsicsResult) -> Trial:
    return trial(renderer, azimuth, seed, PRESSES[renderer](seed, azimuth), intrinsics)


def run(quick: bool = False, progress: Callable[[str], None] = lambda _: None, jobs: int = 1) -> LightingResult:
    """Quick: 1 seed and 10 chessboard views; full: 10 seeds and 20 views. `jobs` worker processes
    (each trial is seeded on its own, so the result does not depend on them)."""
    stamp = provenance("calib_lighting", quick, *(["--jobs", str(jobs)] if jobs > 1 else []))
    seeds = 1 if quick else 10
    views = 10 if quick else 20
    boards = [(board, seed) for board in sorted(set(BOARD_RENDERER.values())) for seed in range(seeds)]
    cases = [(renderer, azimuth, seed) for renderer in RENDERERS for azimuth in AZIMUTHS for seed in range(seeds)]

    def report(t: Trial) -> None:
        progress(f"{t.renderer} {t.azimuth_deg:g}° seed {t.seed}: theta {t.theta_err_deg:+.3f}° "
                 f"(without the lights-off frame {t.theta_err_no_dark_deg:+.3f}°)")

    if jobs <= 1:
        intrinsics = {key: _intrinsics_job(*key, views) for key in boards}
        trials = []
        for renderer, azimuth, seed in cases:
            trials.append(_trial_job(renderer, azimuth, seed, intrinsics[BOARD_RENDERER[renderer], seed]))
            report(trials[-1])
        return LightingResult(stamp, quick, seeds, views, tuple(trials))
    from concurrent.futures import ProcessPoolExecutor

    with ProcessPoolExecutor(max_workers=jobs) as pool:
        solved = {key: pool.submit(_intrinsics_job, *key, views) for key in boards}
        intrinsics = {key: future.result() for key, future in solved.items()}
        futures = [pool.submit(_trial_job, renderer, azimuth, seed, intrinsics[BOARD_RENDERER[renderer], seed])
                   for renderer, azimuth, seed in cases]
        trials = []
        for future in futures:
            trials.append(future.result())
            report(trials[-1])
    return LightingResult(stamp, quick, seeds, views, tuple(trials))


def markdown(result: LightingResult) -> list[str]:
    within, count = result.within_2_sigma()
    within_no_dark, count_no_dark = result.within_2_sigma(no_dark=True)
    lines = [f"Whole calibration with its defaults: intrinsics from {result.views} chessboard views (boards in the "
             f"central half), then theta and d from 10 presses lit by one LED from the azimuth of the row, with a "
             f"no-contact reference and a lights-off frame; {result.seeds} seeds per cell. 'without lights-off': the "
             "same presses solved without that frame (the rows' strengths then from the imprints' extent, which no "
             "light level changes, instead of their energy relative to the light). theta and d: worst "
             "absolute error over the seeds. 'plain mean': the paper's plain mean over the same views. Row balance: "
             "how many seeds kept it (held-out prediction), and the median margin and its spread (px of held-out "
             "reprojection RMS, kept when the margin exceeds 2 x the spread). The four azimuths of a seed share "
             "that seed's chessboard views, so an intrinsics error repeats across them.", "",
             "| press set | light azimuth | theta worst (°) | d worst (mm) | plain mean theta worst (°) | theta worst "
             "without lights-off (°) | refused | row balance kept | margin / spread (px) | within 2 sigma | "
             "within 2 sigma without lights-off |",
             "|---|---|---|---|---|---|---|---|---|---|---|"]
    for c in result.cells():
        lines.append(f"| {c.renderer} | {c.azimuth_deg:g}° | {c.theta_worst_deg:.3f} | {c.d_worst_mm:.4f} | "
                     f"{c.plain_theta_worst_deg:.3f} | {c.theta_worst_no_dark_deg:.3f} | {c.refused}/{c.trials} | "
                     f"{c.balance_kept}/{c.trials} | "
                     f"{c.margin_median_px:+.3f} / {c.spread_median_px:.3f} | {100 * c.within_2_sigma:.0f} % | "
                     f"{100 * c.within_2_sigma_no_dark:.0f} % |")
    lines += ["", f"Goals: theta within {GOALS['theta_deg']}° and d within {GOALS['d_mm']} mm on every seed, no "
              f"refusal where the paper's plain method solves, about 95 % within 2 sigma. Worst: theta "
              f"{result.theta_worst():.3f}°, d {result.d_worst():.4f} mm with the lights-off frame, theta "
              f"{result.theta_worst_no_dark():.3f}°, d {result.d_worst_no_dark():.4f} mm without it; refusals "
              f"{sum(1 for t in result.trials if t.refused)} ({result.refusals_where_plain_solves()} where the plain "
              f"method solves); {100 * within:.0f} % of {count} errors within 2 sigma with the lights-off frame, "
              f"{100 * within_no_dark:.0f} % of {count_no_dark} without it.", ""]
    example = next((t for t in result.trials if t.choices), None)
    if example is not None:
        lines += [f"The terms as the calibration reports them ({example.renderer}, {example.azimuth_deg:g}°, "
                  f"seed {example.seed}):", "", *(f"- {line}" for line in example.choices), ""]
    refused = [t for t in result.trials if t.refused]
    if refused:
        lines += ["Refused:", "", *(f"- {t.renderer} {t.azimuth_deg:g}° seed {t.seed}: {t.refused}"
                                     for t in refused), ""]
    return lines


def to_markdown(result: LightingResult) -> str:
    return "\n".join([provenance_markdown(result.provenance), "", *markdown(result)])


def load(path: Path) -> LightingResult:
    """A result written by `main` (its JSON), e.g. for the report."""
    data = json.loads(Path(path).read_text())
    trials = tuple(Trial(**{**t, "choices": tuple(t["choices"])}) for t in data["trials"])
    return LightingResult(Provenance(**data["provenance"]), bool(data["quick"]), int(data["seeds"]),
                          int(data["views"]), trials)


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="1 seed and 10 chessboard views (indicative only)")
    parser.add_argument("--jobs", type=int, default=1, help="worker processes (the result does not depend on them)")
    args = parser.parse_args()
    if args.jobs < 1:
        parser.error(f"--jobs must be at least 1, got {args.jobs}")
    result = run(quick=args.quick, progress=lambda line: print(line, file=sys.stderr, flush=True), jobs=args.jobs)
    write_results(results_path("calib_lighting", args.quick), TITLE, result, to_markdown)
    print(to_markdown(result))
    return 0


if __name__ == "__main__":
    sys.exit(main())
