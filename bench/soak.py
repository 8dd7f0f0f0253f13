"""Soak: the camera and perception nodes as real processes for a set number of frames: memory and rate.

Each node is started as its own process, as `ros2 run` starts it (`python -m
touchroller_bringup.nodes.camera_node --ros-args ...`), on a ROS domain of its own with localhost
discovery: the simulated sensor playing its scene over and over (`source:=sim loop:=true`, at `--rate`
times real time) into the perception node with its default parameters (contacts and the live map; no
sweep node, so no sweep ever starts a new map). This process only watches: every `--every` seconds it
reads the resident set size (VmRSS) of both processes from /proc and the perception node's own figures
from `/diagnostics` (frames taken, median processing time per frame, the map's dropped rows), until the
perception node has taken `--frames` frames.

Memory growth is the least-squares slope of the perception process's RSS against the frames it took,
after `warm-up` frames; a steady rate compares the last quarter of the run with the first quarter after
warm-up: the median processing time per frame (what the node spends on a frame, less sensitive to other
load on the machine than frames per second, which is shown beside it).
"""
from __future__ import annotations

import argparse
import math
import os
import re
import signal
import subprocess
import sys
import tempfile
import threading
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from bench._common import ROOT, Provenance, load_json, loadavg, provenance, provenance_markdown, results_path, to_json

FRAMES = 54_000            # 30 minutes of frames at 30 Hz
QUICK_FRAMES = 750         # a CI-sized run: the trend after warm-up from samples every second
GOAL_MB_PER_1000 = 5.0     # RSS growth per 1000 processed frames, after warm-up
GOAL_STEADY = 1.25         # the last quarter's median ms per frame within this factor of the first quarter's
DEFAULT_RATE = 3.0         # simulated seconds per second: 90 frames/s offered, about what one node takes
PERCEPTION, CAMERA = "perception", "camera"


@dataclass(frozen=True)
class Sample:
    elapsed_s: float
    processed: int          # frames the perception node took (its frames_received)
    published: int          # frames the camera published
    perception_mb: float
    camera_mb: float
    processing_ms: float    # the perception node's median processing time per frame (its last 200 frames)
    map_rows_dropped: int
    level: int              # the perception node's diagnostics level (0 OK, 1 WARN, 2 ERROR)
    message: str


@dataclass(frozen=True)
class Trend:
    """One process's memory over the run."""

    process: str
    start_mb: float          # at the first sample after warm-up
    end_mb: float
    peak_mb: float
    slope_mb_per_1000: float  # least squares, after warm-up


@dataclass(frozen=True)
class SoakResult:
    provenance: Provenance
    quick: bool
    frames_target: int
    camera_rate: float
    warmup_frames: int
    samples: tuple[Sample, ...]
    memory: tuple[Trend, ...]
    duration_s: float
    first_ms: float          # median processing ms per frame, first quarter after warm-up
    last_ms: float           # and the last quarter
    first_fps: float         # frames the node took per second, the same quarters
    last_fps: float
    messages: tuple[str, ...]   # the perception node's diagnostics messages seen, in order of first sight
    exit_codes: tuple[int | None, ...]   # camera, perception after SIGINT
    loadavg_after: str
    goal_mb_per_1000: float = GOAL_MB_PER_1000
    goal_steady: float = GOAL_STEADY

    @property
    def perception(self) -> Trend:
        return next(t for t in self.memory if t.process == PERCEPTION)

    @property
    def processed(self) -> int:
        return self.samples[-1].processed if self.samples else 0

    @property
    def memory_met(self) -> bool:
        return all(t.slope_mb_per_1000 <= self.goal_mb_per_1000 for t in self.memory)

    @property
    def steady(self) -> float:
        """last / first median processing time per frame."""
        return self.last_ms / self.first_ms if self.first_ms > 0 else math.nan

    @property
    def steady_met(self) -> bool:
        return math.isfinite(self.steady) and self.steady <= self.goal_steady


def rss_mb(pid: int) -> float:
    try:
        status = Path(f"/proc/{pid}/status").read_text()
    except OSError:
        return math.nan
    line = next((x for x in status.splitlines() if x.startswith("VmRSS:")), None)
    return int(line.split()[1]) / 1024.0 if line else math.nan


