"""The camera's latency from when the image shows the roller touching down and lifting off: no texture needed.

The membrane pressed against any surface, smooth glass included, changes the band's shading (it bends
and flattens where the ground meets it); in the air the band looks the same from frame to frame. So
each frame says "pressed" or "in the air" without any texture (`ContactTimer`: the band's RMS
difference from the mean of frames surely in the air, between that level (0) and the pressed level (1),
above `ContactTimingConfig.level`). Where that flips between two frames, the roller touched (or left)
the surface between their exposures; TF says when the arm's height crossed the height at which it
touches. With latency L, the frame stamped t was exposed at t - L, so a touchdown between frames
stamped a and b means the touching height z* lies between the arm's heights at a - L and b - L
(`ContactEvent`). z* is not known (the pressed depth, the membrane), but it is the same at every
touchdown and lift-off; a touchdown bounds it from one side as L grows and a lift-off from the other,
so only a range of L keeps every event's bracket overlapping (`latency_from_contacts`). Its centre is
the estimate and its width over sqrt(12) the standard deviation (the touch is anywhere between the two
frames). A single touchdown and lift-off leave a range about a frame wide: at least `min_events` of
each are needed, and the caller's `max_sigma` decides whether it pins the latency down.
No rclpy here.
"""
from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass

import cv2
import numpy as np
from numpy.typing import NDArray

from touchroller_perception.fast_stats import median

FloatArray = NDArray[np.float64]
#: T_world_cylinder (N, 4, 4) at each of N stamps (ns), all-NaN where it is not known (yet).
PoseLookup = Callable[[NDArray[np.int64]], FloatArray]
CONTACT_TIMING = "contact_timing"
_DESCRIPTOR = (16, 8)   # (columns, rows) a band is reduced to: the shading change spans the band
SUMMARY_SHAPE = (_DESCRIPTOR[1], _DESCRIPTOR[0])   # (rows, columns) of a `band_summary`
_CROPS: dict[tuple[int, ...], tuple[slice, slice] | None] = {}   # per band shape: the block summarised


def band_summary(band: np.ndarray) -> np.ndarray | None:
    """What `ContactTimer` keeps of a frame's band (grey or colour, any dtype): its centre, cropped to whole
    blocks, area-averaged to 8 x 16 (float32); None for a band smaller than that. Depends on the band alone."""
    crop = _crop(band)
    if crop is None:
        return None
    out = np.empty(SUMMARY_SHAPE, np.float32)
    _summarise(crop, out)
    return out


def _crop(band: np.ndarray) -> np.ndarray | None:
    grey = band if band.ndim == 2 else cv2.cvtColor(band, cv2.COLOR_BGR2GRAY)
    shape = grey.shape
    if shape not in _CROPS:
        # whole blocks (the fast area average): the band's centre cropped to multiples of the summary
        rows, cols = shape[0] // _DESCRIPTOR[1] * _DESCRIPTOR[1], shape[1] // _DESCRIPTOR[0] * _DESCRIPTOR[0]
        r0, c0 = (shape[0] - rows) // 2, (shape[1] - cols) // 2
        _CROPS[shape] = (slice(r0, r0 + rows), slice(c0, c0 + cols)) if rows and cols else None
    crop = _CROPS[shape]
    if crop is None:
        return None
    block = grey[crop]
    return block if block.dtype == np.float32 or block.dtype == np.uint8 else block.astype(np.float32)


def _summarise(block: np.ndarray, out: np.ndarray) -> None:
    """The area average of `block` into `out` (8 x 16 float32)."""
    if block.dtype == np.float32:
        cv2.resize(block, _DESCRIPTOR, dst=out, interpolation=cv2.INTER_AREA)
    else:
        out[...] = cv2.resize(block, _DESCRIPTOR, interpolation=cv2.INTER_AREA)


