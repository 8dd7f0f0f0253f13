"""The world map over a grid of motions, latencies and raster yaws, on the second raster generator.

Issue 22's measures. Every raster here is filmed by `bench.raster_generator` (its own surfaces, band
model, shading, noise and arm; it imports nothing of `touchroller_driver.sim`), so no figure of this
bench rests on the simulator's assumptions. Each cell: a boustrophedon raster of 3 passes under one motion
profile (ramp, blend, constant, pauses + jitter) x one true camera latency (0, 20, 50, 120 ms) x one raster
yaw (0 and 35 deg), /tf at 125 Hz with jitter; `touchroller map BAG --out map.png` as a user runs it, not
told the latency; the map scored in place against the truth (`bench.raster_score`): the latency found and
its error (and whether the mapper said it estimated it, or warned), SSIM, each pass's residual shift,
coverage, seams (at every pass border and band edge: a dip or step of the map's profile across the passes
beyond the truth's own texture, fitted locally; and the same measure away from any border, the floor
that texture alone reads). Then surface rows: the periodic weave (no pass placed a period off), the smooth painted
panel and glass (coverage, the planted cracks and dents in place).

`python -m bench.world_map_grid [--quick]` -> bench/results/world_map_grid.md + .json (quick/ with --quick);
the report calls `run(quick)`, `to_markdown(result)`, and `load(path)` for a recorded result.
"""
from __future__ import annotations

import argparse
import dataclasses
import json
import math
import shutil
import subprocess
import sys
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path

from bench._common import ROOT, Provenance, provenance, provenance_markdown, results_path, to_json
from bench.raster_generator import Look, MotionConfig, RasterSpec, generate, load_camera
from bench.raster_score import FeatureScore, MapRun, MapScore, parse_map_output, score_map
from touchroller_perception.files import atomic_write_text

PARAMS = ROOT / "config" / "touchroller.yaml"


@dataclass(frozen=True)
class GridSize:
    """What a run films: the grid (profiles x latencies x yaws on the grained surface) and the surface rows
    (surface, profile, latency ms, yaw deg), all over one raster rectangle (x, y, length, width)."""

    profiles: tuple[str, ...]
    latencies_ms: tuple[float, ...]
    yaws: tuple[float, ...]
    area: tuple[float, float, float, float]
    passes: int
    surfaces: tuple[tuple[str, str, float, float], ...]
    single_pass: tuple[tuple[str, str, float, float], ...] = ()


FULL = GridSize(profiles=("ramp", "blend", "constant", "pauses"), latencies_ms=(0.0, 20.0, 50.0, 120.0),
                yaws=(0.0, 35.0), area=(0.40, -0.055, 0.05, 0.11), passes=3,
                surfaces=(("weave", "blend", 50.0, 0.0), ("panel", "blend", 50.0, 0.0), ("panel", "ramp", 20.0, 35.0),
                          ("glass", "blend", 50.0, 0.0)),
                single_pass=(("grained", "constant", 35.0, 0.0), ("grained", "constant", 35.0, 35.0)))
QUICK = GridSize(profiles=("blend",), latencies_ms=(50.0,), yaws=(0.0,), area=(0.40, -0.05, 0.04, 0.10), passes=2,
                 surfaces=(("panel", "ramp", 20.0, 0.0),))
TF_RATE = 125.0
LOOK = dataclasses.replace(Look(), exposure_samples=1)   # the grid's 36 rasters: one render per frame (no motion blur)

# the goals
LATENCY_MS = 3.0
SSIM = 0.90
RESIDUAL_MM = 0.1
COVERAGE = 98.0
SEAM = 0.25
FEATURE_MM = 0.2


@dataclass(frozen=True)
class Cell:
    """One raster through `touchroller map`, scored."""

    surface: str
    profile: str
    latency_true_ms: float
    yaw_deg: float
    frames: int
    map: MapRun
    score: MapScore

    @property
    def latency_error_ms(self) -> float:
        found = self.map.latency_ms if self.map.latency_ms is not None else 0.0
        return abs(found - self.latency_true_ms)

    @property
    def latency_ok(self) -> bool:
        """Within 3 ms of the truth as an estimate (every cell's raster has boustrophedon passes over shared
        ground, so the latency is observable in all of them)."""
        return self.map.latency_estimated and self.latency_error_ms <= LATENCY_MS


@dataclass(frozen=True)
class GridResult:
    provenance: Provenance
    quick: bool
    area: tuple[float, float, float, float]
    passes: int
    tf_rate: float
    cells: list[Cell]
    surfaces: list[Cell]
    seconds: float
    single_pass: list[Cell] = dataclasses.field(default_factory=list)   # one pass at constant speed: unobservable


