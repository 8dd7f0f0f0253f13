"""Inspection (issue 24): cracks, dents and bumps found and measured on synthetic height maps, then end to end.

The maps come from `bench.inspection_maps`, a generator written for this bench alone (it does not import
`touchroller_driver.sim`): height maps with no sensor in the loop, the detector's input as the world
height map will give it. Five backgrounds (painted metal, a grained surface, brushed metal, a plain weave, a
panel joint declared by a mask), each with planted cracks, dents and bumps and the truth in the findings'
format; and the same backgrounds without defects, for false findings per m².

The thresholds (`InspectionConfig`'s defaults) were set looking at seeds 0-4 only; the figures are on
seeds 5-19 (the worst seed shown). Measures: recall of cracks 0.1-0.5 mm wide, >= 20 µm deep, >= 5 mm
long; false cracks per m² on defect-free maps; for the cracks found, the centreline's distance to the true
trunk (median over its points, then over cracks), width error, relative depth and length errors; dents and
bumps >= 1 mm across and >= 20 µm: recall, centre error, relative depth error; the smallest crack found
90 % of the time as a function of width and depth (a grid of planted cracks on painted metal); speed in
megapixels of map per second on one core.

End to end (`end_to_end`, the scans in `bench.inspection_scan`): `touchroller scan` of the simulator's
inspection_panel scene (the simulator plants the defects; sensor, arm, world map and detector in the loop),
its intensity map and its height map (`--height`), findings.csv against the truth_findings.csv the scan
writes with the same measures; the sensor's blur calibrated on another set of defects
(`inspection_panel:reference`) and declared to the scored scan (`findings.blur`); the live findings' latency
from the frames on that scan; and the time to inspect 1 m² at 0.1 mm per pixel against the paper's
press-lift-shift GelSight.

`python -m bench.inspection [--quick]` -> bench/results/inspection.md + .json + inspection_sensitivity.png
(quick/ with --quick); `touchroller report` calls `run(quick)` and `to_markdown(result)`.
`python -m bench.inspection --live-latency` runs only the live findings' scans (the scored scan with the latency
estimated, the default, and with it known) and writes their rows into the recorded run (bench/results/
inspection.json + .md, the rest of it as recorded), with their own provenance. `--speed` measures the
detector's speed again alone (seconds; CPU time still grows on a crowded machine) and writes it, with the square
metre's inspection time that follows from it, into the recorded run, with its own provenance.
"""
from __future__ import annotations

import argparse
import math
import os
import sys
import time
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np
from scipy.spatial import cKDTree

from bench import inspection_scan
from bench._common import Provenance, load_json, provenance, provenance_markdown, results_path, save_figure, to_json
from bench.inspection_maps import BACKGROUNDS, CrackSpec, make_map
from bench.inspection_scan import Latency, LineSpread, SquareMetre, densify, geometry
from touchroller_perception.files import atomic_write_text
from touchroller_perception.inspection import Finding, InspectionConfig, inspect

TUNE_SEEDS = range(0, 5)
FULL = {"seeds": list(range(5, 20)), "grid_maps": 3, "speed_repeats": 3, "speed_tiles": (5, 4)}
QUICK = {"seeds": [5], "grid_maps": 1, "speed_repeats": 1, "speed_tiles": (2, 2)}
GRID_WIDTHS_MM = (0.05, 0.1, 0.2, 0.3, 0.5, 1.0)
GRID_DEPTHS_UM = (5.0, 8.0, 10.0, 15.0, 20.0, 30.0, 50.0)
CLEAN_SIZE = (0.1, 0.1)           # m: the defect-free maps


@dataclass(frozen=True)
class CrackScore:
    background: str
    seed: int
    width_mm: float
    depth_um: float
    length_mm: float
    found: bool
    centreline_mm: float          # median distance of the true trunk to the found centreline (NaN if not found)
    width_err_mm: float           # found - true
    depth_rel: float              # found / true - 1
    length_rel: float


@dataclass(frozen=True)
class BlobScore:
    background: str
    seed: int
    kind: str
    diameter_mm: float
    depth_um: float
    found: bool
    centre_mm: float
    depth_rel: float


@dataclass(frozen=True)
class CleanScore:
    background: str
    seed: int
    area_m2: float
    cracks: int
    compact: int


