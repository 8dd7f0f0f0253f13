"""A square metre scanned by the simulator: the live graph's memory and map update, then `touchroller map` on
its recording (issue 25's measures on a simulated scan, not on frames synthesised into the mapper).

For each side (1 m and 0.5 m; the 0.5 m run is the 0.25 m² reference of "memory flat in area"):

* a scene of the simulator's smooth painted panel (`large_surface:panel`: 2 um of orange peel, its own
  grooves and dents) of the side plus a margin, at 0.1 mm per cell, made tile by tile (`surface.lazy`),
  with planted cracks, dents and bumps (`surface.defects`) spread over it, is written as a scene file;
* `touchroller scan`'s machinery (`touchroller_bringup.scan.run_scan`: the whole graph in one process,
  simulated arm and camera on the simulated clock in lockstep with the perception node, `sim.rate` 20 so
  simulated time runs as fast as the frames are taken) rolls a raster over the side x side square at
  `SPEED` (boustrophedon passes of the default usable width and overlap: 22 passes for 1 m), recording on
  (the default compressed recording: lossless PNG images, MCAP). The simulated arm is given
  `arm.reach` 1.8 m (a square metre is beyond a UR5's 0.85 m) and `sweep.approach_speed` 0.05 m/s (moves
  between passes); live findings are off (`inspect:=false`: the measure is the map's);
* measured live: the scan process's peak resident memory (VmHWM; every node of the graph, the simulator and
  the recorder are in it, so it bounds the perception node's), sampled RSS and the world map's tiles in
  memory; each `WorldMapper.push` (the map update of a frame, timed by wrapping the method in this process:
  CPU time of the calling thread, and wall time, which includes waits for the other threads' GIL) and each
  `publish_map` (the live views);
* then `touchroller map RECORDING --out DIR/map.png` as its own process: its peak RSS (wait4), wall and CPU
  time, and frames per second as a whole command (the recording's images over the command's wall time);
* the recording's size, then the recording and the outputs are deleted (free disk checked first).

Goals (issue 25): `touchroller map` peak RSS <= 1 GB and the 1 m² run's within 15 % of the 0.25 m² run's,
>= 500 frames/s as a whole command; the live graph's perception RSS <= 1 GB, map update <= 2 ms per frame
(median, judged on CPU time); the recording holds every frame the camera published ("nothing lost").

Which source the figures rest on: the simulator only (its panel scene varied in area); the synthesised-frame
bench (`bench/map_scale.py`, its own procedural texture, no simulator) measures the mapper alone.

`python -m bench.scan_square_metre [--quick] [--sides 1.0,0.5] [--speed 0.05]` -> bench/results/
scan_square_metre.md + .json. Each side runs in a new process (`--case`), so its peak RSS is its own.
"""
from __future__ import annotations

import argparse
import json
import math
import os
import shutil
import subprocess
import sys
import tempfile
import threading
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import yaml

from bench._common import (
    ROOT,
    Provenance,
    load_json,
    loadavg,
    provenance,
    provenance_markdown,
    results_path,
    to_json,
    write_results,
)
from bench._scan_graph import map_tiles_mb, own_domain, perception_node, status_mb
from touchroller_perception.files import atomic_write_text

SPEED = 0.05              # m/s along a pass
FULL_SIDES = (1.0, 0.5)
QUICK_SIDES = (0.12, 0.06)
RESOLUTION = 1e-4         # m per surface cell and per map pixel
SURFACE_X0 = 0.30         # m: world x of the surface's start edge
MARGIN = 0.02             # m of surface around the raster's area
GOAL_RSS_MB = 1024.0
GOAL_RSS_RATIO = 1.15
GOAL_FPS = 500.0
GOAL_UPDATE_MS = 2.0
MIN_FREE_GB = 15.0        # free disk needed before a 1 m² recording


@dataclass(frozen=True)
class LiveResult:
    outcome: str
    message: str
    wall_s: float                    # run_scan, start to outputs written
    cpu_s: float                     # the process's CPU time over it
    frames_published: int
    frames_processed: int
    frames_dropped: int
    recorded_images: int
    map_px: tuple[int, ...]          # the published view's shape
    coverage_percent: float          # of the raster's rectangle the world map covers
    passes: int                      # passes mapped
    peak_rss_mb: float               # VmHWM of the scan process (all nodes, simulator, recorder)
    rss_samples: tuple[tuple[float, int, float, float], ...]   # (elapsed s, frames taken, RSS MB, map tiles MB)
    pushes: int
    push_cpu_ms_median: float        # WorldMapper.push, CPU time of the calling thread
    push_cpu_ms_p95: float
    push_wall_ms_median: float
    push_wall_ms_p95: float
    publishes: int
    publish_cpu_ms_median: float     # PerceptionNode.publish_map (the live views)
    publish_cpu_ms_max: float
    surface_tiles_made: int          # the simulator's surface tiles made (raw), a dropped tile made again counts
    surface_peak_tiles: int
    recording_mb: float
    world_map: str                   # the scan's world map summary (frame, resolution, latency, passes)


