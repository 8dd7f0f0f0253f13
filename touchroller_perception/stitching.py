"""Stitching the contact bands of a rolling TouchRoller into one tactile map (issue 5).

Two methods share one incremental API (`Stitcher.push` per frame, `Stitcher.map_image` at any time):

* ``"paper"`` — the paper's method, kept for comparison: a 70-row patch centred in the image, the
  integer shift in [-search, search] minimising the mean absolute error to the previous patch, patches
  pasted at their integer offsets (the newest wins).
* ``"default"`` — subpixel keyframe registration:
  - the band is resampled to surface coordinates through the camera model when one is given (rows
    uniform in membrane y, columns uniform in x), so a roll is a pure translation across the whole band
    whatever theta, d and the lens distortion;
  - what does not move with the surface (gel background, LED shading, vignetting, dust) is divided out
    with a flat field: the band's mean over frames, in which the moving texture averages away (running
    while live; from all frames in a second pass offline);
  - registration runs on a high-passed band with columns binned (speed): an integer SAD search around a
    prediction — the caller's motion prior (arm speed) or recent velocity times the stamp interval, so
    dropped or duplicated frames and speed changes are followed — widened to the full range when the
    match is poor, then a Lucas–Kanade refinement of the row shift and of a lateral (axial) shift;
  - drift is held down by registering against a keyframe kept until the overlap gets small: errors add
    up once per keyframe, not once per frame, and subpixel bias does not scale with the frame rate;
  - textureless stretches (an indistinct minimum, or much less texture energy than usual) fall back on
    the motion prior, flagged in `StitchStep.used_prior`;
  - every frame is splatted into the map at its subpixel position with weights tapered across the
    band, so seams blend and noise averages out without blurring detail.

Sign convention: ``shift_px`` is how far the surface content moved down the image (+v) since the
previous frame. The map keeps the first frame's orientation; its rows run along the rolling direction.
No rclpy here.
"""
from __future__ import annotations

import dataclasses
import math
import statistics
from collections import deque
from collections.abc import Iterable, Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import cv2
import numpy as np

from touchroller_perception.images import to_grey

if TYPE_CHECKING:  # the geometry module is only needed when a camera model is passed
    from touchroller_perception.geometry import CameraModel

METHODS = ("default", "paper")
DEFAULT_FRAME_NS = 33_333_333  # 30 fps when frames carry no usable stamps
_TEXTURELESS_FRACTION = 0.5  # moving texture below this share of the usual counts as textureless
_STATIC_FRACTION = 0.3  # an image shift below this share of the arm's is taken as seeing only static things
_WEAK_CONFIDENCE = 0.5  # below this a match that contradicts the recent velocity is not believed
_VELOCITY_FRAMES = 5  # confident shifts whose median predicts the next
_FLAT_FIELD_MEMORY = 300  # frames the live flat field averages over
_FINE_FIELD_FRAMES = 60   # frames a final flat field with its fine column profile (flat_sigma_cols 0) needs
# 1 - NCC above this at the best shift: the keyframe no longer shows what the frame shows (contact
# began or ended, a jump); registered rolls stay below ~0.3 even at 5 s with motion blur.
_MISMATCH_COST = 0.5
_STILL_PX = 1.0  # less motion than this (px) counts as standing still
DEFAULT_HISTORY = 1000  # per-frame records a Stitcher keeps unless told otherwise
MAX_MAP_PIXELS = 256_000_000  # the most pixels a resampled (metric) map may have: 256 MB of grey
DEFAULT_MAX_ROWS = 10_000  # map rows a live Stitcher keeps (1 m at 0.1 mm per row) unless told otherwise


@dataclass(frozen=True)
class StitchStep:
    """What one `Stitcher.push` found.

    shift_px: surface motion along the image rows (v) since the previous frame, map pixels.
    confidence: 0..1, how distinct the registration minimum was (0 = textureless / no overlap).
    used_prior: the shift came from the motion prior (arm speed or recent velocity), not the image.
    lateral_px: motion along the axis (u) since the previous frame, pixels.
    position_px: cumulative shift since the first frame.
    """

    shift_px: float
    confidence: float
    used_prior: bool
    lateral_px: float = 0.0
    position_px: float = 0.0


