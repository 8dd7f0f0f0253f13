"""Contact detection + localisation time per 640x480 frame (median, one core).

Frames: the simulator's contact_localisation scene (no-contact frames and taps with 3 contacts) and
surface_mapping scene (a contact band across the image), or the fallback TapRenderer when the
simulator is not installed. Per frame: `ContactDetector.detect` then `localise` through the
per-pixel `SurfaceLookup` (PointStamped has no covariance, so the node does not compute it), as
the perception node does. OpenCV is limited to one thread.

Goal (issue 4): <= 1 ms median per frame. Results: bench/results/contacts_bench.md.
"""
from __future__ import annotations

import argparse
import os
import platform
import sys
import time
from pathlib import Path

import cv2
import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from touchroller_perception.contacts import ContactDetector, DetectorConfig  # noqa: E402
from touchroller_perception.localisation import (  # noqa: E402
    TABLE_II_CAMERA,
    SurfaceLookup,
    TapRenderer,
    localise,
)

RESULTS = ROOT / "bench" / "results" / "contacts_bench.md"


def machine() -> str:
    cpu = "unknown CPU"
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                cpu = line.split(":", 1)[1].strip()
                break
    except OSError:
        pass
    return (f"nproc {len(os.sched_getaffinity(0))} (of {os.cpu_count()}), {cpu}, Python {platform.python_version()}, "
            f"OpenCV {cv2.__version__}, numpy {np.__version__}")


def sim_workloads(frames_per_kind: int) -> tuple[dict[str, tuple[list, list[np.ndarray]]], object]:
    """name -> (reference frames, frames) from the simulator, and the camera."""
    from touchroller_driver.sim import SimulatedSensor, load_scene

    sensor = SimulatedSensor(load_scene("contact_localisation"), seed=0)
    frames = list(sensor.frames())
    references = [f.image for f in frames if f.truth.get("phase") == "reference"]
    taps = [f.image for f in frames if f.truth.get("phase") == "tap"][:frames_per_kind]
    idle = [f.image for f in frames if f.truth.get("phase") == "gap"][:frames_per_kind]
    workloads = {"no contact (contact_localisation gaps)": (references, idle),
                 "3 contacts (contact_localisation taps)": (references, taps)}
    mapping = SimulatedSensor(load_scene("surface_mapping"), seed=0)
    mapping_frames = [f.image for _, f in zip(range(frames_per_kind + 5), mapping.frames(), strict=False)]
    # the band is in contact from the first frame, so the reference holds it too: this measures the
    # detector on textured, changing frames, not a meaningful contact count
    workloads["rolling over fabric (surface_mapping)"] = (mapping_frames[:5], mapping_frames[5:])
    return workloads, sensor.camera


def synthetic_workloads(frames_per_kind: int):
    renderer = TapRenderer(TABLE_II_CAMERA, seed=0)
    rng = np.random.default_rng(0)
    camera = TABLE_II_CAMERA
    references = [renderer.render([], rng) for _ in range(5)]
    points = camera.surface_point(np.array([-0.025, 0.0, 0.025]), np.array([0.0, 0.26, -0.26]))
    uv, _ = camera.project(points)
    return {"no contact (TapRenderer)": (references, [renderer.render([], rng) for _ in range(frames_per_kind)]),
            "3 contacts (TapRenderer)": (references, [renderer.render(uv, rng) for _ in range(frames_per_kind)])}, camera


def time_workload(references, frames, camera, config: DetectorConfig, repeats: int) -> dict[str, float]:
    detector = ContactDetector(config)
    detector.set_reference(references)
    detector.detect(frames[0])   # warm caches (downscaled reference)
    lookup = SurfaceLookup(camera)   # built once per camera model, as in the node
    times, counts = [], []
    for _ in range(repeats):
        for frame in frames:
            start = time.perf_counter()
            contacts = detector.detect(frame)
            localise(camera, contacts, covariance=False, lookup=lookup)   # what the perception node does
            times.append(time.perf_counter() - start)
            counts.append(len(contacts))
    t = np.array(times) * 1e3
    return {"median_ms": float(np.median(t)), "p90_ms": float(np.percentile(t, 90)), "max_ms": float(t.max()),
            "frames": len(t), "contacts_per_frame": float(np.mean(counts))}


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="fewer frames and repeats")
    parser.add_argument("--out", default=str(RESULTS))
    args = parser.parse_args(argv)
    cv2.setNumThreads(1)
    frames_per_kind, repeats = (10, 3) if args.quick else (40, 10)
    try:
        workloads, camera = sim_workloads(frames_per_kind)
        source = "touchroller_driver.sim"
    except ImportError:
        workloads, camera = synthetic_workloads(frames_per_kind)
        source = "touchroller_perception.localisation.TapRenderer (simulator not installed)"
    rows = []
    for name, (references, frames) in workloads.items():
        for method in ("colour", "paper"):
            result = time_workload(references, frames, camera, DetectorConfig(method=method), repeats)
            rows.append((name, method, result))
            print(f"{name:45s} {method:7s} median {result['median_ms']:.3f} ms  p90 {result['p90_ms']:.3f} ms  "
                  f"contacts/frame {result['contacts_per_frame']:.2f}", flush=True)
    command = "python bench/contacts_bench.py" + (" --quick" if args.quick else "")
    lines = ["# Contact detection + localisation time per frame", "",
             f"Command: `{command}` (cv2.setNumThreads(1)); frames: {source}, 640x480 bgr8.",
             f"Machine: {machine()}.",
             f"Measured {time.strftime('%Y-%m-%d %H:%M UTC', time.gmtime())} while the machine was shared "
             "with other engineers' jobs (timings are contended).", "",
             "| frames | method | median ms | p90 ms | max ms | frames timed | contacts/frame |",
             "|---|---|---|---|---|---|---|"]
    for name, method, r in rows:
        lines.append(f"| {name} | {method} | {r['median_ms']:.3f} | {r['p90_ms']:.3f} | {r['max_ms']:.3f} | "
                     f"{r['frames']} | {r['contacts_per_frame']:.2f} |")
    lines += ["", "Goal: detection + localisation <= 1 ms median per 640x480 frame on one core (colour detector):"]
    for name, method, r in rows:
        if method == "colour":
            verdict = "met" if r["median_ms"] <= 1.0 else "NOT met"
            lines.append(f"- {name}: **{verdict}** ({r['median_ms']:.3f} ms, {r['contacts_per_frame']:.1f} blobs/frame)")
    lines += ["", "The rolling-over-fabric frames are a stress case, not a contact-localisation workload: the "
              "roller is in contact from the first frame, so the reference holds the band and the moving "
              "texture shows up as many blobs, each refined at full resolution (cost grows ~0.1-0.2 ms per blob)."]
    Path(args.out).parent.mkdir(parents=True, exist_ok=True)
    Path(args.out).write_text("\n".join(lines) + "\n", encoding="utf-8")
    print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