@dataclass(frozen=True)
class ContactTimingConfig:
    """How contact timing works.

    lifted: the roller is surely in the air when the arm is this far above its pressed height at every
      latency searched, m.
    pressed: and surely pressed within this of it, m.
    level: the image says "pressed" above this share of the way from the air's level to the pressed one.
    tolerance: how far apart (arm height, m) the touching height may be between events (noise, hysteresis)
      when no latency keeps every bracket overlapping.
    max_gap: the two frames bracketing a touch are at most this far apart, s (a dropped frame widens it).
    steady_frames: the image's state holds this many frames either side of a flip (no flicker).
    min_events: touchdowns and lift-offs needed, each.
    capacity: frames kept (a 16 x 8 summary each) until their events are read.
    """

    lifted: float = 1.5e-3
    pressed: float = 1e-4
    level: float = 0.5
    tolerance: float = 2e-5
    max_gap: float = 0.1
    steady_frames: int = 3
    min_events: int = 2
    capacity: int = 4000

    def __post_init__(self) -> None:
        if not (self.lifted > self.pressed > 0 and 0 < self.level < 1 and self.tolerance >= 0 and self.max_gap > 0
                and self.steady_frames >= 1 and self.min_events >= 1 and self.capacity >= 10):
            raise ValueError("contact timing needs lifted > pressed > 0, 0 < level < 1, tolerance >= 0, "
                             "max_gap > 0, steady_frames and min_events >= 1, capacity >= 10")


@dataclass(frozen=True)
class ContactEvent:
    """The image's state flipped between the frames stamped `before_ns` and `after_ns`: a touchdown (air to
    pressed) or a lift-off (pressed to air)."""

    touchdown: bool
    before_ns: int
    after_ns: int


@dataclass(frozen=True)
class ContactTiming:
    """What the touchdowns and lift-offs say: the latency (s) at the centre of the range that keeps every
    event consistent, its sigma (s), the range (s) and the events counted."""

    value: float
    sigma: float
    low: float
    high: float
    touchdowns: int
    liftoffs: int