@dataclass(frozen=True)
class Summary:
    cracks_in_scope: int
    crack_recall: float
    crack_recall_worst_seed: float
    worst_seed: int
    recall_by_background: dict[str, float]
    false_cracks_per_m2: float                 # over all defect-free maps
    false_cracks_per_m2_worst_background: float
    worst_background: str
    false_compact_per_m2: float
    false_cracks_on_defect_maps_per_m2: float
    centreline_mm_median: float
    width_err_mm_median_abs: float
    depth_rel_median_abs: float
    length_rel_median_abs: float
    blobs_in_scope: int
    blob_recall: float
    blob_centre_mm_median: float
    blob_depth_rel_median_abs: float


@dataclass(frozen=True)
class Speed:
    megapixels: float
    seconds: float
    megapixels_per_s: float
    repeats: int


@dataclass(frozen=True)
class ScanScore:
    """One scan's findings.csv against its truth_findings.csv (the issue's measures, on one scene)."""

    command: str
    layer: str                     # what the scan inspected: the world map's height or intensity
    blur_mm: float                 # the blur declared to the detector (findings.blur), FWHM
    cracks: list[CrackScore]
    blobs: list[BlobScore]         # matched by sign on a height map; either sign on an intensity map
    false_findings: int            # findings whose geometry lies (median) over 1 mm from every planted defect
    findings: int
    mapped_m2: float
    summary: Summary
    scan_s: float


@dataclass(frozen=True)
class EndToEnd:
    """`touchroller scan` of the simulator's inspection_panel scene (it plants the defects; sensor, arm, world
    map and detector in the loop). The sensor's blur is calibrated on another set of defects
    (`inspection_panel:reference`, its line spread off its own height map against its own truth) and declared
    to the scored scan (`findings.blur`); the same height map inspected without it shows what it changes."""

    intensity: ScanScore
    reference_command: str
    reference_spread: list[LineSpread]      # the calibration: the reference scan's cracks
    blur_mm: float                          # median of their blurs: what the scored scan declares
    height: ScanScore                       # the scored scan, the blur declared
    height_undeclared: ScanScore            # its height map inspected without the blur
    spread: list[LineSpread]                # the scored scan's own line spread (a diagnostic, not used)
    latency: list[Latency]                  # live findings after the frames, on the scored scan
    square_metre: SquareMetre
    # live findings with the camera's latency known (as after calibrating it): not estimated, so frames
    # wait for nothing but the pressed height (`live_latency_scan(known=True)`)
    latency_known: list[Latency] = field(default_factory=list)
    latency_known_command: str = ""
    # when both live rows were measured again by `--live-latency` (its own scans): how, and the estimated
    # case's command (else `latency` is the scored scan's own)
    live_provenance: Provenance | None = None
    latency_command: str = ""


@dataclass(frozen=True)
class InspectionBenchResult:
    provenance: Provenance
    quick: bool
    seeds: list[int]
    config: InspectionConfig
    cracks: list[CrackScore]
    blobs: list[BlobScore]
    clean: list[CleanScore]
    false_on_defect_maps: int
    defect_map_area_m2: float
    tune: Summary | None                      # seeds 0-4, what the thresholds were set on
    summary: Summary
    grid_widths_mm: list[float]
    grid_depths_um: list[float]
    grid_recall: list[list[float]]            # [width][depth]
    smallest_depth_um: dict[str, float | None]   # per width: the smallest depth found >= 90 % of the time
    speed: Speed
    end_to_end: EndToEnd | None = None
    # when the detector's speed was measured again by `--speed` (alone, on a quieter machine): how
    speed_provenance: Provenance | None = None


def _tolerance(width: float) -> float:
    return max(5e-4, width)


