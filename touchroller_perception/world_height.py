"""The world height map: each pressed frame's relief in metres, placed in the world as the intensity is.

Per frame (`BandHeights`, stateless once built, so a node may cut it in another thread):

1. slopes from the photometric model (`touchroller_perception.height`) over the image rows the contact can
   reach and some beyond it (`contact_band` of `band_depth`): rows whose membrane a press of that depth
   cannot reach;
2. integrated to the membrane's indentation D (m, into the gel) by an exact DCT solver (by default of the
   pixels' mean slopes over their footprints, `footprint_integrate`, `WorldHeightConfig.slopes`), its constant
   set by those outer rows, where the membrane is undeformed (D = 0): a robust best plane through them is 0;
3. resampled onto the world mapper's band (the strip stitcher's `BandSampler`: rows uniform in membrane y,
   columns in x, the contact patch pressed flat), and turned into the surface's relief: under a flat press
   at depth d the membrane at band row y is indented d - (r - sqrt(r^2 - y^2)), so relief = D + r -
   sqrt(r^2 - y^2) - d; the unknown d (and a tilt of the surface) goes with the pass's best plane (below).
   Band pixels indented less than `min_indentation` are not in contact (a valley the membrane did not
   reach): no height there.
4. the band rows' static error (the press shape as the model reads it: each row's relief against the frame's
   mean, averaged over the frames placed, `HeightLayer.observe`) is taken out once `row_frames` frames are in.

Per pass (`HeightLayer`, on two pairs of named float32 layers of the mapper's tiled canvas: the pass being
rolled, and what earlier passes left): the pass's frames are accumulated as weighted sums (the intensity's
weights times the contact), and when the pass ends its height is levelled: its best plane is removed (the press depth
and the surface's tilt under the roller), then it is levelled against the earlier passes where they overlap
(their difference's median, and its tilt along the directions the overlap spans), and added to them.
The result is the relief relative to the surface's base plane under the roller, float32 metres, NaN
where nothing was mapped. No rclpy here.
"""
from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass
from typing import Any

import cv2
import numpy as np

from touchroller_perception.geometry import CameraModel
from touchroller_perception.height.estimate import contact_band, level_plane
from touchroller_perception.height.integrate import column_heights, footprint_integrate, integrate
from touchroller_perception.height.photometric import PhotometricModel, SlopeLookup

#: the canvas's named layers the height uses (float32 tiles): sum(w h) and sum(w) of the passes done,
#: then of the pass being rolled
DONE, DONE_W, PASS, PASS_W = "height_done", "height_done_w", "height_pass", "height_pass_w"
HEIGHT_LAYERS = (DONE, DONE_W, PASS, PASS_W)
#: `WorldHeightConfig.resampling`: how a frame's relief goes onto the map grid -> OpenCV's interpolation for the
#: relief itself (None: the weighted relief splatted bilinearly with the intensity's placement)
RESAMPLING: dict[str, int | None] = {"cubic": cv2.INTER_CUBIC, "lanczos4": cv2.INTER_LANCZOS4, "linear": None}
#: `WorldHeightConfig.slopes`: what a pixel's slope is taken to be when a frame's slopes are integrated
SLOPES = ("footprint", "centre")


