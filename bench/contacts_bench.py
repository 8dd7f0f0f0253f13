"""Contact detection + localisation time per 640x480 frame (median, one core), and accuracy against settings.

Frames: the simulator's contact_localisation scene (no-contact frames and taps with 3 contacts) and
surface_mapping scene (rolling over fabric). Per frame: `ContactDetector.detect` then `localise` through the per-pixel
`SurfaceLookup` (PointStamped has no covariance, so the node does not compute it), as the
perception node does. OpenCV is limited to one thread.

Goal (issue 4): <= 1 ms median per frame. Results: bench/results/contacts_bench.md
(`python -m bench.contacts_bench [--quick]`; the report generator calls `run` and `to_markdown`).
"""
from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from bench._common import load_dict, provenance, provenance_markdown, results_path, save_figure, write_results
from touchroller_perception.contacts import BackgroundModel, ContactDetector, DetectorConfig
from touchroller_perception.localisation import SurfaceLookup, localise

#: Detector settings compared for accuracy against time on the tap frames.
SETTINGS: dict[str, dict[str, Any]] = {
    "colour, downscale 4 (default)": {},
    "colour, downscale 2": {"downscale": 2},
    "colour, downscale 8": {"downscale": 8},
    "colour, no refinement blur": {"refine_blur_sigma": 0.0},
    "colour, threshold 4 sigma": {"threshold_sigma": 4.0},
    "paper pipeline": {"method": "paper"},
}


def sim_workloads(frames_per_kind: int):
    """name -> (reference frames, frames, truth per frame), the camera, and the source's name."""
    from touchroller_driver.sim import SimulatedSensor, load_scene

    sensor = SimulatedSensor(load_scene("contact_localisation"), seed=0)
    frames = list(sensor.frames())
    references = [f.image for f in frames if f.truth.get("phase") == "reference"]
    taps = [f for f in frames if f.truth.get("phase") == "tap"][:frames_per_kind]
    idle = [f.image for f in frames if f.truth.get("phase") == "gap"][:frames_per_kind]
    workloads = {
        "no contact (contact_localisation gaps)": (references, idle, [[]] * len(idle)),
        "3 contacts (contact_localisation taps)": (references, [f.image for f in taps],
                                                   [[c["point"] for c in f.truth["contacts"]] for f in taps]),
    }
    mapping = SimulatedSensor(load_scene("surface_mapping"), seed=0)
    mapping_frames = [f.image for _, f in zip(range(frames_per_kind + 5), mapping.frames(), strict=False)]
    # the band is in contact from the first frame, so the reference holds it too: this measures the
    # detector on textured, changing frames, not a meaningful contact count
    workloads["rolling over fabric (surface_mapping)"] = (mapping_frames[:5], mapping_frames[5:], None)
    return workloads, sensor.camera, "touchroller_driver.sim"


def time_workload(references, frames, truths, camera, lookup, config: DetectorConfig, repeats: int) -> dict[str, Any]:
    """Each frame's time is its best over `repeats` passes over the same frames (a noisy machine only ever
    adds time); every pass starts from a fresh detector, so each frame does the same work every time
    (the background refits fall on the same frames)."""
    best = np.full(len(frames), np.inf)
    counts, errors, missed = [], [], 0
    for repeat in range(repeats):
        detector = ContactDetector(config)
        detector.set_reference(references)
        detector.detect(frames[0])   # warm caches (downscaled reference)
        detector.background = BackgroundModel()   # back to the state a stream starts in (the cache stays)
        for k, frame in enumerate(frames):
            start = time.perf_counter()
            contacts = detector.detect(frame)
            located = localise(camera, contacts, covariance=False, lookup=lookup)   # what the node does
            best[k] = min(best[k], time.perf_counter() - start)
            if repeat == 0:
                counts.append(len(contacts))
            if truths is not None and repeat == 0:
                for point in truths[k]:
                    distances = [np.linalg.norm(loc.point - np.asarray(point)) for loc in located if loc.valid]
                    if distances and min(distances) < 3e-3:
                        errors.append(1e3 * min(distances))
                    else:
                        missed += 1
    t = best * 1e3
    return {"median_ms": float(np.median(t)), "p90_ms": float(np.percentile(t, 90)), "max_ms": float(t.max()),
            "frames_timed": len(t), "contacts_per_frame": float(np.mean(counts)),
            "error_mm": float(np.mean(errors)) if errors else float("nan"), "matched": len(errors), "missed": missed}


def run(quick: bool = False) -> dict[str, Any]:
    stamp = provenance("contacts_bench", quick)
    cv2.setNumThreads(1)
    frames_per_kind, repeats = (10, 3) if quick else (40, 10)
    workloads, camera, source = sim_workloads(frames_per_kind)
    lookup = SurfaceLookup(camera)   # built once per camera model, as in the node
    speed = []
    for name, (references, frames, truths) in workloads.items():
        result = time_workload(references, frames, truths, camera, lookup, DetectorConfig(), repeats)
        speed.append({"workload": name, **result})
        print(f"{name:45s} median {result['median_ms']:.3f} ms  p90 {result['p90_ms']:.3f} ms  "
              f"contacts/frame {result['contacts_per_frame']:.2f}", flush=True)
    tap_name = next(n for n in workloads if n.startswith("3 contacts"))
    references, frames, truths = workloads[tap_name]
    settings = []
    for label, changes in SETTINGS.items():
        result = time_workload(references, frames, truths, camera, lookup, DetectorConfig(**changes), repeats)
        settings.append({"setting": label, **result})
        print(f"{label:45s} median {result['median_ms']:.3f} ms  error {result['error_mm']:.4f} mm  "
              f"missed {result['missed']}", flush=True)
    return {"speed": speed, "settings": settings, "tap_frames": tap_name, "source": source, "quick": quick,
            "provenance": stamp}


