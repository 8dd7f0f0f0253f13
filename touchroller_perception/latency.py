"""The camera's latency (exposure to stamp) from a scan's data: the image-registered roll against the arm's.

`LatencyEstimator` takes windows of the strip stitcher's confident image positions around each start and
stop of a roll and finds the latency at which they follow the arm's roll from TF; its `result()` is a
`LatencyEstimate` (value, sources, whether the data pinned it down). No rclpy here.
"""
from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray

from touchroller_perception.fast_stats import median

FloatArray = NDArray[np.float64]
#: T_world_cylinder (N, 4, 4) at each of N stamps (ns), all-NaN where it is not known (yet).
PoseLookup = Callable[[NDArray[np.int64]], FloatArray]


@dataclass(frozen=True)
class LatencyConfig:
    """How a `LatencyEstimator` works.

    max_latency: the largest latency searched, s.
    before, after: the window around a start or stop of the roll, s.
    max_residual_px: a window the model does not fit (RMS above this: a slip, lost texture) is left out.
    """

    max_latency: float = 0.2
    before: float = 1.0
    after: float = 1.0
    max_residual_px: float = 0.3

    def __post_init__(self) -> None:
        if not (0 < self.max_latency <= 1.0):
            raise ValueError(f"max_latency must be in (0, 1] s, got {self.max_latency}")
        if not (self.before > 0 and self.after > 0 and self.max_residual_px > 0):
            raise ValueError("before, after and max_residual_px must be > 0")


@dataclass(frozen=True)
class LatencyEstimate:
    """What the data say of the latency: `value` (s), its standard deviation `sigma` (s, None where not
    known), the kinds of evidence it rests on, and whether they pinned it down (`observable`)."""

    value: float
    sigma: float | None
    sources: tuple[str, ...]
    observable: bool


@dataclass
class _Window:
    """Frames around one start or stop of the roll: (stamp ns, image position px), confident ones only."""

    stamps: list[int] = field(default_factory=list)
    positions: list[float] = field(default_factory=list)
    latency: float | None = None   # its own estimate, s (None: it has no clear minimum)
    residual_px: float | None = None
    solved: bool = False


class LatencyEstimator:
    """The camera's latency from the data: the strip stitcher's image position P_k (rows the surface
    moved in the band) must follow the arm: P_k = c + s Y(t_k - L), Y = the roll along the band's rows
    from TF (m / m_per_row). At constant speed any L fits (c absorbs it), so the fit uses windows around
    each start and stop of a roll, where the image and the arm must start (stop) together; L minimises
    the sum of the windows' least-squares residuals (c and s fitted per window, s for the scale error of
    a calibration), searched over [0, max_latency] at 1 ms, then refined by a parabola."""

    def __init__(self, m_per_row: float, config: LatencyConfig | None = None) -> None:
        self.config = config = config or LatencyConfig()
        self.max_latency_ns = round(config.max_latency * 1e9)
        self.m_per_row = m_per_row
        self.before_ns, self.after_ns = round(config.before * 1e9), round(config.after * 1e9)
        self.max_residual_px = config.max_residual_px
        self.windows: list[_Window] = []
        self.estimate: float | None = None   # seconds
        self.residual_px: float | None = None  # RMS of the fit at the estimate

    def add_window(self, stamps: Sequence[int], positions: Sequence[float]) -> None:
        if len(stamps) >= 8:
            self.windows.append(_Window(list(stamps), list(positions)))

    def _scan(self, window: _Window, candidates: NDArray[np.int64], poses: PoseLookup) -> tuple[np.ndarray, int] | None:
        """The window's cost (mean squared residual of the best line P = c + s Y, px^2) at each candidate
        latency (NaN where a pose is missing), all candidates in one lookup; with the best's index."""
        stamps = np.asarray(window.stamps, np.int64)
        transforms = poses((stamps[None, :] - candidates[:, None]).reshape(-1))
        transforms = transforms.reshape(len(candidates), len(stamps), 4, 4)
        # where a point fixed in the world (the first pose's origin) lies along the cylinder's y axis
        offsets = transforms[:, :1, :3, 3] - transforms[:, :, :3, 3]
        y = np.einsum("cki,cki->ck", transforms[:, :, :3, 1], offsets) / self.m_per_row
        p = np.asarray(window.positions, np.float64)
        dy = y - y.mean(axis=1, keepdims=True)
        dp = p - p.mean()
        syy, syp, spp = (dy * dy).sum(axis=1), dy @ dp, float(dp @ dp)
        slope_part = np.divide(syp * syp, syy, out=np.zeros_like(syy), where=syy > 1e-12)
        costs = np.maximum(spp - slope_part, 0.0) / len(p)
        costs[~np.isfinite(transforms).all(axis=(1, 2, 3))] = np.nan
        if not np.isfinite(costs).any():
            return None
        return costs, int(np.nanargmin(costs))

    def _solve_window(self, window: _Window, poses: PoseLookup) -> float | None:
        """The latency that fits one window best: a 5 ms grid over [0, max_latency], then 1 ms around its
        best, then a parabola through the three best; None when the window says nothing (flat costs)."""
        coarse = self._scan(window, np.arange(0, self.max_latency_ns + 1, 5_000_000), poses)
        if coarse is None:
            return None
        costs, best = coarse
        finite = costs[np.isfinite(costs)]
        if finite.max() < 4.0 * max(finite.min(), 1e-6):   # no clear minimum: no start or stop in it
            return None
        centre = best * 5_000_000
        candidates = np.arange(max(centre - 6_000_000, 0), min(centre + 6_000_000, self.max_latency_ns) + 1, 1_000_000)
        fine = self._scan(window, candidates, poses)
        if fine is None:
            return None
        costs, best = fine
        offset = 0.0
        if 0 < best < len(costs) - 1 and np.isfinite(costs[best - 1]) and np.isfinite(costs[best + 1]):
            a, b, c = costs[best - 1], costs[best], costs[best + 1]
            den = a - 2 * b + c
            if den > 0:
                offset = float(np.clip(0.5 * (a - c) / den, -0.5, 0.5))
        window.latency = max(float(candidates[best]) + offset * 1e6, 0.0) * 1e-9
        window.residual_px = math.sqrt(max(float(costs[best]), 0.0))
        return window.latency

    def solve(self, poses: PoseLookup) -> float | None:
        """The median of the windows' estimates (each window solved once): None until one has a clear
        minimum. One bad window (a slip, a textureless start) does not move the median."""
        for window in self.windows:
            if window.latency is None and not window.solved:
                # every candidate needs the poses of the window's frames: wait until TF has its last one
                # (else the short latencies, the most recent poses, would be missing from the comparison)
                if not np.isfinite(poses(np.asarray(window.stamps[-1:], np.int64))).all():
                    continue
                window.solved = True
                self._solve_window(window, poses)
        good = [(w.latency, w.residual_px) for w in self.windows if w.latency is not None
                and w.residual_px is not None and w.residual_px <= self.max_residual_px]
        if not good:
            return None
        self.estimate = median([latency for latency, _ in good])
        self.residual_px = median([residual for _, residual in good])
        return self.estimate

    def result(self) -> LatencyEstimate | None:
        """The estimate as a typed result, None while there is none."""
        if self.estimate is None:
            return None
        return LatencyEstimate(self.estimate, None, ("start_stop",), True)
