"""Ball-press photometric calibration in our simulator: does it recover the renderer's own slopes?

The `ball_presses` scene (a 4 mm ball pressed at random places of the roller's contact band, three
coloured lights, uneven background, vignetting, noise) is rendered; the presses are labelled from the
scene's truth, loosened as a hand label is (centre moved up to 2 px, radius +-15 %); even presses
calibrate (`touchroller_perception.height`, pixel size from the camera model at each press), odd
presses are measured: the model's slopes against the renderer's slopes (its Sobel of the
indentation, scaled by its metres per pixel) inside the true contact, less one pixel. This rests on
our simulator alone (the same light model trained and tested): the real-data figures are in
bench/height_real.py.
"""
from __future__ import annotations

import argparse
import dataclasses
import json
import math
import sys
from pathlib import Path

import cv2
import numpy as np

from bench._common import Provenance, provenance, provenance_markdown, results_path, to_json
from touchroller_perception.files import atomic_write_text
from touchroller_perception.height import (
    BallPress,
    PressCalibrationConfig,
    calibrate_photometric,
    normal_angles_deg,
    pixel_size_at,
)

GOAL_DEG = 2.0


@dataclasses.dataclass(frozen=True)
class HeightSimResult:
    provenance: Provenance
    presses: int
    angle_deg: float              # median over held-out presses of each press's median
    angle_p90_deg: float          # pooled p90 over the held-out pixels
    per_press_deg: tuple[float, ...]
    contact_px: float             # median contact radius in pixels
    in_sample_deg: float


def run(quick: bool = False, seed: int = 7) -> HeightSimResult:
    import touchroller_driver.sim as sim

    stamp = provenance("height_sim", quick)
    presses_n = 16 if quick else 30
    sensor = sim.SimulatedSensor(sim.load_scene("ball_presses", **{"motion.presses": presses_n}), seed=seed)
    rng = np.random.default_rng(seed)
    refs, items = [], []
    for frame in sensor.frames():
        phase = frame.truth.get("phase")
        if phase == "reference":
            refs.append(frame.image)
        elif phase == "press":
            items.append(frame)
    reference = np.median(np.stack(refs), axis=0).astype(np.uint8)
    camera = sensor.camera
    presses, truths = [], []
    for k, frame in enumerate(items):
        contact = frame.truth["contacts"][0]
        u, v = contact["pixel"]
        r = contact["radius_px"]
        du, dv = rng.uniform(-2, 2, size=2)
        presses.append(BallPress(frame.image, u + du, v + dv, r * rng.uniform(0.85, 1.15), pixel_size_at(camera, u, v),
                                 str(k), float(camera.radius)))
        state = sim.RollerState(depth=-1.0, indenters=tuple(
            sim.Indenter(tuple(i["centre"]), i["radius"]) for i in frame.truth["state"]["indenters"]))
        D = sensor.render_layers(state)["indentation"]
        gx = cv2.Sobel(D, cv2.CV_32F, 1, 0, ksize=3) * sensor._sobel_ku     # the renderer's own slopes
        gy = cv2.Sobel(D, cv2.CV_32F, 0, 1, ksize=3) * sensor._sobel_kv
        inside = cv2.erode((D > 0).astype(np.uint8), np.ones((3, 3), np.uint8)).astype(bool)
        truths.append((gx, gy, inside))
    ball = float(items[0].truth["contacts"][0]["ball_radius"])
    train = list(range(0, len(presses), 2))
    cal = calibrate_photometric([presses[i] for i in train], reference, ball, PressCalibrationConfig())
    per_press, pooled = [], []
    for i in range(1, len(presses), 2):
        gx_true, gy_true, inside = truths[i]
        gx, gy = cal.model.slopes(presses[i].image, reference)
        err = normal_angles_deg(gx[inside], gy[inside], gx_true[inside], gy_true[inside])
        per_press.append(float(np.median(err)))
        pooled.append(err)
    all_err = np.concatenate(pooled)
    return HeightSimResult(stamp, len(presses), float(np.median(per_press)), float(np.percentile(all_err, 90)),
                           tuple(per_press), float(np.median([p.radius_px for p in presses])), cal.normal_error_deg)


def to_markdown(r: HeightSimResult) -> str:
    met = "met" if r.angle_deg <= GOAL_DEG else "NOT met"
    return (provenance_markdown(r.provenance) + "\n\n"
            f"Simulator `ball_presses` scene, {r.presses} presses (contact radius about {r.contact_px:.0f} px), even "
            "presses calibrate, odd measured against the renderer's own slopes (simulator only).\n\n"
            f"- normal-angle error, median of the held-out presses: {r.angle_deg:.2f} deg (pooled p90 "
            f"{r.angle_p90_deg:.2f}); goal <= {GOAL_DEG:g} deg: **{met}**\n"
            f"- in-sample residual against the sphere: {r.in_sample_deg:.2f} deg\n"
            f"- per press: {', '.join(f'{a:.2f}' for a in r.per_press_deg)}\n")


def load(path: Path) -> HeightSimResult:
    raw = json.loads(Path(path).read_text())
    raw["provenance"] = Provenance(**raw["provenance"])
    raw["per_press_deg"] = tuple(raw["per_press_deg"])
    return HeightSimResult(**raw)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="16 presses")
    args = parser.parse_args(argv)
    result = run(quick=args.quick)
    out = results_path("height_sim", args.quick)
    out.parent.mkdir(parents=True, exist_ok=True)
    text = "# Photometric calibration in the simulator\n\n" + to_markdown(result)
    atomic_write_text(out, text)
    atomic_write_text(out.with_suffix(".json"), to_json(result, indent=1))
    print(text)
    return 0 if math.isfinite(result.angle_deg) else 1


if __name__ == "__main__":
    sys.exit(main())
