"""Square metres: the world map's memory, the pyramid's write time and window reads on large rasters.

Issue 25's measures, at 0.1 mm per pixel:

* peak resident memory (RSS) of mapping a 1 m x 1 m raster (22 passes) and writing its files, against the
  same for 0.5 m x 0.5 m (11 passes): <= 1 GB, and the 1 m² run within 15 % of the 0.25 m² run's
  (memory flat in area: the map's tiles beyond the cache live on disk);
* writing the pyramid of 1 m² (map.tif with its overviews, map.png + map.yaml): goal <= 10 s, judged in CPU
  time (wall time beside it);
* any 512 x 512 window of any level read back from map.tif (the file open, as a viewer keeps it): goal
  <= 10 ms (the slowest of 10 random windows per level), in CPU time beside the wall time (the machine
  the figures are taken on is shared: its wall time includes waits for the other jobs).

* the map update per frame (`WorldMapper.push_band`, CPU time of the calling thread; median and p95) on a
  1 m raster rolled at the live scan's 50 mm/s with the live node's settings (the latency estimated, not
  told; frames waiting for it placed provisionally), over two surfaces: the bench's texture, and a featureless
  one (grey 130 and a grey level of sensor noise per frame, a smooth painted panel as far as registration is
  concerned: no registration finds an offset): goal <= 2 ms (median) on each.

The frames are synthesised straight into the mapper API (`WorldMapper.push_band` with a pose lookup), not
rendered by the simulator (the mapper alone, no renderer and no graph; `bench/scan_square_metre.py` scans a
simulated square metre through the whole graph and `touchroller map`): each band is
the bench's own procedural texture (band-limited noise, periodic over 0.2 m, sampled at the world points
of the band's pixels as the mapper's geometry defines them) at a boustrophedon raster's pose (20 mm/s at
30 frames/s, pressed; lifted by 3 mm between passes, over a fifth of the 1 s move each way); the latency
is told (0), registration is on. Each area runs in a new process (`--case`), so its peak RSS is its own.

`python -m bench.map_scale [--quick]` -> bench/results/map_scale.md + .json. The report calls `run(quick)`
and `to_markdown(result)`; quick mode maps 0.2 m x 0.2 m and 0.1 m x 0.1 m, and times the update on the first
3 passes of the 1 m raster (the full run: all 22).
"""
from __future__ import annotations

import argparse
import json
import math
import resource
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np

from bench._common import ROOT, Provenance, loadavg, provenance, provenance_markdown, results_path, to_json
from touchroller_perception.files import atomic_write_text

SPEED = 0.02        # m/s along a pass
FPS = 30.0
PASS_STEP = 0.045   # m between passes (64 mm bands, 25 % overlap)
LIFT = 0.003        # m above the pressed height between passes
PRESSED_Z = 0.10    # the cylinder frame's height when pressed, m
RES = 1e-4
FULL = {"sides": (1.0, 0.5), "update_passes": None}   # None: the whole raster
QUICK = {"sides": (0.2, 0.1), "update_passes": 3}
UPDATE_SIDE = 1.0   # m: the raster the map update is timed on
LIVE_SPEED = 0.05   # m/s: the live square-metre scan's (bench.scan_square_metre)
SURFACES = ("textured", "featureless")
GOAL_UPDATE_MS = 2.0
GOAL_RSS_MB = 1024.0
GOAL_RSS_RATIO = 1.15
GOAL_WRITE_S = 10.0
GOAL_WINDOW_MS = 10.0


@dataclass(frozen=True)
class CaseResult:
    side_m: float
    passes: int
    frames: int
    mapped: int
    map_px: tuple[int, int]          # (rows, columns) of map.tif
    map_s: float                     # pushing the frames and finalise() (wall time)
    map_cpu_s: float                 # the same in CPU time (the machine may be shared)
    frames_per_s: float
    peak_rss_map_mb: float           # after mapping
    peak_rss_mb: float               # after writing the files too
    most_tiles_in_memory: int
    tiles: int                       # level-0 tiles of one layer the map has
    spilled: int
    write_s: float                   # map.tif + map.png + map.yaml (wall time)
    write_cpu_s: float               # the same in CPU time (all threads of the process)
    tif_mb: float
    levels: int
    view_downscale: int
    window_ms_max: float             # the slowest random 512 x 512 window of any level (wall time)
    window_ms_median: float
    window_cpu_ms_max: float         # the same windows' CPU time (the machine may be shared)
    window_cpu_ms_median: float