class ContactTimer:
    """Collects each frame's band summary (`push`) and finds the touchdowns and lift-offs (`update`) once TF
    and the pressed height say which frames were surely in the air or pressed."""

    def __init__(self, max_latency: float, config: ContactTimingConfig | None = None) -> None:
        self.config = config = config or ContactTimingConfig()
        self.max_latency_ns = round(max_latency * 1e9)
        self._lags = np.linspace(0, self.max_latency_ns, 5).astype(np.int64)
        # per frame, in arrays with room for twice `capacity` (appending is O(1); the oldest go once
        # `capacity` is exceeded): its stamp, band summary, and the arm's height at its stamp less each
        # lag (NaN until TF has it; looked up again only while the frame is recent)
        room = 2 * config.capacity
        self._stamp_arr = np.zeros(room, np.int64)
        self._summary_arr = np.zeros((room, _DESCRIPTOR[1], _DESCRIPTOR[0]), np.float32)
        self._height_arr = np.full((room, len(self._lags)), np.nan)
        self._start = self._end = 0
        self._done_until = -1   # events up to this stamp were read
        self.events: list[ContactEvent] = []
        # (start, frames in the air, their mean summary, each frame's difference from it): kept while the
        # frames in the air stay the same (while pressed): only the new frames' differences are computed
        self._signal_cache: tuple[int, NDArray[np.bool_], np.ndarray, np.ndarray] | None = None

    def __len__(self) -> int:
        return self._end - self._start

    def push(self, stamp_ns: int, band: np.ndarray | None = None, summary: np.ndarray | None = None) -> None:
        """One frame's band (grey or colour, any dtype), or its `band_summary` made already (e.g. by the
        process that cut the band: it depends on the band alone)."""
        end = self._end
        if end > self._start and stamp_ns <= self._stamp_arr[end - 1]:
            return   # out of order: the state sequence needs stamps in order
        crop = None
        if summary is None:
            if band is None:
                raise ValueError("push needs a band or its summary")
            crop = _crop(band)
            if crop is None:
                return
        elif summary.shape != SUMMARY_SHAPE:
            raise ValueError(f"a band summary is {SUMMARY_SHAPE[0]}x{SUMMARY_SHAPE[1]}, got {summary.shape}")
        if end == len(self._stamp_arr):   # full: move the newest `capacity` to the front
            keep = slice(end - self.config.capacity, end)
            for array in (self._stamp_arr, self._summary_arr, self._height_arr):
                array[:self.config.capacity] = array[keep]
            self._height_arr[self.config.capacity:] = np.nan
            self._start, self._end = 0, self.config.capacity
            self._signal_cache = None
            end = self._end
        if crop is not None:
            _summarise(crop, self._summary_arr[end])   # straight into its row of the summaries
        else:
            self._summary_arr[end] = summary
        self._stamp_arr[end] = stamp_ns
        self._height_arr[end] = np.nan
        self._end = end + 1
        if self._end - self._start > self.config.capacity:
            self._start += 1

    def _arm_heights(self, poses: PoseLookup, latest_ns: int, final: bool) -> FloatArray:
        """(frames, 5): the arm's height at each frame's stamp less 0, 1/4, ... the whole max latency, looked
        up once TF has it (frames more than two seconds old that TF never covered are not asked again,
        except at the end)."""
        stamps = self._stamp_arr[self._start:self._end]
        heights = self._height_arr[self._start:self._end]
        missing = ~np.isfinite(heights).all(axis=1)
        if not final:
            missing &= stamps >= latest_ns - 2_000_000_000 - self.max_latency_ns
        index = np.flatnonzero(missing)
        if len(index):
            found = poses((stamps[index, None] - self._lags[None, :]).reshape(-1))[:, 2, 3]
            heights[index] = np.asarray(found, np.float64).reshape(len(index), len(self._lags))
        return heights

    def _levels(self, heights: FloatArray) -> tuple[FloatArray, float, float] | None:
        """Per frame, the band's RMS difference from the mean of the frames surely in the air (`heights`: the
        arm over the pressed height at each lag), and its median level in the air and pressed; None with
        fewer than 3 frames of either or when pressing does not change the image beyond its noise."""
        c = self.config
        known = np.isfinite(heights).all(axis=1)
        air = known & (heights.min(axis=1, initial=np.inf) > c.lifted)
        pressed = known & (np.abs(heights).max(axis=1, initial=0.0) < c.pressed)
        if air.sum() < 3 or pressed.sum() < 3:
            return None
        signal = self._signal(air)
        low, high = median(signal[air]), median(signal[pressed])
        noise = 1.4826 * median(np.abs(signal[air] - low))
        if not high - low > max(6.0 * noise, 1e-3):
            return None
        return signal, low, high

    def _signal(self, air: NDArray[np.bool_]) -> np.ndarray:
        """Each frame's RMS difference from the mean summary of the frames in the air (`air`). While those
        frames are the same ones as at the last call (the roller pressed) the mean is too, and only the
        frames added since are computed: the same numbers, at a cost that does not grow with the frames kept."""
        summaries = self._summary_arr[self._start:self._end]
        cached = self._signal_cache
        if cached is not None and cached[0] == self._start and len(cached[1]) <= len(air):
            start, was_air, reference, signal = cached
            done = len(was_air)
            if np.array_equal(was_air, air[:done]) and not air[done:].any():
                if done < len(air):
                    signal = np.concatenate([signal, np.sqrt(((summaries[done:] - reference) ** 2).mean(axis=(1, 2)))])
                self._signal_cache = (start, air.copy(), reference, signal)
                return signal
        reference = summaries[air].mean(axis=0)
        signal = np.sqrt(((summaries - reference) ** 2).mean(axis=(1, 2)))
        self._signal_cache = (self._start, air.copy(), reference, signal)
        return signal

    def shows_pressing(self, poses: PoseLookup, height: float, latest_ns: int) -> bool:
        """Whether the image confirms that the roller is pressed with the arm at `height`: the frames taken
        with the arm there (at every lag) differ from those taken with it surely in the air, beyond the
        noise, as pressing changes the band on any surface, smooth or not. An arm moving in the air at
        that height (a lead-in above the surface) leaves the band as it is in the air: not confirmed."""
        if len(self) < 6:
            return False
        return self._levels(self._arm_heights(poses, latest_ns, final=False) - height) is not None

    def update(self, poses: PoseLookup, pressed_height: float | None, latest_ns: int,
               final: bool = False) -> list[ContactEvent]:
        """The events found since the last call (also added to `events`): flips of the image's state with
        `steady_frames` of the same state either side, the arm in the air at some time in the second before
        a touchdown and pressed at some time in the second after it (the other way round for a lift-off).
        The image's levels come from frames surely in the air and surely pressed (at every lag)."""
        c = self.config
        if pressed_height is None or len(self) < 2 * c.steady_frames + 2:
            return []
        stamps = self._stamp_arr[self._start:self._end]
        heights = self._arm_heights(poses, latest_ns, final) - pressed_height
        levels = self._levels(heights)
        if levels is None:
            return []   # too few frames surely in the air or pressed, or pressing changes nothing visible
        signal, low, high = levels
        with np.errstate(invalid="ignore"):   # NaN: lags TF does not cover (the recording's ends)
            up = (heights > c.lifted).any(axis=1)
            down = (np.abs(heights) < c.pressed).any(axis=1)
        state = (signal - low) / (high - low) > c.level
        n, k = len(stamps), c.steady_frames
        horizon = latest_ns - self.max_latency_ns - 500_000_000
        found: list[ContactEvent] = []
        for i in np.flatnonzero(state[1:] != state[:-1]) + 1:   # state flips between frames i - 1 and i
            if i < k or i + k > n or stamps[i] <= self._done_until:
                continue
            if stamps[i] > horizon and not final:
                break   # its neighbours and poses may still come
            if (state[i - k:i] != state[i - 1]).any() or (state[i:i + k] != state[i]).any():
                continue   # flicker
            if (stamps[i] - stamps[i - 1]) * 1e-9 > c.max_gap:
                continue
            touchdown = bool(state[i])
            # TF: the arm came down through the contact zone around it (in the air at some time in the
            # second before, pressed at some time in the second after; at any latency TF covers), or rose
            window = (stamps >= stamps[i] - 1_000_000_000) & (stamps <= stamps[i] + 1_000_000_000)
            before, after = window & (stamps < stamps[i]), window & (stamps >= stamps[i])
            first, then = (up, down) if touchdown else (down, up)
            if not ((before & first).any() and (after & then).any()):
                continue
            found.append(ContactEvent(touchdown, int(stamps[i - 1]), int(stamps[i])))
        if found:
            self._done_until = found[-1].after_ns
        self.events += found
        return found