def score(truth: list[Finding], found: list[Finding], background: str, seed: int, same_sign: bool = True
          ) -> tuple[list[CrackScore], list[BlobScore], int]:
    """Each true crack, dent and bump against the findings; and the found cracks that lie on no true crack.
    A found crack covers >= half the true trunk within max(0.5 mm, its width); a dent or bump is the nearest
    compact finding (of its kind when `same_sign`) within max(0.5 mm, its radius)."""
    found_cracks = [f for f in found if f.kind == "crack"]
    trees = [cKDTree(densify(f.polylines)) for f in found_cracks]
    cracks, blobs = [], []
    claimed = np.zeros(len(found_cracks), bool)
    for t in truth:
        if t.kind != "crack":
            continue
        trunk = densify(t.polylines[:1])
        best, best_cover, distances = -1, 0.0, np.array([np.inf])
        for j, tree in enumerate(trees):
            d, _ = tree.query(trunk)
            cover = float(np.mean(d <= _tolerance(t.width_m)))
            if cover > best_cover:
                best, best_cover, distances = j, cover, d
        ok = best_cover >= 0.5
        if ok:
            claimed[best] = True
        f = found_cracks[best] if ok else None
        cracks.append(CrackScore(background, seed, t.width_m * 1e3, t.depth_m * 1e6, t.length_m * 1e3, ok,
                                 float(np.median(distances)) * 1e3 if ok else math.nan,
                                 (f.width_m - t.width_m) * 1e3 if f else math.nan,
                                 f.depth_m / t.depth_m - 1 if f else math.nan,
                                 f.length_m / t.length_m - 1 if f else math.nan))
    truth_lines = [densify(t.polylines) for t in truth if t.kind == "crack"]
    truth_tree = cKDTree(np.vstack(truth_lines)) if truth_lines else None
    false = 0
    for j, f in enumerate(found_cracks):
        if claimed[j]:
            continue
        if truth_tree is None:
            false += 1
            continue
        d, _ = truth_tree.query(densify(f.polylines))
        false += int(np.mean(d <= 1e-3) < 0.5)
    compact = [f for f in found if f.kind != "crack"]
    for t in truth:
        if t.kind == "crack":
            continue
        diameter = 2 * t.width_m
        near = [f for f in compact if (f.kind == t.kind or not same_sign)
                and math.hypot(f.x - t.x, f.y - t.y) <= max(5e-4, diameter / 2)]
        f = min(near, key=lambda g: math.hypot(g.x - t.x, g.y - t.y)) if near else None
        blobs.append(BlobScore(background, seed, t.kind, diameter * 1e3, abs(t.depth_m) * 1e6, f is not None,
                               math.hypot(f.x - t.x, f.y - t.y) * 1e3 if f else math.nan,
                               f.depth_m / t.depth_m - 1 if f else math.nan))
    return cracks, blobs, false


def in_scope(c: CrackScore) -> bool:
    return 0.1 <= c.width_mm <= 0.5 and c.depth_um >= 20 and c.length_mm >= 5


def blob_in_scope(b: BlobScore) -> bool:
    return b.diameter_mm >= 1.0 and b.depth_um >= 20


def _median(values: list[float]) -> float:
    finite = [v for v in values if math.isfinite(v)]
    return float(np.median(finite)) if finite else math.nan


def summarise(cracks: list[CrackScore], blobs: list[BlobScore], clean: list[CleanScore], false_on_maps: int,
              map_area: float) -> Summary:
    scope = [c for c in cracks if in_scope(c)]
    found = [c for c in scope if c.found]
    seeds = sorted({c.seed for c in scope})
    by_seed = {s: np.mean([c.found for c in scope if c.seed == s]) for s in seeds}
    worst = min(by_seed, key=lambda s: by_seed[s]) if by_seed else -1
    by_bg = {b: float(np.mean([c.found for c in scope if c.background == b])) for b in BACKGROUNDS
             if any(c.background == b for c in scope)}
    clean_area = sum(c.area_m2 for c in clean)
    per_bg = {b: sum(c.cracks for c in clean if c.background == b) / max(sum(c.area_m2 for c in clean
                                                                             if c.background == b), 1e-12)
              for b in {c.background for c in clean}}
    worst_bg = max(per_bg, key=lambda b: per_bg[b]) if per_bg else ""
    bscope = [b for b in blobs if blob_in_scope(b)]
    bfound = [b for b in bscope if b.found]
    return Summary(
        len(scope), len(found) / max(len(scope), 1), float(by_seed[worst]) if by_seed else math.nan, worst, by_bg,
        sum(c.cracks for c in clean) / clean_area if clean_area > 0 else math.nan, per_bg.get(worst_bg, math.nan),
        worst_bg, sum(c.compact for c in clean) / clean_area if clean_area > 0 else math.nan,
        false_on_maps / max(map_area, 1e-12),
        _median([c.centreline_mm for c in found]), _median([abs(c.width_err_mm) for c in found]),
        _median([abs(c.depth_rel) for c in found]), _median([abs(c.length_rel) for c in found]),
        len(bscope), len(bfound) / max(len(bscope), 1), _median([b.centre_mm for b in bfound]),
        _median([abs(b.depth_rel) for b in bfound]))