@dataclass(frozen=True)
class UpdateResult:
    """The map update per frame on one surface (`run_update`)."""

    surface: str                     # "textured" (the bench's texture) or "featureless"
    side_m: float
    passes: int
    speed: float                     # m/s along a pass
    frames: int
    mapped: int
    registrations: int               # frames registered against the earlier passes
    registered: int                  # ... of which found an offset
    cpu_ms_median: float             # push_band, CPU time of the calling thread
    cpu_ms_p95: float
    cpu_ms_mean: float
    spilled: int                     # tiles written out to disk over the run
    loaded: int                      # tiles read back


@dataclass(frozen=True)
class MapScaleResult:
    provenance: Provenance
    quick: bool
    cases: list[CaseResult]
    rss_ratio: float                 # the largest case's peak RSS over the smallest's
    loadavg_after: str
    goal_rss_mb: float = GOAL_RSS_MB
    goal_rss_ratio: float = GOAL_RSS_RATIO
    goal_write_s: float = GOAL_WRITE_S
    goal_window_ms: float = GOAL_WINDOW_MS
    updates: list[UpdateResult] = field(default_factory=list)
    goal_update_ms: float = GOAL_UPDATE_MS


def _texture(seed: int = 0, size: int = 2048) -> np.ndarray:
    """Band-limited noise (features of 0.3-2 mm at 0.1 mm per pixel), periodic, grey levels ~60-200."""
    rng = np.random.default_rng(seed)

    def periodic_blur(sigma: float) -> np.ndarray:
        pad = int(4 * sigma)
        noise = np.pad(rng.normal(0, 1, (size, size)).astype(np.float32), pad, mode="wrap")
        return cv2.GaussianBlur(noise, (0, 0), sigma)[pad:-pad, pad:-pad]

    fine, coarse = periodic_blur(2.0), periodic_blur(8.0)
    texture = fine / fine.std() + 0.7 * coarse / coarse.std()
    return (130 + 35 * texture / texture.std()).astype(np.float32)


class Raster:
    """A boustrophedon raster over a square of `side` m from (0, 0): passes along world x at `speed`,
    `PASS_STEP` apart along y, the roller's axis along y; lifted and moved across between passes."""

    def __init__(self, side: float, speed: float = SPEED) -> None:
        self.side = side
        self.speed = speed
        self.passes = max(1, math.ceil((side - 0.064) / PASS_STEP) + 1)
        self.pass_s = side / speed
        self.move_s = 1.0   # lifted, across to the next pass
        self.duration = self.passes * self.pass_s + (self.passes - 1) * self.move_s

    def poses(self, stamps_ns: np.ndarray) -> np.ndarray:
        """T_world_cylinder (N, 4, 4): columns x = world y (the axis), y = world x (the roll), z = down."""
        t = np.asarray(stamps_ns, np.float64) * 1e-9
        period = self.pass_s + self.move_s
        k = np.clip(np.floor(t / period), 0, self.passes - 1)
        into = t - k * period
        rolling = into <= self.pass_s
        forward = (k % 2) == 0
        along = np.clip(into, 0, self.pass_s) * self.speed
        x = np.where(forward, along, self.side - along)
        frac = np.clip((into - self.pass_s) / self.move_s, 0, 1)
        y = 0.032 + (k + np.where(rolling, 0.0, frac)) * PASS_STEP
        # lifted and lowered over a fifth of the move each (the mapper sees the roller leave the surface)
        z = PRESSED_Z + np.where(rolling, 0.0, LIFT * np.clip(np.minimum(frac, 1 - frac) * 5, 0, 1))
        out = np.zeros((len(t), 4, 4))
        out[:, 0, 1] = out[:, 1, 0] = 1.0
        out[:, 2, 2] = -1.0
        out[:, 3, 3] = 1.0
        out[:, 0, 3], out[:, 1, 3], out[:, 2, 3] = x, y, z
        return out


