"""Scan soak: the whole scan graph in one process (`touchroller scan`'s `run_scan`) over a long raster of
the large scene: memory against frames processed, the world map's own growth taken out, and the rate.

A sampler thread reads the process's resident set size (VmRSS) and the perception node's count of frames
taken every `--every` seconds, and the bytes of the world map's tiles in memory (they grow with the
area mapped up to the tile cache: that growth is the map's, not a leak). Memory growth is the
least-squares slope of (RSS - those bytes) against frames, after warm-up; a steady rate compares the
frames per second of the last quarter of the run with the first quarter after warm-up. `--trace` also
takes tracemalloc snapshots after warm-up and at the end and lists where Python memory grew most
(slower: for finding a leak, not for the figures).
"""
from __future__ import annotations

import argparse
import os
import sys
import tempfile
import threading
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from bench._common import (
    Provenance,
    load_json,
    loadavg,
    provenance,
    provenance_markdown,
    results_path,
    write_results,
)
from bench._scan_graph import map_tiles_mb, own_domain, perception_node, status_mb

AREA = (0.40, -0.08, 0.16, 0.16)     # x, y, length, width (m) of the raster on the large scene
QUICK_AREA = (0.42, -0.045, 0.03, 0.09)
SPEED = 0.01                         # m/s along a pass
GOAL_MB_PER_1000 = 5.0
GOAL_STEADY = 1.25


@dataclass(frozen=True)
class Sample:
    elapsed_s: float
    frames: int
    rss_mb: float
    canvas_mb: float


@dataclass(frozen=True)
class ScanSoakResult:
    provenance: Provenance
    quick: bool
    area: tuple[float, float, float, float]
    speed: float
    outcome: str
    duration_s: float
    frames: int
    warmup_frames: int
    samples: tuple[Sample, ...]
    slope_mb_per_1000: float          # RSS less the canvas, per 1000 frames after warm-up
    raw_slope_mb_per_1000: float      # RSS alone
    first_fps: float
    last_fps: float
    steady: float                     # first_fps / last_fps
    goal_mb_per_1000: float
    goal_steady: float
    top_growth: tuple[str, ...]       # tracemalloc: where Python memory grew most (with --trace)
    loadavg_after: str

    @property
    def memory_met(self) -> bool:
        return self.slope_mb_per_1000 <= self.goal_mb_per_1000

    @property
    def steady_met(self) -> bool:
        return self.steady <= self.goal_steady


def _malloc_trim() -> None:
    import ctypes

    try:
        ctypes.CDLL(None).malloc_trim(0)
    except (OSError, AttributeError):
        pass


def measure(area: tuple[float, float, float, float], speed: float, every: float, quick: bool,
            trace: bool = False, trim: bool = False, overrides: dict | None = None) -> ScanSoakResult:
    from touchroller_bringup.scan import ScanOptions, run_scan

    stamp = provenance("scan_soak", quick, *([] if area == (QUICK_AREA if quick else AREA) else
                                              ["--area", ",".join(map(str, area))]),
                       *([] if speed == SPEED * (2 if quick else 1) else ["--speed", f"{speed:g}"]),
                       *(["--trace"] if trace else []), *(["--trim"] if trim else []),
                       *(arg for k, v in (overrides or {}).items() for arg in ("--set", f"{k}:={v}")))
    samples: list[Sample] = []
    done = threading.Event()
    started = time.monotonic()
    snapshots: list = []
    warmup_frames = 300 if quick else 1000

    def sample() -> None:
        perception = None
        while not done.wait(every):
            perception = perception or perception_node()
            frames = int(getattr(perception, "received", 0)) if perception is not None else 0
            if trim:   # free heap pages back to the system first: what stays is held, not fragmentation
                _malloc_trim()
            samples.append(Sample(time.monotonic() - started, frames, status_mb(), map_tiles_mb(perception)))
            if trace and not snapshots and frames >= warmup_frames:
                import tracemalloc

                snapshots.append(tracemalloc.take_snapshot())

    if trace:
        import tracemalloc

        tracemalloc.start(8)
    sampler = threading.Thread(target=sample, name="scan-soak-sampler", daemon=True)
    sampler.start()
    out = Path(tempfile.mkdtemp(prefix="scan_soak_"))
    try:
        with own_domain():
            result = run_scan(ScanOptions(out_dir=out, arguments={"scene": "large_surface",
                                                                  "area": ",".join(map(str, area)),
                                                                  "sweep_speed": str(speed)},
                                          overrides=dict(overrides or {}), progress=None))
    finally:
        done.set()
        sampler.join()
    top: list[str] = []
    if trace and snapshots:
        import tracemalloc

        end = tracemalloc.take_snapshot()
        tracemalloc.stop()
        grown = sorted(end.compare_to(snapshots[0], "lineno"), key=lambda s: s.size_diff, reverse=True)
        for stat in grown[:12]:
            frame = stat.traceback[-1]
            top.append(f"{stat.size_diff / 2**20:+.2f} MB in {stat.count_diff:+d} blocks: {frame.filename}:"
                       f"{frame.lineno}")
    frames = result.frames_processed
    slope, raw, first_fps, last_fps = summarise(samples, warmup_frames)
    return ScanSoakResult(stamp, quick, tuple(area), speed, result.outcome, result.duration_s, frames, warmup_frames,
                          tuple(samples), slope, raw, first_fps, last_fps,
                          first_fps / last_fps if last_fps > 0 else float("nan"), GOAL_MB_PER_1000, GOAL_STEADY,
                          tuple(top), loadavg())