@dataclass(frozen=True)
class WorldHeightConfig:
    """How each frame's height is made and passes are levelled; the perception node's `map.height.*`
    parameters map onto these fields.

    band_depth: the rows integrated are those a press this deep reaches (m); the rows beyond the actual
      press (undeformed membrane) give the zero. More than the scan's press depth.
    outer_fraction: the rows at either end of those, this fraction each, are taken as undeformed.
    min_indentation: band pixels indented less than this are not in contact (no height there), m.
    min_weight: a map cell has a height where its summed weight is at least this (the intensity's 0.05).
    min_overlap: cells two passes must share to be levelled against each other (else only the plane).
    axis_sigma: along the roller's axis, the height's variation slower than a Gaussian of this sigma
      (px) comes from each column's own slopes across the band, summed from the undeformed rows on
      either side (their closure removed), not from integrating along the axis: a slope bias along a
      640-pixel band integrates to tens of micrometres, across the band it cannot. 0: the 2-D solution.
    smoothing: the image's smoothing (Gaussian sigma, px) before the colour features when a frame's slopes are
      read; None: the photometric model's own (what it was calibrated with). The calibration's smoothing
      denoises its fit, where a ball's slopes change slowly; the map averages some twenty frames per cell, so it
      can read with less and keep more of the relief a few pixels across (a Gaussian of 1 px keeps 0.29 of a
      4-pixel wavelength's depth, one of 0.5 px 0.73) for more noise per frame.
    follow_arm: each frame's relief is raised by the roller's height above its pressed height (the arm's pose,
      given to `HeightLayer.planes`): a press that deepens or eases along a pass (the roller touching down or
      lifting off at speed) is not read as relief. False: the press depth is taken as constant along a pass.
    row_frames: the band's rows' static error is taken out of each frame's relief once this many frames have been
      averaged (0: never). Every frame presses the same membrane shape, so what its relief reads per band row
      (the row's mean over its contact against the frame's mean), averaged over the frames mapped, is the
      model's error of that shape (the pressed cylinder read a few per cent too shallow or deep by a slope gain
      that is not quite 1, a tilt across the rows from a slope bias), not the surface, which moves under the
      band. Inside a pass each cell is crossed by all of the band's rows and the error averages to a constant
      the pass's plane takes; where the band does not cross a cell whole (a pass's ends, the cells only its
      leading or trailing rows reach) it stays, unless it is taken out. The frames before it is known are
      placed as read.
    slopes: what a pixel's slope is, for the integration (`SLOPES`). "footprint": the mean slope over the pixel's
      area (a camera's pixel gathers the light of its whole footprint), i.e. the height's difference across the
      pixel, averaged across it; integrated by `footprint_integrate`, exact at every wavelength the pixels hold.
      "centre": the slope at the pixel's centre, two neighbours averaged into the difference between their
      centres (`height.integrate`'s model): of footprint slopes it keeps cos(pi / wavelength in px) of the
      depth (0.5 at 3 px, 0.71 at 4, 0.87 at 6), a fine relief read shallow.
    resampling: how a frame's relief is put on the map grid (`RESAMPLING`). "cubic" / "lanczos4": the relief is
      interpolated onto the map's cells (OpenCV's bicubic, a = -0.75, or its 8x8 Lanczos) and multiplied there by
      the weights placed bilinearly (weights stay non-negative and do not blur the relief); "linear": the product
      of weight and relief splatted bilinearly as the intensity is (a tent kernel: averaged over a pass's
      sub-pixel phases it keeps sinc^2 of a wavelength, 0.85 of a 4.5-cell one, and along the axis, where a
      pass's phase stays put, as little as cos(pi / wavelength), 0.77, at half a cell).
    """

    band_depth: float = 1.2e-3
    outer_fraction: float = 0.12
    min_indentation: float = 1e-5
    min_weight: float = 0.05
    min_overlap: int = 400
    axis_sigma: float = 20.0
    smoothing: float | None = 0.5
    follow_arm: bool = True
    resampling: str = "lanczos4"
    row_frames: int = 30
    slopes: str = "footprint"

    def __post_init__(self) -> None:
        if not (math.isfinite(self.band_depth) and 0 < self.band_depth < 0.01):
            raise ValueError(f"band_depth must be in (0, 0.01) m, got {self.band_depth}")
        if not (math.isfinite(self.outer_fraction) and 0.02 <= self.outer_fraction <= 0.4):
            raise ValueError(f"outer_fraction must be in [0.02, 0.4], got {self.outer_fraction}")
        if not (math.isfinite(self.min_indentation) and self.min_indentation >= 0):
            raise ValueError(f"min_indentation must be >= 0 m, got {self.min_indentation}")
        if not (math.isfinite(self.min_weight) and self.min_weight > 0):
            raise ValueError(f"min_weight must be > 0, got {self.min_weight}")
        if not (math.isfinite(self.axis_sigma) and 0 <= self.axis_sigma <= 200):
            raise ValueError(f"axis_sigma must be in [0, 200] px, got {self.axis_sigma}")
        if self.min_overlap < 10:
            raise ValueError(f"min_overlap must be >= 10 cells, got {self.min_overlap}")
        if not (isinstance(self.row_frames, int) and 0 <= self.row_frames <= 1_000_000):
            raise ValueError(f"row_frames must be an int in [0, 1000000] (0: off), got {self.row_frames!r}")
        if self.slopes not in SLOPES:
            raise ValueError(f"slopes must be one of {', '.join(SLOPES)}, got {self.slopes!r}")
        if self.resampling not in RESAMPLING:
            raise ValueError(f"resampling must be one of {', '.join(RESAMPLING)}, got {self.resampling!r}")
        if self.smoothing is not None and not (math.isfinite(self.smoothing) and 0 <= self.smoothing <= 20):
            raise ValueError(f"smoothing must be in [0, 20] px or None (the model's own), got {self.smoothing}")