def _band(texture: np.ndarray, pose: np.ndarray, rows_m: np.ndarray, cols_m: np.ndarray) -> np.ndarray:
    """The band at `pose`: pixel (i, j) is the texture at world (x + rows_m[i], y + cols_m[j]) (module
    docstring), the texture periodic."""
    period = texture.shape[0]
    u = np.mod((pose[0, 3] + rows_m) / RES, period).astype(np.float32)   # texture column: world x
    v = np.mod((pose[1, 3] + cols_m) / RES, period).astype(np.float32)   # texture row: world y
    map_x = np.broadcast_to(u[:, None], (len(rows_m), len(cols_m)))
    map_y = np.broadcast_to(v[None, :], (len(rows_m), len(cols_m)))
    return cv2.remap(texture, np.ascontiguousarray(map_x), np.ascontiguousarray(map_y), cv2.INTER_LINEAR,
                     borderMode=cv2.BORDER_WRAP)


def _band_grid(mapper: object) -> tuple[np.ndarray, np.ndarray]:
    """(rows_m, cols_m): where the band's pixels lie from the roller's contact line, m (module docstring)."""
    sampler = mapper.strip.sampler   # type: ignore[attr-defined]
    assert sampler is not None and sampler.mm_per_px and sampler.mm_per_px_cols and sampler.centre_u is not None
    rows, cols = sampler.rows, sampler.cols
    rows_m = (np.arange(rows) - (rows - 1) / 2.0) * sampler.mm_per_px * 1e-3
    cols_m = (np.arange(cols) - sampler.centre_u) * sampler.mm_per_px_cols * 1e-3
    return rows_m, cols_m


def run_update(surface: str, passes: int | None = None, side: float = UPDATE_SIDE,
               speed: float = LIVE_SPEED) -> UpdateResult:
    """The map update per frame (`WorldMapper.push_band`, CPU time of this thread) over the first `passes` passes
    (None: all) of a `side` raster at `speed`, with the live node's settings (latency estimated, provisional
    placing); the band synthesised outside the timing. `surface`: "textured" (the bench's texture) or
    "featureless" (grey 130 and N(0, 1) grey levels of noise, new every frame)."""
    from touchroller_perception.geometry import CameraModel
    from touchroller_perception.tiles import TileConfig
    from touchroller_perception.world_map import WorldMapConfig, WorldMapper

    if surface not in SURFACES:
        raise ValueError(f"surface is one of {SURFACES}, got {surface!r}")
    camera = CameraModel()
    raster = Raster(side, speed)
    passes = raster.passes if passes is None else min(passes, raster.passes)
    with tempfile.TemporaryDirectory(prefix="map-update-") as folder:
        config = WorldMapConfig(resolution=RES, latency=None, provisional=True, tiles=TileConfig(folder=folder))
        mapper = WorldMapper(camera, raster.poses, config)
        calls = [0, 0]
        register = mapper._register

        def counted(*args, **kwargs):   # type: ignore[no-untyped-def]
            calls[0] += 1
            found = register(*args, **kwargs)
            calls[1] += found is not None
            return found

        mapper._register = counted   # type: ignore[method-assign]
        mapper.source_rows((camera.height, camera.width))
        rows_m, cols_m = _band_grid(mapper)
        texture = _texture()
        rng = np.random.default_rng(7)
        duration = passes * raster.pass_s + (passes - 1) * raster.move_s
        stamps = np.arange(0, duration, 1.0 / FPS)
        cpu = np.empty(len(stamps))
        for k, t in enumerate(stamps):
            stamp = int(round(t * 1e9))
            if surface == "textured":
                band = _band(texture, raster.poses(np.array([stamp]))[0], rows_m, cols_m)
            else:
                band = np.float32(130.0) + rng.normal(0.0, 1.0, (len(rows_m), len(cols_m))).astype(np.float32)
            begin = time.thread_time()
            mapper.push_band(band, stamp)
            cpu[k] = time.thread_time() - begin
        mapper.finalise()
        store = mapper.canvas.store
        result = UpdateResult(surface, side, passes, speed, len(stamps), mapper.stats.mapped, calls[0], calls[1],
                              1e3 * float(np.median(cpu)), 1e3 * float(np.percentile(cpu, 95)),
                              1e3 * float(cpu.mean()), store.spilled, store.loaded)
        mapper.close()
    return result


