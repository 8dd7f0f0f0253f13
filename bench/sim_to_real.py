"""How far simulated presses are from real ones, and our accuracy under an ideal and a realistic appearance.

Per sensor of the `taxim` wheel (bench/real_presses.py): `touchroller_driver.sim.realistic.fit_appearance`
fits the press shape, colour response and noise on the even presses; the odd (held-out) presses are
then rendered at their labelled place and radius, with that realistic appearance and with the
simulator's ideal one (Lambert shading, flat background, white noise), and compared with the real
frames: correlation of the difference images (frame minus background, all channels, within 2.5
contact radii) and RMS per-pixel error (grey levels).

Then presses at random places and radii (known exactly) are rendered with each appearance and
detected, ours and the paper's pipeline, from one reference frame: found, centre error, false
contacts, as in the real-press section.

Results: bench/results/sim_to_real.md (`python -m bench.sim_to_real [--quick]`; the report generator
calls `run`, `to_markdown` and `figures`).
"""
from __future__ import annotations

import argparse
import functools
import math
import sys
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from bench._common import load_dict, provenance, provenance_markdown, results_path, write_results
from bench.real_presses import SENSORS, PressSet, available, load_presses, match
from touchroller_driver.sim.realistic import (
    REACH,
    IdealPressRenderer,
    RealAppearance,
    RealisticPressRenderer,
    fit_appearance,
    refine_centres,
)
from touchroller_perception.contacts import ContactDetector, DetectorConfig
from touchroller_perception.files import atomic_path

METHODS = {"ours (colour)": DetectorConfig(), "paper's pipeline": DetectorConfig(method="paper")}


#: rounds of centre refinement in the realistic fit (quick runs: fewer)
ROUNDS, QUICK_ROUNDS = 6, 1


@functools.lru_cache(maxsize=8)
def fitted(sensor: str, rounds: int = 0, every: int = 1) -> tuple[PressSet, RealAppearance]:
    """The sensor's presses and the appearance fitted on its even (tuning) presses (every `every`-th of
    them): around the hand labels (`rounds` 0), or around centres refined by the model over `rounds` rounds."""
    presses = load_presses(sensor)
    return presses, fit_appearance(presses.background, presses.presses, presses.centres, presses.radii,
                                   presses.tuning[::every], refine_rounds=rounds)


def model_centres(presses: PressSet, appearance: RealAppearance, indices) -> np.ndarray:
    """The labelled centres with those of `indices` moved to where `appearance` explains each frame best."""
    return refine_centres(presses.background, presses.presses, presses.centres, presses.radii, indices,
                          appearance.shape, appearance.response)


def realism(presses: PressSet, renderer, indices, centres: np.ndarray | None = None) -> dict[str, float]:
    """Median over the presses of the difference images' correlation and RMS error against the real frames,
    each press rendered at its labelled place (or at `centres`) and radius."""
    h, w = presses.background.shape[:2]
    yy, xx = np.mgrid[0:h, 0:w]
    places = presses.centres if centres is None else centres
    correlations, errors = [], []
    for i in indices:
        (u, v), radius = places[i], float(presses.radii[i])
        near = np.hypot(xx - u, yy - v) < REACH * radius
        real = (presses.presses[i].astype(np.float32) - presses.background)[near].ravel()
        simulated = renderer.change((u, v), radius)[near].ravel()
        correlations.append(float(np.corrcoef(real, simulated)[0, 1]))
        errors.append(float(np.sqrt(np.mean((real - simulated) ** 2))))
    return {"correlation": float(np.median(correlations)), "rms": float(np.median(errors)),
            "correlation_min": float(np.min(correlations))}


def random_presses(presses: PressSet, count: int, seed: int) -> list[tuple[float, float, float]]:
    """Places and contact radii like the sensor's own presses, anywhere at least 2.5 radii inside the image."""
    rng = np.random.default_rng(seed)
    h, w = presses.background.shape[:2]
    lo, hi = float(presses.radii.min()), float(presses.radii.max())
    out = []
    for _ in range(count):
        radius = float(rng.uniform(lo, hi))
        margin = REACH * radius
        out.append((float(rng.uniform(margin, w - margin)), float(rng.uniform(margin, h - margin)), radius))
    return out


