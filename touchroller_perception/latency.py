"""The camera's latency (exposure to stamp) from every kind of evidence a scan holds, with its uncertainty.

A frame stamped t was exposed at t - L; placed at the pose of t - L0, it lands v (L - L0) ahead along
the roll. Three kinds of evidence measure L, each with a standard deviation, combined by inverse variance:

* `start_stop`: frames around a start or stop of the roll while pressed: the image-registered position
  must follow the arm's roll, P = c + s Y(t - L); at constant speed any L fits, around a start or a stop
  only the right one does (c and s fitted per window, s for a scale error of the calibration).
* `pass_roll`: the same model over a whole pass's steady rolling (the frames outside the start/stop
  windows): it sees any variation of the speed (jitter, a blend), and says nothing at constant speed.
* `opposite_passes`: passes rolled in opposite directions over the same ground are placed
  (v + v') (L - L0) apart along the roll, v and v' their speeds there; the registered offset of one
  against the other measures L directly (each frame's value from both passes' speeds over its ground,
  where the arm was at the latency found: a speed that varies along the passes differs between them
  there; their median's sigma is inflated by
  the values' correlation along the pass, as a window's is).
* `contact_timing`: when the image shows the roller touching down and lifting off against when TF shows
  the arm's height crossing the touching height (`touchroller_perception.contact_timing`); it needs no
  texture, so it is what a smooth panel or glass has.

Each window's L is where the sum of squared residuals S(L) is least (a 5 ms grid, then a parabola fitted
to a 1 ms grid around it); its variance is sigma_res^2 / (S''/2), sigma_res^2 the residuals' variance,
inflated by their lag-1 correlation (registration errors of neighbouring frames are not independent).
`LatencyEstimator.result()` combines what it has (items more than 4 sigma off the weighted mean are left
out, the combined sigma is scaled up when the items disagree more than their sigmas say) into a
`LatencyEstimate`: `observable` only when its sigma is at most `LatencyConfig.max_sigma` (or, resting on
contact timing and inside the range it leaves, `max_sigma_contact`); otherwise the caller keeps its
configured latency and says so. No rclpy here.
"""
from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from touchroller_perception.contact_timing import (
    CONTACT_TIMING,
    ContactEvent,
    ContactTiming,
    ContactTimingConfig,
    latency_from_contacts,
)

FloatArray = NDArray[np.float64]
#: T_world_cylinder (N, 4, 4) at each of N stamps (ns), all-NaN where it is not known (yet).
PoseLookup = Callable[[NDArray[np.int64]], FloatArray]


START_STOP, PASS_ROLL, OPPOSITE_PASSES = "start_stop", "pass_roll", "opposite_passes"


@dataclass(frozen=True)
class LatencyConfig:
    """How a `LatencyEstimator` works.

    max_latency: the largest latency searched, s.
    before, after: the window around a start or stop of the roll, s.
    max_residual_px: a window the model does not fit (RMS above this: a slip, lost texture) is left out.
    max_sigma: the combined estimate pins the latency down (`observable`) when its sigma is at most this, s.
    sigma_floor: the least sigma any one item of evidence is given, s (TF interpolation, the model's limits).
    max_sigma_contact: an estimate that contact timing takes part in, and that lies inside the range the
      touchdowns and lift-offs leave, is `observable` up to this sigma, s: that range's width is what it
      is (the touch lies between two frames), where a fit's sigma assumes its model holds.
    """

    max_latency: float = 0.2
    before: float = 1.0
    after: float = 1.0
    max_residual_px: float = 0.3
    max_sigma: float = 0.002
    sigma_floor: float = 3e-4
    max_sigma_contact: float = 0.006

    def __post_init__(self) -> None:
        if not (0 < self.max_latency <= 1.0):
            raise ValueError(f"max_latency must be in (0, 1] s, got {self.max_latency}")
        if not (self.before > 0 and self.after > 0 and self.max_residual_px > 0 and self.max_sigma > 0
                and self.sigma_floor >= 0 and self.max_sigma_contact > 0):
            raise ValueError("before, after, max_residual_px, max_sigma and max_sigma_contact must be > 0, "
                             "sigma_floor >= 0")


