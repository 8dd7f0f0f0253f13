"""Soak: 20 000 frames through the real graph without memory growth.

Camera node -> perception node -> contact probe, 640x480 bgr8 at `--fps` (default 100 Hz) for
`--frames` frames. The resident set size (VmRSS) of the process holding the nodes is sampled every
1000 frames (with two processes: the perception process and the camera process separately).
Growth is measured from the sample after `--warmup` frames (allocators and caches settle) to the
end, with a least-squares slope per 1000 frames. Results: bench/results/dds_soak.md.

What it does not cover: the frames are a few synthetic images played from memory (`MemorySource`) by a
camera node built in this process, and they do not roll, so the stitched map never grows past its first
rows. `bench/soak.py` runs the real camera (the simulator's scene) and perception nodes as processes
for a set number of frames, with the real map growing as it would.
"""
from __future__ import annotations

import argparse
import dataclasses
import gc
import json
import os
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

from bench import dds_latency as common
from touchroller_perception.files import atomic_write_text

# Run in the perception process with --tracemalloc: Python/numpy allocations that grew between a snapshot
# after warm-up and now, rewritten every few seconds (the process is terminated, not asked to report).
TRACEMALLOC_PRELUDE = """
import gc as _gc, threading as _threading, time as _time, tracemalloc as _tm
_tm.start(6)
def _trace_growth(path={path!r}, warmup_s={warmup_s}, every_s={every_s}):
    _time.sleep(warmup_s)
    _gc.collect()
    base, started = _tm.take_snapshot(), _time.monotonic()
    filters = [_tm.Filter(False, _tm.__file__), _tm.Filter(False, "<frozen importlib._bootstrap>")]
    base = base.filter_traces(filters)
    while True:
        _time.sleep(every_s)
        _gc.collect()
        stats = _tm.take_snapshot().filter_traces(filters).compare_to(base, "traceback")
        lines = [f"{{_time.monotonic() - started:.0f}} s after the warm-up snapshot; traced now "
                 f"{{_tm.get_traced_memory()[0] / 1e6:.2f}} MB"]
        for stat in stats[:12]:
            lines.append(f"{{stat.size_diff / 1e6:+.4f}} MB in {{stat.count_diff:+d}} blocks "
                         f"(now {{stat.size / 1e6:.3f}} MB):")
            lines += ["    " + str(frame) for frame in reversed(stat.traceback)]
        with open(path, "w") as out:
            out.write("\\n".join(lines) + "\\n")
_threading.Thread(target=_trace_growth, daemon=True).start()
"""


def rss_mb(pid: int | None = None) -> float:
    status = Path(f"/proc/{pid or os.getpid()}/status").read_text()
    line = next(x for x in status.splitlines() if x.startswith("VmRSS:"))
    return int(line.split()[1]) / 1024.0


def run_child(processes: int, transport: str, frames: int, fps: float, map_rate: float,
              tracemalloc_path: str = "", warmup: int = 2000) -> dict:
    common.use_transport(transport)
    references, contacts = common.synthetic_frames()
    source = common.MemorySource(references, contacts, fps=fps, count=frames, record=False)
    prelude = ""
    if tracemalloc_path:
        prelude = TRACEMALLOC_PRELUDE.format(path=tracemalloc_path, warmup_s=warmup / fps + 3.0,
                                             every_s=max(5.0, frames / fps / 20))
    graph = common.Graph(processes=processes, record=False, map_rate=map_rate, perception_prelude=prelude)
    samples: list[tuple[int, float, float | None]] = []
    next_sample = [0]

    def monitor() -> None:
        if source.seq >= next_sample[0]:
            child = rss_mb(graph.child.pid) if graph.child is not None else None
            samples.append((source.seq, rss_mb(), child))
            next_sample[0] += 1000

    started = time.monotonic()
    try:
        graph.run_camera(source, timeout_s=frames / fps * 3 + 120, monitor=monitor)
        time.sleep(1.2)
        gc.collect()
        samples.append((source.seq, rss_mb(), rss_mb(graph.child.pid) if graph.child is not None else None))
        contacts_received = graph.probe.count
        recent = np.array(graph.probe.recent_ms)
        perception = dict(graph.probe.perception_status)
    finally:
        graph.close()
    return {"frames": source.seq, "contacts": contacts_received, "seconds": time.monotonic() - started,
            "samples": samples, "recent_latency": dataclasses.asdict(common.summarise(recent)),
            "perception_dropped": perception.get("frames_dropped", "?"),
            "perception_received": perception.get("frames_received", "?")}