class _Watcher:
    """An rclpy node in this process that keeps the latest /diagnostics status of each node."""

    def __init__(self, domain_id: int) -> None:
        import rclpy
        from diagnostic_msgs.msg import DiagnosticArray
        from rclpy.executors import SingleThreadedExecutor

        from touchroller_bringup.ros_diagnostics import status_values

        self.context = rclpy.context.Context()
        rclpy.init(context=self.context, domain_id=domain_id)
        self.node = rclpy.create_node("soak_watcher", context=self.context)
        self.latest: dict[str, tuple[int, str, dict[str, str]]] = {}
        self._lock = threading.Lock()

        def on_diagnostics(array: DiagnosticArray) -> None:
            with self._lock:
                for status in array.status:
                    key = status.name.rsplit("/", 1)[-1]
                    self.latest[key] = (int.from_bytes(status.level, "little") if isinstance(status.level, bytes)
                                        else int(status.level), status.message, status_values(status))

        self.node.create_subscription(DiagnosticArray, "/diagnostics", on_diagnostics, 10)
        self.executor = SingleThreadedExecutor(context=self.context)
        self.executor.add_node(self.node)
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._spin, daemon=True)
        self._thread.start()

    def _spin(self) -> None:
        while not self._stop.is_set() and self.context.ok():
            self.executor.spin_once(timeout_sec=0.1)

    def status(self, key: str) -> tuple[int, str, dict[str, str]] | None:
        with self._lock:
            return self.latest.get(key)

    def close(self) -> None:
        self._stop.set()
        self._thread.join(timeout=5.0)
        self.executor.shutdown()
        self.node.destroy_node()
        self.context.try_shutdown()


def _number(values: dict[str, str], key: str, default: float = math.nan) -> float:
    try:
        return float(values[key])
    except (KeyError, ValueError):
        return default


def _start(module: str, parameters: dict[str, str], env: dict[str, str], log: Path) -> subprocess.Popen:
    args = [sys.executable, "-m", f"touchroller_bringup.nodes.{module}", "--ros-args"]
    for name, value in parameters.items():
        args += ["-p", f"{name}:={value}"]
    with open(log, "w") as out:
        return subprocess.Popen(args, cwd=ROOT, env=env, stdout=out, stderr=subprocess.STDOUT)


def _stop(processes: list[subprocess.Popen]) -> tuple[int | None, ...]:
    for process in processes:
        if process.poll() is None:
            process.send_signal(signal.SIGINT)
    codes = []
    for process in processes:
        try:
            codes.append(process.wait(timeout=30))
        except subprocess.TimeoutExpired:
            process.kill()
            process.wait(timeout=10)
            codes.append(None)
    return tuple(codes)


def trend(process: str, frames: np.ndarray, mb: np.ndarray, warmup: int) -> Trend:
    after = frames >= warmup
    if after.sum() < 2:
        after = np.zeros_like(after)
        after[-2:] = True
    x, y = frames[after] / 1000.0, mb[after]
    slope = float(np.polyfit(x, y, 1)[0]) if len(x) >= 2 and np.ptp(x) > 0 else math.nan
    return Trend(process, float(y[0]), float(y[-1]), float(np.nanmax(mb)), slope)


def quarters(samples: tuple[Sample, ...], warmup: int) -> tuple[float, float, float, float]:
    """(first-quarter ms, last-quarter ms, first-quarter frames/s, last-quarter frames/s) after warm-up."""
    after = [s for s in samples if s.processed >= warmup]
    if len(after) < 8:
        return math.nan, math.nan, math.nan, math.nan
    n = len(after) // 4

    def rate(part: list[Sample]) -> float:
        dt = part[-1].elapsed_s - part[0].elapsed_s
        return (part[-1].processed - part[0].processed) / dt if dt > 0 else math.nan

    def ms(part: list[Sample]) -> float:
        values = [s.processing_ms for s in part if math.isfinite(s.processing_ms)]
        return float(np.median(values)) if values else math.nan

    first, last = after[:n + 1], after[-(n + 1):]
    return ms(first), ms(last), rate(first), rate(last)