@dataclass(frozen=True)
class HeightBand:
    """One frame's relief on the world mapper's band: metres (float32, or float16 while held long) and
    where it is in contact (bool), both the band's shape."""

    relief: np.ndarray
    contact: np.ndarray

    def compact(self) -> HeightBand:
        """The same in half the memory (float16 metres: steps of half a micrometre below a millimetre)."""
        return self if self.relief.dtype == np.float16 else HeightBand(self.relief.astype(np.float16), self.contact)


@dataclass(frozen=True)
class HeightMapLayer:
    """The world height map: float32 metres (rows growing with y, as the canvas), NaN where unmapped;
    `origin` the world (x, y) of cell (0, 0)'s lower-left corner, `resolution` m per cell."""

    height: np.ndarray
    origin: tuple[float, float]
    resolution: float


class BandHeights:
    """Per-frame relief on the mapper's band. `sampler`: the world mapper's band sampler (the strip
    stitcher's `BandSampler`, rectified through the camera model)."""

    def __init__(self, model: PhotometricModel, reference: np.ndarray, camera: CameraModel, sampler: Any,
                 config: WorldHeightConfig | None = None) -> None:
        self.config = config = config or WorldHeightConfig()
        reference = np.asarray(reference)
        if reference.ndim != 3 or reference.shape[2] != 3:
            raise ValueError(f"the height reference must be a colour image (H x W x 3), got shape {reference.shape}")
        if (reference.shape[1], reference.shape[0]) != (model.width, model.height):
            raise ValueError(f"the reference is {reference.shape[1]}x{reference.shape[0]} but the photometric "
                             f"model was calibrated on {model.width}x{model.height} images")
        if (camera.width, camera.height) != (model.width, model.height):
            raise ValueError(f"the camera is {camera.width}x{camera.height} but the photometric model was "
                             f"calibrated on {model.width}x{model.height} images")
        if sampler is None or sampler.maps is None or sampler.mm_per_px is None:
            raise ValueError("a world height map needs the rectified band (the camera model's default method)")
        band = contact_band(camera, config.band_depth)
        s0, s1 = sampler.src_rows
        self.rows = (min(band.rows[0], s0), max(band.rows[1], s1))   # the sampler's rows inside, always
        self.src_offset = s0 - self.rows[0]
        self.pixel_size = band.pixel_size
        if config.smoothing is not None:   # read with another smoothing than the model was calibrated with
            model = dataclasses.replace(model, config=dataclasses.replace(model.config, smoothing=config.smoothing))
        self.lookup: SlopeLookup = model.compile(reference)
        self.maps = (sampler.maps[0], sampler.maps[1] + np.float32(self.src_offset))
        n = self.rows[1] - self.rows[0]
        k = max(2, round(config.outer_fraction * n))
        self.outer = np.zeros((n, reference.shape[1]), bool)
        self.outer[:k] = True
        self.outer[-k:] = True
        r = float(camera.radius)
        ys = (np.arange(sampler.rows) - (sampler.rows - 1) / 2.0) * sampler.mm_per_px * 1e-3
        self.cylinder = (r - np.sqrt(r * r - ys * ys)).astype(np.float32)[:, None]   # m below the contact line

    def indentation(self, image: np.ndarray, row0: int = 0) -> np.ndarray:
        """D (float32 m, into the gel) over `rows` of the frame, or of the frame's rows from `row0` on."""
        v0, v1 = self.rows
        image = np.asarray(image)
        if v0 < row0 or v1 - row0 > image.shape[0]:
            raise ValueError(f"the height needs frame rows {v0} to {v1}, got {row0} to {row0 + image.shape[0]}")
        gx, gy = self.lookup.slopes(image[v0 - row0:v1 - row0], rows=slice(v0, v1))
        if self.config.slopes == "footprint":
            z = footprint_integrate(gx, gy, self.pixel_size)
        else:
            z = integrate(gx, gy, self.pixel_size, dtype=np.float32)
        z -= level_plane(z, self.outer)
        sigma = self.config.axis_sigma
        if sigma <= 0:
            return z
        # each column on its own, from its slopes across the band, zero on the outer rows
        column = column_heights(gy, self.pixel_size[1], self.config.slopes)
        column -= column[self.outer[:, 0]].mean(axis=0, keepdims=True)
        # the slow variation along the axis from the columns, the rest from the whole surface
        kernel = cv2.getGaussianKernel(int(6 * sigma) | 1, sigma, cv2.CV_32F)
        one = np.ones((1, 1), np.float32)

        def along(a: np.ndarray) -> np.ndarray:
            return cv2.sepFilter2D(a, cv2.CV_32F, kernel, one, borderType=cv2.BORDER_REFLECT)

        return along(column) + z - along(z)

    def __call__(self, image: np.ndarray, row0: int = 0) -> HeightBand:
        depth = self.indentation(image, row0)
        band = cv2.remap(depth, self.maps[0], self.maps[1], cv2.INTER_CUBIC, borderMode=cv2.BORDER_CONSTANT,
                         borderValue=0.0)
        contact = band > self.config.min_indentation
        return HeightBand(np.add(band, self.cylinder, dtype=np.float32), contact)