def summarise(samples: list[Sample] | tuple[Sample, ...], warmup_frames: int) -> tuple[float, float, float, float]:
    """(MB per 1000 frames of RSS less the map's own memory, of RSS alone, frames/s of the first quarter
    after warm-up, of the last quarter); NaN with fewer than 4 samples after warm-up."""
    after = [s for s in samples if s.frames >= warmup_frames]
    if len(after) < 4:
        return (float("nan"),) * 4   # type: ignore[return-value]
    x = np.array([s.frames for s in after], float)
    slope = float(np.polyfit(x, [s.rss_mb - s.canvas_mb for s in after], 1)[0] * 1000)
    raw = float(np.polyfit(x, [s.rss_mb for s in after], 1)[0] * 1000)
    quarter = max(2, len(after) // 4)

    def fps(part: list[Sample]) -> float:
        return (part[-1].frames - part[0].frames) / max(part[-1].elapsed_s - part[0].elapsed_s, 1e-9)
    return slope, raw, fps(after[:quarter]), fps(after[-quarter:])


def run(quick: bool = False) -> ScanSoakResult:
    return measure(QUICK_AREA if quick else AREA, SPEED * (2 if quick else 1), 2.0, quick)


def load(path: Path) -> ScanSoakResult:
    """A result this bench wrote (its JSON), e.g. for the report to render it again."""
    result: ScanSoakResult = load_json(ScanSoakResult, path)
    return result


def to_markdown(r: ScanSoakResult) -> str:
    verdict = {True: "met", False: "NOT met"}
    lines = [provenance_markdown(r.provenance) + "  ", f"Load average at the end: {r.loadavg_after}.", "",
             f"`touchroller scan` in one process over a raster of the large scene (area {r.area} m, "
             f"{r.speed * 1e3:g} mm/s): {r.outcome}, {r.frames} frames processed in {r.duration_s:.0f} s; warm-up "
             f"{r.warmup_frames} frames.", "",
             f"**Goal: memory growth <= {r.goal_mb_per_1000:g} MB per 1000 frames after the world map's own growth: "
             f"{verdict[r.memory_met]} ({r.slope_mb_per_1000:+.2f} MB per 1000 frames; RSS alone "
             f"{r.raw_slope_mb_per_1000:+.2f}).**", "",
             f"**Goal: a steady rate (the first quarter's frames per second within {r.goal_steady:g}x of the last "
             f"quarter's): {verdict[r.steady_met]} ({r.first_fps:.1f} -> {r.last_fps:.1f} frames/s, "
             f"x{r.steady:.2f}).**", "",
             "| elapsed (s) | frames | RSS (MB) | world map canvas (MB) |", "|---:|---:|---:|---:|"]
    step = max(1, len(r.samples) // 20)
    for s in r.samples[::step]:
        lines.append(f"| {s.elapsed_s:.0f} | {s.frames} | {s.rss_mb:.1f} | {s.canvas_mb:.1f} |")
    if r.top_growth:
        lines += ["", "Where Python memory grew most after warm-up (tracemalloc):", "",
                  *(f"- {line}" for line in r.top_growth)]
    return "\n".join(lines) + "\n"


def write(result: ScanSoakResult, out: Path | None = None) -> Path:
    path = out or results_path("scan_soak", result.quick)
    write_results(path, "Scan soak: the scan graph in one process (`bench/scan_soak.py`)", result, to_markdown)
    return path


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="a short raster (CI-sized)")
    parser.add_argument("--area", default=None, help="x,y,length,width of the raster, m")
    parser.add_argument("--speed", type=float, default=None, help="m/s along a pass")
    parser.add_argument("--every", type=float, default=2.0, help="seconds between samples")
    parser.add_argument("--trace", action="store_true", help="tracemalloc: where Python memory grew")
    parser.add_argument("--trim", action="store_true", help="malloc_trim before each sample: memory that stays "
                        "is held by something, not free pages the allocator kept (a diagnosis, not the figures)")
    parser.add_argument("--set", action="append", default=[], metavar="NAME:=VALUE",
                        help="a node parameter for the scan (e.g. map.publish_rate:=0.0), as `touchroller scan`")
    parser.add_argument("--out", type=Path, default=None)
    args = parser.parse_args(argv)
    from touchroller_bringup.commands.scan import parse_items

    _, _, overrides = parse_items(args.set)
    area = tuple(float(v) for v in args.area.split(",")) if args.area else (QUICK_AREA if args.quick else AREA)
    speed = args.speed or SPEED * (2 if args.quick else 1)
    result = measure(area, speed, args.every, args.quick, args.trace, args.trim,   # type: ignore[arg-type]
                     overrides)
    path = write(result, args.out)
    print(path.read_text())
    return 0


if __name__ == "__main__":
    os.environ.setdefault("ROS_AUTOMATIC_DISCOVERY_RANGE", "LOCALHOST")
    sys.exit(main())