def latency_from_contacts(events: Sequence[ContactEvent], poses: PoseLookup, max_latency: float,
                          config: ContactTimingConfig | None = None, step: float = 5e-4) -> ContactTiming | None:
    """The range of latencies (on a `step` grid over [-0.05 s, max_latency]: a range must close on both
    sides, also around a latency of 0) at which one touching height lies within every event's bracket
    (to `config.tolerance` when none does exactly), as a `ContactTiming` (the part at or above 0); None
    with fewer than `min_events` touchdowns or lift-offs, when no latency keeps them consistent, or when
    the range reaches an end of the grid (not pinned down)."""
    c = config or ContactTimingConfig()
    downs = sum(e.touchdown for e in events)
    ups = len(events) - downs
    if downs < c.min_events or ups < c.min_events:
        return None
    step_ns = max(round(step * 1e9), 1)
    candidates = np.arange(-50_000_000, round(max_latency * 1e9) + 1, step_ns, dtype=np.int64)
    before = np.array([e.before_ns for e in events], np.int64)
    after = np.array([e.after_ns for e in events], np.int64)
    z_before = poses((before[:, None] - candidates[None, :]).reshape(-1))[:, 2, 3].reshape(len(events), -1)
    z_after = poses((after[:, None] - candidates[None, :]).reshape(-1))[:, 2, 3].reshape(len(events), -1)
    down = np.array([e.touchdown for e in events])[:, None]
    # a touchdown: the arm at `after - L` at or below the touching height, at `before - L` above it
    lower = np.where(down, z_after, z_before)
    upper = np.where(down, z_before, z_after)
    with np.errstate(invalid="ignore"):
        gap = lower.max(axis=0) - upper.min(axis=0)   # > 0: no height within every bracket
    ok = np.isfinite(gap) & (gap <= 0.0)
    if not ok.any():   # the brackets miss each other a little (noise at the threshold): within the tolerance
        ok = np.isfinite(gap) & (gap <= c.tolerance)
    if not ok.any():
        return None
    best = int(np.argmin(np.where(np.isfinite(gap), gap, np.inf)))
    if not ok[best]:
        return None
    lo = hi = best
    while lo > 0 and ok[lo - 1]:
        lo -= 1
    while hi < len(ok) - 1 and ok[hi + 1]:
        hi += 1
    if lo == 0 or hi == len(ok) - 1:
        return None   # the range runs off the grid: a bound, not an estimate
    # a latency is not negative: the range below 0 is left out
    low, high = max(candidates[lo] * 1e-9, 0.0), candidates[hi] * 1e-9
    if high < low:
        return None
    width = high - low + step
    return ContactTiming(0.5 * (low + high), width / math.sqrt(12.0), low, high, downs, ups)