def simulated_accuracy(renderer, truth: list[tuple[float, float, float]], config: DetectorConfig,
                       seed: int) -> dict[str, Any]:
    rng = np.random.default_rng(seed)
    detector = ContactDetector(config, reference_frames=1)
    detector.set_reference([renderer.render([], rng)])
    errors, found, false = [], 0, 0
    for u, v, radius in truth:
        contacts = detector.detect(renderer.render([(u, v, radius)], rng))
        contact, error, others = match(contacts, (u, v), radius)
        false += others
        if contact is not None:
            found += 1
            errors.append(error)
    e = np.array(errors) if errors else np.array([math.nan])
    return {"presses": len(truth), "found": found, "median_px": float(np.median(e)),
            "p90_px": float(np.percentile(e, 90)), "false_contacts": false}


def run(quick: bool = False) -> dict[str, Any]:
    stamp = provenance("sim_to_real", quick)
    if not available():
        raise RuntimeError("the taxim wheel (real GelSight presses) is not installed: pip install -r requirements.txt")
    count = 16 if quick else 60
    rounds = QUICK_ROUNDS if quick else ROUNDS
    every = 3 if quick else 1          # a quick run fits and compares a third of the presses
    sensors = []
    for sensor in SENSORS:
        presses, at_labels = fitted(sensor, 0, every)
        _, refined = fitted(sensor, rounds, every)
        held_out = presses.held_out[::every]
        ideal = IdealPressRenderer(presses.background.shape[:2], refined.shape)
        looks = {"ideal": ideal, "realistic, fitted at the labels": RealisticPressRenderer(at_labels),
                 "realistic, centres refined": RealisticPressRenderer(refined)}
        truth = random_presses(presses, count, seed=1)
        accuracy = []
        for look, renderer in looks.items():
            for method, config in METHODS.items():
                accuracy.append({"appearance": look, "method": method,
                                 **simulated_accuracy(renderer, truth, config, seed=2)})
        places = model_centres(presses, refined, held_out)
        looks_realism = [{"appearance": look, "place": "labels", **realism(presses, renderer, held_out)}
                         for look, renderer in looks.items()]
        looks_realism.append({"appearance": "realistic, centres refined", "place": "the model's",
                              **realism(presses, looks["realistic, centres refined"], held_out, places)})
        fits = [{"fit": name, "ball_ratio": a.shape.ball_ratio, "halo": a.shape.halo, "fit_rms": a.fit_rms,
                 "noise_std": [float(x) for x in a.noise_std], "noise_correlation_px": a.noise_correlation_px}
                for name, a in (("at the labels", at_labels), (f"centres refined ({rounds} rounds)", refined))]
        entry = {"sensor": sensor, "fitted_on": len(presses.tuning[::every]), "compared_on": len(held_out),
                 "fits": fits, "realism": looks_realism, "accuracy": accuracy}
        sensors.append(entry)
        for r in looks_realism:
            print(f"{sensor:14s} {r['appearance']:32s} at {r['place']:12s} corr {r['correlation']:.3f} "
                  f"rms {r['rms']:.1f}", flush=True)
        for a in accuracy:
            print(f"{sensor:14s} {a['appearance']:32s} {a['method']:18s} {a['found']}/{a['presses']} "
                  f"median {a['median_px']:.2f} px", flush=True)
    return {"sensors": sensors, "random_presses": count, "rounds": rounds, "every": every, "quick": quick,
            "provenance": stamp}


