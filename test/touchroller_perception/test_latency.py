"""The latency estimator: its evidence combined by sigma, and a WARN-worthy result when nothing pins it down."""
from __future__ import annotations

import math

import numpy as np
import pytest

from touchroller_perception.contact_timing import ContactEvent
from touchroller_perception.latency import (
    CONTACT_TIMING,
    OPPOSITE_PASSES,
    LatencyConfig,
    LatencyEstimator,
    LatencyEvidence,
    combine,
)

T0 = 1_000_000_000_000
PRESSED, TOUCH = 0.07, 0.0705


def arm(passes: int, vertical: float = 0.008) -> tuple[np.ndarray, np.ndarray]:
    """(times s, heights m): down at `vertical` m/s, pressed 2 s, up, `passes` times."""
    times, heights, t = [0.0], [PRESSED + 2.5e-3], 0.0
    for k in range(passes):
        for dt, h in ((1.5 + 0.0123 * k, PRESSED + 2.5e-3), (2.5e-3 / vertical, PRESSED), (2.0 + 0.0071 * k, PRESSED),
                      (2.5e-3 / vertical, PRESSED + 2.5e-3)):
            t += dt
            times.append(t)
            heights.append(h)
    times.append(t + 1.5)
    heights.append(PRESSED + 2.5e-3)
    return np.array(times), np.array(heights)


def poses_of(times: np.ndarray, heights: np.ndarray):
    def poses(stamps: np.ndarray) -> np.ndarray:
        t = (np.asarray(stamps, np.int64) - T0) * 1e-9
        out = np.tile(np.eye(4), (len(t), 1, 1))
        out[:, 2, 3] = np.interp(t, times, heights)
        return out
    return poses


def contact_events(times: np.ndarray, heights: np.ndarray, latency: float) -> list[ContactEvent]:
    """What the image shows at 30 Hz, stamped `latency` late: the membrane touching below TOUCH."""
    exposures = np.arange(0.05, times[-1] - 0.2, 1 / 30)
    touching = np.interp(exposures, times, heights) < TOUCH
    stamps = T0 + np.round((exposures + latency) * 1e9).astype(np.int64)
    flips = np.flatnonzero(touching[1:] != touching[:-1]) + 1
    return [ContactEvent(bool(touching[i]), int(stamps[i - 1]), int(stamps[i])) for i in flips]


@pytest.mark.parametrize("latency", [0.0, 0.02, 0.05, 0.12])
def test_touchdowns_and_liftoffs_alone_give_an_estimate_with_its_source(latency):
    """A textureless raster (no window, no pair of registered passes): contact timing is the estimate."""
    times, heights = arm(4)
    poses = poses_of(times, heights)
    estimator = LatencyEstimator(1e-4)
    estimator.add_contact_events(contact_events(times, heights, latency))
    estimate = estimator.solve(poses)
    assert estimate is not None and estimate.observable
    assert estimate.sources == (CONTACT_TIMING,)
    assert estimate.sigma is not None and abs(estimate.value - latency) <= 3 * estimate.sigma
    assert abs(estimate.value - latency) <= 0.005


def test_a_single_pass_of_contact_timing_is_not_an_estimate():
    times, heights = arm(1)
    estimator = LatencyEstimator(1e-4)
    estimator.add_contact_events(contact_events(times, heights, 0.035))
    assert estimator.solve(poses_of(times, heights)) is None   # no evidence at all: the caller warns
    assert estimator.result(0.0) is None


def test_contact_timing_combines_with_the_opposite_passes_by_sigma():
    times, heights = arm(3)
    estimator = LatencyEstimator(1e-4)
    estimator.add_contact_events(contact_events(times, heights, 0.05))
    estimator.add_opposite_passes(0.0501, 3e-4)
    estimate = estimator.solve(poses_of(times, heights))
    assert estimate is not None and estimate.observable
    assert set(estimate.sources) == {CONTACT_TIMING, OPPOSITE_PASSES}
    assert estimate.value == pytest.approx(0.0501, abs=3e-4)   # the sharper item weighs most
    assert estimate.sigma is not None and estimate.sigma <= 3e-4


def test_evidence_too_loose_is_said_as_not_observable_with_the_fallback():
    estimator = LatencyEstimator(1e-4, LatencyConfig(max_sigma=0.002))
    estimator.add_opposite_passes(0.05, 0.01)
    estimate = estimator.result(fallback=0.03)
    assert estimate is not None and not estimate.observable
    assert estimate.value == 0.03 and estimate.sources == ("configured",)
    assert "not observable" in estimate.describe()


def test_combine_leaves_out_an_item_far_off_the_others():
    items = [LatencyEvidence(OPPOSITE_PASSES, 0.050, 3e-4), LatencyEvidence(OPPOSITE_PASSES, 0.0502, 3e-4),
             LatencyEvidence(CONTACT_TIMING, 0.120, 4e-3)]
    combined = combine(items)
    assert combined is not None
    value, sigma, used = combined
    assert value == pytest.approx(0.0501, abs=2e-4) and len(used) == 2
    assert math.isfinite(sigma)


def test_opposite_passes_a_period_off_are_left_out_by_the_contact_timings_range():
    """A periodic texture (1.2 mm at 20 mm/s) registers the opposite passes a period off: 30 ms off the
    truth with a sigma of 0.3 ms, which outweighs everything else; the touchdowns and lift-offs bound the
    latency, and the item outside their range is left out."""
    times, heights = arm(3)
    estimator = LatencyEstimator(1e-4)
    estimator.add_contact_events(contact_events(times, heights, 0.05))
    estimator.add_opposite_passes(0.08, 3e-4)
    estimate = estimator.solve(poses_of(times, heights))
    assert estimate is not None and estimate.observable
    assert estimate.sources == (CONTACT_TIMING,)
    assert abs(estimate.value - 0.05) <= 0.005