@dataclass(frozen=True)
class LatencyEvidence:
    """One item of evidence: its kind (`START_STOP`, `PASS_ROLL`, `OPPOSITE_PASSES`, `CONTACT_TIMING`),
    value and sigma, s."""

    kind: str
    value: float
    sigma: float


@dataclass(frozen=True)
class LatencyEstimate:
    """What the data say of the latency: `value` (s, the one used), its standard deviation `sigma` (s,
    None when no evidence has a finite one), the kinds of evidence it rests on, whether they pinned it
    down (`observable`; else `value` is the configured latency, `sources` ("configured",)), and the
    items combined."""

    value: float
    sigma: float | None
    sources: tuple[str, ...]
    observable: bool
    evidence: tuple[LatencyEvidence, ...] = ()

    def describe(self) -> str:
        """One line: "estimated 35.2 ms (sigma 0.3 ms; opposite_passes, start_stop)", or when not observable
        "not observable (...): configured 0.0 ms used"."""
        if self.observable and self.sigma is not None:
            return f"estimated {self.value * 1e3:.1f} ms (sigma {self.sigma * 1e3:.1f} ms; {', '.join(self.sources)})"
        spread = "no evidence" if self.sigma is None else f"the evidence leaves sigma {self.sigma * 1e3:.0f} ms"
        return f"not observable ({spread}): configured {self.value * 1e3:.1f} ms used"

    def as_dict(self) -> dict[str, object]:
        """For map.yaml and reports: value_ms, sigma_ms (None), sources, observable."""
        return {"value_ms": round(self.value * 1e3, 3),
                "sigma_ms": None if self.sigma is None else round(self.sigma * 1e3, 3),
                "sources": list(self.sources), "observable": bool(self.observable)}


def combine(items: Sequence[LatencyEvidence]) -> tuple[float, float, tuple[LatencyEvidence, ...]] | None:
    """(value, sigma, items used): the inverse-variance mean of the items, those more than 4 sigma off it
    left out (twice), sigma scaled by sqrt(reduced chi^2) when that is above 1; None without items."""
    used = [e for e in items if math.isfinite(e.value) and math.isfinite(e.sigma) and e.sigma > 0]
    for _ in range(3):
        if not used:
            return None
        w = np.array([1.0 / e.sigma ** 2 for e in used])
        x = np.array([e.value for e in used])
        mean = float(w @ x / w.sum())
        sigma = math.sqrt(1.0 / float(w.sum()))
        keep = [e for e in used if abs(e.value - mean) <= 4.0 * math.sqrt(e.sigma ** 2 + sigma ** 2)]
        if len(keep) == len(used) or not keep:
            break
        used = keep
    if len(used) > 1:
        chi2 = float(w @ (x - mean) ** 2) / (len(used) - 1)
        sigma *= math.sqrt(max(chi2, 1.0))
    return mean, sigma, tuple(used)


@dataclass
class _Window:
    """Confident frames (stamp ns, image position px) of one start or stop, or of a pass's steady rolling."""

    stamps: list[int]
    positions: list[float]
    kind: str = START_STOP
    latency: float | None = None   # its own estimate, s (None: it says nothing)
    sigma: float | None = None
    residual_px: float | None = None
    solved: bool = False


