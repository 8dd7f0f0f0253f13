"""Coverage time: a flat 1.6 x 1.2 cm sensor by press-lift-shift against one roll over 8 x 11 cm.

Both are timed from the arm's speed and acceleration limits with trapezoidal moves
(touchroller_driver.sim.flat_sensor, parameters from config/scenes/flat_sensor_comparison.yaml).

    .venv/bin/python -m bench.coverage [--quick]
"""
from __future__ import annotations

import argparse
import sys
from dataclasses import dataclass
from pathlib import Path

from bench._common import command, load_json, results_path, to_json
from touchroller_driver.sim import load_scene  # noqa: E402
from touchroller_driver.sim.flat_sensor import CoverageComparison, compare  # noqa: E402
from touchroller_perception.files import atomic_write_text


@dataclass(frozen=True)
class DwellRow:
    dwell_s: float
    total_s: float      # the flat sensor's whole raster with that dwell per press


@dataclass(frozen=True)
class CoverageResult:
    comparison: CoverageComparison
    dwell_sweep: tuple[DwellRow, ...]   # the paper does not give its dwell per press
    command: str


def run(quick: bool = False) -> CoverageResult:
    scene = load_scene("flat_sensor_comparison")
    settings = scene.data.get("comparison", {})
    sweep = tuple(DwellRow(dwell, compare({**settings, "dwell": dwell}, scene.motion).flat_sensor.total_s)
                  for dwell in (0.5, 1.0, 2.0, 3.0))
    return CoverageResult(compare(settings, scene.motion), sweep, command("coverage", quick))


def to_markdown(result: CoverageResult) -> str:
    c = result.comparison
    flat, roller, paper, p = c.flat_sensor, c.touchroller, c.paper, c.parameters
    lines = [
        f"Command: `{result.command}` (arm times from the scene's limits, not measured, so no machine).",
        "",
        "| | presses | time (s) | paper |",
        "|---|---|---|---|",
        f"| flat sensor {p['flat_sensor'][1] * 100:.1f} x {p['flat_sensor'][0] * 100:.1f} cm, press-lift-shift | "
        f"{flat.presses} ({flat.grid[0]} x {flat.grid[1]}) | {flat.total_s:.1f} | "
        f"{paper.flat_presses} presses, {paper.flat_total_s:.0f} s |",
        f"| TouchRoller, one roll (lower, roll {roller.roll_s:.1f} s, lift) | 1 | {roller.total_s:.1f} | "
        f"1 roll, {paper.touchroller_total_s:.0f} s |",
        "",
        f"Speed-up: **{c.speedup:.1f}x** (paper: {paper.flat_total_s / paper.touchroller_total_s:.1f}x). "
        f"One press cycle: {flat.press_cycle_s:.2f} s (descend {flat.descend_s:.2f}, slow approach "
        f"{flat.approach_s:.2f}, dwell {flat.dwell_s:.2f}, lift {flat.lift_s:.2f}); arm {p['arm_speed']} m/s, "
        f"{p['arm_accel']} m/s^2.",
        "",
        "The paper does not give its dwell per press; the flat sensor's total against it:",
        "",
        "| dwell (s) | flat sensor total (s) |",
        "|---|---|",
        *(f"| {row.dwell_s:.1f} | {row.total_s:.1f} |" for row in result.dwell_sweep),
    ]
    return "\n".join(lines) + "\n"

def load(path: Path) -> CoverageResult:
    """A result this bench wrote (its JSON), for the report to render without running it again."""
    result: CoverageResult = load_json(CoverageResult, path)
    return result



def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="the same (this bench is instant)")
    parser.add_argument("--json", action="store_true", help="print the raw result as JSON too")
    args = parser.parse_args()
    result = run(quick=args.quick)
    out = results_path("coverage", args.quick)
    out.parent.mkdir(parents=True, exist_ok=True)
    atomic_write_text(out, "# Coverage: press-lift-shift against one roll\n\n" + to_markdown(result) + "\n")
    atomic_write_text(out.with_suffix(".json"), to_json(result, indent=1))
    print(to_markdown(result))
    if args.json:
        print(to_json(result, indent=1))
    print(f"wrote {out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
