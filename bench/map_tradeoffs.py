"""Surface mapping: the paper's Table I reproduced in the simulator, and what map accuracy costs (issue 5).

* Table I: the `surface_mapping` scene (8 cm x 11 cm fabric) rolled in 15 s, 10 s and 5 s; the paper's
  stitching (integer Δy in [-25, 25] by MAE, `method="paper"`) and ours (`"default"`), scored
  - like for like against the simulator's ideal tactile rendering of the true surface
    (`surface_map_truth().tactile`: same modality, no blur/noise/background), aligned by translation only
    (no scale, so drift is not hidden), both images standardised to the same mean and contrast;
  - with the paper's protocol against the height map (standing in for its grey top-down photo): the
    3-point constrained affine alignment (getAffineTransform + warpAffine), points at the fabric's true
    top and bottom;
  - length (drift) error: stitched travel against the arm's, and the largest position error on the way.
  plus the per-frame Δy histograms of the paper's figure.
* Trade-offs: methods and settings (search range, subpixel, window, keyframes, motion prior, background
  model, ...) — map quality against compute time per frame; and map quality against scan time.
* Speed: the live map update (`Stitcher.push`) per frame. The speed of `touchroller map` as a whole command
  against reading the bag is `bench/map_speed.py`'s (its own report section).

Every frame is stitched as the perception node and the CLI do: `Stitcher.push` one frame at a time,
then `finalise()`. OpenCV is limited to one thread.

`python -m bench.map_tradeoffs [--quick]` -> bench/results/map_tradeoffs.md + map_tradeoffs.png +
map_dy_histograms.png + map_tradeoffs.json; the report generator calls `run(quick)`, `to_markdown` and
`figures` (the two PNGs beside the report).
"""
from __future__ import annotations

import argparse
import sys
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from bench._common import load_json, provenance, provenance_markdown, results_path, save_figure, to_json
from touchroller_perception.files import atomic_write_text
from touchroller_perception.metrics import (  # noqa: E402
    align_affine_3pt,
    compare_to_truth,
    scores,
    standardise,
    valid_box,
)
from touchroller_perception.stitching import Stitcher, StitcherConfig  # noqa: E402

SPEEDS = {"slow": 15.0, "medium": 10.0, "fast": 5.0}  # the paper's three scan times (s)
PAPER_TABLE_I = {"slow": (0.291, 15.09, 15.03), "medium": (0.305, 14.41, 16.43), "fast": (0.330, 15.59, 14.04)}

#: name -> (method, Stitcher keywords, use the arm's speed as a motion prior)
SWEEP: dict[str, tuple[str, dict[str, Any], bool]] = {
    "paper: integer MAE, ±25 px": ("paper", {}, False),
    "paper: integer MAE, ±10 px": ("paper", {"search": 10}, False),
    "default": ("default", {}, False),
    "default + arm speed prior": ("default", {}, True),
    "no subpixel (integer shifts)": ("default", {"subpixel": False}, False),
    "frame-to-frame (no keyframes)": ("default", {"keyframes": False}, False),
    "no motion prior (full ±25 search)": ("default", {"motion_prior": False}, False),
    "no background model (flat field)": ("default", {"background": False}, False),
    "no rectification (plain crop)": ("default", {"rectify": False}, False),
    "window 30 rows": ("default", {"band_rows": 30}, False),
    "window 120 rows": ("default", {"band_rows": 120}, False),
    "columns binned x1": ("default", {"column_bin": 1}, False),
    "columns binned x8": ("default", {"column_bin": 8}, False),
    "no lateral tracking": ("default", {"lateral": False}, False),
}
SCAN_TIMES = (4.0, 5.0, 7.5, 10.0, 15.0, 20.0)


@dataclass
class Roll:
    images: list[np.ndarray]
    stamps: list[int]
    travel: np.ndarray  # m per frame (the arm's)
    speed: np.ndarray  # m/s per frame (the arm's)
    camera: Any
    mm_per_px: float  # along the roll at the contact line
    truth: Any  # the simulator's TruthMap


