"""Coverage time: a flat 1.6 x 1.2 cm sensor by press-lift-shift against one roll over 8 x 11 cm.

Both are timed from the arm's speed and acceleration limits with trapezoidal moves
(touchroller_driver.sim.flat_sensor, parameters from config/scenes/flat_sensor_comparison.yaml).

    .venv/bin/python -m bench.coverage [--quick]
"""
from __future__ import annotations

import argparse
import json
import sys
from typing import Any

from bench._common import command
from touchroller_driver.sim import load_scene  # noqa: E402
from touchroller_driver.sim.flat_sensor import compare  # noqa: E402


def run(quick: bool = False) -> dict[str, Any]:
    scene = load_scene("flat_sensor_comparison")
    result = compare(scene.data.get("comparison"), scene.motion)
    result["command"] = command("coverage", quick)
    # what the flat sensor costs as its dwell (settle and capture) grows: the paper does not give it
    result["dwell_sweep"] = [
        {"dwell_s": dwell, "total_s": compare({**scene.data.get("comparison", {}), "dwell": dwell},
                                              scene.motion)["flat_sensor"]["total_s"]}
        for dwell in (0.5, 1.0, 2.0, 3.0)
    ]
    return result


def to_markdown(result: dict[str, Any]) -> str:
    flat, roller, paper = result["flat_sensor"], result["touchroller"], result["paper"]
    p = result["parameters"]
    lines = [
        f"Command: `{result['command']}` (arm times from the scene's limits, not measured, so no machine).",
        "",
        "| | presses | time (s) | paper |",
        "|---|---|---|---|",
        f"| flat sensor {p['flat_sensor'][1] * 100:.1f} x {p['flat_sensor'][0] * 100:.1f} cm, press-lift-shift | "
        f"{flat['presses']} ({flat['grid'][0]} x {flat['grid'][1]}) | {flat['total_s']:.1f} | "
        f"{paper['flat_presses']} presses, {paper['flat_total_s']:.0f} s |",
        f"| TouchRoller, one roll (lower, roll {roller['roll_s']:.1f} s, lift) | 1 | {roller['total_s']:.1f} | "
        f"1 roll, {paper['touchroller_total_s']:.0f} s |",
        "",
        f"Speed-up: **{result['speedup']:.1f}x** (paper: {paper['flat_total_s'] / paper['touchroller_total_s']:.1f}x). "
        f"One press cycle: {flat['press_cycle_s']:.2f} s (descend {flat['descend_s']:.2f}, slow approach "
        f"{flat['approach_s']:.2f}, dwell {flat['dwell_s']:.2f}, lift {flat['lift_s']:.2f}); arm {p['arm_speed']} m/s, "
        f"{p['arm_accel']} m/s^2.",
        "",
        "The paper does not give its dwell per press; the flat sensor's total against it:",
        "",
        "| dwell (s) | flat sensor total (s) |",
        "|---|---|",
        *(f"| {row['dwell_s']:.1f} | {row['total_s']:.1f} |" for row in result["dwell_sweep"]),
    ]
    return "\n".join(lines) + "\n"


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="the same (this bench is instant)")
    parser.add_argument("--json", action="store_true", help="print the raw result as JSON too")
    args = parser.parse_args()
    result = run(quick=args.quick)
    print(to_markdown(result))
    if args.json:
        print(json.dumps(result, indent=1, default=float))
    return 0


if __name__ == "__main__":
    sys.exit(main())
