"""Surfaces under the roller: relief heightmaps in metres on a regular grid.

Grid convention: `height[row, col]`, rows along the rolling direction Y (world), columns along the
roller axis X; cell centres at X = x0 + (col + 0.5) * resolution, Y = y0 + (row + 0.5) * resolution.
Heights are >= 0 and add to the roller's penetration depth (0 = the surface's base plane).
Outside the grid the surface is its flat base plane. `surface.lazy: true`, or a grid past
`EAGER_MAX_CELLS`, makes a `TiledSurface` instead (touchroller_driver.sim.tiled_surface: tiles made on
demand, a bounded cache) for the kinds that can be made by window (`lazy_surfaces.LAZY_KINDS`).

Procedural fabrics (plain weave, twill, knit) are built from yarn cross-section profiles with
per-thread jitter, fibre noise and low-frequency wrinkles, so they are not perfectly periodic
(a perfectly periodic texture would make stitching ambiguous in a way real cloth is not).
Real texture images (CC0 photographs shipped in `touchroller_driver/data/textures`) use grey level
as relief — an approximation, see docs/simulator.md.
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from importlib import resources
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from touchroller_driver.sim.defects import surface_defects
from touchroller_driver.sim.lazy_surfaces import LAZY_KINDS, PEEL_SCALES, lazy_surface
from touchroller_driver.sim.tiled_surface import TiledSurface

FABRIC_PATTERNS = ("plain_weave", "twill", "knit")
#: a surface grid larger than this is made tile by tile (LAZY_KINDS) or refused
EAGER_MAX_CELLS = 40_000_000


@dataclass(frozen=True)
class Surface:
    height: np.ndarray        # float32 [rows=Y, cols=X], metres, >= 0
    resolution: float         # metres per cell
    x0: float                 # world X of the grid's left edge
    y0: float                 # world Y of the grid's top edge
    description: str = ""

    @property
    def width(self) -> float:
        return self.height.shape[1] * self.resolution

    @property
    def length(self) -> float:
        return self.height.shape[0] * self.resolution

    @property
    def max_height(self) -> float:
        return float(self.height.max()) if self.height.size else 0.0

    def lowpassed(self, sigma: float) -> Surface:
        """The relief as the membrane can follow it: Gaussian low-pass with `sigma` metres."""
        if sigma <= 0:
            return self
        sigma_px = sigma / self.resolution
        smoothed = cv2.GaussianBlur(self.height, (0, 0), sigmaX=sigma_px, sigmaY=sigma_px,
                                    borderType=cv2.BORDER_REPLICATE)
        return Surface(smoothed.astype(np.float32), self.resolution, self.x0, self.y0, self.description)

    def sample(self, X: np.ndarray, Y: np.ndarray) -> np.ndarray:  # noqa: N803 - world coordinates
        """Bilinear heights at world points (0 outside the grid)."""
        mx = ((np.asarray(X, np.float64) - self.x0) / self.resolution - 0.5).astype(np.float32)
        my = ((np.asarray(Y, np.float64) - self.y0) / self.resolution - 0.5).astype(np.float32)
        shape = mx.shape
        n = mx.size
        cols = 1024   # cv2.remap wants both sides < 32767: sample in rows of 1024 points
        padded = -(-n // cols) * cols
        flat_x = np.full(padded, -1e6, np.float32)
        flat_y = np.full(padded, -1e6, np.float32)
        flat_x[:n] = mx.ravel()
        flat_y[:n] = my.ravel()
        out = cv2.remap(self.height, flat_x.reshape(-1, cols), flat_y.reshape(-1, cols), cv2.INTER_LINEAR,
                        borderMode=cv2.BORDER_CONSTANT, borderValue=0.0)
        return out.ravel()[:n].reshape(shape)

    def remap(self, mx: np.ndarray, my: np.ndarray) -> np.ndarray:
        """Bilinear heights at grid coordinates (float32 column and row, cell centres whole; 0 outside)."""
        return cv2.remap(self.height, mx, my, cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT, borderValue=0.0)


def make_surface(spec: dict[str, Any], rng: np.random.Generator) -> Surface | TiledSurface:
    """Build the scene's surface from its `surface:` block."""
    kind = spec.get("kind", "flat")
    width = float(spec.get("width", 0.08))
    length = float(spec.get("length", 0.11))
    resolution = float(spec.get("resolution", 5e-5))
    relief = float(spec.get("relief", 3e-4))
    if not (width > 0 and length > 0 and resolution > 0 and relief >= 0):
        raise ValueError("surface: width, length and resolution must be > 0 and relief >= 0")
    cols = max(1, round(width / resolution))
    rows = max(1, round(length / resolution))
    x0 = -0.5 * width + float(spec.get("x_offset", 0.0))
    y0 = float(spec.get("y_offset", 0.0))
    if bool(spec.get("lazy", False)) or (rows * cols > EAGER_MAX_CELLS and kind in LAZY_KINDS):
        return lazy_surface(spec, rows, cols, resolution, relief, x0, y0, rng)
    if rows * cols > EAGER_MAX_CELLS:
        raise ValueError(f"surface grid {rows}x{cols} is too large for a {kind} surface; raise surface.resolution "
                         f"(kinds {', '.join(LAZY_KINDS)} are made tile by tile at any size)")
    if kind == "flat":
        unit = np.zeros((rows, cols), np.float32)
        desc = "flat plane"
    elif kind == "fabric":
        pattern = spec.get("pattern", "plain_weave")
        if pattern not in FABRIC_PATTERNS:
            raise ValueError(f"surface.pattern must be one of {', '.join(FABRIC_PATTERNS)}, got {pattern!r}")
        pitch = float(spec.get("yarn_pitch", 8e-4))
        unit = fabric(pattern, rows, cols, resolution, pitch, rng, irregularity=float(spec.get("irregularity", 1.0)))
        desc = f"{pattern} fabric, yarn pitch {pitch * 1e3:.2f} mm"
    elif kind == "image":
        name = str(spec.get("image", "gravel.png"))
        unit = image_relief(name, rows, cols)
        desc = f"texture image {name}"
    elif kind == "grain":  # sandpaper, leather: random relief at several scales, nowhere periodic
        scales = [float(v) for v in spec.get("scales", [3e-4, 1e-3, 4e-3])]
        unit = np.zeros((rows, cols))
        for k, scale in enumerate(scales):
            unit += _smooth_noise(rows, cols, scale / resolution, rng) / (k + 1)
        unit -= unit.min()
        unit = unit / unit.max() if unit.max() > 0 else unit
        desc = "grain: random relief at " + ", ".join(f"{v * 1e3:g}" for v in scales) + " mm"
    elif kind == "stripes":  # validation target: thin ridges across the rolling direction
        period = float(spec.get("period", 5e-3))
        ridge = float(spec.get("ridge_width", 3e-4))
        y = (np.arange(rows) + 0.5) * resolution
        profile = (np.mod(y, period) < ridge).astype(np.float32)
        unit = np.repeat(profile[:, None], cols, axis=1)
        desc = f"ridges every {period * 1e3:.1f} mm"
    elif kind in ("panel", "glass"):
        # smooth painted metal: orange peel of `peel` m RMS (wavelengths of a few mm) with `cracks`
        # V-grooves and `dents` spherical caps; glass: `peel` of a fraction of a micrometre, nothing planted
        heights, desc = _panel(spec, rows, cols, resolution, rng, glass=(kind == "glass"))
        heights -= heights.min()
        relief = float(heights.max())
        unit = heights / relief if relief > 0 else heights
    else:
        raise ValueError(f"surface.kind must be flat, fabric, image, grain, stripes, panel or glass, got {kind!r}")
    height = (unit * relief).astype(np.float32)
    plan = surface_defects(spec)   # `surface.defects`: planted on any kind (sim/defects.py), its own seed
    if plan:
        plan.render(height, x0, y0, resolution)
        desc += f"; planted {len(plan.cracks)} crack(s), {len(plan.blobs)} dent(s)/bump(s)"
    return Surface(height, resolution, x0, y0, desc)