def simulate(duration: float, seed: int = 0, **overrides: Any) -> Roll:
    from touchroller_driver.sim import SimulatedSensor, load_scene

    scene = load_scene("surface_mapping", **{"motion.duration": duration, **overrides})
    sensor = SimulatedSensor(scene, seed=seed)
    images, stamps, travel, speed = [], [], [], []
    for frame in sensor.frames():
        images.append(frame.image)
        stamps.append(frame.stamp_ns)
        travel.append(frame.truth["state"]["travel"])
        speed.append(frame.truth["state"]["speed"])
    _, mpp_v = sensor.metres_per_px_at_contact()
    return Roll(images, stamps, np.array(travel), np.array(speed), sensor.camera, mpp_v * 1e3,
                sensor.surface_map_truth())


def stitch_roll(roll: Roll, method: str, settings: dict[str, Any], arm_prior: bool) -> tuple[Stitcher, float]:
    """Stitch frame by frame as the node/CLI do; returns the stitcher and the push time per frame (ms)."""
    stitcher = Stitcher(StitcherConfig(method=method, history=None, **settings), camera=roll.camera)
    px_per_m = 1e3 / roll.mm_per_px
    dt = np.diff(np.array(roll.stamps, dtype=np.float64), prepend=roll.stamps[0]) * 1e-9
    # the surface moves up the image (-v) as the roller travels forward
    priors = -roll.speed * dt * px_per_m if arm_prior else [None] * len(roll.images)
    start = time.perf_counter()
    for image, stamp, prior in zip(roll.images, roll.stamps, priors, strict=True):
        stitcher.push(image, stamp, prior)
    stitcher.finalise()
    return stitcher, (time.perf_counter() - start) / len(roll.images) * 1e3


def evaluate(roll: Roll, stitcher: Stitcher) -> dict[str, Any]:
    image = stitcher.map_image()
    truth = roll.truth
    like = compare_to_truth(image, truth.tactile, valid=stitcher.map_coverage())
    true_px = (roll.travel - roll.travel[0]) * 1e3 / roll.mm_per_px
    est_px = -np.array([s.position_px for s in stitcher.steps])
    length_error = (est_px[-1] - true_px[-1]) / true_px[-1] * 100.0
    drift = float(np.max(np.abs(est_px - true_px)) / abs(true_px[-1]) * 100.0)
    # The paper's protocol against the height map: the top of the map placed where the fabric's top is
    # (from the like-for-like fit), the bottom where the fabric's true bottom is (the true length).
    dy, dx = like["offset_rows"], like["offset_cols"]
    true_rows = abs(true_px[-1]) + stitcher.band_rows - 1
    x0 = image.shape[1] / 2.0
    warped, valid, _ = align_affine_3pt(image, truth.image, [(x0, 0.0), (x0, image.shape[0] - 1.0)],
                                        [(x0 + dx, dy), (x0 + dx, dy + true_rows)])
    box = valid_box(valid)
    paper = {"ssim": float("nan"), "psnr": float("nan"), "mae_percent": float("nan")}
    if box is not None and min(box[0].stop - box[0].start, box[1].stop - box[1].start) > 16:
        paper = scores(standardise(warped[box]), standardise(truth.image[box].astype(np.float64)))
    return {
        "ssim": like["ssim"], "psnr": like["psnr"], "mae_percent": like["mae_percent"],
        "paper_ssim": paper["ssim"], "paper_psnr": paper["psnr"], "paper_mae_percent": paper["mae_percent"],
        "length_error_percent": float(length_error), "drift_percent": drift,
        "prior_frames": int(sum(s.used_prior for s in stitcher.steps)), "frames": len(stitcher.steps),
        "shifts": [float(s) for s in stitcher.shifts[1:]],
    }