def evaluate(seeds: list[int], config: InspectionConfig, clean: bool = True
             ) -> tuple[list[CrackScore], list[BlobScore], list[CleanScore], int, float]:
    cracks: list[CrackScore] = []
    blobs: list[BlobScore] = []
    clean_scores: list[CleanScore] = []
    false, area = 0, 0.0
    for seed in seeds:
        for kind in BACKGROUNDS:
            m = make_map(kind, seed)
            found = inspect(m.height, m.resolution, m.origin, m.mask, config).findings
            c, b, f = score(m.truth, found, m.background, seed)
            cracks += c
            blobs += b
            false += f
            area += m.height.size * m.resolution**2
            if clean:
                m = make_map(kind, 1000 + seed, size_m=CLEAN_SIZE, cracks=0, blobs=0)
                found = inspect(m.height, m.resolution, m.origin, m.mask, config).findings
                clean_scores.append(CleanScore(kind, seed, m.height.size * m.resolution**2,
                                               sum(f.kind == "crack" for f in found),
                                               sum(f.kind != "crack" for f in found)))
    return cracks, blobs, clean_scores, false, area


def sensitivity(seeds: list[int], maps: int, config: InspectionConfig) -> list[list[float]]:
    """Recall of 8 mm cracks on painted metal per (width, depth) cell: `maps` maps of 4 cracks each."""
    grid = []
    for w in GRID_WIDTHS_MM:
        row = []
        for d in GRID_DEPTHS_UM:
            hits, total = 0, 0
            for k in range(maps):
                seed = seeds[k % len(seeds)] * 1000 + int(w * 1000) + int(d) * 7
                specs = [CrackSpec(w * 1e-3, d * 1e-6, 8e-3)] * 4
                m = make_map("painted", seed, size_m=(0.04, 0.04), crack_specs=specs, blobs=0, branch_probability=0)
                found = inspect(m.height, m.resolution, m.origin, m.mask, config).findings
                c, _, _ = score(m.truth, found, m.background, seed)
                hits += sum(x.found for x in c)
                total += len(c)
            row.append(hits / max(total, 1))
        grid.append(row)
    return grid


def measure_speed(tiles: tuple[int, int], repeats: int, config: InspectionConfig) -> Speed:
    import cv2

    m = make_map("painted", 5)
    height = np.tile(m.height, (tiles[1], tiles[0]))
    threads = cv2.getNumThreads()
    cv2.setNumThreads(1)
    try:
        best = math.inf
        for _ in range(repeats):
            start = time.process_time()
            inspect(height, m.resolution, m.origin, None, config)
            best = min(best, time.process_time() - start)
    finally:
        cv2.setNumThreads(threads)
    mp = height.size / 1e6
    return Speed(mp, best, mp / best, repeats)


E2E_ARGUMENTS = {"scene": "inspection_panel", "sweep_length": "0.03", "inspect": "true"}   # the sweep's speed
# the simulated webcam's latency and the same told to the graph, as a user who calibrated it does: the camera
# node subtracts it from the stamps and the world map does not estimate what is left
KNOWN_LATENCY_S = 0.035
KNOWN_LATENCY = {"sim.latency": KNOWN_LATENCY_S, "camera.latency": KNOWN_LATENCY_S, "map.latency_estimate": False}


def scored(scanned: inspection_scan.Scanned, found: list[Finding] | None = None, blur_mm: float = 0.0) -> ScanScore:
    """The scan's findings.csv (or `found`, its map inspected otherwise) against its truth_findings.csv."""
    from touchroller_bringup.findings_files import read_findings_csv
    from touchroller_bringup.map_files import read_world_map

    out, result = scanned.out, scanned.result
    found = read_findings_csv(out / "findings.csv") if found is None else found
    truth = read_findings_csv(out / "truth_findings.csv")
    layer = "height" if "in the height map" in result.findings_summary else "intensity"
    cracks, blobs, false_cracks = score(truth, found, "inspection_panel", 3, same_sign=layer == "height")
    planted = cKDTree(np.vstack([geometry(t) for t in truth]))
    false = sum(float(np.median(planted.query(geometry(f))[0])) > 1e-3 for f in found)
    _, alpha, meta = read_world_map(out / "map.yaml")
    mapped = float((alpha > 0).sum()) * float(meta["resolution"]) ** 2
    return ScanScore(scanned.command, layer, blur_mm, cracks, blobs, false, len(found), mapped,
                     summarise(cracks, blobs, [], false_cracks, mapped), scanned.seconds)


def live_latency_scan(blur_mm: float, known: bool) -> tuple[list[Latency], str]:
    """The scored scan again (height, the blur declared): how soon live findings follow the frames, with the
    latency estimated (the default: frames wait for the estimate) or known (`KNOWN_LATENCY`: the world map
    places frames as they come)."""
    from touchroller_bringup.findings_files import read_findings_csv, read_height_tif

    overrides: dict[str, object] = {"findings.blur": round(blur_mm * 1e-3, 6), **(KNOWN_LATENCY if known else {})}
    scanned = inspection_scan.run_scan(E2E_ARGUMENTS, height=True, overrides=overrides)
    values, res, origin = read_height_tif(scanned.out / "height.tif")
    extent = (origin[0], origin[1], origin[0] + values.shape[1] * res, origin[1] + values.shape[0] * res)
    truth = read_findings_csv(scanned.out / "truth_findings.csv")
    return inspection_scan.live_latency(scanned.watch, truth, extent), scanned.command