def run_case(side: float, out_dir: Path) -> CaseResult:
    """Map one raster and write its files (in this process: its peak RSS is the case's)."""
    from touchroller_bringup.geotiff import PyramidReader
    from touchroller_bringup.map_files import write_world_map
    from touchroller_perception.geometry import CameraModel
    from touchroller_perception.tiles import TileConfig
    from touchroller_perception.world_map import WorldMapConfig, WorldMapper

    camera = CameraModel()
    raster = Raster(side)
    config = WorldMapConfig(resolution=RES, latency=0.0, tiles=TileConfig(folder=str(out_dir)))
    mapper = WorldMapper(camera, raster.poses, config)
    mapper.source_rows((camera.height, camera.width))
    rows_m, cols_m = _band_grid(mapper)
    texture = _texture()
    stamps = np.arange(0, raster.duration, 1.0 / FPS)
    most = 0
    start, start_cpu = time.perf_counter(), time.process_time()
    for k, t in enumerate(stamps):
        stamp = int(round(t * 1e9))
        pose = raster.poses(np.array([stamp]))[0]
        mapper.push_band(_band(texture, pose, rows_m, cols_m), stamp)
        if k % 50 == 0:
            most = max(most, mapper.canvas.store.resident())
    mapper.finalise()
    map_s, map_cpu_s = time.perf_counter() - start, time.process_time() - start_cpu
    most = max(most, mapper.canvas.store.resident())
    rss_map = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0
    start, start_cpu = time.perf_counter(), time.process_time()
    png, yaml_path = write_world_map(out_dir / "map.png", mapper.view(), "base")
    write_s, write_cpu_s = time.perf_counter() - start, time.process_time() - start_cpu
    rss = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0
    import yaml

    meta = yaml.safe_load(yaml_path.read_text())
    tif = out_dir / "map.tif"
    rng = np.random.default_rng(1)
    times, cpu = [], []
    with PyramidReader(tif) as reader:   # as a viewer reads it: the file open, a window at a time
        for level in range(meta["geotiff"]["levels"]):
            w, h = (math.ceil(n / 2 ** level) for n in meta["geotiff"]["size"])
            for _ in range(10):
                r0, c0 = int(rng.integers(0, max(h - 512, 1))), int(rng.integers(0, max(w - 512, 1)))
                begin, begin_cpu = time.perf_counter(), time.thread_time()
                window = reader.window(level, r0, c0, 512, 512)
                times.append(time.perf_counter() - begin)
                cpu.append(time.thread_time() - begin_cpu)
                assert window.shape[0] == min(512, h - r0)
    geotiff = meta["geotiff"]
    result = CaseResult(side, raster.passes, len(stamps), mapper.stats.mapped, (geotiff["size"][1], geotiff["size"][0]),
                        map_s, map_cpu_s, len(stamps) / map_s, rss_map, rss, most,
                        len(mapper.canvas.store.tiles("weight")), mapper.canvas.store.spilled, write_s, write_cpu_s,
                        tif.stat().st_size / 1e6, geotiff["levels"], meta["view"]["downscale"], 1e3 * max(times),
                        1e3 * float(np.median(times)), 1e3 * max(cpu), 1e3 * float(np.median(cpu)))
    mapper.close()
    return result


