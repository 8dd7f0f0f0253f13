"""The second generator's surfaces: height fields (metres) synthesised here, placed in `base`.

Four kinds, each a height field on a square grid of `resolution` (m) plus the features planted on it:

* `grained`: isotropic band-limited noise (a Gaussian random field whose spectrum is a ring between two
  wavelengths, made by filtering white noise in the Fourier domain), a few tens of micrometres RMS,
  with grooves and pits planted on top;
* `panel`: a smooth painted panel: a micrometre-scale orange peel (long wavelengths only) with a few
  cracks (narrow V-grooves along polylines) and dents (shallow spherical caps);
* `glass`: glass-smooth: a sub-micrometre waviness and the same kind of planted cracks and dents;
* `weave`: a periodic plain weave (warp and weft threads as raised cosine lobes that alternate over and
  under), `weave_period` (m) between threads, with slight thread-to-thread irregularity.

Nothing here comes from the simulator (`touchroller_driver.sim`): its surfaces are image-based and
shaded there; these are heights, shaded by `render`.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numpy as np

KINDS = ("grained", "panel", "glass", "weave")


@dataclass(frozen=True)
class Feature:
    """A planted feature, in `base` (m): a crack (a groove from `start` to `end`) or a dent / pit (a cap
    of `radius` around `start`, `end` equal to `start`). `depth` (m, > 0 is into the surface)."""

    kind: str            # "crack", "groove", "dent" or "pit"
    start: tuple[float, float]
    end: tuple[float, float]
    width: float         # m: the groove's width, or the dent's diameter
    depth: float

    @property
    def centre(self) -> tuple[float, float]:
        return (0.5 * (self.start[0] + self.end[0]), 0.5 * (self.start[1] + self.end[1]))


@dataclass(frozen=True)
class Surface:
    """`height` (rows, cols) m, row r / column c at surface-frame (x, y) = ((c + 0.5) res, (r + 0.5) res);
    the surface frame sits at `origin` (x, y, z of its corner, m) in `base`, turned by `yaw` (rad) about z.
    The surface's mean plane is at base z = origin[2]."""

    kind: str
    height: np.ndarray
    resolution: float
    origin: tuple[float, float, float]
    yaw: float
    features: tuple[Feature, ...]
    weave_period: float | None = None

    def to_surface(self, xy: np.ndarray) -> np.ndarray:
        """Base (x, y) (..., 2) -> surface-frame grid coordinates (column, row) as floats (..., 2)."""
        c, s = math.cos(self.yaw), math.sin(self.yaw)
        dx, dy = xy[..., 0] - xy.dtype.type(self.origin[0]), xy[..., 1] - xy.dtype.type(self.origin[1])
        scale = xy.dtype.type(1.0 / self.resolution)
        return np.stack([(xy.dtype.type(c) * dx + xy.dtype.type(s) * dy) * scale - xy.dtype.type(0.5),
                         (xy.dtype.type(-s) * dx + xy.dtype.type(c) * dy) * scale - xy.dtype.type(0.5)], axis=-1)

    def to_base(self, surface_xy: np.ndarray) -> np.ndarray:
        """Surface-frame metres (..., 2) -> base (x, y)."""
        c, s = math.cos(self.yaw), math.sin(self.yaw)
        x, y = surface_xy[..., 0], surface_xy[..., 1]
        return np.stack([self.origin[0] + c * x - s * y, self.origin[1] + s * x + c * y], axis=-1)

    def sample(self, xy: np.ndarray, height: np.ndarray | None = None) -> np.ndarray:
        """Bilinear samples of `height` (the surface's own by default) at base points (..., 2); 0 outside."""
        xy = np.asarray(xy)
        grid = self.to_surface(xy if xy.dtype == np.float32 else xy.astype(np.float64)).astype(np.float32)
        field = self.height if height is None else height
        shape = grid.shape[:-1]
        if grid.ndim != 3:   # remap wants a 2-D map of fewer than 32767 columns
            count = int(np.prod(shape))
            cols = 1024
            padded = np.zeros((-(-count // cols) * cols, 2), np.float32)
            padded[:count] = grid.reshape(-1, 2)
            grid = padded.reshape(-1, cols, 2)
        out = cv2.remap(field, grid[..., 0], grid[..., 1], cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT,
                        borderValue=0.0)
        return out.reshape(-1)[:int(np.prod(shape))].reshape(shape)


def ring_noise(shape: tuple[int, int], resolution: float, short: float, long: float,
               rng: np.random.Generator) -> np.ndarray:
    """Zero-mean, unit-RMS Gaussian field whose spectrum fills wavelengths [short, long] (m), smooth edges."""
    white = rng.standard_normal(shape)
    fy = np.fft.fftfreq(shape[0], resolution)[:, None]
    fx = np.fft.rfftfreq(shape[1], resolution)[None, :]
    f = np.hypot(fx, fy)
    lo, hi = 1.0 / long, 1.0 / short
    # raised-cosine shoulders one octave wide on each side
    f = np.maximum(f, 1e-12)
    gain = np.clip(np.log2(f / (lo / 2)), 0, 1) * np.clip(np.log2(2 * hi / f), 0, 1)
    gain = np.sin(0.5 * np.pi * gain) ** 2
    field = np.fft.irfft2(np.fft.rfft2(white) * gain, s=shape)
    std = float(field.std()) or 1.0
    return (field / std).astype(np.float32)


def _plant(height: np.ndarray, resolution: float, feature_local: tuple[str, tuple[float, float], tuple[float, float],
           float, float]) -> None:
    """Cut one feature (kind, start, end, width, depth in surface-frame metres) into `height` in place."""
    kind, start, end, width, depth = feature_local
    rows, cols = height.shape
    half = width / 2 + 3 * resolution
    x0, x1 = min(start[0], end[0]) - half, max(start[0], end[0]) + half
    y0, y1 = min(start[1], end[1]) - half, max(start[1], end[1]) + half
    c0, c1 = max(int(x0 / resolution), 0), min(int(x1 / resolution) + 2, cols)
    r0, r1 = max(int(y0 / resolution), 0), min(int(y1 / resolution) + 2, rows)
    if c0 >= c1 or r0 >= r1:
        return
    xs = (np.arange(c0, c1) + 0.5) * resolution
    ys = (np.arange(r0, r1) + 0.5) * resolution
    xx, yy = np.meshgrid(xs, ys)
    if kind in ("crack", "groove"):
        a, b = np.array(start), np.array(end)
        d = b - a
        t = np.clip(((xx - a[0]) * d[0] + (yy - a[1]) * d[1]) / float(d @ d), 0.0, 1.0)
        dist = np.hypot(xx - (a[0] + t * d[0]), yy - (a[1] + t * d[1]))
        profile = np.clip(1.0 - dist / (width / 2), 0.0, 1.0)          # a V-groove
        if kind == "groove":
            profile = np.sqrt(profile)                                    # a rounder, milled groove
        cut = depth * profile
    else:                                                                 # dent / pit: a spherical cap
        rho2 = (xx - start[0]) ** 2 + (yy - start[1]) ** 2
        cut = depth * np.clip(1.0 - rho2 / (width / 2) ** 2, 0.0, 1.0)
        if kind == "pit":
            cut = np.sqrt(cut * depth)
    height[r0:r1, c0:c1] -= cut.astype(np.float32)


def make_surface(kind: str, size: tuple[float, float], origin: tuple[float, float, float], yaw: float = 0.0,
                 resolution: float = 5e-5, seed: int = 0, weave_period: float = 1.2e-3,
                 features: int = 8, feature_margin: float = 0.02) -> Surface:
    """A `kind` surface of `size` (m along its x, y), its corner at `origin` in base, turned `yaw`; `features`
    planted at random at least `feature_margin` (m) in from its edges (4 dents on a weave)."""
    if kind not in KINDS:
        raise ValueError(f"unknown surface kind {kind!r} (one of {', '.join(KINDS)})")
    rng = np.random.default_rng(np.random.SeedSequence([seed, 2204]))
    shape = (int(math.ceil(size[1] / resolution)), int(math.ceil(size[0] / resolution)))
    if kind == "grained":
        height = 20e-6 * ring_noise(shape, resolution, 0.4e-3, 2.0e-3, rng) \
            + 6e-6 * ring_noise(shape, resolution, 2.0e-3, 10e-3, rng)
    elif kind == "panel":      # orange peel: a few micrometres, long wavelengths only
        height = 2.0e-6 * ring_noise(shape, resolution, 2.0e-3, 15e-3, rng)
    elif kind == "glass":
        height = 0.2e-6 * ring_noise(shape, resolution, 5.0e-3, 30e-3, rng)
    else:
        height = _weave(shape, resolution, weave_period, rng)
    height = height.astype(np.float32)
    planted = []
    margin = feature_margin if min(size) > 2.5 * feature_margin else 0.25 * min(size)   # a small surface: its middle
    for k in range(features if kind != "weave" else min(features, 4)):
        cx, cy = rng.uniform(margin, size[0] - margin), rng.uniform(margin, size[1] - margin)
        if kind == "grained":
            feature_kind = "groove" if k % 2 == 0 else "pit"
        elif kind == "weave":
            feature_kind = "dent"
        else:
            feature_kind = "crack" if k % 2 == 0 else "dent"
        if feature_kind in ("crack", "groove"):
            length = rng.uniform(0.006, 0.02)
            angle = rng.uniform(0, math.pi)
            half = 0.5 * length * np.array([math.cos(angle), math.sin(angle)])
            start, end = (cx - half[0], cy - half[1]), (cx + half[0], cy + half[1])
            width = rng.uniform(0.15e-3, 0.3e-3) if feature_kind == "crack" else rng.uniform(0.4e-3, 0.7e-3)
            depth = rng.uniform(15e-6, 40e-6)
        else:
            start = end = (cx, cy)
            width = rng.uniform(0.8e-3, 1.6e-3)
            depth = rng.uniform(8e-6, 20e-6) if feature_kind == "dent" else rng.uniform(25e-6, 50e-6)
        _plant(height, resolution, (feature_kind, start, end, width, depth))
        planted.append((feature_kind, start, end, width, depth))
    c, s = math.cos(yaw), math.sin(yaw)

    def in_base(p: tuple[float, float]) -> tuple[float, float]:
        return (float(origin[0] + c * p[0] - s * p[1]), float(origin[1] + s * p[0] + c * p[1]))

    placed = tuple(Feature(kind_, in_base(a), in_base(b), float(w), float(d)) for kind_, a, b, w, d in planted)
    return Surface(kind, height, resolution, (float(origin[0]), float(origin[1]), float(origin[2])), float(yaw),
                   placed, weave_period if kind == "weave" else None)


def _weave(shape: tuple[int, int], resolution: float, period: float, rng: np.random.Generator) -> np.ndarray:
    """A plain weave: threads along x and along y, `period` apart, each a raised cosine across its width,
    passing over and under the crossing threads alternately (a sinusoid along it of twice the period)."""
    rows, cols = shape
    x = (np.arange(cols) + 0.5) * resolution
    y = (np.arange(rows) + 0.5) * resolution
    # slight irregularity: each thread's phase wanders a little (a real cloth is not perfect)
    wobble_x = 0.04 * period * ring_noise((1, cols), resolution, 5e-3, 40e-3, rng)[0]
    wobble_y = 0.04 * period * ring_noise((1, rows), resolution, 5e-3, 40e-3, rng)[0]
    px = 2 * np.pi * (x + wobble_x) / period
    py = 2 * np.pi * (y + wobble_y) / period
    across_warp = np.cos(py / 2)[:, None] ** 2 * np.ones((1, cols))        # warp threads (along x) at y = k period
    across_weft = np.cos(px / 2)[None, :] ** 2 * np.ones((rows, 1))        # weft threads (along y)
    over = np.sin(px / 2)[None, :] * np.sign(np.cos(py / 2))[:, None]       # which thread is on top
    warp = across_warp * (1 + 0.5 * over)
    weft = across_weft * (1 - 0.5 * over)
    return (25e-6 * (np.maximum(warp, weft) - 0.75)).astype(np.float32)