def _plane(values: np.ndarray, weights: np.ndarray, mask: np.ndarray, step: int = 4) -> np.ndarray:
    """Coefficients (c, a_col, b_row) of the weighted least-squares plane through values over mask
    (a 1-in-`step` grid of it, or every cell when that is too few)."""
    h, w = values.shape
    rr, cc = np.mgrid[0:h:step, 0:w:step]
    sub = mask[::step, ::step]
    z, wt = values[::step, ::step][sub], weights[::step, ::step][sub]
    if len(z) < 3:
        (rr, cc), sub = np.mgrid[0:h, 0:w], mask
        z, wt = values[sub], weights[sub]
    r, c = rr[sub].astype(np.float64), cc[sub].astype(np.float64)
    if len(z) < 3:
        return np.zeros(3)
    sw = np.sqrt(np.asarray(wt, np.float64))
    A = np.c_[np.ones(len(z)), c, r] * sw[:, None]
    coef, *_ = np.linalg.lstsq(A, np.asarray(z, np.float64) * sw, rcond=None)
    return np.asarray(coef, np.float64)


def _plane_values(coef: np.ndarray, shape: tuple[int, int]) -> np.ndarray:
    rows = np.arange(shape[0], dtype=np.float32)[:, None]
    cols = np.arange(shape[1], dtype=np.float32)[None, :]
    out: np.ndarray = np.float32(coef[0]) + np.float32(coef[1]) * cols + np.float32(coef[2]) * rows
    return out