def end_to_end(megapixels_per_s: float) -> EndToEnd:
    """The scans (see EndToEnd): intensity; the reference's height (recorded: mapping CPU); the scored height."""
    from touchroller_bringup.findings_files import read_findings_csv, read_height_tif

    intensity = scored(inspection_scan.run_scan(E2E_ARGUMENTS))
    reference_args = {**E2E_ARGUMENTS, "scene": "inspection_panel:reference"}
    reference = inspection_scan.run_scan(reference_args, height=True, record=True)
    reference_spread = inspection_scan.line_spread(reference.out / "height.tif",
                                                   read_findings_csv(reference.out / "truth_findings.csv"))
    blur_mm = float(np.median([s.blur_fwhm_mm for s in reference_spread]))
    ms_per_frame, frames = inspection_scan.map_cpu(reference)
    target = inspection_scan.run_scan(E2E_ARGUMENTS, height=True, overrides={"findings.blur": round(blur_mm * 1e-3, 6)})
    height = scored(target, blur_mm=blur_mm)
    truth = read_findings_csv(target.out / "truth_findings.csv")
    values, res, origin = read_height_tif(target.out / "height.tif")
    undeclared = scored(target, inspect(values, res, origin, config=InspectionConfig()).findings)
    extent = (origin[0], origin[1], origin[0] + values.shape[1] * res, origin[1] + values.shape[0] * res)
    known, known_command = live_latency_scan(blur_mm, known=True)
    return EndToEnd(intensity, reference.command, reference_spread, blur_mm, height, undeclared,
                    inspection_scan.line_spread(target.out / "height.tif", truth),
                    inspection_scan.live_latency(target.watch, truth, extent),
                    inspection_scan.square_metre(target.watch, ms_per_frame, frames, megapixels_per_s),
                    known, known_command)


def run(quick: bool = False) -> InspectionBenchResult:
    os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
    stamp = provenance("inspection", quick)
    plan = QUICK if quick else FULL
    config = InspectionConfig()
    seeds = list(plan["seeds"])
    cracks, blobs, clean, false, area = evaluate(seeds, config)
    tune = None
    if not quick:
        t = evaluate(list(TUNE_SEEDS), config)
        tune = summarise(*t)
    grid = sensitivity(seeds, int(plan["grid_maps"]), config)
    smallest: dict[str, float | None] = {}
    for w, row in zip(GRID_WIDTHS_MM, grid, strict=True):
        ok = [d for d, r in zip(GRID_DEPTHS_UM, row, strict=True) if r >= 0.9]
        smallest[f"{w:g}"] = min(ok) if ok else None
    speed = measure_speed(tuple(plan["speed_tiles"]), int(plan["speed_repeats"]), config)
    return InspectionBenchResult(stamp, quick, seeds, config, cracks, blobs, clean, false, area, tune,
                                 summarise(cracks, blobs, clean, false, area), list(GRID_WIDTHS_MM),
                                 list(GRID_DEPTHS_UM), grid, smallest, speed, end_to_end(speed.megapixels_per_s))


def _pct(v: float) -> str:
    return f"{100 * v:.1f} %" if math.isfinite(v) else "—"


def _summary_rows(s: Summary, label: str) -> list[str]:
    return [
        f"| {label} | {s.cracks_in_scope} | {s.crack_recall:.3f} (worst seed {s.worst_seed}: "
        f"{s.crack_recall_worst_seed:.3f}) | {s.false_cracks_per_m2:.2f} (worst: {s.worst_background} "
        f"{s.false_cracks_per_m2_worst_background:.2f}) | {s.centreline_mm_median:.3f} | "
        f"{s.width_err_mm_median_abs:.3f} | {_pct(s.depth_rel_median_abs)} | {_pct(s.length_rel_median_abs)} | "
        f"{s.blobs_in_scope} | {s.blob_recall:.3f} | {s.blob_centre_mm_median:.3f} | "
        f"{_pct(s.blob_depth_rel_median_abs)} |"]