@dataclass(frozen=True)
class OfflineResult:
    returncode: int
    peak_rss_mb: float               # wait4's ru_maxrss of `touchroller map`
    wall_s: float
    cpu_s: float
    frames: int                      # the recording's images
    frames_per_s: float              # frames / wall_s: the whole command
    summary: str                     # the command's last line of output


@dataclass(frozen=True)
class CaseResult:
    side_m: float
    surface_cells: tuple[int, int]
    defects: str
    free_disk_gb: float
    live: LiveResult
    offline: OfflineResult


@dataclass(frozen=True)
class ScanSquareMetreResult:
    provenance: Provenance
    quick: bool
    speed: float
    cases: list[CaseResult]
    offline_rss_ratio: float         # the largest side's `touchroller map` peak RSS over the smallest's
    live_rss_ratio: float
    loadavg_after: str
    note: str = ""                   # how the run deviated from the command (an adopted case)
    goal_rss_mb: float = GOAL_RSS_MB
    goal_rss_ratio: float = GOAL_RSS_RATIO
    goal_fps: float = GOAL_FPS
    goal_update_ms: float = GOAL_UPDATE_MS


# ------------------------------------------------------------------------------------------------ the scene
def scene_data(side: float) -> tuple[dict, tuple[float, float, float, float]]:
    """The scene (a full mapping for a scene file) and the raster's area (x, y, length, width) in `base`."""
    from touchroller_driver.sim import load_scene

    width = length = side + 2 * MARGIN
    cracks = max(2, round(8 * side * side))
    blobs = max(1, round(4 * side * side))
    defects = {"seed": 11, "cracks": cracks, "dents": blobs, "bumps": blobs, "crack_width": [1.5e-4, 4e-4],
               "crack_depth": [4e-5, 1.2e-4], "crack_length": [8e-3, 2.5e-2], "blob_diameter": [1.5e-3, 3e-3],
               "blob_depth": [4e-5, 1.2e-4], "clearance": 5e-3}
    scene = load_scene("large_surface", "panel", **{
        "surface.width": width, "surface.length": length, "surface.resolution": RESOLUTION, "surface.lazy": True,
        "surface.defects": defects, "world.surface_origin": [SURFACE_X0, 0.0, 0.05],
        "description": f"issue 25's square metre: a painted panel {width:g} m x {length:g} m with planted defects"})
    data = {k: v for k, v in scene.data.items() if k not in ("variants", "variant")}   # the variant applied
    data["name"] = f"panel_{side:g}m"
    area = (SURFACE_X0 + MARGIN, -side / 2, side, side)
    return data, area


# ------------------------------------------------------------------------------------------------ live
def _du_mb(path: Path) -> float:
    return sum(p.stat().st_size for p in path.rglob("*") if p.is_file()) / 2**20 if path.exists() else 0.0