def to_markdown(result: dict[str, Any]) -> str:
    lines = [provenance_markdown(result["provenance"]), ""]
    if result.get("note"):
        lines += [result["note"], ""]
    lines += [
             f"OpenCV on one thread (cv2.setNumThreads(1)); frames: {result['source']}, 640x480 bgr8. "
             "Each frame's time is its best of several passes over the same frames, each pass from a fresh "
             "detector (the same work every time; load on the machine only adds time); median, p90 and max "
             "are over the frames.", "",
             "| workload | median ms | p90 ms | max ms | frames timed | contacts/frame |",
             "|---|---|---|---|---|---|"]
    for r in result["speed"]:
        lines.append(f"| {r['workload']} | {r['median_ms']:.3f} | {r['p90_ms']:.3f} | {r['max_ms']:.3f} | "
                     f"{r['frames_timed']} | {r['contacts_per_frame']:.2f} |")
    lines += ["", "Goal: detection + localisation <= 1 ms median per 640x480 frame on one core "
                  "(default colour detector):"]
    for r in result["speed"]:
        verdict = "met" if r["median_ms"] <= 1.0 else "NOT met"
        lines.append(f"- {r['workload']}: **{verdict}** ({r['median_ms']:.3f} ms, "
                     f"{r['contacts_per_frame']:.1f} blobs/frame)")
    lines += ["", "The rolling-over-fabric frames are a stress case, not a contact-localisation workload: the "
              "roller is in contact from the first frame, so the reference holds the band and the moving "
              "texture keeps about a fifth of the image changed and shows up as blobs. All blobs of a frame "
              "are refined at full resolution in one batch (their windows packed into one mosaic), so the "
              "cost grows with the blobs' pixels rather than with a dozen OpenCV/numpy calls per blob.", "",
              f"### Accuracy against time on the tap frames ({result['tap_frames']}, exact calibration)", "",
              "| detector setting | median ms | mean error mm | contacts found / missed |", "|---|---|---|---|"]
    for r in result["settings"]:
        lines.append(f"| {r['setting']} | {r['median_ms']:.3f} | {r['error_mm']:.4f} | "
                     f"{r['matched']} / {r['missed']} |")
    return "\n".join(lines) + "\n"


def figures(result: dict[str, Any], out_dir: Path) -> list[Path]:
    """Contact error against detector time per setting (the tap frames), beside the per-workload cost."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    fig, (ax, bx) = plt.subplots(1, 2, figsize=(12, 4.2))
    for i, r in enumerate(result["settings"], 1):
        colour = "tab:red" if "paper" in r["setting"] else "tab:blue"
        ax.scatter(r["median_ms"], max(r["error_mm"], 1e-4), color=colour, label=f"{i}: {r['setting']}")
        ax.annotate(str(i), (r["median_ms"], max(r["error_mm"], 1e-4)), fontsize=8, xytext=(3, 3),
                    textcoords="offset points")
    ax.set_yscale("log")
    ax.axvline(1.0, color="k", lw=0.8, ls="--")
    ax.set_xlabel("detection + localisation, median ms per frame")
    ax.set_ylabel("mean contact error, mm")
    ax.set_title(f"Contact error against detector time ({result['tap_frames'].split(' (')[0]})", fontsize=10)
    ax.legend(fontsize=7)
    ax.grid(alpha=0.3)
    names = [r["workload"].split(" (")[0] for r in result["speed"]]
    y = np.arange(len(names))
    bx.barh(y - 0.2, [r["median_ms"] for r in result["speed"]], 0.4, label="median")
    bx.barh(y + 0.2, [r["p90_ms"] for r in result["speed"]], 0.4, label="p90")
    bx.axvline(1.0, color="k", lw=0.8, ls="--", label="goal 1 ms (median)")
    bx.set_yticks(y, names, fontsize=8)
    bx.set_xlabel("ms per 640x480 frame (default detector)")
    bx.set_title("Cost per workload", fontsize=10)
    bx.legend(fontsize=7)
    fig.tight_layout()
    path = out_dir / "contacts_bench.png"
    save_figure(fig, path, dpi=110)
    plt.close(fig)
    return [path]

load = load_dict   # the report reads the recorded JSON back through the bench's `load`



def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="fewer frames and repeats")
    parser.add_argument("--out", help="results file (default: bench/results/contacts_bench.md, quick/ with --quick)")
    parser.add_argument("--note", help="a line about the conditions, written under the machine line "
                                       "(e.g. that the machine was shared)")
    args = parser.parse_args(argv)
    result = run(quick=args.quick)
    if args.note:
        result["note"] = args.note
    out = Path(args.out) if args.out else results_path("contacts_bench", args.quick)
    write_results(out, "Contact detection + localisation time per frame", result, to_markdown, figures)
    print(f"wrote {out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