def to_markdown(r: InspectionBenchResult) -> str:
    s = r.summary
    lines = [provenance_markdown(r.provenance), "",
             "Synthetic height maps (`bench/inspection_maps.py`, a generator of its own: no sensor and no simulator in "
             "the loop) at 0.1 mm per pixel (the end-to-end scans through the simulator are at the end). Thresholds "
             "(InspectionConfig's defaults) set on seeds 0-4; figures on "
             f"seeds {r.seeds[0]}-{r.seeds[-1]}{' (quick run)' if r.quick else ''}.", "",
             "| seeds | cracks in scope | crack recall | false cracks per m² (defect-free) | centreline mm (median) | "
             "width error mm (median abs) | depth error (median rel) | length error (median rel) | dents/bumps in "
             "scope | dent/bump recall | centre mm (median) | depth error (median rel) |",
             "|---|---|---|---|---|---|---|---|---|---|---|---|"]
    lines += _summary_rows(s, f"{r.seeds[0]}-{r.seeds[-1]}")
    if r.tune is not None:
        lines += _summary_rows(r.tune, "0-4 (tuning)")
    lines += ["", "Cracks in scope: 0.1-0.5 mm wide, >= 20 µm deep, >= 5 mm long; dents and bumps >= 1 mm across and "
              ">= 20 µm. Crack recall by background: " + ", ".join(f"{b} {v:.3f}" for b, v in
                                                               s.recall_by_background.items()) + ".",
              f"False cracks on the maps with defects (found cracks on no true crack): "
              f"{s.false_cracks_on_defect_maps_per_m2:.1f} per m²; false dents/bumps on defect-free maps "
              f"{s.false_compact_per_m2:.1f} per m².", "",
              "Smallest crack found >= 90 % of the time (8 mm cracks on painted metal, "
              f"{'1 map' if r.quick else '3 maps'} of 4 per cell):", "",
              "| width mm | " + " | ".join(f"{d:g} µm" for d in r.grid_depths_um) + " | smallest depth found 90 % |",
              "|---|" + "---|" * (len(r.grid_depths_um) + 1)]
    for w, row in zip(r.grid_widths_mm, r.grid_recall, strict=True):
        smallest = r.smallest_depth_um.get(f"{w:g}")
        lines.append(f"| {w:g} | " + " | ".join(f"{v:.2f}" for v in row) +
                     f" | {'—' if smallest is None else f'{smallest:g} µm'} |")
    sp = r.speed
    lines += ["", f"Speed: {sp.megapixels_per_s:.1f} megapixels of map per second on one core (CPU time, best of "
              f"{sp.repeats}, a {sp.megapixels:.1f} MP map with defects; OpenCV on one thread)."]
    if r.speed_provenance is not None:
        lines += ["", "Speed measured again by `--speed` (alone; the square metre's inspection time follows it):  ",
                  provenance_markdown(r.speed_provenance)]
    if r.end_to_end is not None:
        lines += ["", end_to_end_markdown(r.end_to_end)]
    return "\n".join(lines)


def _f(value: float, digits: int = 3) -> str:
    return f"{value:.{digits}f}" if math.isfinite(value) else "—"


def _scan_row(label: str, e: ScanScore) -> str:
    s = e.summary
    found = sum(c.found for c in e.cracks)
    blobs = sum(b.found for b in e.blobs)
    return (f"| {label} | {e.layer} | {_f(e.blur_mm, 2) if e.blur_mm else '—'} | {found} of {len(e.cracks)} | "
            f"{_f(s.centreline_mm_median)} | {_f(s.width_err_mm_median_abs)} | {_pct(s.depth_rel_median_abs)} | "
            f"{_pct(s.length_rel_median_abs)} | {blobs} of {len(e.blobs)} | {_f(s.blob_centre_mm_median)} | "
            f"{_pct(s.blob_depth_rel_median_abs)} | {e.false_findings} of {e.findings} "
            f"({e.false_findings / max(e.mapped_m2, 1e-12):.0f} per m²) |")