def run(quick: bool = False) -> MapScaleResult:
    stamp = provenance("map_scale", quick)
    plan = QUICK if quick else FULL
    updates = [run_update(surface, plan["update_passes"]) for surface in SURFACES]
    cases = []
    for side in plan["sides"]:
        with tempfile.TemporaryDirectory(prefix="map-scale-") as folder:
            done = subprocess.run([sys.executable, "-m", "bench.map_scale", "--case", str(side), "--dir", folder],
                                  cwd=ROOT, capture_output=True, text=True)
            if done.returncode:
                raise RuntimeError(f"map_scale case {side} m failed: {done.stderr.strip().splitlines()[-1:]}")
            data = json.loads(done.stdout.strip().splitlines()[-1])
            data["map_px"] = tuple(data["map_px"])
            cases.append(CaseResult(**data))
    ratio = max(cases, key=lambda c: c.side_m).peak_rss_mb / min(cases, key=lambda c: c.side_m).peak_rss_mb
    return MapScaleResult(stamp, quick, cases, ratio, loadavg(), updates=updates)


def load(path: Path) -> MapScaleResult:
    """A recorded result (bench/results/map_scale.json) read back."""
    data = json.loads(Path(path).read_text())
    data["provenance"] = Provenance(**data["provenance"])
    data["cases"] = [CaseResult(**{**c, "map_px": tuple(c["map_px"])}) for c in data["cases"]]
    data["updates"] = [UpdateResult(**u) for u in data.get("updates", [])]
    return MapScaleResult(**data)


def largest(result: MapScaleResult) -> CaseResult:
    return max(result.cases, key=lambda c: c.side_m)


def goals(result: MapScaleResult) -> list[tuple[str, str, bool | None]]:
    """(goal, figure, met) for the report's goal rows; a quick run (small areas) is not judged."""
    big = largest(result)
    judge = (lambda ok: None) if result.quick else (lambda ok: ok)
    area = f"{big.side_m:g} m x {big.side_m:g} m"
    return [
        ("peak RSS", f"{big.peak_rss_mb:.0f} MB mapping + writing {area} ({big.most_tiles_in_memory} tiles in memory "
                     f"at most of {big.tiles})", judge(big.peak_rss_mb <= result.goal_rss_mb)),
        ("flat in area", f"{result.rss_ratio:.2f}x the smallest raster's peak RSS",
         judge(result.rss_ratio <= result.goal_rss_ratio)),
        ("pyramid write", f"{big.write_cpu_s:.1f} s CPU ({big.write_s:.1f} s wall) for {area} ({big.map_px[1]} x "
                          f"{big.map_px[0]} px, {big.levels} levels, {big.tif_mb:.0f} MB)",
         judge(big.write_cpu_s <= result.goal_write_s)),
        ("window read", f"slowest {big.window_cpu_ms_max:.2f} ms CPU ({big.window_ms_max:.2f} ms wall) of "
                        f"{10 * big.levels} random 512 x 512 windows over {big.levels} levels",
         judge(big.window_cpu_ms_max <= result.goal_window_ms)),
        _update_goal(result, judge),
    ]


def _update_goal(result: MapScaleResult, judge: Callable[[bool], bool | None]) -> tuple[str, str, bool | None]:
    """The map update's goal row: the slower surface's median, both surfaces' figures."""
    if not result.updates:
        return "map update", "not measured by this run", None
    worst = max(result.updates, key=lambda u: u.cpu_ms_median)
    first = result.updates[0]
    figures = "; ".join(f"{u.surface} {u.cpu_ms_median:.2f} ms (p95 {u.cpu_ms_p95:.2f})" for u in result.updates)
    return ("map update", f"{worst.cpu_ms_median:.2f} ms CPU median, {worst.surface} ({figures}; {first.frames} "
                          f"frames, {first.passes} passes of {first.side_m:g} m at {first.speed * 1e3:g} mm/s)",
            judge(worst.cpu_ms_median <= result.goal_update_ms))