class _Canvas:
    """A growable weighted-average accumulator for the map.

    Layers of rows x cols float32 sums (layer 0: weighted bands; layer 1, with a background model:
    the weighted flat field at the same places) and one weight per row. Bands are splatted at
    subpixel positions by bilinear splatting (the adjoint of bilinear interpolation: no resampling
    pass, no blur beyond the interpolation itself). Columns are reported where every band reached.

    `placed[left]` holds, per canvas row, the total bilinear share of the bands whose integer corner
    landed at that (row, left): enough to re-fill a layer with one patch at every place a band went
    (`refill`, what `Stitcher.finalise` needs), in memory that grows with the map, not the frames.

    With `max_rows` the map is a rolling window: once it spans more rows, the rows farthest from the
    band just added are dropped (counted in `dropped_rows`) and the memory stays bounded whatever the
    number of frames. Rows within a band's height of a cut may be approximate after `refill`.
    """

    def __init__(self, cols: int, layers: int = 1, rows: int = 2048, max_rows: int | None = None) -> None:
        self.max_rows = max_rows
        self.dropped_rows = 0  # map rows dropped to keep within max_rows
        self.band_cols: int | None = None  # width of the bands placed (all the same)
        if max_rows is not None:
            rows = min(rows, max_rows)
        self.layers = [np.zeros((rows, cols), np.float32) for _ in range(layers)]
        self.weight = np.zeros(rows, np.float32)
        self.placed: dict[int, np.ndarray] = {}
        self.origin_row = rows // 2  # canvas row of map row 0
        self.origin_col = 16  # room for a little lateral wander before growing
        self.row_min = math.inf
        self.row_max = -math.inf
        self.col_lo = -math.inf  # columns covered by every band so far: [col_lo, col_hi)
        self.col_hi = math.inf

    def _ensure(self, top: int, left: int, height: int, width: int) -> None:
        rows, cols = self.layers[0].shape
        grow_top = max(0, -(top + self.origin_row))
        grow_bottom = max(0, top + self.origin_row + height - rows)
        grow_left = max(0, -(left + self.origin_col))
        grow_right = max(0, left + self.origin_col + width - cols)
        if not (grow_top or grow_bottom or grow_left or grow_right):
            return
        # Grow geometrically so that a long scan reallocates O(log n) times (by at most a quarter of
        # the bound when there is one: the window is trimmed long before that is used up).
        step = rows if self.max_rows is None else max(min(rows, self.max_rows // 4), 1)
        pad_t = max(grow_top, step) if grow_top else 0
        pad_b = max(grow_bottom, step) if grow_bottom else 0
        pad_l = max(grow_left, 32) if grow_left else 0
        pad_r = max(grow_right, 32) if grow_right else 0
        self.layers = [np.pad(layer, ((pad_t, pad_b), (pad_l, pad_r))) for layer in self.layers]
        self.weight = np.pad(self.weight, (pad_t, pad_b))
        self.placed = {left: np.pad(shares, (pad_t, pad_b)) for left, shares in self.placed.items()}
        self.origin_row += pad_t
        self.origin_col += pad_l

    def add(self, patches: Sequence[np.ndarray | None], row_weights: np.ndarray, top: float, left: float,
            *, subpixel: bool) -> None:
        """Add weighted patches (already multiplied by their row weights) with the top-left corner at
        map (top, left); `None` leaves a layer alone."""
        h, w = next(p for p in patches if p is not None).shape
        if subpixel:
            # Columns within 0.05 px of a whole pixel are placed on it: lateral jitter is mostly that
            # small, and it halves the splatting work (2 row terms, not 4) for an error far below the
            # registration's. Rows always split: the roll moves them by fractions.
            itop, ileft = math.floor(top), round(left)
            fr, fc = top - itop, 0.0
            if abs(left - ileft) >= 0.05:
                ileft = math.floor(left)
                fc = left - ileft
        else:
            itop, ileft, fr, fc = round(top), round(left), 0.0, 0.0
        self._ensure(itop, ileft, h + 1, w + 1)
        r0, c0 = itop + self.origin_row, ileft + self.origin_col
        terms = [(0, 0, (1 - fr) * (1 - fc)), (1, 0, fr * (1 - fc)), (0, 1, (1 - fr) * fc), (1, 1, fr * fc)]
        for dr, dc, share in terms:
            if share > 1e-6:
                shares = self.placed.get(ileft + dc)
                if shares is None:
                    shares = self.placed[ileft + dc] = np.zeros(self.weight.shape[0])
                shares[r0 + dr] += share
        for layer, patch in zip(self.layers, patches, strict=True):
            if patch is None:
                continue
            for dr, dc, share in terms:
                if share > 1e-6:
                    view = layer[r0 + dr:r0 + dr + h, c0 + dc:c0 + dc + w]
                    cv2.scaleAdd(patch, share, view, dst=view)
        self.weight[r0:r0 + h] += (1 - fr) * row_weights
        if fr > 1e-6:
            self.weight[r0 + 1:r0 + 1 + h] += fr * row_weights
        # The map's rows: those a band reached with a real share (a 1 % sliver of a row at the edge
        # would show as a dark line).
        first = itop + (fr > 0.95)
        self.band_cols = w
        self._extend(first, itop + h + (fr > 0.05) - first, ileft + (fc > 1e-6), ileft + w)
        self._bound(itop, h + 1)

    def paste(self, patch: np.ndarray, top: int, left: int) -> None:
        """Overwrite layer 0 (the paper's stitching: the newest patch wins)."""
        h, w = patch.shape
        self._ensure(top, left, h, w)
        r0, c0 = top + self.origin_row, left + self.origin_col
        self.layers[0][r0:r0 + h, c0:c0 + w] = patch
        self.weight[r0:r0 + h] = 1.0
        self._extend(top, h, left, left + w)
        self._bound(top, h)

    def _bound(self, top: int, h: int) -> None:
        """With `max_rows`: once the map spans more rows, keep three quarters of the bound around the band
        just placed at map rows [top, top + h) -- the rows it came from first -- and free the rest."""
        if self.max_rows is None or self.row_max - self.row_min <= self.max_rows:
            return
        budget = max(self.max_rows * 3 // 4 - h, 0)
        below = max(top - int(self.row_min), 0)          # map rows before the band (lower indices)
        above = max(int(self.row_max) - (top + h), 0)    # and after it
        keep_below = min(below, max(budget - above, budget // 2))
        keep_above = min(above, budget - keep_below)
        lo, hi = top - keep_below, top + h + keep_above
        self._trim(lo, hi, margin=h + 2)
        if keep_below < below:   # rows near the cut lost part of their bands' shares
            self.row_min = min(lo + h, top)
        else:
            self.row_min = max(self.row_min, lo)
        self.row_max = min(self.row_max, hi)
        self.dropped_rows += (below - keep_below) + (above - keep_above)

    def _trim(self, lo: int, hi: int, margin: int) -> None:
        """Keep map rows [lo, hi) (plus `margin` rows of room beyond either end, so a band placed just
        inside still fits whole) and the columns the remaining bands cover; free everything else."""
        rows, cols = self.layers[0].shape
        r0 = max(lo - margin + self.origin_row, 0)
        r1 = min(hi + margin + self.origin_row, rows)
        keep_r0, keep_r1 = lo + self.origin_row, hi + self.origin_row   # placements kept: corners in here
        placed = {}
        for left, shares in self.placed.items():
            kept = shares[r0:r1].copy()
            kept[:max(keep_r0 - r0, 0)] = 0.0
            kept[max(keep_r1 - r0, 0):] = 0.0
            if kept.any():
                placed[left] = kept
        c0, c1 = 0, cols
        if placed and self.band_cols is not None:   # columns: those the remaining bands reach, and room
            c0 = max(min(placed) + self.origin_col - 32, 0)
            c1 = min(max(placed) + self.origin_col + self.band_cols + 33, cols)
            self.col_lo = max(placed)
            self.col_hi = min(placed) + self.band_cols
        self.layers = [np.ascontiguousarray(layer[r0:r1, c0:c1]) for layer in self.layers]
        self.weight = self.weight[r0:r1].copy()
        a, b = max(keep_r0 - r0, 0), max(keep_r1 - r0, 0)   # what dropped bands left in the margins goes too
        for array in (*self.layers, self.weight):
            array[:a] = 0.0
            array[b:] = 0.0
        self.placed = placed
        self.origin_row -= r0
        self.origin_col -= c0

    def _extend(self, top: int, h: int, col_lo: int, col_hi: int) -> None:
        self.row_min = min(self.row_min, top)
        self.row_max = max(self.row_max, top + h)
        self.col_lo = max(self.col_lo, col_lo)
        self.col_hi = min(self.col_hi, col_hi)

    def refill(self, index: int, patch: np.ndarray) -> None:
        """Layer `index` := `patch` added at every place a band went, with the bands' bilinear shares
        (exactly what splatting `patch` along with every band would have given)."""
        layer = self.layers[index]
        layer[:] = 0.0
        h, w = patch.shape
        for left, shares in self.placed.items():
            c0 = left + self.origin_col
            for r0 in np.flatnonzero(shares):
                view = layer[r0:r0 + h, c0:c0 + w]
                cv2.scaleAdd(patch, float(shares[r0]), view, dst=view)

    def _window(self) -> tuple[slice, slice] | None:
        if self.row_min == math.inf or self.col_hi <= self.col_lo:
            return None
        r0, r1 = int(self.row_min) + self.origin_row, int(self.row_max) + self.origin_row
        c0, c1 = int(self.col_lo) + self.origin_col, int(self.col_hi) + self.origin_col
        return slice(r0, r1), slice(c0, c1)

    def coverage(self, min_weight: float) -> np.ndarray:
        window = self._window()
        if window is None:
            return np.zeros((0, 0), bool)
        rows = self.weight[window[0]] > min_weight
        return np.repeat(rows[:, None], window[1].stop - window[1].start, axis=1)

    def image(self, scale: float | None = None, min_weight: float = 1e-3) -> np.ndarray:
        """uint8 map: layer 0 / row weight, or `scale` * layer 0 / layer 1 (flat-field corrected)."""
        window = self._window()
        if window is None:
            return np.zeros((0, 0), np.uint8)
        s = self.layers[0][window]
        if scale is None:
            w = self.weight[window[0]][:, None]
            out = np.divide(s, w, out=np.zeros_like(s), where=w > min_weight)
        else:
            d = self.layers[1][window]
            known = (self.weight[window[0]][:, None] > min_weight) & (d > 1e-6)
            out = np.divide(s * np.float32(scale), d, out=np.zeros_like(s), where=known)
        return np.clip(out + 0.5, 0, 255).astype(np.uint8)


class BandSampler:
    """Cuts the band out of a frame as float32 grey: a plain row crop, or a resampling of the membrane
    around the contact line onto a grid uniform in membrane y (rows) and x (columns)."""

    def __init__(self, shape: tuple[int, int], band_rows: int, camera: CameraModel | None,
                 centre_row: float | None, rectify: bool) -> None:
        height, width = shape
        if band_rows < 8 or band_rows > height:
            raise ValueError(f"band_rows must be in [8, {height}] for {height}-row images, got {band_rows}")
        self.rows, self.cols = band_rows, width
        self.maps: tuple[np.ndarray, np.ndarray] | None = None
        self.mm_per_px: float | None = None  # along the rows (rolling direction)
        self.mm_per_px_cols: float | None = None
        self.centre_u: float | None = None  # image column of the contact line's centre (x = 0), with a camera
        if camera is not None:
            self._from_camera(camera, shape, band_rows, rectify)
            return
        centre = (height - 1) / 2.0 if centre_row is None else float(centre_row)
        self._crop(centre, height)

    def _crop(self, centre: float, height: int) -> None:
        self.row0 = int(np.clip(round(centre - (self.rows - 1) / 2.0), 0, height - self.rows))
        self.src_rows = (self.row0, self.row0 + self.rows)

    def _from_camera(self, camera: CameraModel, shape: tuple[int, int], band_rows: int, rectify: bool) -> None:
        height, width = shape
        if (camera.width, camera.height) != (width, height):
            raise ValueError(f"camera model is {camera.width}x{camera.height} but the images are {width}x{height}")
        r = float(camera.radius)
        eps = 1e-5
        uv, valid = camera.project(np.stack([camera.surface_point(0.0, 0.0), camera.surface_point(0.0, eps),
                                             camera.surface_point(eps * r, 0.0)]))
        if not np.all(valid):
            raise ValueError("the camera model does not see the contact line (check theta and d)")
        m_per_row = eps * r / float(np.hypot(*(uv[1] - uv[0])))  # membrane metres per image row
        m_per_col = eps * r / float(np.hypot(*(uv[2] - uv[0])))
        self.mm_per_px, self.mm_per_px_cols = m_per_row * 1e3, m_per_col * 1e3
        centre_u, centre_v = uv[0]
        self.centre_u = float(centre_u)
        if not rectify:
            self._crop(centre_v, height)
            return
        ys = (np.arange(band_rows) - (band_rows - 1) / 2.0) * m_per_row
        if np.abs(ys).max() >= r:
            raise ValueError("band_rows reaches round the whole tube")
        xs = (np.arange(width) - centre_u) * m_per_col
        xx, aa = np.meshgrid(xs, np.arcsin(ys / r))
        uv, valid = camera.project(camera.surface_point(xx, aa))
        if not valid.any():
            raise ValueError("the rectified band falls outside the image")
        v = uv[..., 1]
        v0 = int(np.clip(math.floor(np.nanmin(v)) - 1, 0, height - 1))
        v1 = int(np.clip(math.ceil(np.nanmax(v)) + 2, v0 + 1, height))
        self.src_rows = (v0, v1)
        self.row0 = int(round(centre_v - (band_rows - 1) / 2.0))
        map_x = np.where(valid, uv[..., 0], -10.0).astype(np.float32)
        map_y = np.where(valid, v - v0, -10.0).astype(np.float32)
        self.maps = (map_x, map_y)  # float maps: as fast as fixed-point ones here, and exact

    def __call__(self, image: np.ndarray, row0: int = 0) -> np.ndarray:
        """The band of a frame, or of the frame's rows from `row0` on (they must hold `src_rows`)."""
        v0, v1 = self.src_rows
        if v0 < row0 or v1 - row0 > image.shape[0]:
            raise ValueError(f"the band needs frame rows {v0} to {v1}, got {row0} to {row0 + image.shape[0]}")
        grey = to_grey(image[v0 - row0:v1 - row0])
        if self.maps is not None:
            grey = cv2.remap(grey, self.maps[0], self.maps[1], cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
        return grey.astype(np.float32)


def _highpass(image: np.ndarray, rows: int, cols: int) -> np.ndarray:
    return cv2.subtract(image, cv2.blur(image, (cols, rows), borderType=cv2.BORDER_REFLECT))


def taper(n: int) -> np.ndarray:
    """Weights across the band: highest at the contact line, small but non-zero at the edges."""
    t = (np.arange(n) + 0.5) / n
    return (0.05 + np.sin(np.pi * t) ** 2).astype(np.float32)


def estimate_flat_field(bands: Iterable[np.ndarray]) -> np.ndarray:
    """The static part of the bands (gel background, shading, dust): their mean over frames, see
    `flat_field_from_mean`."""
    total, count = None, 0
    for band in bands:
        total = band.astype(np.float64) if total is None else total + band
        count += 1
    if total is None:
        raise ValueError("no frames to estimate a flat field from")
    return flat_field_from_mean((total / count).astype(np.float32))


def flat_field_from_mean(mean: np.ndarray, sigma_cols: float = 15.0) -> np.ndarray:
    """The static part of a band from its mean over frames.

    Texture moving along the rows averages away in the mean, except texture that is constant along
    the roll (yarns parallel to the rolling direction): it stays as a fine column pattern. Static
    illumination varies slowly across columns, dust is local, so the mean's column profile is kept
    only at low spatial frequency; the fine part belongs to the surface and is left in the map.
    """
    mean = np.maximum(np.asarray(mean, np.float32), 1.0)
    if sigma_cols <= 0:   # the whole mean: every fine column feature of the gel divides out too
        return mean
    profile = mean.mean(axis=0, keepdims=True)
    smooth = cv2.GaussianBlur(profile, (0, 0), sigmaX=sigma_cols, sigmaY=1e-3, borderType=cv2.BORDER_REFLECT)
    return mean * (smooth / profile)


@dataclass(frozen=True)
class StitcherConfig:
    """How a `Stitcher` works; the perception node's `map.*` parameters map onto these fields.

    method: "default" (subpixel keyframe registration) or "paper" (the paper's integer MAE search).
    band_rows: rows of the band cut around the contact line (the paper: 70).
    search: largest |shift| per frame searched, pixels (the paper: 25).
    centre_row: without a camera model, the image row the band is centred on (None: the middle row).
    rectify: with a camera model, resample the band to membrane coordinates (default method).
    subpixel: subpixel registration and placement (default method).
    keyframes: register against a keyframe (less drift) rather than the previous frame.
    keyframe_overlap: a new keyframe is taken when the overlap with the current one drops below this.
    motion_prior: predict each shift (the caller's prior, else the recent velocity) and search near it first.
    local_search: half-width of that first search, pixels.
    background: divide out a flat field (the band's mean over frames): what does not move with the surface.
    lateral: also track a shift along the axis (u).
    column_bin: columns averaged together for registration (speed; rows are never binned).
    highpass: box size of the high-pass filter that removes residual shading before registration.
    min_confidence: below this the motion prior is used instead of the image.
    live_map: keep the flat-field correction of the map current frame by frame (for `map_image` while
      stitching); an offline caller that calls `finalise()` at the end can turn it off and save time.
    history: how many per-frame records (`steps`, `stamps`, `shifts`) to keep, the newest; None keeps
      all (offline evaluation). Bounded by default so a live stitcher's memory grows only with the map.
    keep_map: build the strip map; False only measures the roll and learns the flat field (what the
      world map, which places the bands itself, asks of it).
    max_rows: the most map rows kept (at 0.1 mm per row the default is 1 m of surface): a longer map is a
      rolling window of the rows nearest the newest band, the rest dropped (`Stitcher.dropped_rows`), so a
      live stitcher fed frames for hours stays within a fixed memory. None: unbounded (offline tools
      that stitch a recording whole).
    flat_sigma_cols: the flat field keeps the column profile of the band's mean only at this low
      spatial frequency (columns): texture constant along the roll stays in a strip map. 0: the whole
      mean divides out (the world map: a fine static feature of the gel would draw a line along every
      pass, at the same place in each): in the final field (`finalise`), once 60 frames were learnt
      (before that, and in the live field, as 15: on a short roll the mean's columns still hold the surface).
    """

    method: str = "default"
    band_rows: int = 70
    search: int = 25
    centre_row: float | None = None
    rectify: bool = True
    subpixel: bool = True
    keyframes: bool = True
    keyframe_overlap: float = 0.6
    motion_prior: bool = True
    local_search: int = 3
    background: bool = True
    lateral: bool = True
    column_bin: int = 4
    highpass: int = 9
    min_confidence: float = 0.15
    live_map: bool = True
    history: int | None = DEFAULT_HISTORY
    keep_map: bool = True
    max_rows: int | None = DEFAULT_MAX_ROWS
    flat_sigma_cols: float = 15.0

    def __post_init__(self) -> None:
        if self.method not in METHODS:
            raise ValueError(f"unknown stitching method {self.method!r}; choose from {', '.join(METHODS)}")
        if self.band_rows < 8:
            raise ValueError(f"band_rows must be >= 8, got {self.band_rows}")
        if self.search < 1:
            raise ValueError(f"search must be >= 1 pixel, got {self.search}")
        if self.column_bin < 1:
            raise ValueError(f"column_bin must be >= 1, got {self.column_bin}")
        if self.highpass < 1 or self.local_search < 0:
            raise ValueError(f"highpass must be >= 1 and local_search >= 0, got {self.highpass}, {self.local_search}")
        if not 0.0 < self.keyframe_overlap < 1.0:
            raise ValueError(f"keyframe_overlap must be in (0, 1), got {self.keyframe_overlap}")
        if not 0.0 <= self.min_confidence <= 1.0:
            raise ValueError(f"min_confidence must be in [0, 1], got {self.min_confidence}")
        if self.history is not None and self.history < 1:
            raise ValueError(f"history must be >= 1 frame or None (all), got {self.history}")
        if self.max_rows is not None and self.max_rows < 8 * self.band_rows:
            raise ValueError(f"max_rows must be >= 8 x band_rows ({8 * self.band_rows}) or None (unbounded), "
                             f"got {self.max_rows}")
        if not (math.isfinite(self.flat_sigma_cols) and self.flat_sigma_cols >= 0):
            raise ValueError(f"flat_sigma_cols must be >= 0, got {self.flat_sigma_cols}")
        if self.centre_row is not None and not math.isfinite(self.centre_row):
            raise ValueError(f"centre_row must be finite or None, got {self.centre_row}")

    def replace(self, **changes: Any) -> StitcherConfig:
        return dataclasses.replace(self, **changes)

    @property
    def shaded(self) -> bool:
        """The map divides out a flat field (default method with a background model)."""
        return self.method == "default" and self.background


class FlatField:
    """What does not move with the surface (gel background, LED shading, vignetting, dust): a static
    gain on the band, estimated as the band's running mean over frames taken at different places
    (`flat_field_from_mean`), or fixed (`fixed`, e.g. from `estimate_flat_field` over a recording).

    Live, a field is offered only once the surface has moved two bands and ten frames were learnt
    (before that the mean still holds texture), and recomputed every ten frames (cost)."""

    def __init__(self, band_rows: int, fixed: np.ndarray | None = None, memory: int = _FLAT_FIELD_MEMORY,
                 sigma_cols: float = 15.0) -> None:
        self.band_rows = band_rows
        self.sigma_cols = sigma_cols
        self.fixed = None if fixed is None else np.asarray(fixed, np.float32)
        self.memory = memory
        self.count = 0  # frames in the running mean
        self._sum: np.ndarray | None = None
        self._field: np.ndarray | None = None  # the live field offered for flattening
        self._dirty = 0  # frames added since it was computed
        self._last_position = 0.0  # position of the last frame learnt
        self._gain: np.ndarray | None = None  # level / field, for the field `_gain_of`
        self._gain_of: np.ndarray | None = None
        self.gain_level = 1.0  # mean grey level of `_gain_of`

    def field(self, travel: float) -> np.ndarray | None:
        """The field to flatten a band with now (None: not known yet)."""
        if self.fixed is not None:
            return self.fixed
        if travel < 2 * self.band_rows or self.count < 10 or self._sum is None:
            return None
        if self._field is None or self._dirty >= 10:
            self._field = flat_field_from_mean(self._sum / self.count, self.sigma_cols or 15.0)
            self._dirty = 0
        return self._field

    def flatten(self, band: np.ndarray, travel: float) -> tuple[np.ndarray, np.ndarray | None]:
        """The band with the field divided out (scaled to the field's mean level), and the field used."""
        field = self.field(travel)
        if field is None:
            return band, None
        if self._gain_of is not field:  # the field changes every few frames at most
            self.gain_level = float(field.mean())
            self._gain, self._gain_of = self.gain_level / np.maximum(field, 1.0), field
        return cv2.multiply(band, self._gain), field

    def level(self, field: np.ndarray) -> float:
        return self.gain_level if self._gain_of is field else float(field.mean())

    def learn(self, band: np.ndarray, position: float) -> None:
        """Add a frame to the running mean if the surface moved since the last one added: the mean of
        frames at one place is the surface itself, not what stays still."""
        if self.fixed is not None or abs(position - self._last_position) < _STILL_PX:
            return
        self._last_position = position
        if self._sum is None:
            self._sum = np.zeros_like(band)
        if self.count >= self.memory:  # a running mean: follows slowly changing light
            cv2.scaleAdd(self._sum, (self.memory - 1) / self.memory, band, dst=self._sum)
        else:
            cv2.add(self._sum, band, dst=self._sum)
            self.count += 1
        self._dirty += 1

    def final(self) -> np.ndarray | None:
        """The best field from everything learnt (None if nothing moved)."""
        if self.fixed is not None:
            return self.fixed
        if self._sum is None or self.count == 0:
            return None
        # sigma_cols 0: the fine column profile in the final field only (the live one, which registration
        # sees, keeps the smooth one), and only once the mean holds enough frames for the surface's own
        # column structure to have averaged out (a short roll keeps the smooth profile)
        fine = self.sigma_cols > 0 or self.count >= _FINE_FIELD_FRAMES
        return flat_field_from_mean(self._sum / self.count, self.sigma_cols if fine else 15.0)


class VelocityPredictor:
    """The expected shift of the next frame: the caller's prior, else the recent velocity (the median of
    the last confident shifts per nanosecond of stamp, so a dropped frame doubles the prediction and a
    duplicated stamp predicts 0; per frame when stamps are unusable)."""

    def __init__(self, enabled: bool = True) -> None:
        self.enabled = enabled
        self._per_ns: deque[float] = deque(maxlen=_VELOCITY_FRAMES)
        self._per_frame: deque[float] = deque(maxlen=_VELOCITY_FRAMES)

    def predict(self, dt: int | None, prior_px: float | None) -> float | None:
        if not self.enabled:
            return None
        if prior_px is not None:
            return float(prior_px)
        if dt == 0:
            return 0.0  # a duplicated frame (same stamp) has not moved
        if dt is not None and dt > 0 and self._per_ns:
            return _velocity(self._per_ns) * dt
        return _velocity(self._per_frame) if self._per_frame else None

    def update(self, shift: float, dt: int | None) -> None:
        """A confident shift, `dt` ns after the previous frame."""
        self._per_frame.append(shift)
        if dt is not None and dt > 0:
            self._per_ns.append(shift / dt)


class PaperRegistration:
    """The paper's method: the integer shift in [-search, search] minimising the mean absolute error to
    the previous patch over the overlapping rows."""

    def __init__(self, search: int) -> None:
        self.search = search
        self._previous: np.ndarray | None = None

    def register(self, band: np.ndarray) -> tuple[float, float]:
        """(shift, confidence) of `band` against the previous one; (0, 0) for the first."""
        shift, confidence = 0.0, 0.0
        if self._previous is not None:
            costs = _sad_costs(band, self._previous, range(-self.search, self.search + 1), min_overlap=1)
            best = int(np.nanargmin(costs))
            shift = float(best - self.search)
            confidence = _confidence(costs, best)
        self._previous = band
        return shift, confidence


@dataclass
class _Keyframe:
    features: np.ndarray  # binned, high-passed (row registration)
    full: np.ndarray  # the raw band (lateral registration)
    energy: np.ndarray  # `_row_energy_cumsum(features)`
    row: float  # map position (rows, columns) when it was taken
    col: float


@dataclass
class _Pending:
    """The latest frame before the roller first moved (see `Stitcher._place`)."""

    band: np.ndarray
    field: np.ndarray | None
    row: float
    col: float


class Stitcher:
    """Incremental stitcher: `push` each frame, read `map_image()` whenever needed.

    `config` (a `StitcherConfig`) sets the method and its tuning. `camera` (a `CameraModel`) locates the
    contact line, gives mm per pixel and (with `config.rectify`) resamples the band to membrane
    coordinates; without it the band is centred on `config.centre_row` and the scale is unknown.
    `flat_field` passes in a fixed flat field (e.g. `estimate_flat_field` over a whole recording).

    Standing still is not motion: frames before the roller first moves (an approach from above, a
    press) do not enter the map except the last one, frames that did not move do not enter the
    background model (they would imprint the surface on it), and a keyframe that no longer matches
    the frame (contact began or ended) is replaced rather than trusted.
    """

    def __init__(self, config: StitcherConfig | None = None, *, camera: CameraModel | None = None,
                 flat_field: np.ndarray | None = None) -> None:
        self.config = config = config or StitcherConfig()
        self.camera = camera
        history = config.history
        # The newest `history` frames (all with None): a list offline, a ring buffer live.
        self.shifts: list[float] | deque[float] = [] if history is None else deque(maxlen=history)
        self.steps: list[StitchStep] | deque[StitchStep] = [] if history is None else deque(maxlen=history)
        self.stamps: list[int] | deque[int] = [] if history is None else deque(maxlen=history)
        self.frames = 0  # frames pushed, and how many of them took the motion prior
        self.prior_frames = 0
        self.flat = FlatField(config.band_rows, flat_field, sigma_cols=config.flat_sigma_cols)
        self.predictor = VelocityPredictor(config.motion_prior)
        self.paper = PaperRegistration(config.search)
        self._shape: tuple[int, int] | None = None
        self._sampler: BandSampler | None = None
        self._canvas: _Canvas | None = None
        self._weights = taper(config.band_rows)
        self._column_weights: np.ndarray | None = None
        self._position = 0.0  # cumulative row shift
        self._lateral_pos = 0.0  # cumulative column shift
        self._last_stamp: int | None = None
        self._key: _Keyframe | None = None
        self._level = 1.0  # the map's flat-field level (its mean grey)
        self._weighted_field: tuple[np.ndarray, np.ndarray] | None = None  # (field, weights x field)
        self._moved = False  # has the roller moved since the first frame?
        self._pending: _Pending | None = None
        self._splat_row = 0.0  # position of the last band added to the map
        self._travel = 0.0
        self._unregistered: tuple[float, int | None] = (0.0, 0)   # motion (px, ns) taken unregistered since
        # the last registered frame (`_push_unregistered`)
        self._typical_energy: float | None = None  # mean |feature| while tracking confidently

    # -- public ------------------------------------------------------------------------------------
    @property
    def method(self) -> str:
        return self.config.method

    @property
    def band_rows(self) -> int:
        return self.config.band_rows

    @property
    def history(self) -> int | None:
        return self.config.history

    @property
    def dropped_rows(self) -> int:
        """Map rows dropped so far to keep the map within `config.max_rows`."""
        return 0 if self._canvas is None else self._canvas.dropped_rows

    @property
    def position_px(self) -> float:
        """Cumulative shift since the first frame (the last step's `position_px`)."""
        return self._position

    @property
    def lateral_px(self) -> float:
        """Cumulative shift along the axis since the first frame."""
        return self._lateral_pos

    def flat_field_now(self) -> np.ndarray | None:
        """The flat field the stitcher divides bands by at this point of the scan (None: not known yet)."""
        if not self.config.shaded:
            return None
        return self.flat.field(self._travel)

    def flat_field_final(self) -> np.ndarray | None:
        """The best flat field from everything stitched so far (what `finalise` uses)."""
        return self.flat.final() if self.config.shaded else None

    @property
    def sampler(self) -> BandSampler | None:
        """How bands are cut (None before the first frame)."""
        return self._sampler

    @property
    def mm_per_px(self) -> float | None:
        """Surface millimetres per map row at the contact line (None without a camera model)."""
        return None if self._sampler is None else self._sampler.mm_per_px

    def pixels_per_metre(self, image_shape: tuple[int, int] | None = None) -> float | None:
        """Map rows per metre of rolled surface: multiply an arm speed (m/s) by the frame interval (s)
        and this to get `prior_px`. None without a camera model."""
        if self._sampler is None and image_shape is not None:
            self.setup((int(image_shape[0]), int(image_shape[1])))
        if self._sampler is None or self._sampler.mm_per_px is None:
            return None
        return 1e3 / self._sampler.mm_per_px

    def band(self, image: np.ndarray, row0: int = 0, frame_height: int | None = None) -> np.ndarray:
        """The float32 grey band this stitcher registers, cut (or resampled) from a full frame, or from
        rows of one: `image` then holds frame rows from `row0` on of a frame `frame_height` rows high
        (they must include `source_rows`)."""
        image = np.asarray(image)
        if image.ndim < 2 or image.size == 0:
            raise ValueError(f"expected a non-empty image, got shape {image.shape}")
        if image.dtype.kind == "f" and not np.isfinite(image).all():
            raise ValueError("the image has non-finite pixel values")
        shape = (int(image.shape[0] if frame_height is None else frame_height), int(image.shape[1]))
        if self._sampler is None:
            self.setup(shape)
        elif shape != self._shape:
            raise ValueError(f"frame size changed from {self._shape} to {shape}")
        assert self._sampler is not None
        return self._sampler(image, row0)

    def source_rows(self, shape: tuple[int, int]) -> tuple[int, int]:
        """(first, end) of the rows of a frame of `shape` (rows, columns) the band is cut from."""
        if self._sampler is None:
            self.setup((int(shape[0]), int(shape[1])))
        elif tuple(shape) != self._shape:
            raise ValueError(f"frame size changed from {self._shape} to {tuple(shape)}")
        assert self._sampler is not None
        return self._sampler.src_rows

    def push(self, image: np.ndarray, stamp_ns: int, prior_px: float | None = None) -> StitchStep:
        """Register one frame against what came before and add it to the map.

        prior_px: the expected shift for this frame if known (e.g. arm speed x interval x pixels_per_metre).
        """
        return self.push_band(self.band(image), stamp_ns, prior_px)

    def push_band(self, band: np.ndarray, stamp_ns: int, prior_px: float | None = None,
                  register: bool = True) -> StitchStep:
        """`push` for a band already cut with `band()` (lets a caller make two passes over a recording).

        register: False moves the frame by `prior_px` (else the recent velocity) without registering the
        image: a caller that knows the roll is steady saves the registration. The next registered frame
        is located against the keyframe as usual, so a wrong guess is not carried on. Ignored without a
        prior or a velocity, before the roller first moved, and by the paper's method."""
        sampler = self._sampler
        if sampler is None:
            raise ValueError("call band() or push() with a full frame first")
        if band.shape != (sampler.rows, sampler.cols):
            raise ValueError(f"band shape {band.shape} differs from {(sampler.rows, sampler.cols)}")
        if prior_px is not None and not math.isfinite(prior_px):
            prior_px = None
        stamp_ns = int(stamp_ns)
        dt = None if self._last_stamp is None else stamp_ns - self._last_stamp
        if self.config.method == "paper":
            step = self._push_paper(band)
        elif not register and self._key is not None and self._moved and (
                motion := self.predictor.predict(dt, prior_px)) is not None:
            step = self._push_unregistered(band, motion, dt)
        else:
            step = self._push_default(band, dt, prior_px)
        self._last_stamp = stamp_ns
        self.frames += 1
        self.prior_frames += step.used_prior
        self.stamps.append(stamp_ns)
        self.shifts.append(step.shift_px)
        self.steps.append(step)
        return step

    def map_image(self, mm_per_px: float | None = None) -> np.ndarray:
        """The map so far as uint8 grey at camera pixel scale, or resampled to `mm_per_px` (needs a camera)."""
        if self._canvas is None or self._sampler is None:
            return np.zeros((0, 0), np.uint8)
        image = self._map_canvas().image(self._level if self.config.shaded else None)
        if mm_per_px is None:
            return image
        if not (mm_per_px > 0 and math.isfinite(mm_per_px)):
            raise ValueError(f"mm_per_px must be a positive number, got {mm_per_px}")
        row_mm, col_mm = self._sampler.mm_per_px, self._sampler.mm_per_px_cols
        if row_mm is None or col_mm is None:
            raise ValueError("a metric map needs a camera model (geometry) to know mm per pixel")
        h, w = image.shape
        size = (max(1, round(w * col_mm / mm_per_px)), max(1, round(h * row_mm / mm_per_px)))
        if size[0] * size[1] > MAX_MAP_PIXELS:
            raise ValueError(f"the map at {mm_per_px:g} mm per pixel would be {size[0]}x{size[1]} px, more than "
                             f"{MAX_MAP_PIXELS:,} pixels; choose a coarser scale")
        shrink = row_mm < mm_per_px
        return cv2.resize(image, size, interpolation=cv2.INTER_AREA if shrink else cv2.INTER_CUBIC)

    def map_coverage(self, min_weight: float = 0.05) -> np.ndarray:
        """Boolean mask, same shape as `map_image()`: pixels that enough frames contributed to."""
        if self._canvas is None:
            return np.zeros((0, 0), bool)
        return self._map_canvas().coverage(min_weight)

    def _map_canvas(self) -> _Canvas:
        """The map's canvas; before the roller first moved, one holding just the latest frame."""
        assert self._canvas is not None
        if self._pending is None:
            return self._canvas
        canvas = _Canvas(self._canvas.layers[0].shape[1], layers=len(self._canvas.layers),
                         rows=4 * self.config.band_rows)
        self._splat(canvas, self._pending)
        return canvas

    # -- setup -------------------------------------------------------------------------------------
    def setup(self, shape: tuple[int, int]) -> None:
        """Prepare for frames of `shape` (rows, columns); `band()` does it on the first frame."""
        config = self.config
        rows = config.band_rows
        if config.method == "paper":  # the paper crops the image centre; a camera only gives the scale
            sampler = BandSampler(shape, rows, None, config.centre_row, False)
            if self.camera is not None:
                scaled = BandSampler(shape, rows, self.camera, None, False)
                sampler.mm_per_px, sampler.mm_per_px_cols = scaled.mm_per_px, scaled.mm_per_px_cols
        else:
            sampler = BandSampler(shape, rows, self.camera, config.centre_row, config.rectify)
        fixed = self.flat.fixed
        if fixed is not None and fixed.shape != (rows, shape[1]):
            raise ValueError(f"flat_field shape {fixed.shape} differs from the band's {(rows, shape[1])}")
        self._shape = shape
        self._sampler = sampler
        self._canvas = _Canvas(shape[1], layers=2 if config.shaded else 1, max_rows=config.max_rows)
        self._column_weights = np.ascontiguousarray(np.repeat(self._weights[:, None], shape[1], axis=1))

    # -- the paper's method ------------------------------------------------------------------------
    def _push_paper(self, band: np.ndarray) -> StitchStep:
        assert self._canvas is not None and self._sampler is not None
        shift, confidence = self.paper.register(band)
        self._position += shift
        self._canvas.paste(band, round(self._sampler.row0 - self._position), 0)
        return StitchStep(shift, confidence, False, 0.0, self._position)

    # -- the default method ------------------------------------------------------------------------
    def finalise(self) -> None:
        """Re-weight the map with the final flat field (offline, after the last frame): the map is
        sum(w * band) / sum(w * field) at each pixel, so early frames, stitched before the field was
        known, are corrected exactly. One patch per map row where bands landed (not per frame); the
        live map skips it. Needs no per-frame history, so it works with a bounded `history`."""
        canvas = self._canvas
        if not self.config.shaded or canvas is None or self._shape is None or self._column_weights is None:
            return
        if self._pending is not None:  # the roller never moved: the map is the last frame
            self._splat(canvas, self._pending)
            self._pending, self._moved = None, True
        field = self.flat.final()
        if field is None:  # nothing moved: nothing tells the static part from the surface
            if self.config.live_map:
                return  # the live layer already holds a flat guess per band
            level = float(canvas.image().mean())  # layer 0 / row weight: the bands' mean grey
            field = np.full((self.config.band_rows, self._shape[1]), max(level, 1.0), np.float32)
        canvas.refill(1, field * self._column_weights)
        self._level = float(field.mean())

    def _bin(self, image: np.ndarray) -> np.ndarray:
        """Columns averaged in groups of `column_bin` (rows untouched)."""
        bin_ = self.config.column_bin
        if bin_ == 1:
            return image
        w = image.shape[1] // bin_
        return cv2.resize(image[:, :w * bin_], (w, image.shape[0]), interpolation=cv2.INTER_AREA)

    def _features(self, band: np.ndarray) -> tuple[np.ndarray, np.ndarray | None, np.ndarray]:
        """(registration features, flat field used, raw band): the flattened band, columns binned,
        high-passed (residual shading off)."""
        flat, field = self.flat.flatten(band, self._travel) if self.config.background else (band, None)
        highpass = self.config.highpass | 1
        feats = _highpass(self._bin(flat), highpass, max(1, highpass // self.config.column_bin) | 1)
        return feats, field, band

    def _push_default(self, band: np.ndarray, dt: int | None, prior_px: float | None) -> StitchStep:
        # Lateral shifts are read from the raw band: the flat field keeps a little texture, which would
        # hold a column profile in place, and its smooth shading is high-passed away in 1-D.
        config = self.config
        feats, field, full = self._features(band)
        energy = float(cv2.norm(feats, cv2.NORM_L1)) / feats.size
        key = self._key
        if key is None:
            self._key = _Keyframe(feats, full, _row_energy_cumsum(feats), self._position, self._lateral_pos)
            self._place(band, field, True)
            return StitchStep(0.0, 0.0, False, 0.0, self._position)
        predicted = self.predictor.predict(dt, prior_px)
        pred_rel = None if predicted is None else self._position + predicted - key.row
        # after frames moved unregistered (`_push_unregistered`) the image's shift is judged from the
        # last registered frame, against the whole motion expected since
        unregistered, unregistered_ns = self._unregistered
        self._unregistered = (0.0, 0)
        rel, confidence, cost = self._register(feats, key, pred_rel, self._position - key.row)
        lat = self._lateral_pos - key.col
        if config.lateral and rel is not None:
            lat = _lateral_shift(full, key.full, rel, lat, config.highpass | 1)
        if self._typical_energy is not None:  # far less texture than usual: a textureless stretch
            confidence *= min(1.0, energy / (_TEXTURELESS_FRACTION * self._typical_energy))
        # A key that matches this frame this badly shows something else (a no-contact band before the
        # roller touched, a jump): its shift means nothing, and the frame becomes the new key below.
        confident = rel is not None and confidence >= config.min_confidence and cost <= _MISMATCH_COST
        expected = None if predicted is None else predicted + unregistered
        if confident and rel is not None and expected is not None and abs(expected) >= 1.0 and (
                prior_px is not None or confidence < _WEAK_CONFIDENCE):
            # The arm (or, on a weak match, the recent velocity) says we roll but the image says we
            # stand still: the image sees only what does not move with the surface (a textureless
            # stretch over a dusty gel). Believe the motion. A real stop decelerates over frames.
            image_shift = key.row + rel - (self._position - unregistered)
            confident = abs(image_shift) >= _STATIC_FRACTION * abs(expected)
        if not confident or rel is None:  # trust the motion prior, or stand still when there is none
            rel = self._position + (predicted or 0.0) - key.row
            lat = self._lateral_pos - key.col
        shift = key.row + rel - self._position
        lateral = key.col + lat - self._lateral_pos if config.lateral else 0.0
        self._position += shift
        self._lateral_pos += lateral
        self._travel += abs(shift)
        if confident:
            if unregistered_ns != 0 and dt is not None and unregistered_ns is not None:
                self.predictor.update(shift + unregistered, dt + unregistered_ns)
            else:
                self.predictor.update(shift, dt)
            self._typical_energy = energy if self._typical_energy is None else (
                0.9 * self._typical_energy + 0.1 * energy)
        self._place(band, field, confident)
        if config.background:
            self.flat.learn(band, self._position)
        overlap = 1.0 - abs(rel) / config.band_rows
        if not config.keyframes or overlap < config.keyframe_overlap or not confident:
            self._key = _Keyframe(feats, full, _row_energy_cumsum(feats), self._position, self._lateral_pos)
        return StitchStep(shift, confidence, not confident and predicted is not None, lateral, self._position)

    def _push_unregistered(self, band: np.ndarray, motion: float, dt: int | None) -> StitchStep:
        """The frame moved by `motion` px (the caller's, or the recent velocity), not registered: the
        keyframe and the velocity stay; the motion is provisional until the next registered frame."""
        field = self.flat.field(self._travel) if self.config.background else None
        self._position += motion
        self._travel += abs(motion)
        done, done_ns = self._unregistered
        self._unregistered = (done + motion, None if dt is None or done_ns is None else done_ns + dt)
        self._place(band, field, True)
        if self.config.background:
            self.flat.learn(band, self._position)
        return StitchStep(motion, 0.0, True, 0.0, self._position)

    def _place(self, band: np.ndarray, field: np.ndarray | None, confident: bool) -> None:
        """Add the band to the map at the current position, unless it adds nothing.

        Until the roller first moves, only the latest frame is kept (pending): a lead-in of frames
        standing still, touching nothing or being pressed, would otherwise all land on the first rows.
        Later, a frame that registered nothing and did not move (lifted off at the end) is left out."""
        assert self._canvas is not None
        here = _Pending(band, field, self._position, self._lateral_pos)
        if not self._moved:
            if abs(self._position) < _STILL_PX:
                self._pending = here
                return
            self._moved = True
            if self._pending is not None:
                self._splat(self._canvas, self._pending)
                self._pending = None
        elif not confident and abs(self._position - self._splat_row) < _STILL_PX:
            return
        self._splat(self._canvas, here)
        self._splat_row = self._position

    def _splat(self, canvas: _Canvas, frame: _Pending) -> None:
        """Accumulate the raw band; with a background model also the flat field at the same place, so
        the map is sum(w * band) / sum(w * field): the static gain divides out pixel by pixel."""
        assert self._sampler is not None and self._column_weights is not None
        if not self.config.keep_map:
            return
        band, field = frame.band, frame.field
        top, left = self._sampler.row0 - frame.row, -frame.col
        subpixel = self.config.subpixel
        weighted_band = cv2.multiply(band, self._column_weights)
        if not self.config.shaded:
            canvas.add((weighted_band,), self._weights, top, left, subpixel=subpixel)
            return
        if not self.config.live_map:  # finalise() fills the flat-field layer
            canvas.add((weighted_band, None), self._weights, top, left, subpixel=subpixel)
            return
        if field is None:  # not known yet: a flat guess, corrected by finalise()
            weighted_field = np.full_like(band, float(band.mean())) * self._column_weights
        else:
            if self._weighted_field is None or self._weighted_field[0] is not field:
                self._weighted_field = (field, field * self._column_weights)
            weighted_field = self._weighted_field[1]
        canvas.add((weighted_band, weighted_field), self._weights, top, left, subpixel=subpixel)
        self._level = float(band.mean()) if field is None else self.flat.level(field)

    def _register(self, feats: np.ndarray, key: _Keyframe, predicted: float | None,
                  current: float) -> tuple[float | None, float, float]:
        """Row shift of `feats` relative to `key`, a confidence, and the cost (1 - NCC) there.

        `predicted` is the expected shift relative to the key (None: unknown), `current` the previous
        frame's shift relative to the key; the wide search covers current ± search.
        """
        config = self.config
        h = feats.shape[0]
        max_rel = int(h * 0.75)  # keep at least a quarter of the band overlapping
        if predicted is not None and abs(predicted) > max_rel:
            # The prediction leaves no overlap with the key (a long gap in the stream, e.g. a camera
            # stall): any match found would be a coincidence, mostly a wrong period of the weave.
            return None, 0.0, math.inf
        wide = np.arange(max(round(current) - config.search, -max_rel),
                         min(round(current) + config.search, max_rel) + 1)
        local = wide
        if predicted is not None:
            centre = round(predicted)
            half = max(2, config.local_search)
            local = np.arange(max(centre - half, -max_rel), min(centre + half, max_rel) + 1)
        candidates, costs, best = _search(feats, key.features, local, key.energy)
        if local is not wide and (best < 0 or best in (0, len(costs) - 1) or costs[best] > _MISMATCH_COST
                                  or _confidence(costs, best) < config.min_confidence):
            # The prediction was off (speed change, a dropped frame): search the whole range.
            candidates, costs, best = _search(feats, key.features, wide, key.energy)
        if best < 0:
            return None, 0.0, math.inf
        confidence = _confidence(costs, best)
        rel = float(candidates[best])
        if config.subpixel:
            rel = _lucas_kanade_rows(feats, key.features, rel + _parabola(costs, best))
        return rel, confidence, float(costs[best])


def _velocity(recent: deque[float]) -> float:
    """The median of the recent confident shifts (one bad registration does not steer it), or the
    latest if slower: a roller slowing down to stop (before lifting off) is not carried on."""
    median = statistics.median(recent)
    return recent[-1] if abs(recent[-1]) < abs(median) else median


def _search(cur: np.ndarray, key: np.ndarray, candidates: np.ndarray,
            key_sq: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray, int]:
    if candidates.size == 0:
        return candidates, np.zeros(0), -1
    costs = _ncc_costs(cur, key, candidates, min_overlap=cur.shape[0] // 4, key_sq=key_sq)
    best = int(np.nanargmin(costs)) if np.isfinite(costs).any() else -1
    return candidates, costs, best


def _sad_costs(cur: np.ndarray, prev: np.ndarray, shifts: Iterable[int], min_overlap: int) -> np.ndarray:
    """Mean |cur(i) - prev(i - d)| over the overlapping rows, for each integer d (NaN if too little overlap)."""
    h = cur.shape[0]
    out = []
    for d in shifts:
        d = int(d)
        a0, a1 = max(0, d), min(h, h + d)
        if a1 - a0 < min_overlap:
            out.append(np.nan)
            continue
        out.append(float(cv2.norm(cur[a0:a1], prev[a0 - d:a1 - d], cv2.NORM_L1)) / ((a1 - a0) * cur.shape[1]))
    return np.asarray(out, np.float64)


def _row_energy_cumsum(image: np.ndarray) -> np.ndarray:
    """Cumulative sum of squared values per row, with a leading 0: energy of rows [a, b) in O(1)."""
    return np.concatenate([[0.0], np.cumsum(np.einsum("ij,ij->i", image, image, dtype=np.float64))])


def _ncc_costs(cur: np.ndarray, key: np.ndarray, shifts: Iterable[int], min_overlap: int,
               key_sq: np.ndarray | None = None) -> np.ndarray:
    """1 - normalised cross-correlation of cur(i) and key(i - d) over the overlapping rows, for each d.

    Unlike a mean absolute difference, this does not favour the shifts whose overlap leaves out the
    textured rows of one image (a band half in a textureless stretch), and it is ~1 everywhere when
    either side has no texture. Features are high-passed, so their mean is ~0.
    """
    h = cur.shape[0]
    cur_sq = _row_energy_cumsum(cur)
    key_sq = _row_energy_cumsum(key) if key_sq is None else key_sq
    out = []
    for d in shifts:
        d = int(d)
        a0, a1 = max(0, d), min(h, h + d)
        if a1 - a0 < min_overlap:
            out.append(np.nan)
            continue
        den = math.sqrt((cur_sq[a1] - cur_sq[a0]) * (key_sq[a1 - d] - key_sq[a0 - d]))
        num = float(np.vdot(cur[a0:a1], key[a0 - d:a1 - d]))
        out.append(1.0 - num / den if den > 1e-12 else 1.0)
    return np.asarray(out, np.float64)


def _confidence(costs: np.ndarray, best: int) -> float:
    """How distinct the minimum is: 1 - min / (median cost away from it); 0 when the curve is flat."""
    c = float(costs[best])
    away = sorted(float(v) for i, v in enumerate(costs) if abs(i - best) >= 2 and v == v)
    if not away or c != c:
        return 0.0
    ref = away[len(away) // 2]
    if ref <= 1e-9:
        return 0.0
    return min(1.0, max(0.0, 1.0 - c / ref))


def _parabola(costs: np.ndarray, best: int) -> float:
    if best <= 0 or best >= len(costs) - 1:
        return 0.0
    a, b, c = costs[best - 1], costs[best], costs[best + 1]
    if not (np.isfinite(a) and np.isfinite(c)):
        return 0.0
    den = a - 2 * b + c
    if den <= 1e-12:
        return 0.0
    return min(0.5, max(-0.5, 0.5 * float(a - c) / float(den)))


def _lucas_kanade_rows(cur: np.ndarray, key: np.ndarray, rel: float, iterations: int = 2) -> float:
    """Refine cur(i) = key(i - rel) by Gauss-Newton on the overlapping rows (removes pixel locking)."""
    h, w = cur.shape
    for _ in range(iterations):
        base = math.floor(rel)
        frac = rel - base
        a0, a1 = max(0, base + 1) + 1, min(h, h + base) - 1  # rows where key(i - base - 1) is defined
        if a1 - a0 < 4:
            break
        # key(i - rel) by linear interpolation between rows i - base and i - base - 1
        k0 = key[a0 - base - 1:a1 - base + 1]  # rows (a0-1 .. a1) - base
        k1 = key[a0 - base - 2:a1 - base]  # one row earlier
        warped = (1.0 - frac) * k0 + frac * k1
        gy = 0.5 * (warped[2:] - warped[:-2])
        resid = cur[a0:a1] - warped[1:-1]
        den = float(np.vdot(gy, gy))
        if den <= 1e-9:
            break
        # cur = key(i - rel - d) ~ warped(i) - d * gy  =>  d = -sum(gy r) / sum(gy^2)
        step = min(1.0, max(-1.0, -float(np.vdot(gy, resid)) / den))
        rel += step
        if abs(step) < 1e-3:
            break
    return rel


def _profile(rows: np.ndarray, highpass: int) -> np.ndarray:
    """Column profile (mean over rows), high-passed in 1-D so smooth shading does not count."""
    profile = cv2.reduce(rows, 0, cv2.REDUCE_AVG)
    return (profile - cv2.blur(profile, (highpass, 1), borderType=cv2.BORDER_REFLECT))[0].astype(np.float64)


def _lateral_shift(cur: np.ndarray, key: np.ndarray, rel: float, guess: float, highpass: int,
                   iterations: int = 3) -> float:
    """Column shift of cur relative to key, from column profiles over the overlapping rows.

    Averaging the rows keeps what runs along the roll (yarns, ridges), which is what shows a sideways
    shift, at full column resolution and 1-D cost.
    """
    h, w = cur.shape
    d = round(rel)
    a0, a1 = max(0, d), min(h, h + d)
    if a1 - a0 < 4:
        return guess
    p_cur = _profile(cur[a0:a1], highpass)
    p_key = _profile(key[a0 - d:a1 - d], highpass)
    lat = guess
    margin = 8
    for _ in range(iterations):
        if abs(lat) > w / 4:
            return guess
        # key profile shifted by lat (linear interpolation) over columns [lo, hi), and its slope
        k = math.floor(lat)
        f = lat - k
        lo, hi = margin + abs(k) + 1, w - margin - abs(k) - 1
        base = p_key[lo - k - 1:hi - k + 1]
        before = p_key[lo - k - 2:hi - k]
        warped = (1.0 - f) * base + f * before  # columns lo-1 .. hi
        g = 0.5 * (warped[2:] - warped[:-2])
        den = float(g @ g)
        if den <= 1e-9:
            return guess
        step = min(1.0, max(-1.0, -float(g @ (p_cur[lo:hi] - warped[1:-1])) / den))
        lat += step
        if abs(step) < 0.02:  # the next step is ~100x smaller (measured): done
            break
    return lat


def stitch(images: Iterable[np.ndarray], config: StitcherConfig | None = None, *,
           camera: CameraModel | None = None, stamps: Sequence[int] | None = None,
           priors: Sequence[float | None] | None = None, two_pass: bool = True) -> tuple[np.ndarray, list[StitchStep]]:
    """Stitch a sequence of frames; returns (uint8 map, one StitchStep per frame).

    Without `stamps` frames are taken as 30 fps. With `two_pass` (default method, background on) the
    flat field is estimated from all frames first, as an offline tool can; a recording too short for
    the texture to average out of it is stitched with the live estimate instead. Every frame's
    StitchStep is kept whatever `config.history` says.
    """
    config = (config or StitcherConfig()).replace(history=None, max_rows=None)
    probe = Stitcher(config, camera=camera)
    bands = [probe.band(image) for image in images]
    if not bands or probe._shape is None:
        return probe.map_image(), []
    shape = probe._shape

    def run(flat_field: np.ndarray | None) -> Stitcher:
        stitcher = Stitcher(config, camera=camera, flat_field=flat_field)
        stitcher.setup(shape)
        for i, band in enumerate(bands):
            stamp = stamps[i] if stamps is not None else i * DEFAULT_FRAME_NS
            stitcher.push_band(band, stamp, priors[i] if priors is not None else None)
        return stitcher

    flat = estimate_flat_field(bands) if two_pass and config.shaded else None
    stitcher = run(flat)
    if flat is not None and abs(stitcher.position_px) < 2 * config.band_rows:
        stitcher = run(None)
    stitcher.finalise()
    return stitcher.map_image(), list(stitcher.steps)