def growth(samples: list[tuple[int, float]], warmup: int) -> tuple[float, float, float]:
    """(RSS after warm-up, RSS at the end, least-squares slope in MB per 1000 frames after warm-up)."""
    settled = [(f, m) for f, m in samples if f >= warmup] or samples[-2:]
    frames = np.array([f for f, _ in settled], float)
    mb = np.array([m for _, m in settled], float)
    slope = float(np.polyfit(frames / 1000.0, mb, 1)[0]) if len(settled) >= 2 else float("nan")
    return float(mb[0]), float(mb[-1]), slope


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="2000 frames instead of 20 000")
    parser.add_argument("--frames", type=int, default=20000)
    parser.add_argument("--fps", type=float, default=100.0)
    parser.add_argument("--warmup", type=int, default=2000)
    parser.add_argument("--processes", type=int, nargs="+", choices=(1, 2), default=[1, 2])
    parser.add_argument("--transport", choices=tuple(common.TRANSPORTS), default="shm")
    parser.add_argument("--map-rates", type=float, nargs="+", default=[1.0, 0.0],
                        help="perception map.publish_rate values to run (0 disables the stitched map)")
    parser.add_argument("--tracemalloc", default="", metavar="PATH",
                        help="also write the perception process's Python allocation growth (tracemalloc) to "
                             "PATH (slows it down; use for finding a leak, not for the RSS figures)")
    parser.add_argument("--out", help="results file (default: bench/results/dds_soak.md, quick/ with --quick)")
    parser.add_argument("--child", action="store_true", help=argparse.SUPPRESS)
    args = parser.parse_args(argv)
    frames = 2000 if args.quick else args.frames
    warmup = min(args.warmup, frames // 4)
    if args.child:
        print(json.dumps(run_child(args.processes[0], args.transport, frames, args.fps, args.map_rates[0],
                                   args.tracemalloc, warmup)), flush=True)
        return 0
    command = "python -m bench.dds_soak " + " ".join(argv if argv is not None else sys.argv[1:])
    lines = [
        "# Soak: frames through the graph without memory growth",
        "",
        f"Command: `{command.strip()}`  ",
        f"Machine: {common.machine()}  ",
        f"Date: {time.strftime('%Y-%m-%d %H:%M UTC', time.gmtime())}  ",
        f"{frames} frames of 640x480 bgr8 at {args.fps:g} Hz, transport {args.transport}; VmRSS sampled every "
        f"1000 frames; growth measured after {warmup} frames of warm-up.",
        "",
        "Pass: less than 0.1 MB per 1000 frames after warm-up (a leak of one VGA frame per 1000 frames would "
        "be 0.9 MB per 1000).",
        "",
        "The perception node's map (map.publish_rate > 0) stitches every frame; runs with the map disabled "
        "(map.publish_rate 0) separate the stitcher's memory from the rest of the graph.",
        "",
        "| map rate | processes | process | frames | contacts | RSS after warm-up (MB) | RSS at end (MB) | "
        "slope (MB/1000 frames) | result |",
        "|---|---|---|---|---|---|---|---|---|",
    ]
    details = []
    for map_rate, processes in [(m, p) for m in args.map_rates for p in args.processes]:
        result = subprocess.run(
            [sys.executable, "-m", __spec__.name, "--child", "--processes", str(processes),
             "--transport", args.transport, "--frames", str(frames), "--fps", str(args.fps),
             "--map-rates", str(map_rate), "--warmup", str(warmup),
             *(["--tracemalloc", f"{args.tracemalloc}.map{map_rate:g}.p{processes}"] if args.tracemalloc else [])],
            capture_output=True, text=True, timeout=3600, cwd=common.ROOT)
        line = next((x for x in reversed(result.stdout.splitlines()) if x.startswith("{")), None)
        if line is None:
            print(result.stderr[-2000:], file=sys.stderr)
            return 1
        r = json.loads(line)
        series = {"camera + probe" if processes == 2 else "all nodes": [(f, m) for f, m, _ in r["samples"]]}
        if processes == 2:
            series["perception"] = [(f, c) for f, _, c in r["samples"]]
        for name, samples in series.items():
            start, end, slope = growth(samples, warmup)
            ok = slope < 0.1
            lines.append(f"| {map_rate:g} | {processes} | {name} | {r['frames']} | {r['contacts']} | "
                         f"{start:.1f} | {end:.1f} | "
                         f"{slope:+.4f} | {'met' if ok else 'NOT met'} |")
            print(lines[-1], flush=True)
        details.append(f"- map rate {map_rate:g}, {processes} process(es): {r['seconds']:.0f} s; perception drops "
                       f"{r['perception_dropped']} of {r['perception_received']} received; latency of the last "
                       f"2000 contacts p50 {r['recent_latency']['p50']:.2f} ms, "
                       f"p99 {r['recent_latency']['p99']:.2f} ms; RSS samples (frames: MB) "
                       + ", ".join(f"{f}: {m:.1f}" + (f"/{c:.1f}" if c is not None else "")
                                   for f, m, c in r["samples"]))
    lines += ["", *details, ""]
    out = Path(args.out) if args.out else common.results_path("dds_soak", args.quick)
    out.parent.mkdir(parents=True, exist_ok=True)
    atomic_write_text(out, "\n".join(lines))
    print(f"wrote {out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
