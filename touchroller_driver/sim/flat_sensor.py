"""Time to cover an area with a flat GelSight (press, lift, shift) versus one roll of the TouchRoller.

Every arm move is a rest-to-rest trapezoid (`touchroller_driver.motion.TrapezoidProfile`) under the
arm's speed and acceleration limits; presses end with a slow, force-limited approach and a dwell to
settle and capture. The paper reports 49 presses and 196 s for the GelSight against 10 s for one roll
(8 cm x 11 cm of fabric, UR5); its per-move speeds and dwell are not given, so ours are parameters.
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

from touchroller_driver.motion import TrapezoidProfile
from touchroller_driver.sim.scenarios import roll_profile

DEFAULTS: dict[str, Any] = {
    "area": [0.08, 0.11], "flat_sensor": [0.012, 0.016], "overlap": 0.0, "lift": 0.01,
    "press_travel": 0.002, "press_speed": 0.002, "dwell": 1.0, "arm_speed": 0.1, "arm_accel": 0.5,
}


def presses_needed(area: float, window: float, overlap: float) -> int:
    """Presses along one side: windows of `window` with `overlap` (fraction) covering `area`."""
    if window <= 0 or not 0 <= overlap < 1:
        raise ValueError("flat sensor window must be > 0 and overlap in [0, 1)")
    if area <= window:
        return 1
    return 1 + math.ceil((area - window) / (window * (1.0 - overlap)) - 1e-9)


@dataclass(frozen=True)
class FlatSensorTiming:
    """The flat sensor's raster of presses, in seconds: each press descends, approaches slowly, dwells
    (settle and capture) and lifts; between presses the arm shifts along a row or to the next row."""

    presses: int
    grid: tuple[int, int]           # presses across x, along y
    press_cycle_s: float
    descend_s: float
    approach_s: float
    dwell_s: float
    lift_s: float
    shift_in_row_s: float
    shift_between_rows_s: float
    total_s: float


@dataclass(frozen=True)
class RollTiming:
    """The roller's single roll: lowered once, rolled once, lifted once."""

    roll_s: float
    roll_peak_speed: float          # m/s
    total_s: float


@dataclass(frozen=True)
class PaperCoverage:
    """What the paper reports for the same area (section V)."""

    flat_presses: int = 49
    flat_total_s: float = 196.0
    touchroller_total_s: float = 10.0


@dataclass(frozen=True)
class CoverageComparison:
    flat_sensor: FlatSensorTiming
    touchroller: RollTiming
    parameters: dict[str, Any]      # the comparison's settings: DEFAULTS updated by the scene's
    paper: PaperCoverage = PaperCoverage()

    @property
    def speedup(self) -> float:
        return self.flat_sensor.total_s / self.touchroller.total_s


def compare(comparison: dict[str, Any] | None, motion: dict[str, Any]) -> CoverageComparison:
    """Timing of the flat sensor's raster of presses and of the roller's single roll (seconds)."""
    p = dict(DEFAULTS)
    p.update(comparison or {})
    (width, length), (win_w, win_l) = p["area"], p["flat_sensor"]
    nx = presses_needed(width, win_w, p["overlap"])
    ny = presses_needed(length, win_l, p["overlap"])
    v, a = float(p["arm_speed"]), float(p["arm_accel"])
    lift, travel = float(p["lift"]), float(p["press_travel"])
    descend = TrapezoidProfile(lift - travel, v, a).duration
    approach = TrapezoidProfile(travel, float(p["press_speed"]), a).duration
    retract = TrapezoidProfile(lift, v, a).duration
    step_x = win_w * (1.0 - p["overlap"])
    step_y = win_l * (1.0 - p["overlap"])
    shift_in_row = TrapezoidProfile(step_x, v, a).duration
    shift_row = TrapezoidProfile(step_y, v, a).duration
    presses = nx * ny
    press_cycle = descend + approach + float(p["dwell"]) + retract
    shifts = (nx - 1) * ny * shift_in_row + (ny - 1) * shift_row    # boustrophedon raster
    flat = FlatSensorTiming(presses, (nx, ny), press_cycle, descend, approach, float(p["dwell"]), retract,
                            shift_in_row, shift_row, presses * press_cycle + shifts)
    roll = roll_profile(motion)
    roller = RollTiming(roll.duration, roll.peak_velocity, descend + approach + roll.duration + retract)
    return CoverageComparison(flat, roller, p)


def flat_press_mosaic(sensor: Any, comparison: dict[str, Any] | None = None, depth: float = 3e-4,
                      mm_per_px: float = 0.1) -> Any:
    """What the flat sensor's presses see, tiled in raster order (bgr8), at `mm_per_px`.

    Each press is a flat gel pressed `depth` into the (gel-low-passed) relief under its window: the
    gel plane sits `depth` below the highest point in the window, D = max(0, h - (h_top - depth)),
    shaded with the roller's own lights so the two sensors are compared like for like.
    """
    import cv2
    import numpy as np

    p = dict(DEFAULTS)
    p.update(comparison or {})
    (width, length), (win_w, win_l) = p["area"], p["flat_sensor"]
    nx = presses_needed(width, win_w, p["overlap"])
    ny = presses_needed(length, win_l, p["overlap"])
    step = mm_per_px * 1e-3
    cols, rows = round(win_w / step), round(win_l / step)
    mosaic = np.zeros((ny * rows, nx * cols, 3), np.uint8)
    relief = sensor._relief
    x_start = relief.x0 + 0.5 * (relief.width - width)
    for j in range(ny):
        for i in range(nx):
            x0 = x_start + i * win_w * (1.0 - p["overlap"])
            y0 = relief.y0 + j * win_l * (1.0 - p["overlap"])
            X, Y = np.meshgrid(x0 + (np.arange(cols) + 0.5) * step, y0 + (np.arange(rows) + 0.5) * step)
            h = relief.sample(X, Y).astype(np.float64)
            D = np.maximum(h - (h.max() - depth), 0.0)
            gy, gx = np.gradient(D, step, step)
            tile = sensor._shade_slopes(gx.astype(np.float32), gy.astype(np.float32))
            mosaic[j * rows:(j + 1) * rows, i * cols:(i + 1) * cols] = cv2.convertScaleAbs(tile)
    return mosaic