def end_to_end_markdown(e: EndToEnd) -> str:
    lines = ["### End to end: the simulator, `touchroller scan`, findings.csv against truth_findings.csv", "",
             "The simulator plants the defects (3 cracks 0.15-0.4 mm wide and 40-120 µm deep, 2 dents and a bump "
             "1.5-3 mm across) and renders the sensor; arm, world map and detector in the loop. One scene and one "
             "seed per row: a check of the path, not a statistic. Widths and depths are medians over the cracks "
             "found; all of them are in the issue's scope.", "",
             f"- intensity: `{e.intensity.command}`",
             f"- height, blur declared: `{e.height.command}` (the blur calibrated on `{e.reference_command}`); "
             "'undeclared' is the same scan's height.tif inspected with the detector's defaults", "",
             "| scan | layer | blur declared mm | cracks found | centreline mm | width error mm | depth error | length "
             "error | dents/bumps found | centre mm | depth error | findings on no planted defect |",
             "|---|---|---|---|---|---|---|---|---|---|---|---|",
             _scan_row("intensity", e.intensity), _scan_row("height, undeclared", e.height_undeclared),
             _scan_row("height, blur declared", e.height), "",
             "The sensor's line spread off its height map (a reference sample of known cracks): across each true "
             "crack the map's full width at half depth W (its half-depth crossings interpolated), the blur beyond the "
             "map's pixel sqrt(W² - w² - p²) (p: the detector's pixel footprint, 1 px, which it adds back), and the "
             "cross-section's area read over the true one.", "",
             "| scan | crack width mm | depth µm | map's FWHM mm | blur FWHM mm | area read / true |",
             "|---|---|---|---|---|---|"]
    for label, spread in (("reference (calibration)", e.reference_spread), ("scored (diagnostic)", e.spread)):
        lines += [f"| {label} | {x.width_mm:.3f} | {x.depth_um:.0f} | {x.map_fwhm_mm:.3f} | {x.blur_fwhm_mm:.3f} | "
                  f"{x.area_ratio:.2f} |" for x in spread]
    lines += ["", f"Declared blur: {e.blur_mm:.3f} mm FWHM (median of the reference's cracks).", "",
              "Live findings (`findings`, MarkerArray): from the arrival of the tool pose of the last frame whose "
              "mapped band reached a planted defect to the arrival of the first `findings` message with a marker of "
              "its kind on it (wall clock; simulated time from the message's stamp; negative: shown before the band "
              "had left it). With the latency estimated (the default: "
              f"`{e.latency_command or e.height.command}`) the world map holds frames until the estimate, which "
              "needs a pass's end; meanwhile the perception node places them provisionally with the configured "
              "latency, for the live findings only (`WorldMapConfig.provisional`). With the latency known "
              "(calibrated: "
              f"`{e.latency_known_command or 'not run'}`) frames are placed as they come, and the pass being "
              "rolled is inspected on its own height.", ""]
    if e.live_provenance is not None:
        lines += ["Live rows measured again by `--live-latency` (their own scans):  ",
                  e.live_provenance.markdown(), ""]
    lines += ["| latency | defect | wall s | simulated s | first shown by |", "|---|---|---|---|---|"]
    lines += [f"| {label} | {x.kind} | {_f(x.wall_s, 2)} | {_f(x.sim_s, 2)} | "
              f"{'the finished map (after the roll)' if x.final else 'the live inspection'} |"
              for label, rows in (("estimated", e.latency), ("known", e.latency_known)) for x in rows]
    q = e.square_metre
    lines += ["", "The headline: 1 m² at 0.1 mm per pixel, scan to findings, with the sweep's defaults "
              "(config/scan.yaml; the planner's pass width and overlap):", "",
              f"- rolling at {q.speed_m_s * 1e3:.0f} mm/s (measured in the scan: {q.measured_speed_m_s * 1e3:.2f} "
              f"mm/s), passes {q.pass_width_m * 1e3:.0f} mm wide every {q.pass_spacing_m * 1e3:.0f} mm: "
              f"{q.passes} passes of 1 m, the arm's plan {q.arm_s:.0f} s ({q.rolling_s:.0f} s of it rolling);",
              f"- mapping (world map with its height layer, `touchroller map` of the reference scan's recording, "
              f"reading included): {q.map_cpu_ms_per_frame:.1f} ms CPU per frame over {q.map_frames} frames, "
              f"{q.frames} frames at {q.fps:.0f} fps: {q.map_cpu_s:.0f} s CPU, "
              f"{'within' if q.map_cpu_s <= q.rolling_s else 'beyond'} the rolling time on one core;",
              f"- inspection of the finished map: {q.megapixels:.0f} MP at the bench's speed, {q.inspect_cpu_s:.1f} s;",
              f"- **{q.total_s:.0f} s ({q.total_s / 60:.0f} min) per m²**, against the paper's press-lift-shift "
              f"GelSight, 196 s for 49 presses over 8 x 11 cm, {q.paper_s:.0f} s ({q.paper_s / 3600:.1f} h, "
              f"{q.paper_presses:.0f} presses) per m² at the same 4 s per press: "
              f"**{q.paper_s / q.total_s:.1f}x** faster.",
              "Assumptions: the arm runs its plan (the simulated arm does; a real UR5 within its limits), the "
              "perception node maps live on a core of its own (mapping adds time only beyond the rolling), the "
              "paper's figure scales with area (its own pixel size, not 0.1 mm), and the files' writing and the "
              "operator's set-up are left out."]
    return "\n".join(lines)