def _panel(spec: dict[str, Any], rows: int, cols: int, resolution: float, rng: np.random.Generator, *,
           glass: bool) -> tuple[np.ndarray, str]:
    """Heights (m, rows x cols) of a smooth painted panel or of glass, and their description."""
    peel = float(spec.get("peel", 2e-7 if glass else 2e-6))
    heights = np.zeros((rows, cols))
    for scale, weight in PEEL_SCALES:
        heights += weight * _smooth_noise(rows, cols, scale / resolution, rng)
    rms = float(np.sqrt(np.mean(heights ** 2)))
    heights *= peel / rms if rms > 0 else 0.0
    if glass:
        return heights, f"glass-smooth: {peel * 1e6:.2f} um RMS"
    cracks, dents = int(spec.get("cracks", 4)), int(spec.get("dents", 4))
    y, x = np.mgrid[0:rows, 0:cols].astype(np.float64) * resolution
    length, width = rows * resolution, cols * resolution
    for _ in range(cracks):   # a straight V-groove 0.15-0.3 mm wide, 15-40 um deep, 2-6 cm long
        cx, cy = rng.uniform(0.15, 0.85) * width, rng.uniform(0.15, 0.85) * length
        angle, half = rng.uniform(0, math.pi), rng.uniform(0.01, 0.03)
        w, depth = rng.uniform(1.5e-4, 3e-4), rng.uniform(1.5e-5, 4e-5)
        ux, uy = math.cos(angle), math.sin(angle)
        along = (x - cx) * ux + (y - cy) * uy
        across = np.abs(-(x - cx) * uy + (y - cy) * ux)
        inside = (np.abs(along) <= half) & (across < w / 2)
        heights[inside] -= depth * (1 - across[inside] / (w / 2))
    for _ in range(dents):   # a spherical cap 0.8-1.6 mm across, 8-20 um deep
        cx, cy = rng.uniform(0.1, 0.9) * width, rng.uniform(0.1, 0.9) * length
        radius, depth = rng.uniform(4e-4, 8e-4), rng.uniform(8e-6, 2e-5)
        r2 = (x - cx) ** 2 + (y - cy) ** 2
        inside = r2 < radius ** 2
        heights[inside] -= depth * (1 - r2[inside] / radius ** 2)
    return heights, f"painted panel: orange peel {peel * 1e6:.1f} um RMS, {cracks} cracks, {dents} dents"


