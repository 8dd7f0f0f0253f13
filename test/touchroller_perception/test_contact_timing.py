"""Contact timing: the latency from when the image shows touchdown and lift-off against TF's heights."""
from __future__ import annotations

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from touchroller_perception.contact_timing import (
    ContactTimer,
    ContactTimingConfig,
    band_summary,
    latency_from_contacts,
)

PRESSED = 0.07     # the arm's pressed height, m
DEPTH = 5e-4       # pressed this far: the membrane touches at PRESSED + DEPTH
T0 = 1_000_000_000_000


def heights_of(passes: int, vertical: float, hold: float = 2.0, lifted: float = 2.5e-3
               ) -> tuple[np.ndarray, np.ndarray]:
    """(times s, heights m) of an arm coming down at `vertical` m/s, pressed for `hold` s, going up, `passes`
    times (1.5 s in the air between)."""
    times, heights, t = [0.0], [PRESSED + lifted], 0.0
    for k in range(passes):
        t += 1.5 + 0.0123 * k   # the frames meet each event at another phase
        times.append(t)
        heights.append(PRESSED + lifted)
        t += lifted / vertical
        times.append(t)
        heights.append(PRESSED)
        t += hold
        times.append(t)
        heights.append(PRESSED)
        t += lifted / vertical
        times.append(t)
        heights.append(PRESSED + lifted)
    times.append(t + 1.5)
    heights.append(PRESSED + lifted)
    return np.array(times), np.array(heights)


def lookup(times: np.ndarray, heights: np.ndarray):
    def poses(stamps: np.ndarray) -> np.ndarray:
        t = (np.asarray(stamps, np.int64) - T0) * 1e-9
        out = np.tile(np.eye(4), (len(t), 1, 1))
        out[:, 2, 3] = np.interp(t, times, heights)
        out[(t < times[0]) | (t > times[-1])] = np.nan
        return out
    return poses


def film(times: np.ndarray, heights: np.ndarray, latency: float, change: float = 40.0, seed: int = 0,
         fps: float = 30.0, shape: tuple[int, int] = (70, 640)) -> list[tuple[int, np.ndarray]]:
    """Frames (stamp ns, band) exposed at 30 Hz, stamped `latency` late: a plain band in the air, its edge
    rows `change` grey levels brighter while the membrane touches (a smooth surface: no texture)."""
    rng = np.random.default_rng(seed)
    exposures = np.arange(0.05, times[-1] - 0.2, 1.0 / fps) + rng.uniform(0, 1.0 / fps)
    frames = []
    for t in exposures:
        band = np.full(shape, 120.0) + rng.normal(0, 2.0, shape)
        if np.interp(t, times, heights) < PRESSED + DEPTH:
            band[:20] += change
            band[-20:] += change
        frames.append((T0 + round((t + latency) * 1e9), band.astype(np.float32)))
    return frames


def events_of(frames, poses, max_latency: float = 0.2):
    timer = ContactTimer(max_latency)
    for stamp, band in frames:
        timer.push(stamp, band)
    timer.update(poses, PRESSED, frames[-1][0], final=True)
    return timer.events


@pytest.mark.parametrize("latency", [0.0, 0.035, 0.12])
@pytest.mark.parametrize("vertical", [0.005, 0.01])   # from rest (an approach) and at speed (a blend)
def test_touchdowns_and_liftoffs_pin_the_latency_down_without_texture(latency, vertical):
    times, heights = heights_of(4, vertical)
    poses = lookup(times, heights)
    events = events_of(film(times, heights, latency, seed=int(latency * 1e3)), poses)
    assert sum(e.touchdown for e in events) == 4 and sum(not e.touchdown for e in events) == 4
    timing = latency_from_contacts(events, poses, 0.2)
    assert timing is not None
    assert timing.low <= latency + 5e-4 and timing.high >= latency - 5e-4   # the truth is in the range
    assert abs(timing.value - latency) <= 3 * timing.sigma and timing.sigma < 0.008


def test_one_touchdown_and_one_liftoff_are_not_enough():
    """A single pass: the range a pair leaves is about a frame wide, and nothing judges it: no estimate."""
    times, heights = heights_of(1, 0.01)
    poses = lookup(times, heights)
    events = events_of(film(times, heights, 0.05), poses)
    assert len(events) == 2
    assert latency_from_contacts(events, poses, 0.2) is None


def test_an_image_that_does_not_change_when_pressed_gives_no_events():
    times, heights = heights_of(3, 0.01)
    poses = lookup(times, heights)
    assert events_of(film(times, heights, 0.05, change=0.0), poses) == []


def test_touchdowns_only_leave_the_latency_open():
    """Every touchdown bounds the touching height from the same side: without lift-offs no range closes."""
    times, heights = heights_of(4, 0.01)
    poses = lookup(times, heights)
    events = [e for e in events_of(film(times, heights, 0.05), poses) if e.touchdown]
    assert latency_from_contacts(events, poses, 0.2, ContactTimingConfig(min_events=1)) is None