def run_cell(surface: str, profile: str, latency_ms: float, yaw: float, area: tuple[float, ...], passes: int,
             seed: int = 0) -> Cell:
    """Film one raster in a temporary folder, map it with `touchroller map` (latency not told), score it."""
    tmp = Path(tempfile.mkdtemp(prefix="world_map_grid_"))
    try:
        spec = RasterSpec(surface=surface, corner=(area[0], area[1]), length=area[2], width=area[3], passes=passes,
                          yaw_deg=yaw, latency=latency_ms / 1e3, tf_rate=TF_RATE,
                          motion=dataclasses.replace(MotionConfig(), profile=profile, seed=seed), seed=seed)
        truth = generate(spec, tmp / "raster", camera=load_camera(str(PARAMS)), look=LOOK)
        out = tmp / "map.png"
        begin = time.perf_counter()
        done = subprocess.run([sys.executable, "-m", "touchroller_bringup.cli", "map", str(tmp / "raster" / "bag"),
                               "--out", str(out)], capture_output=True, text=True, cwd=ROOT)
        seconds = time.perf_counter() - begin
        if done.returncode != 0:
            raise RuntimeError(f"touchroller map failed on {surface}/{profile}/{latency_ms} ms/{yaw} deg: "
                               f"{done.stderr.strip().splitlines()[-1:]}")
        run = parse_map_output(done.stdout, done.stderr, seconds)
        return Cell(surface, profile, latency_ms, yaw, truth.frames, run, score_map(out.with_suffix(".yaml"), truth))
    finally:
        shutil.rmtree(tmp, ignore_errors=True)


def run(quick: bool = False) -> GridResult:
    size = QUICK if quick else FULL
    stamp = provenance("world_map_grid", quick)
    begin = time.perf_counter()
    plan = [(kind, profile, latency, yaw) for kind, profile, latency, yaw in size.surfaces]
    plan += [("grained", profile, latency, yaw) for yaw in size.yaws for profile in size.profiles
             for latency in size.latencies_ms]
    plan += [(kind, profile, latency, yaw) for kind, profile, latency, yaw in size.single_pass]
    done = []
    for k, (kind, profile, latency, yaw) in enumerate(plan):
        passes = 1 if k >= len(plan) - len(size.single_pass) else size.passes
        done.append(run_cell(kind, profile, latency, yaw, size.area, passes))
        print(f"[{k + 1}/{len(plan)}] {kind} {profile} {latency:g} ms {yaw:g} deg: "
              f"{done[-1].map.summary.rsplit(';', 1)[-1].strip()}", file=sys.stderr, flush=True)
    n_surfaces, n_single = len(size.surfaces), len(size.single_pass)
    surfaces, cells = done[:n_surfaces], done[n_surfaces:len(done) - n_single]
    single = done[len(done) - n_single:]
    return GridResult(stamp, quick, size.area, size.passes, TF_RATE, cells, surfaces, time.perf_counter() - begin,
                      single)


# ------------------------------------------------------------------------------------------------ reading back
def _map_score(data: dict) -> MapScore:
    data = dict(data)
    data["features"] = [FeatureScore(**{**f, "centre": tuple(f["centre"]), "offset_mm": tuple(f["offset_mm"])})
                        for f in data["features"]]
    data["pass_residual_mm"] = [tuple(r) for r in data["pass_residual_mm"]]
    data["seams"] = [tuple(s) for s in data["seams"]]
    return MapScore(**data)


def _cell(data: dict) -> Cell:
    return Cell(data["surface"], data["profile"], data["latency_true_ms"], data["yaw_deg"], data["frames"],
                MapRun(**data["map"]), _map_score(data["score"]))


def load(path: Path) -> GridResult:
    """A result written by this bench (its JSON), to render again."""
    data = json.loads(Path(path).read_text(encoding="utf-8"))
    x, y, length, width = data["area"]
    return GridResult(Provenance(**data["provenance"]), data["quick"], (x, y, length, width), data["passes"],
                      data["tf_rate"], [_cell(c) for c in data["cells"]], [_cell(c) for c in data["surfaces"]],
                      data["seconds"], [_cell(c) for c in data.get("single_pass", [])])


# ------------------------------------------------------------------------------------------------ goals
def _nan_max(values: list[float]) -> float:
    finite = [v for v in values if math.isfinite(v)]
    return max(finite) if finite else math.nan