def live_case(side: float, speed: float, work: Path, progress: bool) -> tuple[LiveResult, tuple[int, int], str]:
    """The scan in this process (call in a fresh process: its peak RSS is the scan's)."""
    from touchroller_bringup.nodes.perception_node import PerceptionNode
    from touchroller_bringup.scan import ScanOptions, run_scan
    from touchroller_driver.sim.defects import surface_defects
    from touchroller_driver.sim.tiled_surface import TiledSurface
    from touchroller_perception.world_map import WorldMapper

    data, area = scene_data(side)
    scene_path = work / "scene.yaml"
    scene_path.write_text(yaml.safe_dump(data, sort_keys=False))
    plan = surface_defects(data["surface"])
    defects = f"{len(plan.cracks)} cracks, {len(plan.blobs)} dents and bumps"
    cells = (round(data["surface"]["length"] / RESOLUTION), round(data["surface"]["width"] / RESOLUTION))

    pushes: list[tuple[float, float]] = []
    publishes: list[float] = []
    push, publish = WorldMapper.push, PerceptionNode.publish_map

    def timed_push(self, *args, **kwargs):   # type: ignore[no-untyped-def]
        wall, cpu = time.perf_counter(), time.thread_time()
        try:
            return push(self, *args, **kwargs)
        finally:
            pushes.append((time.thread_time() - cpu, time.perf_counter() - wall))

    def timed_publish(self, *args, **kwargs):   # type: ignore[no-untyped-def]
        cpu = time.thread_time()
        try:
            return publish(self, *args, **kwargs)
        finally:
            publishes.append(time.thread_time() - cpu)

    surfaces: list[TiledSurface] = []   # the simulator's surfaces, as they are made
    init = TiledSurface.__init__

    def tracked_init(self, *args, **kwargs):   # type: ignore[no-untyped-def]
        init(self, *args, **kwargs)
        surfaces.append(self)

    TiledSurface.__init__ = tracked_init       # type: ignore[method-assign]
    WorldMapper.push = timed_push              # type: ignore[method-assign]
    PerceptionNode.publish_map = timed_publish  # type: ignore[method-assign]

    samples: list[tuple[float, int, float, float]] = []
    done = threading.Event()
    started = time.monotonic()

    def sample() -> None:
        perception = None
        while not done.wait(2.0):
            perception = perception or perception_node()
            frames = int(getattr(perception, "received", 0)) if perception is not None else 0
            samples.append((time.monotonic() - started, frames, status_mb("VmRSS"), map_tiles_mb(perception)))
            if progress and len(samples) % 15 == 0:
                print(f"  {samples[-1][0]:.0f} s: {frames} frames, RSS {samples[-1][2]:.0f} MB", flush=True)

    sampler = threading.Thread(target=sample, name="square-metre-sampler", daemon=True)
    sampler.start()
    out = work / "scan"
    cpu0 = time.process_time()
    wall0 = time.monotonic()
    try:
        with own_domain():
            result = run_scan(ScanOptions(
                out_dir=out, record=True, storage="mcap", compress=True, progress=None,
                reference_timeout_s=600.0,   # the camera node makes the surface first: passes over 1 m²
                arguments={"scene": str(scene_path), "area": ",".join(f"{v:g}" for v in area),
                           "sweep_speed": f"{speed:g}", "inspect": "false"},
                overrides={"arm.reach": 1.8, "sim.rate": 20.0, "sweep.approach_speed": 0.05,
                           "sweep.max_duration": 7200.0}))
    finally:
        done.set()
        sampler.join()
        WorldMapper.push = push                # type: ignore[method-assign]
        TiledSurface.__init__ = init           # type: ignore[method-assign]
        PerceptionNode.publish_map = publish   # type: ignore[method-assign]
    wall, cpu = time.monotonic() - wall0, time.process_time() - cpu0
    raw = max(surfaces, key=lambda s: s.tiles_made, default=None)
    push_cpu = np.array([p[0] for p in pushes]) * 1e3
    push_wall = np.array([p[1] for p in pushes]) * 1e3
    pub = np.array(publishes) * 1e3

    def stat(values: np.ndarray, q: float) -> float:
        return float(np.percentile(values, q)) if values.size else float("nan")

    coverage = result.coverage
    fraction = getattr(coverage, "fraction", None)
    live = LiveResult(
        result.outcome, result.message, wall, cpu, result.frames_published, result.frames_processed,
        result.frames_dropped, int(sum(n for topic, n in result.recorded.items() if "image_raw" in topic)),
        tuple(result.map_shape or ()), 100.0 * fraction if fraction is not None else float("nan"),
        int(getattr(coverage, "passes_mapped", 0) or 0), status_mb("VmHWM"), tuple(samples), len(pushes),
        stat(push_cpu, 50), stat(push_cpu, 95), stat(push_wall, 50), stat(push_wall, 95), len(publishes),
        stat(pub, 50), float(pub.max()) if pub.size else float("nan"),
        raw.tiles_made if raw is not None else 0, raw.peak_tiles if raw is not None else 0,
        _du_mb(out / "recording"), json.dumps(result.world_map, default=str)[:400] if result.world_map else "")
    return live, cells, defects