# --------------------------------------------------------------------------- fabrics
def fabric(pattern: str, rows: int, cols: int, resolution: float, pitch: float,
           rng: np.random.Generator, irregularity: float = 1.0) -> np.ndarray:
    """Unit-height (0..1) fabric relief on a rows x cols grid."""
    X = (np.arange(cols, dtype=np.float64) + 0.5) * resolution
    Y = (np.arange(rows, dtype=np.float64) + 0.5) * resolution
    # Threads wander a little (a real loom is not a lattice): smooth displacement fields.
    wander = 0.25 * pitch * irregularity
    dX = _smooth_noise(rows, cols, 4.0 * pitch / resolution, rng) * wander
    dY = _smooth_noise(rows, cols, 4.0 * pitch / resolution, rng) * wander
    Xw = X[None, :] + dX
    Yw = Y[:, None] + dY
    if pattern == "knit":
        unit = _knit(Xw, Yw, pitch)
    else:
        unit = _weave(Xw, Yw, pitch, rng, twill=(pattern == "twill"), irregularity=irregularity)
    fibres = _smooth_noise(rows, cols, max(1.0, 0.06 * pitch / resolution), rng)
    wrinkles = _smooth_noise(rows, cols, 12e-3 / resolution, rng)
    unit = unit * (0.85 + 0.15 * irregularity * fibres) + 0.08 * irregularity * (wrinkles + 1.0)
    unit -= unit.min()
    top = unit.max()
    return (unit / top if top > 0 else unit).astype(np.float32)


