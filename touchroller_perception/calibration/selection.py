"""Which optional terms a calibration uses, decided by what they predict, and which views count.

A correction that fits the presses better is not yet a correction that helps: fitted on a
renderer's (or a sensor's) habits, it can explain them and still move the answer away from the
truth. So each optional term (the row balance, the rejection of views) is kept only when it
predicts what it was not fitted on: each press is left out in turn, its imprint positions are
predicted from the other presses with and without the term, and the term stays only when its
held-out prediction is better by a margin larger than that margin's spread (`TermChoice`).

Views are judged against each other, not against a fixed number of pixels: a view is an outlier
when its reprojection RMS lies far above the set's (`gate_by_rms`: median + k robust standard
deviations), so a sensor whose every view is a little worse than this project's simulators still
calibrates, with a warning (`rms_warning`).
"""
from __future__ import annotations

import dataclasses
import math
from collections.abc import Sequence

import numpy as np
from numpy.typing import NDArray

#: the reprojection RMS (px) of a hemisphere-frame view on this project's two renderers: above a few
#: times this, the imprints or the model are worse than anything the method was checked on
SIMULATED_VIEW_RMS = 0.15


@dataclasses.dataclass(frozen=True)
class TermChoice:
    """One optional term and the held-out evidence for it.

    `margin_px`: the mean over the left-out presses of (prediction error without the term - with
    it), in px of reprojection RMS; positive when the term predicts better. `spread_px`: that mean's
    standard error over the presses. The term is `kept` when the margin exceeds `needed` x spread."""

    term: str
    kept: bool
    margin_px: float
    spread_px: float
    needed: float
    presses: int
    reason: str = ""

    def line(self) -> str:
        """One line: the choice and its margin."""
        verdict = "kept" if self.kept else "left out"
        if not math.isfinite(self.margin_px):
            return f"{self.term}: {verdict} ({self.reason})"
        return (f"{self.term}: {verdict}, held-out margin {self.margin_px:+.3f} px "
                f"({'>' if self.kept else '<='} {self.needed:g} x spread {self.spread_px:.3f} px, "
                f"{self.presses} presses left out in turn)" + (f"; {self.reason}" if self.reason else ""))


def choose_term(term: str, without: Sequence[float] | NDArray[np.float64],
                with_term: Sequence[float] | NDArray[np.float64], needed: float = 2.0,
                reason: str = "") -> TermChoice:
    """Keep `term` when its held-out errors (`with_term`, one per left-out press, px) beat those
    without it by more than `needed` standard errors of the paired difference. Fewer than 3
    finite pairs cannot judge it: the term is left out."""
    a = np.asarray(without, dtype=np.float64)
    b = np.asarray(with_term, dtype=np.float64)
    ok = np.isfinite(a) & np.isfinite(b)
    n = int(ok.sum())
    if n < 3:
        return TermChoice(term, False, math.nan, math.nan, needed, n, f"{n} presses cannot judge it")
    diff = a[ok] - b[ok]
    margin = float(diff.mean())
    spread = float(diff.std(ddof=1) / math.sqrt(n))
    kept = margin > 0 and margin > needed * spread
    return TermChoice(term, bool(kept), margin, spread, needed, n, reason)


def not_judged(term: str, reason: str) -> TermChoice:
    """A term that was not put to the test (switched off, or nothing to decide)."""
    return TermChoice(term, False, math.nan, math.nan, math.nan, 0, reason)


def gate_by_rms(rms: Sequence[float] | NDArray[np.float64], k: float = 4.0, floor: float = 0.05) -> NDArray[np.bool_]:
    """Views whose reprojection RMS is not far above the set's: at most median + k x the robust
    standard deviation (1.4826 MAD, at least 10 % of the median and `floor` px). Relative to the
    set, so a sensor whose views are all a little worse than another's keeps them all."""
    values = np.asarray(rms, dtype=np.float64)
    finite = np.isfinite(values)
    if finite.sum() < 3:
        return finite
    median = float(np.median(values[finite]))
    scale = max(1.4826 * float(np.median(np.abs(values[finite] - median))), 0.1 * median, floor)
    return finite & (values <= median + k * scale)


def rms_warning(median_rms: float, theta_sigma_deg: float, d_sigma_mm: float,
                reference: float = SIMULATED_VIEW_RMS) -> str | None:
    """A warning when the views' median RMS is well above what the simulators give: how much worse,
    and what it costs (the presses' share of the sigmas grows about in proportion)."""
    if not (math.isfinite(median_rms) and median_rms > 2.0 * reference):
        return None
    ratio = median_rms / reference
    return (f"the views' median reprojection RMS is {median_rms:.2f} px, {ratio:.1f}x what this project's "
            f"simulators give ({reference:.2f} px): the imprints or the camera model are worse than anything the "
            f"method was checked on; used, but the presses' share of the sigma (theta {theta_sigma_deg:.3f}°, "
            f"d {d_sigma_mm:.4f} mm) is about {ratio:.0f}x what such views would give")