def to_markdown(result: MapScaleResult) -> str:
    lines = [provenance_markdown(result.provenance), "",
             "Frames synthesised straight into `WorldMapper.push_band` (the bench's own periodic texture and "
             "raster poses; not the simulator), 0.1 mm per pixel, each area in its own process.", "",
             "| raster | passes | frames | map (px) | mapping | peak RSS after mapping | peak RSS with the files "
             "| tiles in memory (most) / of the map | write map.tif + png + yaml | map.tif | levels | "
             "512² window, slowest / median (wall; CPU) |",
             "|---|---|---|---|---|---|---|---|---|---|---|---|"]
    for c in sorted(result.cases, key=lambda c: -c.side_m):
        lines.append(f"| {c.side_m:g} m x {c.side_m:g} m | {c.passes} | {c.frames} | {c.map_px[1]} x {c.map_px[0]} "
                     f"| {c.map_s:.1f} s ({c.frames_per_s:.0f} frames/s; {c.map_cpu_s:.1f} s CPU) "
                     f"| {c.peak_rss_map_mb:.0f} MB "
                     f"| {c.peak_rss_mb:.0f} MB | {c.most_tiles_in_memory} / {c.tiles} ({c.spilled} spilled) "
                     f"| {c.write_s:.1f} s ({c.write_cpu_s:.1f} s CPU) | {c.tif_mb:.0f} MB "
                     f"| {c.levels} (map.png 1/{c.view_downscale}) "
                     f"| {c.window_ms_max:.2f} / {c.window_ms_median:.2f} ms; {c.window_cpu_ms_max:.2f} / "
                     f"{c.window_cpu_ms_median:.2f} ms |")
    lines += ["", f"Peak RSS of the largest raster over the smallest's: {result.rss_ratio:.2f} "
                  f"(goal <= {result.goal_rss_ratio:.2f}). Load average at the end: {result.loadavg_after}."]
    if result.updates:
        lines += ["", "The map update per frame (`WorldMapper.push_band`, CPU time of the calling thread) with the "
                      "live node's settings (latency estimated, provisional placing), the band synthesised outside the "
                      f"timing (goal <= {result.goal_update_ms:g} ms, median, on each surface):", "",
                  "| surface | raster | frames (mapped) | registered against earlier passes (found an offset) "
                  "| update CPU median / p95 / mean (ms) | tiles spilled / read back |",
                  "|---|---|---|---|---|---|"]
        for u in result.updates:
            lines.append(f"| {u.surface} | {u.passes} passes of {u.side_m:g} m at {u.speed * 1e3:g} mm/s "
                         f"| {u.frames} ({u.mapped}) | {u.registrations} ({u.registered}) "
                         f"| {u.cpu_ms_median:.2f} / {u.cpu_ms_p95:.2f} / {u.cpu_ms_mean:.2f} "
                         f"| {u.spilled} / {u.loaded} |")
    return "\n".join(lines) + "\n"


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--quick", action="store_true")
    parser.add_argument("--case", type=float, help=argparse.SUPPRESS)
    parser.add_argument("--dir", help=argparse.SUPPRESS)
    parser.add_argument("--update", choices=SURFACES, help="only time the map update on this surface (printed, "
                                                           "not recorded)")
    parser.add_argument("--passes", type=int, help="with --update: the raster's first passes only")
    args = parser.parse_args(argv)
    if args.update is not None:
        print(to_json(run_update(args.update, args.passes), indent=1))
        return 0
    if args.case is not None:
        print(to_json(run_case(args.case, Path(args.dir))))
        return 0
    result = run(args.quick)
    results_path("map_scale", args.quick).parent.mkdir(parents=True, exist_ok=True)
    atomic_write_text(results_path("map_scale", args.quick, ".json"), to_json(result, indent=1) + "\n")
    atomic_write_text(results_path("map_scale", args.quick), "# Square metres: memory, pyramid, windows\n\n"
                      + to_markdown(result))
    print(to_markdown(result))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