# ------------------------------------------------------------------------------------------------ offline
def offline_map(recording: Path, out: Path, frames: int) -> OfflineResult:
    """`touchroller map` on the recording as its own process: peak RSS (wait4), wall and CPU time."""
    out.mkdir(parents=True, exist_ok=True)
    command = [str(Path(sys.executable).with_name("touchroller")), "map", str(recording), "--out",
               str(out / "map.png")]
    log = out / "map.log"
    start = time.monotonic()
    with log.open("w") as stream:
        process = subprocess.Popen(command, stdout=stream, stderr=subprocess.STDOUT, cwd=ROOT)
        _, status, usage = os.wait4(process.pid, 0)
    wall = time.monotonic() - start
    process.returncode = os.waitstatus_to_exitcode(status)
    lines = [line for line in log.read_text().splitlines() if line.strip()]
    return OfflineResult(process.returncode, usage.ru_maxrss / 1024, wall, usage.ru_utime + usage.ru_stime, frames,
                         frames / wall if wall > 0 else float("nan"), lines[-1][:300] if lines else "")


def _wait_for(case_json: Path, pid: int | None, timeout_s: float = 4 * 3600.0) -> None:
    """An adopted case: wait until its process has written `case_json` (or has gone without it)."""
    deadline = time.monotonic() + timeout_s
    while not case_json.exists():
        if pid is not None and not Path(f"/proc/{pid}").exists() and not case_json.exists():
            raise SystemExit(f"scan_square_metre: the adopted case process {pid} ended without {case_json}")
        if time.monotonic() > deadline:
            raise SystemExit(f"scan_square_metre: no {case_json} after {timeout_s:.0f} s")
        time.sleep(5.0)


def run_case(side: float, speed: float, progress: bool, adopt: tuple[Path, int | None] | None = None) -> CaseResult:
    """One side: the live scan in a new process, then `touchroller map` on its recording; deleted after.
    `adopt` (work folder, pid): the live scan of a `--case` process already running there (started by an
    earlier invocation of this bench whose parent was stopped): wait for it instead of starting one."""
    work = adopt[0] if adopt is not None else Path(tempfile.mkdtemp(prefix=f"square_metre_{side:g}_"))
    try:
        free = shutil.disk_usage(work).free / 2**30
        need = MIN_FREE_GB * side * side
        if adopt is None and free < need:
            raise SystemExit(f"scan_square_metre: {free:.0f} GB free at {work}, {need:.0f} GB needed for {side:g} m")
        case_json = work / "live.json"
        if adopt is not None:
            _wait_for(case_json, adopt[1])
        else:
            child = subprocess.run([sys.executable, "-m", "bench.scan_square_metre", "--case", f"{side:g}",
                                    "--speed", f"{speed:g}", "--work", str(work),
                                    *(["--progress"] if progress else [])], cwd=ROOT, check=False)
            if child.returncode != 0 or not case_json.exists():
                raise SystemExit(f"scan_square_metre: the {side:g} m scan failed (exit {child.returncode})")
        payload = json.loads(case_json.read_text())
        from bench._common import from_json

        live = from_json(LiveResult, payload["live"])
        if progress:
            print(f"{side:g} m live: {live.outcome}, {live.frames_processed} frames in {live.wall_s:.0f} s, peak RSS "
                  f"{live.peak_rss_mb:.0f} MB, push {live.push_cpu_ms_median:.2f} ms CPU median; recording "
                  f"{live.recording_mb:.0f} MB", flush=True)
        offline = offline_map(work / "scan" / "recording", work / "offline", live.recorded_images)
        if progress:
            print(f"{side:g} m offline: exit {offline.returncode}, peak RSS {offline.peak_rss_mb:.0f} MB, "
                  f"{offline.frames_per_s:.0f} frames/s, {offline.summary}", flush=True)
        return CaseResult(side, tuple(payload["cells"]), payload["defects"], free, live, offline)
    finally:
        shutil.rmtree(work, ignore_errors=True)


def run(quick: bool = False, sides: tuple[float, ...] | None = None, speed: float = SPEED,
        progress: bool = False, adopt: dict[float, tuple[Path, int | None]] | None = None) -> ScanSquareMetreResult:
    sides = sides or (QUICK_SIDES if quick else FULL_SIDES)
    default = QUICK_SIDES if quick else FULL_SIDES
    extra = [*([] if sides == default else ["--sides", ",".join(f"{s:g}" for s in sides)]),
             *([] if speed == SPEED else ["--speed", f"{speed:g}"])]
    stamp = provenance("scan_square_metre", quick, *extra)
    adopt = adopt or {}
    unknown = set(adopt) - set(sides)
    if unknown:
        raise SystemExit(f"scan_square_metre: --adopt names sides not run: {sorted(unknown)}")
    # the sides to scan first, while the adopted ones' processes go on
    order = [s for s in sides if s not in adopt] + [s for s in sides if s in adopt]
    done = {side: run_case(side, speed, progress, adopt.get(side)) for side in order}
    cases = [done[side] for side in sides]
    note = "; ".join(f"the {side:g} m case's live scan was a `--case` process started by an earlier invocation of "
                     "this command (its parent stopped so that the other sides could run beside it)"
                     for side in sides if side in adopt)
    big, small = max(cases, key=lambda c: c.side_m), min(cases, key=lambda c: c.side_m)
    return ScanSquareMetreResult(stamp, quick, speed, cases, big.offline.peak_rss_mb / small.offline.peak_rss_mb,
                                 big.live.peak_rss_mb / small.live.peak_rss_mb, loadavg(), note=note)


