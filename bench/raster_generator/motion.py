"""The second generator's arm: a boustrophedon raster with a chosen motion profile, sampled at 1 kHz.

The trajectory is the roller's axis (the `touchroller_cylinder` origin) in a raster frame: u along the
passes, w across them, h the height above the pressed height (0: pressed `depth` into the surface;
`depth`: the membrane just touching; `clearance`: lifted). A pass rolls `length` along u at one w; passes
alternate in direction. Profiles (`PROFILES`):

* `ramp`: the roller presses at rest at the pass's start, accelerates (`accel`), rolls, stops, lifts;
* `blend`: touchdown and lift-off at speed (the roller comes down and goes up over `lead` of travel
  while rolling, as `movel`s with blend radii move), the speed varying slowly by `variation` (1 %)
  along the pass, no stop between passes;
* `constant`: touchdown and lift-off at speed, the speed constant to the last digit;
* `pauses`: as `ramp`, with `pauses` stops of `pause_s` inside each pass and a smooth random speed
  jitter of `jitter` (RMS, 1-5 %).

Speeds are integrated under an acceleration limit (each stop planned back from where it must be
reached), so the position is what an arm's controller would do, not a formula of time.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

PROFILES = ("ramp", "blend", "constant", "pauses")
DT = 1e-3     # s, the trajectory's sampling step


@dataclass(frozen=True)
class MotionConfig:
    profile: str = "blend"
    speed: float = 0.02          # m/s along a pass
    accel: float = 0.1           # m/s^2
    depth: float = 5e-4          # m pressed
    clearance: float = 2e-3      # m above the pressed height between passes
    approach_speed: float = 0.005   # m/s, vertical moves of ramp / pauses
    transit_speed: float = 0.04  # m/s, ramp / pauses: from one pass to the next (lifted)
    lead: float = 5e-3           # m of travel over which `blend` / `constant` touch down or lift off
    variation: float = 0.01      # blend: relative amplitude of the slow speed variation
    variation_period: float = 3.0   # s
    jitter: float = 0.03         # pauses: RMS relative speed jitter
    pauses: int = 2
    pause_s: float = 0.4
    dwell_s: float = 0.2         # ramp / pauses: rest pressed before rolling and after stopping
    seed: int = 0

    def __post_init__(self) -> None:
        if self.profile not in PROFILES:
            raise ValueError(f"unknown motion profile {self.profile!r} (one of {', '.join(PROFILES)})")


@dataclass(frozen=True)
class PassTruth:
    """One pass as rolled: its line in the raster frame and when the roller was pressed (h < depth)."""

    index: int
    w: float                     # m across
    u_start: float
    u_end: float                 # u_end < u_start for a pass rolled backwards
    contact_start_s: float       # time the membrane first touches
    contact_end_s: float         # time it last touches


@dataclass(frozen=True)
class Trajectory:
    t: np.ndarray                # (N,) s
    u: np.ndarray                # (N,) m
    w: np.ndarray
    h: np.ndarray
    passes: tuple[PassTruth, ...]

    def at(self, times: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(u, w, h) at `times` (s), linear between the 1 kHz samples, held beyond the ends."""
        return (np.interp(times, self.t, self.u), np.interp(times, self.t, self.w), np.interp(times, self.t, self.h))