class HeightLayer:
    """The height's share of the canvas: its four named layers (`HEIGHT_LAYERS`, made by `add_layers`), a
    pass's frames added with `add` (`pass_planes`), levelled and added to the earlier passes with `end_pass`
    over the window the pass reached (its tiles), never the whole map."""

    def __init__(self, config: WorldHeightConfig | None = None) -> None:
        self.config = config or WorldHeightConfig()
        self.passes = 0
        self.levelled: list[tuple[float, float, float]] = []   # per pass: plane removed at the pass's centre
        # (m), offset against the earlier passes (m), overlap cells
        # the band rows' relief against their frame's mean, summed over the frames observed, and how many
        self._row_sum: np.ndarray | None = None
        self._row_count: np.ndarray | None = None
        self.row_frames = 0
        self._row_error: np.ndarray | None = None   # (rows, 1) float32, once `row_frames` frames are in

    def observe(self, band: HeightBand) -> None:
        """Add a placed frame's relief per band row (each row's mean over its contact, against the frame's mean
        over its rows in contact over at least half the band) to the rows' static error (`row_frames`)."""
        if self.config.row_frames <= 0:
            return
        contact = band.contact
        rows, cols = contact.shape
        counts = np.count_nonzero(contact, axis=1)
        held = counts >= 0.5 * cols
        if int(np.count_nonzero(held)) < max(3, rows // 2):   # barely pressed (touching down, lifting off)
            return
        sums = np.where(contact, band.relief, np.float32(0.0)).sum(axis=1, dtype=np.float64)
        means = sums[held] / counts[held]
        if not np.isfinite(means).all():
            return
        if self._row_sum is None or self._row_sum.shape != (rows,):
            self._row_sum, self._row_count, self.row_frames = np.zeros(rows), np.zeros(rows), 0
        assert self._row_count is not None
        self._row_sum[held] += means - float(means.mean())
        self._row_count[held] += 1
        self.row_frames += 1
        if self.row_frames >= self.config.row_frames:
            seen = self._row_count > 0
            error = np.zeros(rows)
            error[seen] = self._row_sum[seen] / self._row_count[seen]
            error[seen] -= float(np.average(error[seen], weights=self._row_count[seen]))
            self._row_error = error.astype(np.float32)[:, None]

    def row_error(self) -> np.ndarray | None:
        """The band rows' static error (float32 m, (rows, 1)), None until `row_frames` frames were observed."""
        return self._row_error

    @staticmethod
    def add_layers(canvas: Any) -> None:
        for name in HEIGHT_LAYERS:
            canvas.add_layer(name, np.float32)

    def planes(self, weights: np.ndarray, band: HeightBand, lift: float = 0.0) -> tuple[np.ndarray, np.ndarray]:
        """(w relief, w) in band coordinates for the pass layers: weight zero where not in contact. `lift`: the
        roller's height above its pressed height when the frame was taken (m, the arm's pose), added to the
        relief with `follow_arm` (the frame was pressed that much less deep)."""
        w = self.contact_weights(weights, band)
        return cv2.multiply(self.relief(band, lift), w), w

    @staticmethod
    def contact_weights(weights: np.ndarray, band: HeightBand) -> np.ndarray:
        """The band's weights where it is in contact, zero elsewhere (the `w` of `planes`)."""
        return np.where(band.contact, weights, np.float32(0.0))

    def relief(self, band: HeightBand, lift: float = 0.0) -> np.ndarray:
        """The band's relief (float32 m), the rows' static error taken out once known (`row_error`), with the
        roller's `lift` added under `follow_arm` (see `planes`)."""
        relief = band.relief.astype(np.float32, copy=False)
        if self._row_error is not None and self._row_error.shape[0] == relief.shape[0]:
            relief = relief - self._row_error
        if self.config.follow_arm and lift and math.isfinite(lift):
            relief = relief + np.float32(lift)
        return relief

    @staticmethod
    def pass_planes(weighted: np.ndarray | None, weights: np.ndarray | None) -> dict[str, np.ndarray | None]:
        """`planes` on the map grid, by layer name, for `WorldCanvas.add_named`."""
        return {PASS: weighted, PASS_W: weights}

    def end_pass(self, canvas: Any) -> None:
        """Level the pass just rolled (its best plane, then against the earlier passes) and add it to them.
        Reads and writes only the window of the tiles the pass reached; the pass's tiles are then dropped."""
        store = canvas.store
        touched = store.tiles(PASS_W)
        try:
            if touched:
                t = store.tile
                ix0, ix1 = min(i for i, _ in touched), max(i for i, _ in touched) + 1
                iy0, iy1 = min(j for _, j in touched), max(j for _, j in touched) + 1
                self._level_pass(store, (iy0 * t, iy1 * t, ix0 * t, ix1 * t), touched)
        finally:   # the pass's sums go with their tiles (memory and spill files), also when it did not fit
            for name in (PASS, PASS_W):
                store.drop_layer(name)
                store.add_layer(name, np.float32)

    def _level_pass(self, store: Any, box: tuple[int, int, int, int], touched: set[tuple[int, int]]) -> None:
        r0, r1, c0, c1 = box   # absolute cells of the store: the tiles `touched` span
        sums, weight = store.read(PASS, r0, r1, c0, c1), store.read(PASS_W, r0, r1, c0, c1)
        mine = weight >= self.config.min_weight
        if int(np.count_nonzero(mine)) < 3:
            return
        done, done_w = store.read(DONE, r0, r1, c0, c1), store.read(DONE_W, r0, r1, c0, c1)
        height = np.divide(sums, weight, out=np.zeros_like(sums), where=mine)
        coef = _plane(height, weight, mine)
        height -= _plane_values(coef, height.shape)
        theirs = done_w >= self.config.min_weight
        both = mine & theirs
        offset, shared = 0.0, int(np.count_nonzero(both))
        if shared >= self.config.min_overlap:
            before = np.divide(done, done_w, out=np.zeros_like(done), where=theirs)
            height += _plane_values(self._level(before - height, both), height.shape)
            offset = float(np.median((before - height)[both]))   # what is left: ~0 once levelled
        centre = _plane_values(coef, height.shape)[mine].mean()
        self.levelled.append((float(centre), offset, shared))
        height[~mine] = 0.0
        added_w = np.where(mine, weight, np.float32(0.0))
        # room for both sums' new tiles first (StorageFull: neither is added, the finished passes kept); only
        # the pass's own tiles (its window's others hold nothing of it)
        store.reserve([(name, ix, iy) for name in (DONE, DONE_W) for ix, iy in touched])
        weighted = height * added_w
        t = store.tile
        for ix, iy in touched:
            part = (slice(iy * t - r0, (iy + 1) * t - r0), slice(ix * t - c0, (ix + 1) * t - c0))
            store.add(DONE, weighted[part], iy * t, ix * t, reserved=True)
            store.add(DONE_W, added_w[part], iy * t, ix * t, reserved=True)
        self.passes += 1

    @staticmethod
    def _level(difference: np.ndarray, both: np.ndarray) -> np.ndarray:
        """The plane (c, a_col, b_row) to add to a pass to meet the earlier ones where they overlap: the
        difference's median, and its tilt along the rows or columns where the overlap spans at least
        a quarter of its bounding box's diagonal (a thin overlap holds only an offset)."""
        rows, cols = np.nonzero(both)
        values = difference[both].astype(np.float64)
        centre = float(np.median(values))
        span_r, span_c = float(np.ptp(rows)), float(np.ptp(cols))
        extent = math.hypot(span_r, span_c)
        coef = np.array([centre, 0.0, 0.0])
        free = [span_c >= 0.25 * extent and span_c > 20, span_r >= 0.25 * extent and span_r > 20]
        if any(free):
            r, c = rows - rows.mean(), cols - cols.mean()
            columns = [np.ones(len(values))] + [x for x, f in zip((c, r), free, strict=True) if f]
            A = np.stack(columns, axis=1)
            keep = np.abs(values - centre) <= 3.0 * (1.4826 * float(np.median(np.abs(values - centre))) + 1e-9)
            solution, *_ = np.linalg.lstsq(A[keep], values[keep], rcond=None)
            slopes = iter(solution[1:])
            a = float(next(slopes)) if free[0] else 0.0
            b = float(next(slopes)) if free[1] else 0.0
            coef = np.array([float(solution[0]) - a * cols.mean() - b * rows.mean(), a, b])
        return coef

    def view(self, canvas: Any) -> Any:
        """The finished passes' height as a `tiles.LayerView` (`WorldCanvas.ratio_view`): metres where their
        summed weight is at least `min_weight`, weighted by it; what `geotiff.write_geotiff(..., "float")`
        writes (height.tif) a tile at a time, over the same cells as the intensity's files."""
        return canvas.ratio_view(DONE, DONE_W, weight=DONE_W, min_denominator=self.config.min_weight)

    def value_in(self, canvas: Any, box: tuple[int, int, int, int]) -> np.ndarray:
        """float32 metres over rows [row0, row1) and columns [column0, column1) of the canvas, NaN where no
        finished pass mapped (the pass being rolled is not in it until it ends)."""
        done_w = canvas.read(DONE_W, box)
        known = done_w >= self.config.min_weight
        out = np.full(done_w.shape, np.nan, np.float32)
        np.divide(canvas.read(DONE, box), done_w, out=out, where=known)
        return out

    def value(self, canvas: Any) -> np.ndarray:
        """`value_in` over the whole canvas."""
        return self.value_in(canvas, (0, canvas.shape[0], 0, canvas.shape[1]))

    def layer(self, canvas: Any, box: tuple[int, int, int, int] | None = None) -> HeightMapLayer | None:
        """The height map with its placement (over `box` of the canvas, else all of it); None when nothing
        has a height yet."""
        if self.passes == 0:
            return None
        box = box or (0, canvas.shape[0], 0, canvas.shape[1])
        res = canvas.resolution
        origin = (canvas.origin[0] + box[2] * res, canvas.origin[1] + box[0] * res)
        return HeightMapLayer(self.value_in(canvas, box), origin, res)


@dataclass(frozen=True)
class HeightSource:
    """What a world mapper needs for a height map: the photometric model, its no-contact reference frame
    (the sensor's, colour, the model's size) and how heights are made and levelled."""

    model: PhotometricModel
    reference: np.ndarray
    config: WorldHeightConfig = WorldHeightConfig()