def goals(r: GridResult) -> list[tuple[str, str, bool | None]]:
    """Issue 22's measures on the second generator: (goal, figure, met); met None: the run has no such raster."""
    cells = r.cells
    latency_bad = [c for c in cells if not c.latency_ok]
    worst_latency = max(cells, key=lambda c: c.latency_error_ms)
    ssim = min(c.score.ssim for c in cells)
    residual = _nan_max([c.score.worst_residual_mm for c in cells])
    coverage = min(c.score.coverage_percent for c in cells)
    every = cells + r.surfaces
    seam = _nan_max([c.score.seam_worst for c in every])
    floor = _nan_max([c.score.seam_floor for c in every])
    weave = [c for c in r.surfaces if c.surface == "weave"]
    smooth = [c for c in r.surfaces if c.surface in ("panel", "glass")]
    rows: list[tuple[str, str, bool | None]] = [
        (f"latency within {LATENCY_MS:g} ms of the truth on every cell (all observable: boustrophedon passes)",
         f"{len(cells) - len(latency_bad)}/{len(cells)} cells; worst {worst_latency.latency_error_ms:.1f} ms off "
         f"({worst_latency.profile}, {worst_latency.latency_true_ms:g} ms, yaw {worst_latency.yaw_deg:g}°)",
         not latency_bad),
        (f"world map in place SSIM >= {SSIM:.2f} on every cell", f"worst {ssim:.3f}", ssim >= SSIM),
        (f"each pass's residual shift <= {RESIDUAL_MM:g} mm on every cell", f"worst {residual:.3f} mm",
         residual <= RESIDUAL_MM),
        (f"coverage >= {COVERAGE:g} % on every cell", f"worst {coverage:.1f} %", coverage >= COVERAGE),
        (f"seams: no dip or step at pass borders or band edges > {SEAM:g} of the map's std, beyond the truth's "
         "texture (every raster)",
         f"worst {seam:.2f} (texture alone, away from borders: up to {floor:.2f})", seam <= SEAM),
    ]
    single_goal = ("unobservable (one pass at constant speed): a WARN, and the configured latency (0) used, "
                   "not an estimate")
    if r.single_pass:
        good = [c for c in r.single_pass if c.map.warned and not c.map.latency_estimated
                and (c.map.latency_ms or 0.0) == 0.0]
        said = "; ".join(f"yaw {c.yaw_deg:g}°: {_said(c)}" for c in r.single_pass)
        rows.append((single_goal, f"{len(good)}/{len(r.single_pass)} ({said})", len(good) == len(r.single_pass)))
    else:
        rows.append((single_goal, "no single-pass raster in this run", None))
    weave_goal = f"weave: no pass a period (1.2 mm) off, residual <= {RESIDUAL_MM:g} mm"
    smooth_goals = (f"smooth panel and glass: coverage >= {COVERAGE:g} %",
                    f"smooth panel and glass: planted cracks and dents in place within {FEATURE_MM:g} mm")
    if weave:
        worst = _nan_max([c.score.worst_residual_mm for c in weave])
        shifts = [math.hypot(*p) for c in weave for p in c.score.pass_residual_mm]
        unmapped = sum(not math.isfinite(v) for v in shifts)
        note = f"; {unmapped} of {len(shifts)} passes not mapped" if unmapped else ""
        rows.append((weave_goal, f"worst {worst:.3f} mm{note}", bool(shifts) and not unmapped and worst <= RESIDUAL_MM))
    else:
        rows.append((weave_goal, "no weave raster in this run", None))
    if not smooth:
        rows += [(goal, "no panel or glass raster in this run", None) for goal in smooth_goals]
    else:
        coverage_s = min(c.score.coverage_percent for c in smooth)
        features = _nan_max([c.score.worst_feature_mm for c in smooth])
        counted = sum(len(c.score.features) for c in smooth)
        rows.append((smooth_goals[0], f"worst {coverage_s:.1f} %", coverage_s >= COVERAGE))
        rows.append((smooth_goals[1], f"worst {features:.3f} mm ({counted} features)",
                     counted > 0 and features <= FEATURE_MM))
    return rows


# ------------------------------------------------------------------------------------------------ report
def _said(c: Cell) -> str:
    m = c.map
    if m.latency_ms is None:
        found = "not found"
    else:
        found = f"{m.latency_ms:.1f} ms" + (f" ± {m.latency_sigma_ms:.1f}" if m.latency_sigma_ms is not None else "")
        found += "" if m.latency_estimated else " (given)"
    return found + (" WARN" if m.warned else "")


