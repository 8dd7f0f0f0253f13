"""The world height map against the true relief, in place, in our simulator.

A 2-pass raster (4 cm x 9 cm at 20 mm/s, pressed 0.5 mm, filmed 30 ms late, latency told) over the
`large_surface` scene's grained surface (0.3 mm relief) and its `panel` variant (planted cracks and dents
in 2 um of orange peel), mapped with a photometric model calibrated on the fly from the `ball_presses`
scene of the same sensor (`touchroller_driver.sim.photometric`), placed by `WorldMapper` with a
`HeightSource`. Score: the map against `SimulatedSensor.world_truth` (the relief as the membrane follows
it) on the same cells, no alignment, over the cells mapped at least 1 mm inside the mapped area: RMS
error after removing one best plane, and correlation. This rests on our simulator alone (the same light
model calibrated and measured); the second raster generator (bench/raster_generator) does not render
relief in metres.
"""
from __future__ import annotations

import argparse
import dataclasses
import json
import math
import sys
import time
from pathlib import Path

import cv2
import numpy as np

from bench._common import Provenance, provenance, provenance_markdown, results_path, to_json
from touchroller_perception.files import atomic_write_text

GOAL_RMS_UM = 10.0
GOAL_CORRELATION = 0.95


@dataclasses.dataclass(frozen=True)
class SurfaceScore:
    surface: str
    relief_rms_um: float      # the true relief on the scored cells, its best plane removed
    rms_um: float             # the error, its best plane removed
    correlation: float
    cells: int
    passes: int
    frames_mapped: int
    map_cpu_s: float


@dataclasses.dataclass(frozen=True)
class HeightMapResult:
    provenance: Provenance
    quick: bool
    presses: int
    normal_error_deg: float   # the calibration's in-sample fit
    surfaces: list[SurfaceScore]


def _detrended(values: np.ndarray, rows: np.ndarray, cols: np.ndarray) -> np.ndarray:
    A = np.c_[np.ones(len(values)), rows, cols]
    coef, *_ = np.linalg.lstsq(A, values, rcond=None)
    out: np.ndarray = values - A @ coef
    return out


def score_surface(variant: str | None, presses: int) -> tuple[SurfaceScore, float]:
    from touchroller_driver.arm import (
        DEFAULT_MOUNT_RPY,
        DEFAULT_MOUNT_XYZ,
        DEFAULT_START_POSE,
        mount_transform,
        plan_raster,
    )
    from touchroller_driver.sim import SimulatedSensor, load_scene
    from touchroller_driver.sim.camera import surface_frame
    from touchroller_driver.sim.photometric import sim_photometric
    from touchroller_driver.sim.sweep import simulate_sweep
    from touchroller_perception.transforms import TransformBuffer
    from touchroller_perception.world_height import HeightSource
    from touchroller_perception.world_map import WorldMapConfig, WorldMapper, buffer_lookup

    sensor = SimulatedSensor(load_scene("large_surface", variant=variant), seed=0)
    photometric = sim_photometric(sensor, presses=presses)
    mount = mount_transform(DEFAULT_MOUNT_XYZ, DEFAULT_MOUNT_RPY)
    area = [0.42, -0.045, 0.04, 0.09]
    plan = plan_raster(np.array(DEFAULT_START_POSE), area=area, mount=mount, speed=0.02, accel=0.1, depth=5e-4,
                       clearance=0.002, approach_speed=0.005)
    events = list(simulate_sweep(sensor, plan, np.array(plan.segments[0].target), mount, latency_s=0.03))
    bounds = (area[0] - 0.01, area[1] - 0.04, area[0] + area[2] + 0.01, area[1] + area[3] + 0.04)
    buffer = TransformBuffer(cache_ns=None)
    buffer.set_transform("tool0", "touchroller_cylinder", 0, mount, static=True)
    mapper = WorldMapper(sensor.camera, buffer_lookup(buffer, "base", "touchroller_cylinder"),
                         WorldMapConfig(bounds=bounds, latency=0.03),
                         height=HeightSource(photometric.calibration.model, photometric.reference))
    begin = time.process_time()
    for event in events:
        if event[0] == "tf":
            buffer.set_transform("base", "tool0", event[1], event[2])
        else:
            mapper.push(event[2], event[1])
    mapper.finalise()
    cpu = time.process_time() - begin
    layer = mapper.height_layer(crop=False)
    if layer is None:
        raise RuntimeError("no height was mapped")
    height = layer.height
    truth, _ = sensor.world_truth(surface_frame(sensor.scene), layer.origin, height.shape, layer.resolution)
    known = np.isfinite(height)
    inside = cv2.erode(known.astype(np.uint8), np.ones((21, 21), np.uint8)) > 0   # 1 mm in from its edge
    rows, cols = np.nonzero(inside)
    mine, true = height[inside].astype(np.float64), truth[inside].astype(np.float64)
    error = _detrended(mine - true, rows, cols)
    relief = _detrended(true, rows, cols)
    name = "grain" if variant is None else variant
    return (SurfaceScore(name, float(relief.std() * 1e6), float(np.sqrt(np.mean(error**2)) * 1e6),
                         float(np.corrcoef(mine, true)[0, 1]), int(inside.sum()), mapper.stats.passes,
                         mapper.stats.mapped, cpu), float(photometric.calibration.normal_error_deg))


