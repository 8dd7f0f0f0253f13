"""Simulated arms for the sweep node's tests (test_sweep_node, test_sweep_action), loaded by file path as
fake_ur_driver.py is (the test folders are not packages, and `test` is the standard library's name).

The arm's clock runs SPEEDUP x wall time to keep tests short; `SlowRollArm` drops to SLOW_ROLL x wall
time once it rolls, so a test that acts on a sweep *while it rolls* does not race a 0.1 s window that a
descheduled test thread misses on a loaded machine.
"""
from __future__ import annotations

import math
import threading
import time

import pytest

from touchroller_driver.arm import SimulatedArm

START = [0.4, 0.0, 0.2, math.pi, 0.0, 0.0]
SWEEP_SPEED = 0.02
SPEEDUP = 10.0
SLOW_ROLL = 0.02   # the roll (1 s of arm time) then lasts 50 s of wall time: no stall on a loaded machine ends it


def fast_clock() -> float:
    return time.monotonic() * SPEEDUP


class ScaledClock:
    """Wall time scaled by a rate the test can change while it runs (continuous, never jumps back)."""

    def __init__(self, rate: float = SPEEDUP) -> None:
        self._lock = threading.Lock()
        self._since, self._base, self.rate = time.monotonic(), time.monotonic() * rate, rate

    def __call__(self) -> float:
        with self._lock:
            return self._base + (time.monotonic() - self._since) * self.rate

    def set_rate(self, rate: float) -> None:
        with self._lock:
            now = time.monotonic()
            self._base += (now - self._since) * self.rate
            self._since, self.rate = now, rate


class SlowRollArm(SimulatedArm):
    """Moves to the surface SPEEDUP x faster than real time, then rolls at SLOW_ROLL x real time; counts
    its linear moves (a rejected goal or start must leave `moves` unchanged)."""

    def __init__(self) -> None:
        super().__init__(START, clock=ScaledClock())
        self.rolling = threading.Event()
        self.moves = 0

    def move_linear(self, target_pose, speed: float, accel: float, asynchronous: bool = True) -> None:
        self.moves += 1
        super().move_linear(target_pose, speed, accel, asynchronous)
        if speed == pytest.approx(SWEEP_SPEED) and not self.rolling.is_set():   # the roll segment
            self.clock.set_rate(SLOW_ROLL)
            self.rolling.set()