def load(path: Path) -> ScanSquareMetreResult:
    """A result this bench wrote (its JSON), e.g. for the report to render it again."""
    result: ScanSquareMetreResult = load_json(ScanSquareMetreResult, path)
    return result


def goals(r: ScanSquareMetreResult) -> list[tuple[str, bool, str]]:
    """(goal, met, measured) for the report's goal rows: judged on the largest side."""
    big = max(r.cases, key=lambda c: c.side_m)
    side = f"{big.side_m:g} m x {big.side_m:g} m simulated panel"
    ok = big.live.outcome == "done" and big.offline.returncode == 0
    return [
        (f"`touchroller map` peak RSS <= {r.goal_rss_mb:g} MB ({side})",
         ok and big.offline.peak_rss_mb <= r.goal_rss_mb, f"{big.offline.peak_rss_mb:.0f} MB"),
        (f"`touchroller map` peak RSS within {100 * (r.goal_rss_ratio - 1):.0f} % of the smallest side's",
         ok and r.offline_rss_ratio <= r.goal_rss_ratio, f"x{r.offline_rss_ratio:.2f}"),
        (f"`touchroller map` >= {r.goal_fps:g} frames/s as a whole command ({side})",
         ok and big.offline.frames_per_s >= r.goal_fps, f"{big.offline.frames_per_s:.0f} frames/s"),
        (f"live graph's perception RSS <= {r.goal_rss_mb:g} MB (the scan process's peak, {side})",
         ok and big.live.peak_rss_mb <= r.goal_rss_mb, f"{big.live.peak_rss_mb:.0f} MB"),
        (f"map update <= {r.goal_update_ms:g} ms per frame, median (CPU, {side})",
         ok and big.live.push_cpu_ms_median <= r.goal_update_ms, f"{big.live.push_cpu_ms_median:.2f} ms"),
        (f"the recording holds every frame the camera published ({side})",
         ok and big.live.recorded_images == big.live.frames_published,
         f"{big.live.recorded_images} of {big.live.frames_published} frames"),
    ]


def scanning_peak_mb(live: LiveResult, end_s: float = 60.0) -> float:
    """The highest sampled RSS before the last `end_s` seconds of the scan (its end, where the map is finished
    and its files written, left out); NaN without samples."""
    last = max((elapsed for elapsed, _, _, _ in live.rss_samples), default=0.0)
    during = [rss for elapsed, _, rss, _ in live.rss_samples if elapsed < last - end_s]
    return max(during) if during else float("nan")