def table_i(seeds: list[int]) -> dict[str, Any]:
    out: dict[str, Any] = {}
    for variant, duration in SPEEDS.items():
        for method in ("paper", "default"):
            runs = []
            for seed in seeds:
                roll = simulate(duration, seed)
                stitcher, ms = stitch_roll(roll, method, {}, False)
                result = evaluate(roll, stitcher)
                result["ms_per_frame"] = ms
                runs.append(result)
            out[f"{variant}/{method}"] = {
                "variant": variant, "method": method, "duration": duration, "seeds": seeds,
                **{k: [r[k] for r in runs] for k in runs[0] if k != "shifts"},
                "shifts": runs[0]["shifts"],
            }
    return out


def sweep(duration: float, seed: int) -> list[dict[str, Any]]:
    roll = simulate(duration, seed)
    rows = []
    for name, (method, settings, arm_prior) in SWEEP.items():
        stitcher, ms = stitch_roll(roll, method, settings, arm_prior)
        result = evaluate(roll, stitcher)
        result.pop("shifts")
        rows.append({"setting": name, "ms_per_frame": ms, **result})
    return rows


def scan_time_sweep(seed: int, times: tuple[float, ...]) -> list[dict[str, Any]]:
    rows = []
    for duration in times:
        roll = simulate(duration, seed)
        for method in ("paper", "default"):
            stitcher, ms = stitch_roll(roll, method, {}, False)
            result = evaluate(roll, stitcher)
            result.pop("shifts")
            speed_px = float(np.max(np.abs(np.diff(roll.travel)))) * 1e3 / roll.mm_per_px
            rows.append({"duration": duration, "method": method, "ms_per_frame": ms,
                         "peak_px_per_frame": speed_px, **result})
    return rows


#: name -> (scan time s, scene overrides): other surfaces, the other direction, glitches
ROBUSTNESS: dict[str, tuple[float, dict[str, Any]]] = {
    "knit, 10 s": (10.0, {"surface.pattern": "knit"}),
    "twill, 10 s": (10.0, {"surface.pattern": "twill"}),
    "gravel photo, 10 s": (10.0, {"surface.kind": "image", "surface.image": "gravel.png"}),
    "reverse roll, 10 s": (10.0, {"motion.direction": -1}),
    "JPEG + 2 % dropped frames, 10 s": (10.0, {"effects": ["background", "vignetting", "noise", "blur",
                                                           "compression", "dropped_frames"]}),
    "5 % dropped frames, 5 s": (5.0, {"effects": ["background", "vignetting", "noise", "blur", "dropped_frames"],
                                      "effect_params.dropped_frames.probability": 0.05}),
}


def robustness(names: list[str], seed: int) -> list[dict[str, Any]]:
    rows = []
    for name in names:
        duration, overrides = ROBUSTNESS[name]
        roll = simulate(duration, seed, **overrides)
        for method in ("paper", "default"):
            stitcher, ms = stitch_roll(roll, method, {}, False)
            result = evaluate(roll, stitcher)
            result.pop("shifts")
            rows.append({"case": name, "method": method, "ms_per_frame": ms, **result})
    return rows


def live_update(frames: int) -> dict[str, Any]:
    """Per-frame cost of `Stitcher.push` on 640x480 bgr8 (what the perception node pays per image)."""
    roll = simulate(10.0, 0)
    images = roll.images[:frames]
    stitcher = Stitcher(camera=roll.camera)
    times, cpu = [], []
    for image, stamp in zip(images, roll.stamps, strict=False):
        start, start_cpu = time.perf_counter(), time.process_time()
        stitcher.push(image, stamp)
        times.append(time.perf_counter() - start)
        cpu.append(time.process_time() - start_cpu)
    start = time.perf_counter()
    stitcher.map_image()
    render_ms = (time.perf_counter() - start) * 1e3
    t = np.array(times[10:]) * 1e3  # first frames allocate the canvas
    return {"frames": len(t), "median_ms": float(np.median(t)), "p90_ms": float(np.percentile(t, 90)),
            "max_ms": float(t.max()), "mean_ms": float(t.mean()), "map_image_ms": render_ms,
            "cpu_mean_ms": float(np.mean(cpu[10:]) * 1e3)}