def run(quick: bool = False) -> HeightMapResult:
    stamp = provenance("height_map", quick)
    presses = 8 if quick else 16
    scores, fit = [], math.nan
    for variant in ((None,) if quick else (None, "panel")):
        score, error = score_surface(variant, presses)
        scores.append(score)
        fit = error if variant is None else fit
    return HeightMapResult(stamp, quick, presses, fit, scores)


def goals(r: HeightMapResult) -> list[tuple[str, str, bool | None]]:
    grain = next((s for s in r.surfaces if s.surface == "grain"), None)
    if grain is None:
        return []
    return [("World height map, grained surface (simulator): RMS error after one best plane",
             f"{grain.rms_um:.1f} um (goal <= {GOAL_RMS_UM:g} um)", grain.rms_um <= GOAL_RMS_UM),
            ("World height map, grained surface (simulator): correlation with the true relief",
             f"{grain.correlation:.3f} (goal >= {GOAL_CORRELATION:g})", grain.correlation >= GOAL_CORRELATION)]


def to_markdown(r: HeightMapResult) -> str:
    lines = [provenance_markdown(r.provenance), "",
             f"2-pass raster (4 x 9 cm, 20 mm/s, 0.5 mm pressed) of `large_surface`, photometric model from "
             f"{r.presses} simulated ball presses of the same sensor (in-sample fit {r.normal_error_deg:.2f} deg); "
             "the height map against the true relief in place, on the cells 1 mm inside the mapped area "
             "(simulator only).", "",
             "| surface | true relief RMS, um | error RMS (one best plane removed), um | correlation | cells | "
             "passes | frames | CPU s |", "|---|---|---|---|---|---|---|---|"]
    for s in r.surfaces:
        lines.append(f"| {s.surface} | {s.relief_rms_um:.1f} | {s.rms_um:.1f} | {s.correlation:.3f} | {s.cells} | "
                     f"{s.passes} | {s.frames_mapped} | {s.map_cpu_s:.1f} |")
    lines.append("")
    for goal, value, met in goals(r):
        lines.append(f"- {goal}: {value}: **{'met' if met else 'NOT met'}**")
    return "\n".join(lines) + "\n"


def load(path: Path) -> HeightMapResult:
    raw = json.loads(Path(path).read_text())
    raw["provenance"] = Provenance(**raw["provenance"])
    raw["surfaces"] = [SurfaceScore(**s) for s in raw["surfaces"]]
    return HeightMapResult(**raw)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="the grained surface only, 8 presses")
    args = parser.parse_args(argv)
    result = run(quick=args.quick)
    out = results_path("height_map", args.quick)
    out.parent.mkdir(parents=True, exist_ok=True)
    text = "# World height map in the simulator\n\n" + to_markdown(result)
    atomic_write_text(out, text)
    atomic_write_text(out.with_suffix(".json"), to_json(result, indent=1))
    print(text)
    return 0 if all(math.isfinite(s.rms_um) for s in result.surfaces) else 1


if __name__ == "__main__":
    sys.exit(main())