class LatencyEstimator:
    """Collects the evidence (`add_window`, `add_pass_window`, `add_opposite_passes`), solves each window
    once its poses are known (`solve`) and combines them (`result`); see the module docstring."""

    def __init__(self, m_per_row: float, config: LatencyConfig | None = None) -> None:
        self.config = config = config or LatencyConfig()
        self.max_latency_ns = round(config.max_latency * 1e9)
        self.m_per_row = m_per_row
        self.before_ns, self.after_ns = round(config.before * 1e9), round(config.after * 1e9)
        self.windows: list[_Window] = []
        self.pairs: list[LatencyEvidence] = []
        self.contact_events: list[ContactEvent] = []
        self.contact: ContactTiming | None = None   # what the touchdowns and lift-offs say (solve)
        self.contact_config = ContactTimingConfig()
        self._contact_solved = 0   # events the contact timing was solved with
        self.estimate: LatencyEstimate | None = None

    def add_window(self, stamps: Sequence[int], positions: Sequence[float]) -> None:
        """The pressed, confident frames around a start or stop of the roll."""
        if len(stamps) >= 8:
            self.windows.append(_Window(list(stamps), list(positions)))

    def add_pass_window(self, stamps: Sequence[int], positions: Sequence[float]) -> None:
        """A pass's pressed, confident frames away from its starts and stops (its steady rolling)."""
        if len(stamps) >= 20:
            self.windows.append(_Window(list(stamps), list(positions), PASS_ROLL))

    def add_opposite_passes(self, value: float, sigma: float) -> None:
        """The latency two passes rolled in opposite directions over the same ground say (s), sigma (s)."""
        if math.isfinite(value) and math.isfinite(sigma) and sigma > 0:
            self.pairs.append(LatencyEvidence(OPPOSITE_PASSES, value, max(sigma, self.config.sigma_floor)))

    def add_contact_events(self, events: Sequence[ContactEvent]) -> None:
        """Touchdowns and lift-offs the image showed (`touchroller_perception.contact_timing`)."""
        self.contact_events.extend(events)

    def _rows(self, window: _Window, candidates: NDArray[np.int64], poses: PoseLookup) -> FloatArray:
        """(candidates, frames): the arm's roll along the band's rows at each candidate latency (NaN rows
        where a pose is missing), all candidates in one lookup."""
        stamps = np.asarray(window.stamps, np.int64)
        transforms = poses((stamps[None, :] - candidates[:, None]).reshape(-1))
        transforms = transforms.reshape(len(candidates), len(stamps), 4, 4)
        # where a point fixed in the world (the first pose's origin) lies along the cylinder's y axis
        offsets = transforms[:, :1, :3, 3] - transforms[:, :, :3, 3]
        y = np.einsum("cki,cki->ck", transforms[:, :, :3, 1], offsets) / self.m_per_row
        y[~np.isfinite(transforms).reshape(len(candidates), -1).all(axis=1)] = np.nan
        return y

    def _scan(self, window: _Window, candidates: NDArray[np.int64], poses: PoseLookup) -> tuple[np.ndarray, int] | None:
        """The window's cost (mean squared residual of the best line P = c + s Y, px^2) at each candidate
        latency (NaN where a pose is missing); with the best's index."""
        y = self._rows(window, candidates, poses)
        p = np.asarray(window.positions, np.float64)
        dy = y - y.mean(axis=1, keepdims=True)
        dp = p - p.mean()
        with np.errstate(invalid="ignore"):
            syy, syp, spp = (dy * dy).sum(axis=1), dy @ dp, float(dp @ dp)
            slope_part = np.divide(syp * syp, syy, out=np.zeros_like(syy), where=syy > 1e-12)
        costs = np.maximum(spp - slope_part, 0.0) / len(p)
        costs[~np.isfinite(y).all(axis=1)] = np.nan
        if not np.isfinite(costs).any():
            return None
        return costs, int(np.nanargmin(costs))

    def _residuals(self, window: _Window, latency_ns: int, poses: PoseLookup) -> FloatArray:
        y = self._rows(window, np.array([latency_ns], np.int64), poses)[0]
        p = np.asarray(window.positions, np.float64)
        design = np.stack([np.ones_like(y), y], axis=1)
        coef, *_ = np.linalg.lstsq(design, p, rcond=None)
        return np.asarray(p - design @ coef, np.float64)

    def _solve_window(self, window: _Window, poses: PoseLookup) -> float | None:
        """The latency that fits one window best and its sigma (module docstring); None when the window
        says nothing (a start/stop window without a clear minimum, a pass at constant speed)."""
        coarse = self._scan(window, np.arange(0, self.max_latency_ns + 1, 5_000_000), poses)
        if coarse is None:
            return None
        costs, best = coarse
        finite = costs[np.isfinite(costs)]
        if window.kind == START_STOP and finite.max() < 4.0 * max(finite.min(), 1e-6):
            return None   # no clear minimum: no start or stop in it
        centre = best * 5_000_000
        candidates = np.arange(max(centre - 6_000_000, 0), min(centre + 6_000_000, self.max_latency_ns) + 1,
                               1_000_000)
        fine = self._scan(window, candidates, poses)
        if fine is None:
            return None
        costs, best = fine
        ok = np.isfinite(costs)
        if ok.sum() < 3:
            return None
        t = (candidates[ok] - candidates[best]) * 1e-9   # s around the best candidate
        a, b, c = np.polyfit(t, costs[ok], 2)
        n = len(window.positions)
        if not a > 0:
            return None   # flat or concave: nothing to read
        vertex = float(np.clip(-b / (2 * a), t.min() - 1e-3, t.max() + 1e-3))
        latency = min(max(candidates[best] * 1e-9 + vertex, 0.0), self.max_latency_ns * 1e-9)
        floor = max(float(costs[best]), float(a * vertex ** 2 + b * vertex + c), 0.0)
        variance = n * floor / max(n - 3, 1) / (a * n)
        residuals = self._residuals(window, round(latency * 1e9), poses)
        rho = 0.0
        if len(residuals) > 4 and float(residuals @ residuals) > 0:
            rho = float(residuals[1:] @ residuals[:-1]) / float(residuals @ residuals)
        rho = min(max(rho, 0.0), 0.95)
        variance *= (1 + rho) / (1 - rho)
        window.latency = latency
        window.sigma = max(math.sqrt(variance), self.config.sigma_floor)
        window.residual_px = math.sqrt(max(float(costs[best]), 0.0))
        return window.latency

    def solve(self, poses: PoseLookup) -> LatencyEstimate | None:
        """Solve the windows not solved yet (each once, when TF has its last frame's pose) and combine all
        evidence (`result`)."""
        for window in self.windows:
            if window.latency is None and not window.solved:
                # every candidate needs the poses of the window's frames: wait until TF has its last one
                # (else the short latencies, the most recent poses, would be missing from the comparison)
                if not np.isfinite(poses(np.asarray(window.stamps[-1:], np.int64))).all():
                    continue
                window.solved = True
                self._solve_window(window, poses)
        if len(self.contact_events) != self._contact_solved:
            self._contact_solved = len(self.contact_events)
            self.contact = latency_from_contacts(self.contact_events, poses, self.config.max_latency,
                                                 self.contact_config)
        self.estimate = self.result()
        return self.estimate

    def evidence(self) -> list[LatencyEvidence]:
        """Every item of evidence with a finite sigma (windows the model fits, pairs of passes, contact
        timing), less those outside the contact timing's range."""
        items = [LatencyEvidence(w.kind, w.latency, w.sigma) for w in self.windows
                 if w.latency is not None and w.sigma is not None and w.residual_px is not None
                 and w.residual_px <= self.config.max_residual_px]
        items += self.pairs
        if self.contact is not None:
            # the range the touchdowns and lift-offs leave is a bound: an item outside it by more than three
            # of its own sigmas is left out (a periodic texture registers a period off with a small sigma,
            # and would outweigh the contact timing)
            low, high = self.contact.low, self.contact.high
            items = [e for e in items if low - 3 * e.sigma - 5e-4 <= e.value <= high + 3 * e.sigma + 5e-4]
            items.append(LatencyEvidence(CONTACT_TIMING, self.contact.value,
                                         max(self.contact.sigma, self.config.sigma_floor)))
        return items

    def result(self, fallback: float = 0.0) -> LatencyEstimate | None:
        """The combined estimate; not `observable` (value `fallback`) when its sigma is above `max_sigma`
        (`max_sigma_contact` for one inside the contact timing's range); None without any evidence."""
        combined = combine(self.evidence())
        if combined is None:
            return None
        value, sigma, used = combined
        kinds = tuple(sorted({e.kind for e in used}))
        bounded = (CONTACT_TIMING in kinds and self.contact is not None and sigma <= self.config.max_sigma_contact
                   and self.contact.low - 5e-4 <= value <= self.contact.high + 5e-4)
        if sigma > self.config.max_sigma and not bounded:
            return LatencyEstimate(fallback, sigma, ("configured",), False, used)
        return LatencyEstimate(value, sigma, kinds, True, used)