def plot(result: dict[str, Any], path: Path, hist_path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 3, figsize=(17, 5.5))
    ax = axes[0]
    for i, r in enumerate(result["sweep"], 1):
        colour = "tab:red" if r["setting"].startswith("paper") else "tab:blue"
        ax.scatter(r["ms_per_frame"], r["ssim"], color=colour, label=f"{i}: {r['setting']}")
        ax.annotate(str(i), (r["ms_per_frame"], r["ssim"]), fontsize=8, xytext=(3, 3), textcoords="offset points")
    ax.set_xlabel("compute per frame (ms, Stitcher.push, contended machine)")
    ax.set_ylabel("SSIM vs ideal tactile truth")
    ax.set_title(f"Quality vs compute ({result['sweep_duration']:.0f} s scan)")
    ax.legend(fontsize=6.5, loc="center right", handletextpad=0.2, markerscale=0.6)
    ax.grid(alpha=0.3)
    ax = axes[1]
    for i, r in enumerate(result["sweep"], 1):
        colour = "tab:red" if r["setting"].startswith("paper") else "tab:blue"
        error = max(abs(r["length_error_percent"]), 1e-3)
        ax.scatter(r["ms_per_frame"], error, color=colour)
        ax.annotate(str(i), (r["ms_per_frame"], error), fontsize=8, xytext=(3, 3), textcoords="offset points")
    ax.set_yscale("log")
    ax.axhline(1.0, color="k", lw=0.8, ls="--")
    ax.set_xlabel("compute per frame (ms)")
    ax.set_ylabel("|length error| (%)")
    ax.set_title("Drift vs compute")
    ax.grid(alpha=0.3)
    ax = axes[2]
    for method, colour in (("paper", "tab:red"), ("default", "tab:blue")):
        rows = [r for r in result["scan_times"] if r["method"] == method]
        ax.plot([r["duration"] for r in rows], [r["ssim"] for r in rows], "o-", color=colour, label=f"{method}: SSIM")
        ax.plot([r["duration"] for r in rows], [min(1.0, abs(r["length_error_percent"]) / 10) for r in rows], "s--",
                color=colour, alpha=0.6, label=f"{method}: |length error| / 10 %")
    ax.axhline(0.85, color="k", lw=0.8, ls="--")
    ax.set_xlabel("scan time for 11 cm (s)")
    ax.set_title("Quality vs scan time (roll speed)")
    ax.legend(fontsize=8)
    ax.grid(alpha=0.3)
    fig.tight_layout()
    save_figure(fig, path, dpi=110)
    plt.close(fig)

    fig, axes = plt.subplots(1, 3, figsize=(15, 4), sharey=False)
    for ax, variant in zip(axes, SPEEDS, strict=True):
        paper = result["table_i"][f"{variant}/paper"]["shifts"]
        ours = result["table_i"][f"{variant}/default"]["shifts"]
        bins = np.arange(-25.5, 26.5, 1.0)
        ax.hist(paper, bins=bins, color="tab:red", alpha=0.6, label="paper (integer Δy)")
        ax.hist(ours, bins=np.arange(-25.5, 26.5, 0.25), color="tab:blue", alpha=0.6, label="ours (subpixel)")
        lo, hi = min(min(paper), min(ours)), max(max(paper), max(ours))
        ax.set_xlim(lo - 2, hi + 2)
        ax.set_title(f"{variant} ({SPEEDS[variant]:.0f} s); search range was [-25, 25]")
        ax.set_xlabel("Δy per frame (px)")
        ax.legend(fontsize=8)
    axes[0].set_ylabel("frames")
    fig.tight_layout()
    save_figure(fig, hist_path, dpi=110)
    plt.close(fig)


def figures(result: dict[str, Any], out_dir: Path) -> list[Path]:
    """The report's plots, written into `out_dir`: quality against compute and scan time, the Δy histograms."""
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    paths = [out_dir / "map_tradeoffs.png", out_dir / "map_dy_histograms.png"]
    plot(result, *paths)
    return paths