def figures(r: InspectionBenchResult, out_dir: Path) -> list[Path]:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(6, 4))
    grid = np.asarray(r.grid_recall)
    image = ax.imshow(grid, origin="lower", cmap="viridis", vmin=0, vmax=1, aspect="auto")
    ax.set_xticks(range(len(r.grid_depths_um)), [f"{d:g}" for d in r.grid_depths_um])
    ax.set_yticks(range(len(r.grid_widths_mm)), [f"{w:g}" for w in r.grid_widths_mm])
    ax.set_xlabel("crack depth, µm")
    ax.set_ylabel("crack width, mm")
    if (grid >= 0.9).any() and (grid < 0.9).any():
        ax.contour(grid, levels=[0.9], colors="white")
    for i in range(grid.shape[0]):
        for j in range(grid.shape[1]):
            ax.text(j, i, f"{grid[i, j]:.2f}", ha="center", va="center", fontsize=7,
                    color="white" if grid[i, j] < 0.6 else "black")
    ax.set_title("Crack recall (synthetic height maps, painted metal)")
    fig.colorbar(image, ax=ax, label="recall")
    fig.tight_layout()
    path = out_dir / "inspection_sensitivity.png"
    save_figure(fig, path, dpi=110)
    plt.close(fig)
    return [path]


def load(path: Path) -> InspectionBenchResult:
    """A result this bench wrote (its JSON), for the report to render without running it again."""
    result: InspectionBenchResult = load_json(InspectionBenchResult, path)
    return result


def remeasure_speed(recorded: InspectionBenchResult, quick: bool) -> InspectionBenchResult:
    """The recorded run with the detector's speed measured again (the plan's tiles and repeats), and the square
    metre's inspection time and total following it."""
    plan = QUICK if quick else FULL
    speed = measure_speed(tuple(plan["speed_tiles"]), int(plan["speed_repeats"]), recorded.config)
    stamp = provenance("inspection", quick, "--speed")
    e = recorded.end_to_end
    if e is not None:
        q = e.square_metre
        inspect_s = q.megapixels / speed.megapixels_per_s
        e = replace(e, square_metre=replace(q, inspect_cpu_s=inspect_s,
                                            total_s=q.total_s - q.inspect_cpu_s + inspect_s))
    return replace(recorded, speed=speed, end_to_end=e, speed_provenance=stamp)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="1 seed, 1 map per sensitivity cell, one timing run")
    parser.add_argument("--speed", action="store_true", help="only the detector's speed (seconds: for a quieter "
                        "moment than the whole run had), written into the recorded run")
    parser.add_argument("--live-latency", action="store_true", help="only the live findings' latency, estimated "
                        "and known (the recorded blur declared), written into the recorded run")
    args = parser.parse_args(argv)
    md, js = results_path("inspection", args.quick), results_path("inspection", args.quick, ".json")
    if args.speed:
        recorded = load(js) if js.exists() else None
        if recorded is None:
            print(f"error: --speed updates a recorded run; {js} has none (run the bench first)", file=sys.stderr)
            return 2
        result = remeasure_speed(recorded, args.quick)
    elif args.live_latency:
        recorded = load(js) if js.exists() else None
        if recorded is None or recorded.end_to_end is None:
            print(f"error: --live-latency updates a recorded run with its end-to-end part; {js} has none "
                  "(run the bench first)", file=sys.stderr)
            return 2
        stamp = provenance("inspection", args.quick, "--live-latency")
        e = recorded.end_to_end
        estimated, estimated_command = live_latency_scan(e.blur_mm, known=False)
        known, known_command = live_latency_scan(e.blur_mm, known=True)
        result = replace(recorded, end_to_end=replace(e, latency=estimated, latency_command=estimated_command,
                                                      latency_known=known, latency_known_command=known_command,
                                                      live_provenance=stamp))
    else:
        result = run(args.quick)
        md.parent.mkdir(parents=True, exist_ok=True)
        figures(result, md.parent)
    atomic_write_text(md, "# Inspection: synthetic height maps and end to end\n\n" + to_markdown(result) +
                      "\n\n![crack recall by width and depth](inspection_sensitivity.png)\n")
    atomic_write_text(js, to_json(result, indent=1) + "\n")
    print(end_to_end_markdown(result.end_to_end) if args.live_latency and result.end_to_end else to_markdown(result))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
