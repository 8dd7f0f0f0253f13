"""One simulated clock for the simulated arm and the simulated camera.

`SimClock` is time that only its owner moves on, one fixed tick at a time (the sweep node's arm loop),
paced against the wall clock by `rate` (1: real time, 2: twice as fast). Everything simulated reads the
same ticks: the arm's moves are functions of the tick times and the arm is polled once per tick, so a
move starts on the tick that notices the previous one ended; the camera renders frame k at exactly
`frame_time_ns(k, fps)`, a grid fixed to whole seconds, which the ticks also hit when the tick rate is
a multiple of the frame rate. Given the same commands the images are the same, whatever the load.
In ROS the owner publishes it on /clock and the nodes run with use_sim_time.
"""
from __future__ import annotations

import math
import threading
import time
from fractions import Fraction

NS = 1_000_000_000


def frame_time_ns(k: int, fps: float) -> int:
    """Stamp of frame k on the frame grid of `fps` (frame 0 at time 0, whole seconds on the grid)."""
    rate = Fraction(fps).limit_denominator(1000)
    return (k * NS * rate.denominator) // rate.numerator


def first_frame_at_or_after(t_ns: int, fps: float) -> int:
    """The index of the first frame of the grid at or after `t_ns`."""
    rate = Fraction(fps).limit_denominator(1000)
    k = (t_ns * rate.numerator) // (NS * rate.denominator)
    while frame_time_ns(k, fps) < t_ns:
        k += 1
    return k


class SimClock:
    """Simulated time in ticks of 1 / `tick_hz` s (tick k exactly at `frame_time_ns(k, tick_hz)` after the
    start, so whole seconds and the frame grid of any frame rate dividing `tick_hz` fall on ticks),
    starting at `start_ns` rounded down to a whole second, advanced only by `advance()`; thread-safe to read."""

    def __init__(self, tick_hz: float, start_ns: int | None = None, rate: float = 1.0) -> None:
        if not (math.isfinite(tick_hz) and tick_hz > 0):
            raise ValueError(f"tick rate must be > 0 Hz, got {tick_hz}")
        if not (math.isfinite(rate) and rate > 0):
            raise ValueError(f"rate must be a finite number > 0, got {rate}")
        self.tick_hz = float(tick_hz)
        self.rate = float(rate)
        start = time.time_ns() if start_ns is None else int(start_ns)
        self._start_ns = start - start % NS
        self._ticks = 0
        self._now_ns = self._start_ns
        self._wall_origin: float | None = None
        self._lock = threading.Lock()

    def now_ns(self) -> int:
        return self._now_ns

    def now(self) -> float:
        """Seconds (what `SimulatedArm` takes as its clock)."""
        return self._now_ns / NS

    def on_whole_second(self) -> bool:
        return self._now_ns % NS == 0

    def step(self) -> int:
        """Move to the next tick at once (no pacing: offline simulation as fast as the machine goes)."""
        with self._lock:
            self._ticks += 1
            self._now_ns = self._start_ns + frame_time_ns(self._ticks, self.tick_hz)
            return self._now_ns

    def advance(self, stop: threading.Event | None = None) -> int:
        """Wait until the next tick is due on the wall clock (scaled by `rate`), then move to it."""
        with self._lock:
            now = time.monotonic()
            if self._wall_origin is None:
                self._wall_origin = now
            due = self._wall_origin + (self._ticks + 1) / self.tick_hz / self.rate
            if due > now:
                if stop is not None:
                    stop.wait(due - now)
                else:
                    time.sleep(due - now)
            elif now - due > 1.0:   # the owner stalled (a debugger, a suspended VM): do not race to catch up
                self._wall_origin += now - due
            self._ticks += 1
            self._now_ns = self._start_ns + frame_time_ns(self._ticks, self.tick_hz)
            return self._now_ns