def to_markdown(result: dict[str, Any]) -> str:
    lines = [provenance_markdown(result["provenance"]), "",
             "### Realism: simulated against real presses (held-out presses, same radius)", "",
             "| sensor | appearance | place | difference-image correlation, median (worst) "
             "| RMS per-pixel error, grey levels |",
             "|---|---|---|---|---|"]
    for s in result["sensors"]:
        for r in s["realism"]:
            lines.append(f"| {s['sensor']} | {r['appearance']} | {r['place']} | {r['correlation']:.3f} "
                         f"({r['correlation_min']:.3f}) | {r['rms']:.1f} |")
    lines += ["", "Fitted on the even presses of each sensor, around the hand labels or around centres the model "
              "moves, round by round, to where it explains each frame best (`fit_appearance(refine_rounds=...)`); "
              "\"the model's\" place of a held-out press is found the same way with the fitted model:", "",
              "| sensor | fit | presses fitted / compared | ball radius / contact radius | halo / contact radius | "
              "response fit RMS | noise std B, G, R | noise correlation length px |",
              "|---|---|---|---|---|---|---|---|"]
    for s in result["sensors"]:
        for f in s["fits"]:
            lines.append(f"| {s['sensor']} | {f['fit']} | {s['fitted_on']} / {s['compared_on']} | "
                         f"{f['ball_ratio']:.1f} | {f['halo']:.2f} | {f['fit_rms']:.1f} | "
                         f"{', '.join(f'{x:.2f}' for x in f['noise_std'])} | {f['noise_correlation_px']:.2f} |")
    lines += ["", f"### Simulated accuracy, ideal and realistic appearance side by side ({result['random_presses']} "
              "presses at random places and radii per sensor, exact truth, one reference frame)", "",
              "| sensor | appearance | method | found | centre error median px | p90 px | false contacts |",
              "|---|---|---|---|---|---|---|"]
    for s in result["sensors"]:
        for a in s["accuracy"]:
            lines.append(f"| {s['sensor']} | {a['appearance']} | {a['method']} | {a['found']}/{a['presses']} | "
                         f"{a['median_px']:.2f} | {a['p90_px']:.2f} | {a['false_contacts']} |")
    lines += ["", "The ideal appearance's colour response is the simulator's Lambert model with its default lights, "
              "not the real sensor's: its difference images correlate poorly with real ones, which is why "
              "simulated accuracy alone says little about a real sensor. A realistic appearance fitted around "
              "hand labels learns the labels' offset from the press as part of its colour response: a press it "
              "renders is not centred on its own true centre, and a detector's error on it measures the labels' "
              "offset as well (compare the two realistic rows)."]
    return "\n".join(lines) + "\n"


def figures(result: dict[str, Any], out_dir: Path) -> list[Path]:
    """One held-out press per sensor: the real change, the realistic and the ideal simulation (x3, grey 128 = 0)."""
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    rows = []
    for sensor in SENSORS:
        presses, appearance = fitted(sensor, result["rounds"], result["every"])
        i = presses.held_out[0]
        (u, v), radius = model_centres(presses, appearance, [i])[i], float(presses.radii[i])
        changes = [presses.presses[i].astype(np.float32) - presses.background,
                   RealisticPressRenderer(appearance).change((u, v), radius),
                   IdealPressRenderer(presses.background.shape[:2], appearance.shape).change((u, v), radius)]
        half = int(REACH * radius)
        y0, x0 = max(0, int(v) - half), max(0, int(u) - half)
        tiles = [np.clip(c[y0:y0 + 2 * half, x0:x0 + 2 * half] * 3 + 128, 0, 255).astype(np.uint8) for c in changes]
        tiles = [cv2.resize(t, (240, 240), interpolation=cv2.INTER_AREA) for t in tiles]
        for tile, label in zip(tiles, ("real", "realistic", "ideal"), strict=True):
            cv2.putText(tile, f"{sensor} {label}", (6, 18), cv2.FONT_HERSHEY_SIMPLEX, 0.45, (255, 255, 255), 1)
        rows.append(np.hstack(tiles))
    path = out_dir / "sim_to_real.png"
    with atomic_path(path) as temporary:
        if not cv2.imwrite(str(temporary), np.vstack(rows)):
            raise OSError(f"cannot write {path}")
    return [path]

load = load_dict   # the report reads the recorded JSON back through the bench's `load`



def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="fewer random presses")
    parser.add_argument("--out", help="results file (default: bench/results/sim_to_real.md, quick/ with --quick)")
    args = parser.parse_args(argv)
    result = run(quick=args.quick)
    out = Path(args.out) if args.out else results_path("sim_to_real", args.quick)
    write_results(out, "Simulated against real presses", result, to_markdown, figures)
    print(f"wrote {out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