def _weave(X: np.ndarray, Y: np.ndarray, pitch: float, rng: np.random.Generator, *,
           twill: bool, irregularity: float) -> np.ndarray:
    i = np.floor(X / pitch).astype(np.int64)
    j = np.floor(Y / pitch).astype(np.int64)
    fx = X / pitch - i
    fy = Y / pitch - j
    yarn_x = np.sqrt(np.clip(np.sin(math.pi * fx), 0.0, 1.0))   # rounded cross-section of warp yarns
    yarn_y = np.sqrt(np.clip(np.sin(math.pi * fy), 0.0, 1.0))
    # Slubs: each thread is a little thicker or thinner than its neighbours.
    thick_warp = 1.0 + 0.15 * irregularity * rng.standard_normal(int(i.max()) + 2)
    thick_weft = 1.0 + 0.15 * irregularity * rng.standard_normal(int(j.max()) + 2)
    if twill:   # 2/2 twill: over two, under two, shifted by one each row -> diagonal ribs
        warp_over = ((i + j) % 4) < 2
        phase = (i + j) / 2.0
    else:       # plain weave: over one, under one
        warp_over = ((i + j) % 2) == 0
        phase = (i + j).astype(np.float64)
    undulation = 0.5 + 0.5 * np.cos(math.pi * (Y / pitch - 0.5 - j + phase))
    warp = yarn_x * thick_warp[np.clip(i, 0, None)] * (0.55 + 0.45 * np.where(warp_over, 1.0, undulation * 0.5))
    weft = yarn_y * thick_weft[np.clip(j, 0, None)] * (0.55 + 0.45 * np.where(warp_over, undulation * 0.5, 1.0))
    return np.maximum(warp, weft)


def _knit(X: np.ndarray, Y: np.ndarray, pitch: float) -> np.ndarray:
    """Jersey knit seen from the face: columns of V-shaped loops (chevrons)."""
    col_pitch = 1.6 * pitch
    row_pitch = 1.2 * pitch
    fx = np.mod(X / col_pitch, 1.0) - 0.5                     # -0.5..0.5 across a wale
    legs = np.mod(Y / row_pitch + 1.2 * np.abs(fx), 1.0)       # V legs slanting up from the centre
    loop = np.sqrt(np.clip(np.sin(math.pi * legs), 0.0, 1.0))
    wale_gap = np.clip(np.cos(math.pi * fx) * 1.4, 0.0, 1.0)   # grooves between wales
    return loop * wale_gap


def _smooth_noise(rows: int, cols: int, scale_px: float, rng: np.random.Generator) -> np.ndarray:
    """Band-limited noise in [-1, 1] with features about `scale_px` cells wide."""
    scale_px = max(scale_px, 1.0)
    small = rng.standard_normal((max(2, int(rows / scale_px) + 3), max(2, int(cols / scale_px) + 3)))
    big = cv2.resize(small.astype(np.float32), (cols, rows), interpolation=cv2.INTER_CUBIC)
    peak = float(np.abs(big).max())
    return (big / peak if peak > 0 else big).astype(np.float64)


# --------------------------------------------------------------------------- texture images
def texture_path(name: str) -> Path:
    """A texture shipped in `touchroller_driver/data/textures`, or a path."""
    candidate = Path(name)
    if candidate.is_file():
        return candidate
    shipped = resources.files("touchroller_driver") / "data" / "textures" / name
    if shipped.is_file():
        return Path(str(shipped))
    raise ValueError(f"no texture {name!r} in touchroller_driver/data/textures (and not a file)")


def image_relief(name: str, rows: int, cols: int) -> np.ndarray:
    image = cv2.imread(str(texture_path(name)), cv2.IMREAD_GRAYSCALE)
    if image is None:
        raise ValueError(f"texture {name!r} is not a readable image")
    resized = cv2.resize(image, (cols, rows), interpolation=cv2.INTER_CUBIC).astype(np.float32)
    resized -= resized.min()
    top = resized.max()
    return resized / top if top > 0 else resized
