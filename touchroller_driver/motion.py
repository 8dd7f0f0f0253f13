"""Trapezoidal velocity profiles: how long a move takes under speed and acceleration limits.

Used by the simulated arm (sweeps) and by the flat-sensor comparison (press, lift, shift timing).
A move of `distance` accelerates at `a_max` up to `v_max`, cruises, then decelerates at `a_max`;
when the move is too short to reach `v_max` the profile is triangular (peak speed sqrt(a·|distance|)).
Negative distances move backwards with the same timing.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import ArrayLike


@dataclass(frozen=True)
class TrapezoidProfile:
    """Position/velocity of a rest-to-rest move; `position(t)` and `velocity(t)` accept arrays.

    Times before 0 clamp to the start, times after `duration` to the end.
    """

    distance: float
    v_max: float
    a_max: float
    _t_ramp: float = field(init=False, repr=False)
    _t_cruise: float = field(init=False, repr=False)
    _v_peak: float = field(init=False, repr=False)

    def __post_init__(self) -> None:
        for name in ("distance", "v_max", "a_max"):
            if not math.isfinite(getattr(self, name)):
                raise ValueError(f"TrapezoidProfile: {name} must be finite, got {getattr(self, name)}")
        if self.v_max <= 0 or self.a_max <= 0:
            raise ValueError(f"TrapezoidProfile: v_max and a_max must be > 0, got {self.v_max}, {self.a_max}")
        length = abs(self.distance)
        v_peak = min(self.v_max, math.sqrt(self.a_max * length))
        t_ramp = v_peak / self.a_max
        t_cruise = (length - v_peak * t_ramp) / v_peak if v_peak > 0 else 0.0
        object.__setattr__(self, "_v_peak", v_peak)
        object.__setattr__(self, "_t_ramp", t_ramp)
        object.__setattr__(self, "_t_cruise", max(t_cruise, 0.0))

    @property
    def duration(self) -> float:
        """Total time of the move in seconds (0 for a zero-length move)."""
        return 2.0 * self._t_ramp + self._t_cruise

    @property
    def peak_velocity(self) -> float:
        """Highest speed reached (v_max, or less for a triangular profile); always >= 0."""
        return self._v_peak

    def position(self, t: ArrayLike) -> np.ndarray | float:
        """Signed distance travelled at time(s) t."""
        t_arr = np.clip(np.asarray(t, dtype=np.float64), 0.0, self.duration)
        a, v, t1 = self.a_max, self._v_peak, self._t_ramp
        t2 = t1 + self._t_cruise
        ramp_up = 0.5 * a * t_arr**2
        cruise = 0.5 * a * t1**2 + v * (t_arr - t1)
        remaining = self.duration - t_arr
        ramp_down = abs(self.distance) - 0.5 * a * remaining**2
        s = np.where(t_arr < t1, ramp_up, np.where(t_arr < t2, cruise, ramp_down))
        s = math.copysign(1.0, self.distance) * s
        return float(s) if s.ndim == 0 else s

    def velocity(self, t: ArrayLike) -> np.ndarray | float:
        """Signed speed at time(s) t (0 outside [0, duration])."""
        t_arr = np.asarray(t, dtype=np.float64)
        a, v, t1 = self.a_max, self._v_peak, self._t_ramp
        t2 = t1 + self._t_cruise
        inside = (t_arr >= 0.0) & (t_arr <= self.duration)
        speed = np.where(t_arr < t1, a * t_arr, np.where(t_arr < t2, v, a * (self.duration - t_arr)))
        speed = np.where(inside, np.clip(speed, 0.0, v), 0.0)
        speed = math.copysign(1.0, self.distance) * speed
        return float(speed) if speed.ndim == 0 else speed