def measure(frames: int, rate: float, every_s: float, quick: bool, log_dir: Path) -> SoakResult:
    from touchroller_bringup.ros_domains import reserve_domain_id

    stamp = provenance("soak", quick, *([] if frames == (QUICK_FRAMES if quick else FRAMES) else
                                        ["--frames", str(frames)]),
                       *([] if rate == DEFAULT_RATE else ["--rate", f"{rate:g}"]))
    warmup = min(5000, frames // 2)
    log_dir.mkdir(parents=True, exist_ok=True)
    samples: list[Sample] = []
    messages: dict[str, str] = {}
    with reserve_domain_id() as lease:
        env = dict(os.environ, ROS_DOMAIN_ID=str(lease.domain_id), ROS_AUTOMATIC_DISCOVERY_RANGE="LOCALHOST",
                   PYTHONUNBUFFERED="1")
        watcher = _Watcher(lease.domain_id)
        processes: list[subprocess.Popen] = []
        started = time.monotonic()
        try:
            processes.append(_start("camera_node", {"source": "sim", "loop": "true", "rate": repr(float(rate))}, env,
                                    log_dir / "camera.log"))
            processes.append(_start("perception_node", {}, env, log_dir / "perception.log"))
            # a node that cannot keep up is the finding, not a hang: stop at 5 frames/s on average
            deadline = started + 120.0 + frames / 5.0
            while time.monotonic() < deadline:
                time.sleep(every_s)
                dead = [p for p in processes if p.poll() is not None]
                if dead:
                    raise RuntimeError(f"a node exited early (code {dead[0].returncode}); logs in {log_dir}")
                perception, camera = watcher.status(PERCEPTION), watcher.status(CAMERA)
                if perception is None or camera is None:
                    continue
                level, message, values = perception
                messages[_kind(message)] = message   # the latest of each kind (counts in it change)
                samples.append(Sample(time.monotonic() - started, int(_number(values, "frames_received", 0)),
                                      int(_number(camera[2], "published", 0)), rss_mb(processes[1].pid),
                                      rss_mb(processes[0].pid), _number(values, "processing_ms_median"),
                                      int(_number(values, "map_rows_dropped", 0)), level, message))
                print(f"soak: {samples[-1].processed} frames, perception {samples[-1].perception_mb:.0f} MB, "
                      f"camera {samples[-1].camera_mb:.0f} MB, {samples[-1].processing_ms:.2f} ms/frame, "
                      f"{message}", flush=True)
                if samples[-1].processed >= frames:
                    break
        finally:
            codes = _stop(processes)
            watcher.close()
    duration = time.monotonic() - started
    if not samples:
        raise RuntimeError(f"no diagnostics from the nodes; logs in {log_dir}")
    done = tuple(samples)
    x = np.array([s.processed for s in done], float)
    memory = (trend(PERCEPTION, x, np.array([s.perception_mb for s in done]), warmup),
              trend(CAMERA, x, np.array([s.camera_mb for s in done]), warmup))
    first_ms, last_ms, first_fps, last_fps = quarters(done, warmup)
    return SoakResult(stamp, quick, frames, rate, warmup, done, memory, duration, first_ms, last_ms, first_fps,
                      last_fps, tuple(messages.values()), codes, loadavg())


def _kind(message: str) -> str:
    """A diagnostics message without its numbers: one kind however the counts in it change."""
    return re.sub(r"\d+", "#", message)


def load(path: Path) -> SoakResult:
    """A result this bench wrote (its JSON), e.g. for the report to render it again."""
    result: SoakResult = load_json(SoakResult, path)
    return result


def run(quick: bool = False) -> SoakResult:
    return measure(QUICK_FRAMES if quick else FRAMES, DEFAULT_RATE, 1.0 if quick else 5.0, quick, _log_dir())


def _log_dir() -> Path:
    """The nodes' output, for when a run fails (not a result)."""
    return Path(tempfile.gettempdir()) / f"touchroller_soak_{os.getpid()}"


def _verdict(met: bool) -> str:
    return "met" if met else "NOT met"


def to_markdown(result: SoakResult) -> str:
    p = result.perception
    lines = [
        provenance_markdown(result.provenance) + "  ",
        f"Load average at the end: {result.loadavg_after}.",
        "",
        f"The camera node (simulated sensor, its scene looped at {result.camera_rate:g} x real time) and the "
        f"perception node (default parameters: contacts and the live map) as two processes; no sweep node, so "
        f"nothing starts a new map. {result.processed} frames taken by the perception node in "
        f"{result.duration_s:.0f} s (target {result.frames_target}); warm-up {result.warmup_frames} frames.",
        "",
        f"**Goal: memory growth <= {result.goal_mb_per_1000:g} MB per 1000 processed frames after warm-up: "
        f"{_verdict(result.memory_met)} (perception {p.slope_mb_per_1000:+.3f} MB per 1000 frames).**",
        "",
        f"**Goal: a steady processing rate (the last quarter's median time per frame within "
        f"{result.goal_steady:g}x of the first quarter's): {_verdict(result.steady_met)} "
        f"({result.first_ms:.2f} -> {result.last_ms:.2f} ms per frame, x{result.steady:.2f}; frames taken per "
        f"second {result.first_fps:.1f} -> {result.last_fps:.1f}).**",
        "",
        "| process | RSS after warm-up (MB) | RSS at the end (MB) | peak (MB) | slope (MB per 1000 frames) |",
        "|---|---:|---:|---:|---:|",
    ]
    for t in result.memory:
        lines.append(f"| {t.process} | {t.start_mb:.1f} | {t.end_mb:.1f} | {t.peak_mb:.1f} | "
                     f"{t.slope_mb_per_1000:+.3f} |")
    dropped = result.samples[-1].map_rows_dropped if result.samples else 0
    latest = list({_kind(m): m for m in result.messages}.values())
    lines += [
        "",
        f"The perception node's diagnostics said (the latest of each kind): {'; '.join(repr(m) for m in latest)}. "
        "Map rows dropped "
        f"to stay within `map.max_rows`: {dropped}. Exit codes after SIGINT (camera, perception): "
        f"{', '.join('killed' if c is None else str(c) for c in result.exit_codes)}.",
        "",
        "| elapsed (s) | frames taken | frames published | perception RSS (MB) | camera RSS (MB) | ms per frame "
        "(median) | map rows dropped |",
        "|---:|---:|---:|---:|---:|---:|---:|",
    ]
    step = max(1, len(result.samples) // 20)
    shown = list(result.samples[::step])
    if result.samples and shown[-1] is not result.samples[-1]:
        shown.append(result.samples[-1])
    for s in shown:
        lines.append(f"| {s.elapsed_s:.0f} | {s.processed} | {s.published} | {s.perception_mb:.1f} | "
                     f"{s.camera_mb:.1f} | {s.processing_ms:.2f} | {s.map_rows_dropped} |")
    return "\n".join(lines) + "\n"


def write(result: SoakResult, out: Path | None = None) -> Path:
    path = out or results_path("soak", result.quick)
    path.parent.mkdir(parents=True, exist_ok=True)
    path.with_suffix(".json").write_text(to_json(result, indent=2))
    path.write_text("# Soak: the real nodes as processes (`bench/soak.py`)\n\n" + to_markdown(result))
    return path


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help=f"{QUICK_FRAMES} frames instead of {FRAMES}")
    parser.add_argument("--frames", type=int, default=None, help=f"frames the perception node takes (default "
                        f"{FRAMES}: 30 minutes at 30 Hz)")
    parser.add_argument("--rate", type=float, default=DEFAULT_RATE,
                        help="the simulated camera's rate, x real time (its scene runs at 30 frames/s)")
    parser.add_argument("--every", type=float, default=None, help="seconds between samples")
    parser.add_argument("--out", type=Path, default=None, help="results file (default bench/results/soak.md, "
                        "quick/ with --quick)")
    args = parser.parse_args(argv)
    frames = args.frames or (QUICK_FRAMES if args.quick else FRAMES)
    if frames < 100 or not (0 < args.rate <= 100):
        parser.error("--frames must be >= 100 and --rate in (0, 100]")
    every = args.every or (1.0 if frames <= QUICK_FRAMES else 2.0 if frames <= 10_000 else 5.0)
    result = measure(frames, args.rate, every, args.quick, _log_dir())
    path = write(result, args.out)
    print(path.read_text())
    return 0


if __name__ == "__main__":
    sys.exit(main())