def _row(c: Cell) -> str:
    s = c.score
    residuals = ", ".join(f"{math.hypot(*p):.2f}" for p in s.pass_residual_mm)
    return (f"| {c.surface} | {c.profile} | {c.yaw_deg:g}° | {c.latency_true_ms:g} ms | {_said(c)} | "
            f"{c.latency_error_ms:.1f} ms | {s.ssim:.3f} | {residuals} | {s.coverage_percent:.1f} % | "
            f"{s.seam_worst:.2f} ({s.seam_floor:.2f}) | "
            f"{c.map.mapped_frames if c.map.mapped_frames is not None else '-'}/{c.frames} |")


def to_markdown(r: GridResult) -> str:
    x, y, length, width = r.area
    head = ("| surface | profile | yaw | true latency | mapper said | latency error | SSIM in place | pass residuals "
            "(mm) | coverage | worst seam (floor), std | frames mapped |")
    rule = "|---|---|---|---|---|---|---|---|---|---|---|"
    lines = [f"Rests on the **second raster generator** (`bench/raster_generator`: its own surfaces, contact band "
             f"model, LED shading, sensor noise and arm; it imports nothing of `touchroller_driver.sim`). Each cell: "
             f"{r.passes} boustrophedon passes over {length * 100:g} x {width * 100:g} cm (corner ({x}, {y}) m, "
             f"turned by the yaw about it), 20 mm/s, 640x480 frames at 30 Hz (one render per frame), `/tf` at "
             f"{r.tf_rate:g} Hz with jitter, `/tf_static` for the mount and camera; `touchroller map BAG --out "
             "map.png` with the default parameters, not told the "
             "latency. Scored in place against the generator's truth (`bench/raster_score.py`): no alignment. "
             "Profiles: ramp (presses at rest, starts and stops in contact), blend (touchdown and lift-off at speed, "
             "speed varying 1 % along a pass), constant (touchdown and lift-off at speed, constant speed), pauses "
             "(stops within each pass, 3 % RMS speed jitter). Seams: the map's and the truth's mean profiles across "
             "the passes (each standardised, averaged along the roll); at every pass border and band edge the "
             "map's profile 2-8 mm either side is fitted as a level per side, a slope and a 5-tap filter (+-0.2 "
             "mm) of the truth's profile (the texture's local gain, blur and phase, held towards the whole "
             "width's gain where the truth is nearly flat); the worst seam is the largest departure from that fit "
             "within 1.5 mm of a border (a dip, never fitted) or difference of the two sides' levels (a step), in "
             "units of the map's std. A line or step at a border is not in the truth and stays; texture the map "
             "shares with the truth is fitted away. In brackets, the floor: the same measure's 95th percentile "
             "at lines 4 mm or more from any border, what texture alone reads (a border is a seam where it "
             "stands out of it).", "",
             "Motion, latency and yaw (grained surface):", "", head, rule]
    lines += [_row(c) for c in r.cells]
    lines += ["", "Surfaces (weave: period 1.2 mm; panel: micrometre orange peel with cracks and dents; glass):", "",
              head + " planted features (worst mm, count) |", rule + "---|"]
    for c in r.surfaces:
        f = c.score
        lines.append(_row(c) + (f" {f.worst_feature_mm:.3f} ({len(f.features)}) |" if f.features else " - |"))
    if r.single_pass:
        lines += ["", "One pass at constant speed (no evidence of the latency: the mapper should warn and use the "
                  "configured value, 0):", "", head, rule]
        lines += [_row(c) for c in r.single_pass]
    lines += ["", "Goals (issue 22, on the second generator):", "", "| goal | measured | |", "|---|---|---|"]
    for goal, figure, met in goals(r):
        lines.append(f"| {goal} | {figure} | {'not run' if met is None else 'met' if met else '**NOT met**'} |")
    rasters = len(r.cells) + len(r.surfaces) + len(r.single_pass)
    lines += ["", f"{rasters} rasters filmed and mapped in {r.seconds / 60:.1f} min.", "",
              provenance_markdown(r.provenance)]
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="one blend cell and one panel row on a small raster")
    parser.add_argument("--render", action="store_true", help="only render the recorded JSON's markdown again")
    args = parser.parse_args(argv)
    md, js = results_path("world_map_grid", args.quick), results_path("world_map_grid", args.quick, ".json")
    if args.render:
        if not js.is_file():
            print(f"error: no recorded result {js}", file=sys.stderr)
            return 1
        atomic_write_text(md, "# World map over motions, latencies and yaws (second generator)\n\n"
                          + to_markdown(load(js)) + "\n")
        return 0
    result = run(args.quick)
    md.parent.mkdir(parents=True, exist_ok=True)
    atomic_write_text(md, "# World map over motions, latencies and yaws (second generator)\n\n"
                      + to_markdown(result) + "\n")
    atomic_write_text(js, to_json(result, indent=1) + "\n")
    print(to_markdown(result))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