def run(quick: bool = False) -> dict[str, Any]:
    cv2.setNumThreads(1)
    seeds = [0] if quick else [0, 1, 2]
    started = time.perf_counter()
    result: dict[str, Any] = {"quick": quick, "provenance": provenance("map_tradeoffs", quick)}
    result["table_i"] = table_i(seeds)
    result["sweep_duration"] = 10.0
    result["sweep"] = sweep(10.0, 0)
    result["scan_times"] = scan_time_sweep(0, (5.0, 10.0, 15.0) if quick else SCAN_TIMES)
    result["robustness"] = robustness(list(ROBUSTNESS)[3:5] if quick else list(ROBUSTNESS), 0)
    result["live"] = live_update(150 if quick else 300)
    result["seconds"] = time.perf_counter() - started
    return result


def _pm(values: list[float], fmt: str) -> str:
    values = [v for v in values if v == v]
    if not values:
        return "n/a"
    if len(values) == 1:
        return fmt.format(values[0])
    return f"{fmt.format(np.mean(values))} ± {fmt.format(np.std(values))}"


def to_markdown(result: dict[str, Any]) -> str:
    lines = [provenance_markdown(result["provenance"]) + "  ",
             "OpenCV limited to one thread (cv2.setNumThreads(1)); simulator scene `surface_mapping` (plain-weave "
             "fabric, 8 cm x 11 cm, 640x480 bgr8 at 30 fps, gel background, vignetting, noise, motion blur). "
             f"Timings depend on the machine's load (above). Took "
             f"{result['seconds']:.0f} s.", "",
             "### Table I reproduced", "",
             "Like for like: the map against the simulator's ideal tactile rendering of the true surface, translation "
             "only, both standardised (mean, contrast). Paper protocol: against the height map with the 3-point "
             "constrained affine alignment. Length error: stitched travel vs the arm's; drift: largest position error "
             f"on the way (% of the length). Seeds: {result['table_i']['fast/paper']['seeds']} (mean ± std).", "",
             "| scan | method | SSIM | PSNR dB | MAE % | length error % | drift % | paper protocol SSIM / PSNR / MAE % "
             "| paper's Table I (photo) | ms/frame |",
             "|---|---|---|---|---|---|---|---|---|---|"]
    for r in result["table_i"].values():
        variant = r["variant"]
        pt = PAPER_TABLE_I[variant]
        paper_cell = f"{pt[0]:.3f} / {pt[1]:.2f} / {pt[2]:.2f}" if r["method"] == "paper" else ""
        lines.append(
            f"| {variant} ({r['duration']:.0f} s) | {r['method']} | {_pm(r['ssim'], '{:.3f}')} "
            f"| {_pm(r['psnr'], '{:.1f}')} "
            f"| {_pm(r['mae_percent'], '{:.1f}')} | {_pm(r['length_error_percent'], '{:+.2f}')} "
            f"| {_pm(r['drift_percent'], '{:.2f}')} | {_pm(r['paper_ssim'], '{:.3f}')} "
            f"/ {_pm(r['paper_psnr'], '{:.1f}')}"
            f" / {_pm(r['paper_mae_percent'], '{:.1f}')} | {paper_cell} | {_pm(r['ms_per_frame'], '{:.2f}')} |")
    lines += ["", "Δy histograms (the paper's figure): `map_dy_histograms.png`.", "",
              f"### Methods and settings: quality against compute ({result['sweep_duration']:.0f} s scan, seed 0)", "",
              "| setting | ms/frame | SSIM | PSNR dB | length error % | drift % | frames on the prior |",
              "|---|---|---|---|---|---|---|"]
    for r in result["sweep"]:
        lines.append(f"| {r['setting']} | {r['ms_per_frame']:.2f} | {r['ssim']:.3f} | {r['psnr']:.1f} | "
                     f"{r['length_error_percent']:+.2f} | {r['drift_percent']:.2f} | {r['prior_frames']} |")
    lines += ["", "### Quality against scan time (roll speed)", "",
              "| scan time s | peak px/frame | method | SSIM | PSNR dB | length error % | drift % |",
              "|---|---|---|---|---|---|---|"]
    for r in result["scan_times"]:
        lines.append(f"| {r['duration']:.1f} | {r['peak_px_per_frame']:.1f} | {r['method']} | {r['ssim']:.3f} | "
                     f"{r['psnr']:.1f} | {r['length_error_percent']:+.2f} | {r['drift_percent']:.2f} |")
    lines += ["", "Plot: `map_tradeoffs.png` (quality and drift against compute; quality against scan time).", "",
              "### Other surfaces, the other direction, glitches (seed 0)", "",
              "| case | method | frames | SSIM | PSNR dB | length error % | drift % | frames on the prior |",
              "|---|---|---|---|---|---|---|---|"]
    for r in result.get("robustness", []):
        lines.append(f"| {r['case']} | {r['method']} | {r['frames']} | {r['ssim']:.3f} | {r['psnr']:.1f} | "
                     f"{r['length_error_percent']:+.2f} | {r['drift_percent']:.2f} | {r['prior_frames']} |")
    lines.append("")
    live = result["live"]
    lines += ["### Speed", "",
              f"- Live map update (`Stitcher.push`, 640x480 bgr8, {live['frames']} frames): median "
              f"{live['median_ms']:.3f} ms, p90 {live['p90_ms']:.3f} ms, max {live['max_ms']:.3f} ms per frame wall "
              f"(mean CPU time {live['cpu_mean_ms']:.3f} ms); rendering the map (`map_image`) "
              f"{live['map_image_ms']:.1f} ms (at the publish rate, not per frame).",
              "- `touchroller map` as a whole command against reading the bag alone: `bench/map_speed.py` "
              "(`bench/results/map_speed.md`, and its own section of the report).", ""]
    goals = []
    ours = [r for r in result["table_i"].values() if r["method"] == "default"]
    worst_ssim = min(min(r["ssim"]) for r in ours)
    worst_len = max(max(abs(v) for v in r["length_error_percent"]) for r in ours)
    goals.append("- SSIM vs ground truth >= 0.85 at all three speeds: "
                 f"**{'met' if worst_ssim >= 0.85 else 'NOT met'}** "
                 f"(lowest {worst_ssim:.3f})")
    goals.append(f"- Length (drift) error <= 1 %: **{'met' if worst_len <= 1.0 else 'NOT met'}** (largest |error| "
                 f"{worst_len:.2f} %)")
    goals.append(f"- Live map update <= 1 ms per frame: **{'met' if live['median_ms'] <= 1.0 else 'NOT met'}** "
                 f"(median {live['median_ms']:.3f} ms)")
    lines += ["### Goals", "", *goals, ""]
    return "\n".join(lines)

def load(path: Path) -> dict[str, Any]:
    """A result this bench wrote (its JSON), for the report to render without running it again."""
    result: dict[str, Any] = load_json(dict, path)
    return result



def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="one seed, fewer scan times and surfaces")
    parser.add_argument("--out", help="results file (default: bench/results/map_tradeoffs.md, quick/ with --quick)")
    args = parser.parse_args(argv)
    result = run(quick=args.quick)
    out = Path(args.out) if args.out else results_path("map_tradeoffs", args.quick)
    out.parent.mkdir(parents=True, exist_ok=True)
    plot(result, out.with_suffix(".png"), out.with_name("map_dy_histograms.png"))
    atomic_write_text(out, "# Surface mapping: Table I and what accuracy costs\n\n" + to_markdown(result))
    atomic_write_text(out.with_suffix(".json"), to_json(result, indent=1))
    print(f"wrote {out}, {out.with_suffix('.png').name}, map_dy_histograms.png, {out.with_suffix('.json').name}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
