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

    def travelled(self, t: float) -> float:
        """The arc length (m) covered t s after the path's start (clamped to its ends)."""
        return float(np.interp(t, self._times, self._travel))

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


def blend_radii(points: ArrayLike, blend: float) -> np.ndarray:
    """The blend radius (m) at each of the waypoints (N, 6): `blend` at an inner corner, at most half the
    shorter leg beside it (so neighbouring blends never overlap, as a UR controller requires), 0 at the
    first and last waypoint."""
    p = np.asarray(points, np.float64)
    legs = np.linalg.norm(np.diff(p[:, :3], axis=0), axis=1)
    radii = np.zeros(len(p))
    if len(p) > 2 and blend > 0:
        radii[1:-1] = np.minimum(blend, 0.5 * np.minimum(legs[:-1], legs[1:]))
    return radii


def _corner_angles(points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(cos(alpha/2), sin(alpha/2)) at each waypoint, alpha the angle between its two legs (pi: straight on;
    the ends count as straight)."""
    half_cos, half_sin = np.zeros(len(points)), np.ones(len(points))
    if len(points) > 2:
        u1 = points[:-2, :3] - points[1:-1, :3]
        u2 = points[2:, :3] - points[1:-1, :3]
        n1, n2 = np.linalg.norm(u1, axis=1), np.linalg.norm(u2, axis=1)
        valid = (n1 > 0) & (n2 > 0)
        cos_alpha = np.where(valid, np.einsum("ij,ij->i", u1, u2) / np.where(valid, n1 * n2, 1.0), -1.0)
        cos_alpha = np.clip(cos_alpha, -1.0, 1.0)
        half_cos[1:-1] = np.sqrt((1.0 + cos_alpha) / 2.0)
        half_sin[1:-1] = np.sqrt((1.0 - cos_alpha) / 2.0)
    return half_cos, half_sin


def corner_accelerations(points: ArrayLike, speed: float, blend: float) -> np.ndarray:
    """The centripetal acceleration (m/s^2) at each waypoint (N, 6) of a path followed at `speed` with
    corners rounded by `blend_radii` (a symmetric quadratic Bezier, sharpest at its middle: curvature
    cos(alpha/2) / (r sin^2(alpha/2))): 0 on a straight line, infinite at a sharp turn (radius 0)."""
    p = np.asarray(points, np.float64)
    half_cos, half_sin = _corner_angles(p)
    radii = blend_radii(p, blend)
    turning = half_cos > 1e-9
    with np.errstate(divide="ignore", invalid="ignore"):
        curvature = np.where(turning, half_cos / (radii * half_sin ** 2), 0.0)
    return np.asarray(np.where(turning & ~np.isfinite(curvature), np.inf, speed ** 2 * curvature), np.float64)


def least_blend(points: ArrayLike, speed: float, accel: float) -> float:
    """The smallest blend radius (m) with which every corner of the path is taken at `speed` within
    `accel` (m/s^2): `constant`'s corners, as sharp as the arm may take them without stopping."""
    p = np.asarray(points, np.float64)
    half_cos, half_sin = _corner_angles(p)
    with np.errstate(divide="ignore", invalid="ignore"):
        radii = np.where(half_cos > 1e-9, speed ** 2 * half_cos / (accel * half_sin ** 2), 0.0)
    return float(np.max(radii, initial=0.0))


def rounded_polyline(points: np.ndarray, blend: float, step: float = 2e-4) -> np.ndarray:
    """The polyline sampled about every `step` m, each inner corner rounded (quadratic Bezier) by its
    `blend_radii` radius: the path a blended motion follows (checked against the arm's limits whole)."""
    return _rounded(np.asarray(points, np.float64), blend, step)


def _rounded(points: np.ndarray, blend: float, step: float) -> np.ndarray:
    """The polyline sampled about every `step` m, each inner corner rounded (quadratic Bezier) by `blend`."""
    out: list[np.ndarray] = [points[0]]
    cursor = points[0]
    radii = blend_radii(points, blend)
    for k in range(1, len(points)):
        corner = points[k]
        r = float(radii[k])
        if r > 0:
            before = float(np.linalg.norm(corner[:3] - points[k - 1][:3]))
            after = float(np.linalg.norm(points[k + 1][:3] - corner[:3]))
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


def fraction_along_path(waypoints: ArrayLike, pose: ArrayLike) -> float:
    """Fraction (0..1) of a polyline's length up to the point on it nearest to the pose's position."""
    points = np.asarray(waypoints, np.float64)[:, :3]
    here = np.asarray(pose, np.float64)[:3]
    if len(points) < 2 or not np.all(np.isfinite(here)):
        return 1.0 if np.all(np.isfinite(here)) else float("nan")
    starts, legs = points[:-1], np.diff(points, axis=0)
    lengths_sq = np.einsum("ij,ij->i", legs, legs)
    total = float(np.sqrt(lengths_sq).sum())
    if total == 0.0:
        return 1.0
    t = np.clip(np.einsum("ij,ij->i", here - starts, legs) / np.where(lengths_sq > 0, lengths_sq, 1.0), 0.0, 1.0)
    gaps = np.linalg.norm(starts + t[:, None] * legs - here, axis=1)
    k = int(np.argmin(gaps))
    before = float(np.sqrt(lengths_sq[:k]).sum())
    return min(max((before + float(t[k]) * float(np.sqrt(lengths_sq[k]))) / total, 0.0), 1.0)


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
