"""A slow consumer skips stale frames instead of queueing them: contact latency stays bounded.

The camera node publishes at 60 Hz while the perception node's image callback is slowed down by
`--delay-ms` (default 50 ms, i.e. it can handle 20 frames/s). If frames were queued, the age of the
contacts would grow by ~2/3 s every second; with the perception node's keep-last depth-1 image
subscription, each processed frame is the newest one and the contact latency stays below about
two processing times. Runs the real graph (bench/dds_latency.py helpers), in one and two processes.
Results: bench/results/dds_slow_consumer.md.
"""
from __future__ import annotations

import argparse
import json
import subprocess
import sys
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from bench import dds_latency as common
from bench._common import to_json
from touchroller_perception.files import atomic_write_text

SLOW_PRELUDE = """
import time as _time
import touchroller_bringup.nodes.perception_node as _perception
_original = _perception.PerceptionNode._on_image
def _slow(self, msg, _original=_original):
    _time.sleep({delay})
    return _original(self, msg)
_perception.PerceptionNode._on_image = _slow
"""


@dataclass(frozen=True)
class SlowConsumerRun:
    """The camera at 60 Hz, the perception callback slowed by `delay_ms`: the contact latency must stay
    bounded (`bound_ms`) and not grow from the first second to the last."""

    processes: int
    transport: str
    seconds: float
    delay_ms: float
    bound_ms: float
    met: bool
    sent: int
    processed: int
    stats: common.LatencyStats
    first_second_median: float
    last_second_median: float

    @classmethod
    def from_json(cls, row: dict) -> SlowConsumerRun:
        return cls(**{**row, "stats": common.LatencyStats(**row["stats"])})


def run_child(processes: int, transport: str, seconds: float, delay_ms: float) -> dict:
    common.use_transport(transport)
    references, contacts = common.synthetic_frames()
    fps = 60.0
    source = common.MemorySource(references, contacts, fps=fps, count=int(seconds * fps))
    graph = common.Graph(processes=processes, perception_prelude=SLOW_PRELUDE.format(delay=delay_ms / 1000.0))
    try:
        graph.run_camera(source, timeout_s=seconds + 60)
        with graph.probe.lock:
            arrivals = dict(graph.probe.arrivals)
    finally:
        graph.close()
    stamps = [s for s in source.contact_stamps if s in arrivals]
    latency = np.array([(arrivals[s] - s) * 1e-6 for s in stamps])
    first = source.contact_stamps[0]
    sent_time = np.array([(s - first) * 1e-9 for s in stamps])
    early = latency[sent_time < 1.0 + sent_time.min()] if latency.size else latency
    late = latency[sent_time > sent_time.max() - 1.0] if latency.size else latency
    return {"sent": len(source.contact_stamps), "processed": int(latency.size),
            "stats": common.summarise(latency),
            "first_second_median": float(np.median(early)) if early.size else float("nan"),
            "last_second_median": float(np.median(late)) if late.size else float("nan")}


def bound_ms(delay_ms: float) -> float:
    """Ideal: one frame in processing + one waiting + a frame period; 2x that for a loaded machine."""
    return 4 * delay_ms + 1000 / 60


def judge(result: dict, processes: int, transport: str, seconds: float, delay_ms: float) -> SlowConsumerRun:
    """A `run_child` result with its configuration and verdict: bounded latency that does not grow."""
    stats = result["stats"]
    stats = stats if isinstance(stats, common.LatencyStats) else common.LatencyStats(**stats)
    met = (stats.max <= bound_ms(delay_ms)
           and result["last_second_median"] <= result["first_second_median"] + delay_ms)
    return SlowConsumerRun(processes, transport, seconds, delay_ms, bound_ms(delay_ms), bool(met), result["sent"],
                           result["processed"], stats, result["first_second_median"], result["last_second_median"])


def run_and_judge(processes: int, transport: str, seconds: float, delay_ms: float) -> SlowConsumerRun:
    """`run_child` in this process (the transport must already be selected), judged."""
    return judge(run_child(processes, transport, seconds, delay_ms), processes, transport, seconds, delay_ms)


def measure(processes: int, transport: str, seconds: float, delay_ms: float) -> SlowConsumerRun:
    """`run_child` in a fresh interpreter, judged."""
    result = subprocess.run(
        [sys.executable, "-m", __spec__.name, "--child", "--processes", str(processes),
         "--transport", transport, "--seconds", str(seconds), "--delay-ms", str(delay_ms)],
        capture_output=True, text=True, timeout=900, cwd=common.ROOT)
    line = next((x for x in reversed(result.stdout.splitlines()) if x.startswith("{")), None)
    if line is None:
        raise RuntimeError(f"slow-consumer child failed: {result.stderr.strip().splitlines()[-3:]}")
    return judge(json.loads(line), processes, transport, seconds, delay_ms)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true")
    parser.add_argument("--seconds", type=float, default=15.0)
    parser.add_argument("--delay-ms", type=float, default=50.0)
    parser.add_argument("--processes", type=int, nargs="+", choices=(1, 2), default=[1, 2])
    parser.add_argument("--transport", choices=tuple(common.TRANSPORTS), default="shm")
    parser.add_argument("--out", help="results file (default: bench/results/dds_slow_consumer.md, quick/ with --quick)")
    parser.add_argument("--child", action="store_true", help=argparse.SUPPRESS)
    args = parser.parse_args(argv)
    seconds = 5.0 if args.quick else args.seconds
    if args.child:
        print(to_json(run_child(args.processes[0], args.transport, seconds, args.delay_ms)), flush=True)
        return 0
    command = "python -m bench.dds_slow_consumer " + " ".join(argv if argv is not None else sys.argv[1:])
    lines = [
        "# Slow consumer: stale frames are skipped, not queued",
        "",
        f"Command: `{command.strip()}`  ",
        f"Machine: {common.machine()}  ",
        f"Date: {time.strftime('%Y-%m-%d %H:%M UTC', time.gmtime())}  ",
        f"Camera at 60 Hz for {seconds:g} s; perception image callback slowed by {args.delay_ms:g} ms; "
        f"transport {args.transport}.",
        "",
        f"Pass: latency max <= {bound_ms(args.delay_ms):.0f} ms "
        "(4 x delay + a frame period; ideal is 2 x delay + a period) and "
        "the last second's median no more than one delay above the first second's. Queueing would instead add "
        "~0.67 s of age per second of run.",
        "",
        "| processes | frames sent | frames with a contact | p50 (ms) | p99 (ms) | max (ms) | first-second median | "
        "last-second median | result |",
        "|---|---|---|---|---|---|---|---|---|",
    ]
    for processes in args.processes:
        r = measure(processes, args.transport, seconds, args.delay_ms)
        s = r.stats
        lines.append(f"| {processes} | {r.sent} | {r.processed} | {s.p50:.1f} | {s.p99:.1f} | "
                     f"{s.max:.1f} | {r.first_second_median:.1f} | {r.last_second_median:.1f} | "
                     f"{'met' if r.met else 'NOT met'} |")
        print(lines[-1], flush=True)
    out = Path(args.out) if args.out else common.results_path("dds_slow_consumer", args.quick)
    out.parent.mkdir(parents=True, exist_ok=True)
    atomic_write_text(out, "\n".join(lines) + "\n")
    print(f"wrote {out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