def to_markdown(r: ScanSquareMetreResult) -> str:
    verdict = {True: "met", False: "NOT met"}
    lines = [provenance_markdown(r.provenance) + "  ", f"Load average at the end: {r.loadavg_after}.", "",
             *([f"Note: {r.note}.", ""] if r.note else []),
             f"A raster at {r.speed * 1e3:g} mm/s over the simulator's painted panel (0.1 mm cells, made tile by tile, "
             "planted defects), live through `touchroller scan`'s graph in one process with the recording on, then "
             "`touchroller map` on the recording in its own process. Source: the simulator only.", ""]
    for goal, met, measured in goals(r):
        lines.append(f"**Goal: {goal}: {verdict[met]} ({measured}).**  ")
    lines += ["", "| side (m) | surface cells | defects | passes | frames taken | outcome | live wall (s) "
              "| live CPU (s) | live peak RSS (MB) | map update CPU median / p95 (ms) | wall median / p95 (ms) "
              "| views published, CPU median / max (ms) | recording (MB) | `touchroller map` peak RSS (MB) "
              "| wall (s) | CPU (s) | frames/s |",
              "|---:|---|---|---:|---:|---|---:|---:|---:|---|---|---|---:|---:|---:|---:|---:|"]
    for c in r.cases:
        lv, of = c.live, c.offline
        lines.append(f"| {c.side_m:g} | {c.surface_cells[0]} x {c.surface_cells[1]} | {c.defects} | {lv.passes} | "
                     f"{lv.frames_processed} | {lv.outcome} | {lv.wall_s:.0f} | {lv.cpu_s:.0f} | "
                     f"{lv.peak_rss_mb:.0f} | "
                     f"{lv.push_cpu_ms_median:.2f} / {lv.push_cpu_ms_p95:.2f} | {lv.push_wall_ms_median:.2f} / "
                     f"{lv.push_wall_ms_p95:.2f} | {lv.publishes}, {lv.publish_cpu_ms_median:.0f} / "
                     f"{lv.publish_cpu_ms_max:.0f} | {lv.recording_mb:.0f} | {of.peak_rss_mb:.0f} | {of.wall_s:.0f} | "
                     f"{of.cpu_s:.0f} | {of.frames_per_s:.0f} |")
    lines += ["", f"`touchroller map` peak RSS, largest side over smallest: x{r.offline_rss_ratio:.2f}; the live scan "
              f"process's: x{r.live_rss_ratio:.2f}. The live scan process's highest RSS sampled (every 2 s) before "
              "the last 60 s of the scan (its end, which finishes the map and writes its files, left out): "
              + ", ".join(f"{c.side_m:g} m {scanning_peak_mb(c.live):.0f} MB" for c in r.cases) + ".", ""]
    for c in r.cases:
        lines.append(f"- {c.side_m:g} m: live {c.live.frames_published} frames published, {c.live.frames_dropped} "
                     f"dropped, {c.live.recorded_images} recorded, coverage {c.live.coverage_percent:.1f} %; "
                     f"simulator surface tiles made {c.live.surface_tiles_made} "
                     f"(at most {c.live.surface_peak_tiles} held); map view {c.live.map_px}; `touchroller map`: "
                     f"exit {c.offline.returncode}, \"{c.offline.summary}\"")
        if c.live.message:
            lines.append(f"  - scan: {c.live.message}")
    return "\n".join(lines) + "\n"


def write(result: ScanSquareMetreResult, out: Path | None = None) -> Path:
    path = out or results_path("scan_square_metre", result.quick)
    write_results(path, "A simulated square metre, live and offline (`bench/scan_square_metre.py`)", result,
                  to_markdown)
    return path


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="small sides (CI-sized)")
    parser.add_argument("--sides", default=None, help="sides of the squares, m, comma-separated")
    parser.add_argument("--speed", type=float, default=SPEED, help="m/s along a pass")
    parser.add_argument("--progress", action="store_true", help="progress lines")
    parser.add_argument("--out", type=Path, default=None)
    parser.add_argument("--adopt", action="append", default=[], metavar="SIDE=WORK[:PID]",
                        help="take side SIDE's live scan from a --case process already running in WORK (pid PID) "
                             "instead of starting one (a run whose parent was stopped); the other sides run first")
    parser.add_argument("--case", type=float, default=None, help=argparse.SUPPRESS)
    parser.add_argument("--work", type=Path, default=None, help=argparse.SUPPRESS)
    args = parser.parse_args(argv)
    if args.case is not None:
        live, cells, defects = live_case(args.case, args.speed, args.work, args.progress)
        atomic_write_text(args.work / "live.json", to_json({"live": live, "cells": cells, "defects": defects}))
        return 0
    sides = tuple(float(v) for v in args.sides.split(",")) if args.sides else None
    if sides is not None and not all(math.isfinite(s) and s > 0 for s in sides):
        parser.error("--sides: positive numbers, m")
    adopt: dict[float, tuple[Path, int | None]] = {}
    for item in args.adopt:
        side, _, where = item.partition("=")
        folder, _, pid = where.partition(":")
        try:
            adopt[float(side)] = (Path(folder), int(pid) if pid else None)
        except ValueError:
            parser.error(f"--adopt {item!r}: SIDE=WORK[:PID]")
        if not Path(folder).is_dir():
            parser.error(f"--adopt {item!r}: no folder {folder}")
    result = run(args.quick, sides, args.speed, args.progress, adopt)
    path = write(result, args.out)
    print(path.read_text())
    return 0


if __name__ == "__main__":
    os.environ.setdefault("ROS_AUTOMATIC_DISCOVERY_RANGE", "LOCALHOST")
    sys.exit(main())
