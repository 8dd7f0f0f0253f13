"""Numerical stability of the camera model in the hard cases, and what the code returns there.

For each case: the share of image pixels that back-project validly, the worst round trip
pixel -> point -> pixel (px) and point -> pixel -> point (m) over the valid ones, and what the
invalid ones return. Also the back-projection cost per pixel.

    .venv/bin/python -m bench.geometry_stability [--quick] [--json out.json]
"""
from __future__ import annotations

import argparse
import math
import sys
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from bench._common import Provenance, load_json, provenance, provenance_markdown, results_path, to_json
from touchroller_perception.files import atomic_write_text
from touchroller_perception.geometry import CameraModel  # noqa: E402

CASES: list[tuple[str, dict]] = [
    ("nominal (paper's sensor, no distortion)", {}),
    ("theta = +60 deg", {"theta": math.radians(60)}),
    ("theta = -60 deg", {"theta": math.radians(-60)}),
    ("d = +0.9 r", {"d": 0.045}),
    ("d = -0.9 r", {"d": -0.045}),
    ("theta = 60 deg and d = 0.9 r", {"theta": math.radians(60), "d": 0.045}),
    ("wide lens (fx = fy = 150 px): grazing rays leave through the tube's ends", {"fx": 150.0, "fy": 150.0}),
    ("strong barrel distortion k1 = -0.9 (folds inside the image)", {"distortion": (-0.9, 0.0, 0.0, 0.0, 0.0)}),
    ("strong distortion with tangential terms",
     {"distortion": (-0.45, 0.25, 0.004, -0.004, -0.05), "theta": 0.3, "d": 0.02}),
]


@dataclass(frozen=True)
class StabilityCase:
    """One hard case over a grid of the image: how many pixels back-project, how well they round-trip,
    and what the invalid ones return."""

    case: str
    pixels: int
    valid_fraction: float
    round_trip_px: float | None      # worst pixel -> point -> pixel; None when no pixel is valid
    round_trip_m: float | None       # worst point -> pixel -> point
    on_cylinder_m: float | None      # worst distance of a back-projected point from the cylinder
    reprojected_valid: bool
    invalid_return: str              # "NaN point, valid=False", or "FINITE (bug)"
    us_per_pixel: float


@dataclass(frozen=True)
class NonFiniteInputs:
    inputs: str
    valid: tuple[bool, ...]
    all_invalid_are_nan: bool


@dataclass(frozen=True)
class StabilityResult:
    cases: tuple[StabilityCase, ...]
    non_finite: NonFiniteInputs
    grid_step_px: int
    provenance: Provenance


def evaluate_case(name: str, model: CameraModel, step: int) -> StabilityCase:
    u, v = np.meshgrid(np.arange(0, model.width, step, dtype=np.float64),
                       np.arange(0, model.height, step, dtype=np.float64))
    uv = np.stack([u, v], axis=-1).reshape(-1, 2)
    start = time.perf_counter()
    points, valid = model.back_project(uv)
    seconds = time.perf_counter() - start
    uv_back, valid_back = model.project(points[valid])
    points_again, valid_again = model.back_project(uv_back)
    invalid_points = points[~valid]
    any_valid = bool(valid.any())
    return StabilityCase(
        case=name,
        pixels=int(len(uv)),
        valid_fraction=float(valid.mean()),
        round_trip_px=float(np.max(np.abs(uv_back - uv[valid]))) if any_valid else None,
        round_trip_m=float(np.max(np.linalg.norm(points_again - points[valid], axis=-1))) if any_valid else None,
        on_cylinder_m=float(np.max(np.abs(np.hypot(points[valid, 1], points[valid, 2]) - model.radius)))
        if any_valid else None,
        reprojected_valid=bool(valid_back.all() and valid_again.all()),
        invalid_return="NaN point, valid=False" if np.isnan(invalid_points).all() else "FINITE (bug)",
        us_per_pixel=1e6 * seconds / len(uv),
    )


def non_finite_inputs() -> NonFiniteInputs:
    model = CameraModel(distortion=(-0.2, 0.05, 0.0, 0.0, 0.0))
    points, valid = model.back_project([[np.nan, 1.0], [np.inf, 1.0], [1.0, -np.inf], [320.0, 240.0]])
    return NonFiniteInputs("NaN, +inf, -inf, finite", tuple(bool(v) for v in valid),
                           bool(np.isnan(points[~valid]).all()))


def run(quick: bool = False) -> StabilityResult:
    stamp = provenance("geometry_stability", quick)
    step = 8 if quick else 2
    cases = tuple(evaluate_case(name, CameraModel(**changes), step) for name, changes in CASES)
    return StabilityResult(cases, non_finite_inputs(), step, stamp)


def to_markdown(result: StabilityResult) -> str:
    lines = [
        provenance_markdown(result.provenance), "",
        "| case | valid pixels | worst px→3D→px (px) | worst 3D→px→3D (m) | off the cylinder (m) "
        "| invalid pixels return | µs/pixel |",
        "|---|---|---|---|---|---|---|",
    ]

    def fmt(x: float | None) -> str:
        return "—" if x is None else f"{x:.1e}"

    for c in result.cases:
        lines.append(f"| {c.case} | {100 * c.valid_fraction:.1f}% | {fmt(c.round_trip_px)} | "
                     f"{fmt(c.round_trip_m)} | {fmt(c.on_cylinder_m)} | {c.invalid_return} | "
                     f"{c.us_per_pixel:.2f} |")
    nf = result.non_finite
    lines.append("")
    lines.append(f"Non-finite pixels ({nf.inputs}): valid = {list(nf.valid)}; the invalid ones are NaN: "
                 f"{nf.all_invalid_are_nan}. Grid: every {result.grid_step_px} px of a 640x480 image.")
    return "\n".join(lines)

def load(path: Path) -> StabilityResult:
    """A result this bench wrote (its JSON), for the report to render without running it again."""
    result: StabilityResult = load_json(StabilityResult, path)
    return result



def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true")
    parser.add_argument("--json", type=Path)
    args = parser.parse_args(argv)
    result = run(quick=args.quick)
    out = results_path("geometry_stability", args.quick)
    out.parent.mkdir(parents=True, exist_ok=True)
    atomic_write_text(out, "# Numerical stability of the camera model\n\n" + to_markdown(result) + "\n")
    atomic_write_text(args.json or out.with_suffix(".json"), to_json(result, indent=1))
    print(to_markdown(result))
    return 0


if __name__ == "__main__":
    sys.exit(main())