def test_the_events_are_found_as_the_frames_come_and_each_once():
    times, heights = heights_of(3, 0.01)
    poses = lookup(times, heights)
    frames = film(times, heights, 0.05)
    timer = ContactTimer(0.2)
    seen = []
    for k, (stamp, band) in enumerate(frames):
        timer.push(stamp, band)
        if k % 8 == 0:
            seen += timer.update(poses, PRESSED, stamp)
    seen += timer.update(poses, PRESSED, frames[-1][0], final=True)
    assert len(seen) == 6 and seen == timer.events
    assert len({e.after_ns for e in seen}) == 6


def test_the_summaries_and_levels_kept_as_frames_come_are_those_computed_afresh():
    # the band summaries (written straight into their row) are the area averages of the band's centre, for
    # float, 8-bit and colour bands; the levels found update after update (only new frames' differences
    # computed while the frames in the air stay the same) are the ones a single look at all frames gives
    import cv2

    times, heights = heights_of(3, 0.01)
    poses = lookup(times, heights)
    frames = film(times, heights, 0.05, shape=(70, 644))
    timer = ContactTimer(0.2)
    for k, (stamp, band) in enumerate(frames):
        timer.push(stamp, band if k % 3 else np.clip(band, 0, 255).astype(np.uint8))
        if k % 7 == 0:
            timer.update(poses, PRESSED, stamp)
    kept = timer._summary_arr[timer._start:timer._end]
    for k, (_, band) in enumerate(frames):
        block = (band if k % 3 else np.clip(band, 0, 255).astype(np.uint8))[3:67, 2:642]
        assert np.array_equal(kept[k], cv2.resize(block, (16, 8), interpolation=cv2.INTER_AREA).astype(np.float32))
    summarised = ContactTimer(0.2)   # the same frames' summaries made beforehand (by the band's reader)
    for k, (stamp, band) in enumerate(frames):
        summarised.push(stamp, summary=band_summary(band if k % 3 else np.clip(band, 0, 255).astype(np.uint8)))
    assert np.array_equal(summarised._summary_arr[:len(frames)], kept)
    with pytest.raises(ValueError):
        summarised.push(frames[-1][0] + 1, summary=np.zeros((4, 4), np.float32))
    assert band_summary(np.zeros((4, 640), np.float32)) is None
    colour = ContactTimer(0.2)
    colour.push(frames[0][0], cv2.cvtColor(np.clip(frames[0][1], 0, 255).astype(np.uint8), cv2.COLOR_GRAY2BGR))
    assert np.array_equal(colour._summary_arr[0], kept[0])
    latest = frames[-1][0]
    heights_now = timer._arm_heights(poses, latest, final=True) - PRESSED
    incremental = timer._levels(heights_now)
    timer._signal_cache = None
    fresh = timer._levels(heights_now)
    assert incremental is not None and fresh is not None
    assert np.array_equal(incremental[0], fresh[0]) and incremental[1:] == fresh[1:]


def test_config_is_checked():
    with pytest.raises(ValueError):
        ContactTimingConfig(level=1.5)
    with pytest.raises(ValueError):
        ContactTimingConfig(lifted=1e-5, pressed=1e-4)


def test_a_touchdown_right_after_tf_begins_counts():
    """A recording that starts as the arm comes down (TF from 50 ms before the descent, so the earlier
    lags of the first frames are unknown): the first touchdown still counts, as does the last lift-off of
    a recording that ends as the arm rises."""
    times, heights = heights_of(3, 0.01)
    full = lookup(times, heights)
    begin, end = T0 + round(1.45e9), T0 + round((times[-1] - 1.45) * 1e9)

    def poses(stamps):
        out = full(stamps)
        out[(np.asarray(stamps) < begin) | (np.asarray(stamps) > end)] = np.nan
        return out

    frames = [(s, b) for s, b in film(times, heights, 0.03) if begin <= s <= end + 30_000_000]
    events = events_of(frames, poses)
    assert sum(e.touchdown for e in events) == 3 and sum(not e.touchdown for e in events) == 3


@settings(max_examples=15, deadline=None, suppress_health_check=list(HealthCheck))
@given(latency=st.floats(0.0, 0.15), vertical=st.floats(0.003, 0.02), passes=st.integers(1, 4),
       fps=st.sampled_from([15.0, 30.0, 60.0]), seed=st.integers(0, 1000))
def test_property_the_range_holds_the_truth_or_there_is_no_estimate(latency, vertical, passes, fps, seed):
    """Any latency, vertical speed, frame rate and number of passes: contact timing either says nothing
    or gives a range that holds the true latency (on its 0.5 ms grid), its value within the range."""
    times, heights = heights_of(passes, vertical)
    poses = lookup(times, heights)
    frames = film(times, heights, latency, seed=seed, fps=fps, shape=(24, 64))
    events = events_of(frames, poses)
    assert len(events) == 2 * passes   # every touchdown and lift-off seen, nothing else
    timing = latency_from_contacts(events, poses, 0.2)
    if passes < 2:
        assert timing is None
    if timing is not None:
        assert timing.low - 5e-4 <= latency <= timing.high + 5e-4
        assert timing.low <= timing.value <= timing.high
