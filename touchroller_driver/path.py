"""A raster rolled as one blended path: touchdown and lift-off at speed, as a UR program of `movel`s
with blend radii moves (`sweep.profile` `blend`; `constant`: the same path with sharp corners).

`BlendedPath(waypoints, speed, accel, blend)` is the polyline through the tool poses (N, 6), each inner
corner rounded by a quadratic Bezier between the points `blend` before and after it (the blend radius,
at most half the shorter leg), followed at `speed` along its length: a trapezoid over the whole length
(accelerating once at the start, decelerating once at the end), the speed varied by `jitter` (a
fraction: a smooth random factor 1 + jitter n(t), n of unit RMS, from `seed`) and stopped for
`pauses` ((arc length m, seconds), ...) along the way. Poses are sampled on the path every
`step` m and interpolated linearly in between.
"""
from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import ArrayLike

from touchroller_driver.motion import TrapezoidProfile


@dataclass(frozen=True)
class BlendedPath:
    waypoints: np.ndarray
    speed: float
    accel: float
    blend: float = 0.0
    jitter: float = 0.0
    seed: int = 0
    pauses: tuple[tuple[float, float], ...] = ()
    step: float = 2e-4
    _points: np.ndarray = field(init=False, repr=False)
    _arc: np.ndarray = field(init=False, repr=False)
    _times: np.ndarray = field(init=False, repr=False)
    _travel: np.ndarray = field(init=False, repr=False)

    def __post_init__(self) -> None:
        points = np.asarray(self.waypoints, np.float64)
        if points.ndim != 2 or points.shape[1] != 6 or len(points) < 2 or not np.isfinite(points).all():
            raise ValueError("a blended path needs at least two finite tool poses (N, 6)")
        if not (self.speed > 0 and self.accel > 0 and self.blend >= 0 and 0 <= self.jitter <= 0.2):
            raise ValueError("a blended path needs speed > 0, accel > 0, blend >= 0 and jitter in [0, 0.2]")
        dense = _rounded(points, self.blend, self.step)
        arc = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(dense[:, :3], axis=0), axis=1))])
        object.__setattr__(self, "_points", dense)
        object.__setattr__(self, "_arc", arc)
        # time -> arc length: the trapezoid's nominal progress, its rate varied by the jitter, with pauses
        profile = TrapezoidProfile(float(arc[-1]), self.speed, self.accel)
        dt = 1e-3
        t = np.arange(0.0, profile.duration + dt, dt)
        nominal = np.asarray(profile.velocity(t), np.float64)
        if self.jitter > 0:
            rng = np.random.default_rng(self.seed)
            freqs = rng.uniform(0.2, 2.0, 6)
            phases = rng.uniform(0, 2 * math.pi, 6)
            wave = np.sin(2 * math.pi * freqs[:, None] * t[None, :] + phases[:, None]).sum(axis=0)
            wave /= max(float(np.sqrt(np.mean(wave ** 2))), 1e-9)
            nominal = nominal * (1.0 + self.jitter * wave)
        travel = np.concatenate([[0.0], np.cumsum(0.5 * (nominal[1:] + nominal[:-1]) * dt)])
        travel *= arc[-1] / max(float(travel[-1]), 1e-12)   # the jitter does not change where it ends
        for where, seconds in sorted(self.pauses, reverse=True):
            k = int(np.searchsorted(travel, where))
            if 0 < k < len(travel) and seconds > 0:
                hold = int(round(seconds / dt))
                t = np.concatenate([t[:k], t[k] + np.arange(hold) * dt, t[k:] + hold * dt])
                travel = np.concatenate([travel[:k], np.full(hold, travel[k]), travel[k:]])
        object.__setattr__(self, "_times", t)
        object.__setattr__(self, "_travel", travel)

    @property
    def duration(self) -> float:
        return float(self._times[-1])

    @property
    def length(self) -> float:
        return float(self._arc[-1])

    def arc_at(self, point: ArrayLike) -> float:
        """The arc length (m) of the path's sample nearest to a position (x, y, z)."""
        p = np.asarray(point, np.float64)[:3]
        return float(self._arc[int(np.argmin(np.linalg.norm(self._points[:, :3] - p, axis=1)))])

    def pose(self, t: float) -> np.ndarray:
        """The tool pose (6,) at t s after the path's start (clamped to its ends)."""
        return self.poses(np.array([t]))[0]

    def poses(self, t: np.ndarray) -> np.ndarray:
        """The tool poses (N, 6) at times t (N,) s after the path's start (clamped to its ends)."""
        s = np.interp(np.asarray(t, np.float64), self._times, self._travel)
        k = np.clip(np.searchsorted(self._arc, s) - 1, 0, len(self._arc) - 2)
        span = self._arc[k + 1] - self._arc[k]
        f = np.divide(s - self._arc[k], span, out=np.zeros_like(s), where=span > 0)
        return np.asarray(self._points[k] + f[:, None] * (self._points[k + 1] - self._points[k]), np.float64)


def _rounded(points: np.ndarray, blend: float, step: float) -> np.ndarray:
    """The polyline sampled about every `step` m, each inner corner rounded (quadratic Bezier) by `blend`."""
    out: list[np.ndarray] = [points[0]]
    cursor = points[0]
    for k in range(1, len(points)):
        corner = points[k]
        r = 0.0
        if k < len(points) - 1 and blend > 0:
            before = float(np.linalg.norm(corner[:3] - points[k - 1][:3]))
            after = float(np.linalg.norm(points[k + 1][:3] - corner[:3]))
            r = min(blend, 0.5 * before, 0.5 * after)
            a = corner + (points[k - 1] - corner) * (r / before if before > 0 else 0.0)
            b = corner + (points[k + 1] - corner) * (r / after if after > 0 else 0.0)
        else:
            a = b = corner
        out.extend(_line(cursor, a, step))
        if b is not a:
            n = max(int(math.ceil(2 * r / step)), 2)
            u = np.linspace(0.0, 1.0, n + 1)[1:, None]
            out.extend((1 - u) ** 2 * a + 2 * (1 - u) * u * corner + u ** 2 * b)
        cursor = b
    dense = np.array(out)
    keep = np.concatenate([[True], np.linalg.norm(np.diff(dense[:, :3], axis=0), axis=1) > 1e-9])
    return np.asarray(dense[keep], np.float64)


def _line(a: np.ndarray, b: np.ndarray, step: float) -> list[np.ndarray]:
    n = max(int(math.ceil(float(np.linalg.norm(b[:3] - a[:3])) / step)), 1)
    return list(a + (b - a) * np.linspace(0.0, 1.0, n + 1)[1:, None])


def raster_waypoints(passes: Sequence[tuple[ArrayLike, ArrayLike]], above: float, lead: float) -> np.ndarray:
    """Tool poses of a raster rolled at speed: for every pass (pressed start pose, pressed end pose), a
    point `above` m higher and `lead` m before its start, the start, the end, and a point `above` higher
    and `lead` beyond its end."""
    out = []
    for start, end in passes:
        a, b = np.asarray(start, np.float64), np.asarray(end, np.float64)
        heading = b[:3] - a[:3]
        heading = heading / max(float(np.linalg.norm(heading)), 1e-12)
        up = np.array([0.0, 0.0, above])
        before, after = a.copy(), b.copy()
        before[:3] += up - lead * heading
        after[:3] += up + lead * heading
        out.extend([before, a, b, after])
    return np.array(out)