class _Builder:
    def __init__(self, config: MotionConfig) -> None:
        self.c = config
        self.t: list[float] = [0.0]
        self.u: list[float] = []
        self.w: list[float] = []
        self.h: list[float] = []
        self.v = 0.0
        self.at = (0.0, 0.0, 0.0)   # where the last move ended
        self.carry = 0.0   # m of the last time step a move ending at speed did not use: the next one starts with it
        rng = np.random.default_rng(np.random.SeedSequence([config.seed, 2205]))
        # a smooth random speed factor: a sum of sinusoids of random phases, periods 0.5-4 s
        periods = rng.uniform(0.5, 4.0, 8)
        phases = rng.uniform(0, 2 * np.pi, 8)
        amplitude = math.sqrt(2.0 / 8)
        self._jitter = lambda t: amplitude * float(np.sum(np.sin(2 * np.pi * t / periods + phases)))
        self._phase = float(rng.uniform(0, 2 * np.pi))

    @property
    def now(self) -> float:
        return self.t[-1]

    def _add(self, u: float, w: float, h: float) -> None:
        if self.u:
            self.t.append(self.t[-1] + DT)
        self.u.append(u)
        self.w.append(w)
        self.h.append(h)

    def start(self, u: float, w: float, h: float) -> None:
        self._add(u, w, h)
        self.at = (u, w, h)

    def _flush(self) -> None:
        """Emit the end of a move that ended at speed inside a time step (before a hold or vertical move)."""
        if self.carry > 0:
            self._add(*self.at)
            self.carry = 0.0

    def hold(self, seconds: float) -> None:
        self._flush()
        for _ in range(max(int(round(seconds / DT)), 1)):
            self._add(self.u[-1], self.w[-1], self.h[-1])

    def vertical(self, h1: float) -> None:
        self._flush()
        h0 = self.h[-1]
        steps = max(int(math.ceil(abs(h1 - h0) / (self.c.approach_speed * DT))), 1)
        for k in range(1, steps + 1):
            self._add(self.u[-1], self.w[-1], h0 + (h1 - h0) * k / steps)
        self.at = (self.u[-1], self.w[-1], self.h[-1])

    def speed_factor(self, kind: str) -> float:
        if kind == "blend":
            return 1.0 + self.c.variation * math.sin(2 * math.pi * self.now / self.c.variation_period + self._phase)
        if kind == "jitter":
            return 1.0 + self.c.jitter * self._jitter(self.now)
        return 1.0

    def move(self, target: tuple[float, float], h1: float, speed: float, *, stop: bool, stops: tuple[float, ...] = (),
             kind: str = "none", pause_s: float = 0.0) -> None:
        """Along the straight line to `target` (u, w), height linear in distance to `h1`; accel-limited;
        `stop`: at rest at the end; `stops`: fractions of the way to stop at (and wait `pause_s`)."""
        u0, w0, h0 = self.at        # where the previous move ended (its last sample may lie short of it)
        self.at = (target[0], target[1], h1)
        total = math.hypot(target[0] - u0, target[1] - w0)
        if total <= 0:
            return
        du, dw = (target[0] - u0) / total, (target[1] - w0) / total
        marks = sorted(s * total for s in stops)
        s = 0.0
        a = self.c.accel
        while s < total - 1e-9:
            next_stop = next((m for m in marks if m > s + 1e-9), total if stop else None)
            if self.carry > 0:    # finish the time step the previous move began
                step, self.carry = min(self.carry, total - s), max(self.carry - (total - s), 0.0)
                s += step
                if self.carry == 0:
                    self._add(u0 + du * s, w0 + dw * s, h0 + (h1 - h0) * s / total)
                continue
            desired = speed * self.speed_factor(kind)
            if next_stop is not None:
                desired = min(desired, math.sqrt(max(2 * a * (next_stop - s), 0.0)))
            self.v = min(max(desired, self.v - a * DT), self.v + a * DT)
            step = self.v * DT
            if next_stop is not None and s + step >= next_stop - 1e-9:
                s = next_stop
                self._add(u0 + du * s, w0 + dw * s, h0 + (h1 - h0) * s / total)
                if next_stop < total - 1e-9 or stop:
                    self.v = 0.0
                if next_stop < total - 1e-9:
                    self.hold(pause_s)
                continue
            if s + step > total:          # the move ends inside this time step, at speed: the next one goes on
                self.carry = s + step - total
                s = total
                continue
            s += step
            self._add(u0 + du * s, w0 + dw * s, h0 + (h1 - h0) * s / total)


def plan(length: float, across: list[float], config: MotionConfig) -> Trajectory:
    """A boustrophedon raster: a pass of `length` (m, along u from 0) at each w in `across`."""
    c = config
    b = _Builder(c)
    passes_rows: list[tuple[int, float, float, float]] = []
    at_speed = c.profile in ("blend", "constant")
    for k, w in enumerate(across):
        forward = k % 2 == 0
        u_start, u_end = (0.0, length) if forward else (length, 0.0)
        sign = 1.0 if forward else -1.0
        if at_speed:
            entry = (u_start - sign * c.lead, w)
            if k == 0:
                b.start(entry[0] - sign * 0.01, w, c.clearance)   # a run-up at clearance height
                b.v = c.speed
                b.move(entry, c.clearance, c.speed, stop=False)
            else:
                b.move(entry, c.clearance, c.speed, stop=False)   # the path speed held round the turn
            kind = "blend" if c.profile == "blend" else "none"
            b.move((u_start, w), 0.0, c.speed, stop=False, kind=kind)
            b.move((u_end, w), 0.0, c.speed, stop=False, kind=kind)
            b.move((u_end + sign * c.lead, w), c.clearance, c.speed, stop=False, kind=kind)
        else:
            if k == 0:
                b.start(u_start, w, c.clearance)
            else:
                b.move((u_start, w), c.clearance, c.transit_speed, stop=True)
            b.vertical(0.0)
            b.hold(c.dwell_s)
            stops = tuple((i + 1) / (c.pauses + 1) for i in range(c.pauses)) if c.profile == "pauses" else ()
            kind = "jitter" if c.profile == "pauses" else "none"
            b.move((u_end, w), 0.0, c.speed, stop=True, stops=stops, kind=kind, pause_s=c.pause_s)
            b.hold(c.dwell_s)
            b.vertical(c.clearance)
        passes_rows.append((k, w, u_start, u_end))
    if at_speed:   # run out at clearance
        last_sign = 1.0 if (len(across) - 1) % 2 == 0 else -1.0
        b.move((b.at[0] + last_sign * 0.01, b.at[1]), c.clearance, c.speed, stop=True)
    t = np.asarray(b.t)
    u, w_arr, h = np.asarray(b.u), np.asarray(b.w), np.asarray(b.h)
    passes = []
    for k, w, u_start, u_end in passes_rows:
        on = (h < c.depth) & (np.abs(w_arr - w) < 1e-9)
        times = t[on]
        passes.append(PassTruth(k, float(w), float(u_start), float(u_end), float(times.min()), float(times.max())))
    return Trajectory(t, u, w_arr, h, tuple(passes))


def pass_spacing(width: float, passes: int, seen: float = 0.064) -> list[float]:
    """`passes` pass lines across `width`, flush with its edges (the camera sees `seen` along the axis)."""
    if passes == 1:
        return [width / 2]
    first, last = seen / 2, width - seen / 2
    return [float(v) for v in np.linspace(first, last, passes)]
