"""One simulated clock for the simulated arm and the simulated camera.

`SimClock` is time that only its owner moves on, one fixed tick at a time (the sweep node's arm loop),
paced against the wall clock by `rate` (1: real time, 2: twice as fast). Everything simulated reads the
same ticks: the arm's moves are functions of the tick times and the arm is polled once per tick, so a
move starts on the tick that notices the previous one ended; the camera renders frame k at exactly
`frame_time_ns(k, fps)`, a grid fixed to whole seconds, which the ticks also hit when the tick rate is
a multiple of the frame rate. Given the same commands the images are the same, whatever the load.
In ROS the owner publishes it on /clock and the nodes run with use_sim_time.

`FrameGate` says when the owner may move the clock on: not past the frames its consumers have not
taken yet, so a slow or loaded machine makes simulated time run slower instead of making the camera
fall behind the arm or a consumer miss frames.
"""
from __future__ import annotations

import bisect
import math
import threading
import time
from collections import deque
from collections.abc import Iterable
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

    def next_ns(self) -> int:
        """The time of the next tick (where `step` or `advance` will move to)."""
        with self._lock:
            return self._start_ns + frame_time_ns(self._ticks + 1, self.tick_hz)

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


class FrameGate:
    """When a simulated clock may move on, given the frames a camera published on it and the ones its
    consumers (the perception node, a recorder) have finished; thread-safe (events come from callbacks, the
    owner asks).

    With consumers present: not more than `lead_ns` past the oldest published frame one of them has not
    finished (they finish frames without the clock, so this never deadlocks). Without one, or with nothing
    unfinished: not more than `lead_ns` past the camera's next frame (newest + frame interval, the
    smallest interval seen between published stamps), so the camera cannot fall behind the arm either.
    Free until the camera has published twice. Stamps are the frames' (latency included); monotonic.
    Each consumer is named (`finished(stamp, consumer)`); `consumers=True` is the unnamed one ("").
    """

    def __init__(self, lead_ns: int, memory: int = 1000) -> None:
        if lead_ns < 0:
            raise ValueError(f"lead must be >= 0 ns, got {lead_ns}")
        self.lead_ns = int(lead_ns)
        self._published: deque[int] = deque(maxlen=memory)   # the newest published stamps, increasing
        self._newest: int | None = None
        self._interval: int | None = None
        self._finished: dict[str, int] = {}   # consumer -> the newest stamp it finished
        self._changed = threading.Condition()
        self.events = 0   # published + finished reports so far (a waiting owner sees whether anything moved)

    def published(self, stamp_ns: int) -> None:
        with self._changed:
            stamp_ns = int(stamp_ns)
            if self._newest is not None:
                if stamp_ns <= self._newest:
                    return
                step = stamp_ns - self._newest
                self._interval = step if self._interval is None else min(self._interval, step)
            self._newest = stamp_ns
            self._published.append(stamp_ns)
            self.events += 1
            self._changed.notify_all()

    def finished(self, stamp_ns: int, consumer: str = "") -> None:
        with self._changed:
            stamp_ns = int(stamp_ns)
            if consumer not in self._finished or stamp_ns > self._finished[consumer]:
                self._finished[consumer] = stamp_ns
            self.events += 1
            self._changed.notify_all()

    def _oldest_unfinished(self, consumer: str) -> int | None:
        done = self._finished.get(consumer)
        index = 0 if done is None else bisect.bisect_right(self._published, done)
        return self._published[index] if index < len(self._published) else None

    def limit_ns(self, consumers: bool | Iterable[str]) -> int | None:
        """The latest time the clock may move to now (None: no limit), with `consumers` present."""
        present = ("",) if consumers is True else () if consumers is False else tuple(consumers)
        with self._changed:
            oldest = [stamp for stamp in map(self._oldest_unfinished, present) if stamp is not None]
            if oldest:
                return min(oldest) + self.lead_ns
            if self._newest is None or self._interval is None:
                return None
            return self._newest + self._interval + self.lead_ns

    def allows(self, t_ns: int, consumers: bool | Iterable[str]) -> bool:
        limit = self.limit_ns(consumers)
        return limit is None or t_ns <= limit

    def wait(self, timeout: float) -> None:
        """Until the next published or finished report, or `timeout` seconds."""
        with self._changed:
            self._changed.wait(timeout)
