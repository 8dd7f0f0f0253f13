"""The surface kinds `make_surface` can also make tile by tile (`TiledSurface`): the same heights as its
eager grid (to float32 rounding), from the same random draws, computed window by window.

* `flat`: zeros.
* `stripes`: ridges across the rolling direction, a closed form of the row.
* `grain`: the eager sum of band-limited noises (`surfaces._smooth_noise`: a random lattice resized
  bicubically, divided by its peak), shifted to 0 and scaled to `relief`. The lattices are drawn up front
  (the same draws, in the same order); the peaks and the sum's range, which the eager surface takes over
  the whole grid, come from one pass over it in blocks (time in proportion to the area, memory of one
  block); each tile is then the lattices resized over its window only (`tiled_surface.cubic_window`).
* `panel` and `glass`: the same sum of noises scaled to the `peel` RMS (the lattices' peaks and the sum's
  mean square from passes over the grid in blocks), the panel's own straight grooves and spherical dents
  carved in closed form where they reach (their draws taken up front in the eager order), shifted to 0 by
  the grid's lowest height: outside the grooves and dents that is the lowest of the scaled sum, which
  the pass takes; inside them, their windows are made once to find it.

`surface.defects` (`defects.DefectPlan`) are drawn into each tile as into the eager grid; the surface's
`max_height` is then the higher of the background's and the highest cell of the defects' windows (an
upper bound of the grid's highest, equal to it unless the background's highest lies under a defect).

Kinds that need the whole grid at once (fabrics, images) stay eager.
"""
from __future__ import annotations

import math
from typing import Any

import numpy as np

from touchroller_driver.sim.defects import DefectPlan, surface_defects
from touchroller_driver.sim.tiled_surface import Render, TileCacheConfig, TiledSurface, blocks, cubic_window

LAZY_KINDS = ("flat", "stripes", "grain", "panel", "glass")
#: the panel's and glass's orange peel: (feature size m, weight) of each band-limited noise, in draw order
PEEL_SCALES = ((2e-3, 0.5), (6e-3, 1.0), (15e-3, 0.7))
#: the largest lattice of a lazy grain, cells (a square metre at 0.1 mm with 0.3 mm grain: 11 million)
MAX_LATTICE_CELLS = 200_000_000


def lazy_surface(spec: dict[str, Any], rows: int, cols: int, resolution: float, relief: float, x0: float,
                 y0: float, rng: np.random.Generator) -> TiledSurface:
    """The surface of `spec` (kind in LAZY_KINDS), with its `defects`, as a TiledSurface; `surface.tile_cells`
    and `surface.max_tiles` set its cache (TileCacheConfig)."""
    kind = spec.get("kind", "flat")
    defaults = TileCacheConfig()
    config = TileCacheConfig(int(spec.get("tile_cells", defaults.tile_cells)),
                             int(spec.get("max_tiles", defaults.max_tiles)))
    render: Render
    if kind == "flat":
        def render(r0: int, r1: int, c0: int, c1: int) -> np.ndarray:
            return np.zeros((r1 - r0, c1 - c0), np.float32)

        top, description = 0.0, "flat plane"
    elif kind == "stripes":
        period = float(spec.get("period", 5e-3))
        ridge = float(spec.get("ridge_width", 3e-4))

        def render(r0: int, r1: int, c0: int, c1: int) -> np.ndarray:
            y = (np.arange(r0, r1) + 0.5) * resolution
            profile = (np.mod(y, period) < ridge).astype(np.float32)
            return np.repeat((profile * relief).astype(np.float32)[:, None], c1 - c0, axis=1)

        any_ridge = bool(np.any(np.mod((np.arange(rows) + 0.5) * resolution, period) < ridge))
        top = float(np.float32(relief)) if any_ridge else 0.0
        description = f"ridges every {period * 1e3:.1f} mm"
    elif kind == "grain":
        render, top, description = _grain(spec, rows, cols, resolution, relief, rng)
    elif kind in ("panel", "glass"):
        render, top, description = _panel(spec, rows, cols, resolution, rng, glass=kind == "glass")
    else:
        raise ValueError(f"surface.kind {kind!r} cannot be made tile by tile (lazy): only {', '.join(LAZY_KINDS)}")
    plan = surface_defects(spec)   # `surface.defects`: as make_surface plants them, tile by tile
    if plan:
        render, top = _planted(render, top, plan, rows, cols, resolution, x0, y0)
        description += f"; planted {len(plan.cracks)} crack(s), {len(plan.blobs)} dent(s)/bump(s)"
    return TiledSurface(rows, cols, resolution, x0, y0, render, top, description, config)


def _lattice(rows: int, cols: int, scale: float, resolution: float, rng: np.random.Generator) -> np.ndarray:
    """`surfaces._smooth_noise`'s random lattice for features of `scale` m (the same draw)."""
    scale_px = max(scale / resolution, 1.0)
    shape = (max(2, int(rows / scale_px) + 3), max(2, int(cols / scale_px) + 3))
    if shape[0] * shape[1] > MAX_LATTICE_CELLS:
        raise ValueError(f"surface: noise at {scale * 1e3:g} mm over {rows}x{cols} cells needs a lattice of "
                         f"{shape[0]}x{shape[1]}; raise surface.resolution or the feature size")
    return rng.standard_normal(shape).astype(np.float32)


def _peaks(lattices: list[np.ndarray], rows: int, cols: int) -> list[float]:
    """The largest |value| of each lattice resized to rows x cols, from a pass over the grid in blocks."""
    peaks = [0.0] * len(lattices)
    for r0, r1, c0, c1 in blocks(rows, cols):
        for k, lattice in enumerate(lattices):
            peaks[k] = max(peaks[k], float(np.abs(cubic_window(lattice, rows, cols, r0, r1, c0, c1)).max()))
    return peaks


def _noise_sum(lattices: list[np.ndarray], peaks: list[float], weights: list[float], rows: int,
               cols: int) -> Render:
    """The window of sum_k weight_k x (lattice k resized to rows x cols / its peak), float64, as the eager
    surfaces add `_smooth_noise`s."""
    def total(r0: int, r1: int, c0: int, c1: int) -> np.ndarray:
        out = np.zeros((r1 - r0, c1 - c0))
        for lattice, peak, weight in zip(lattices, peaks, weights, strict=True):
            big = cubic_window(lattice, rows, cols, r0, r1, c0, c1)
            out += weight * (big / peak if peak > 0 else big).astype(np.float64)
        return out
    return total


def _grain(spec: dict[str, Any], rows: int, cols: int, resolution: float, relief: float,
           rng: np.random.Generator) -> tuple[Render, float, str]:
    scales = [float(v) for v in spec.get("scales", [3e-4, 1e-3, 4e-3])]
    lattices = [_lattice(rows, cols, scale, resolution, rng) for scale in scales]   # _smooth_noise's order
    unit = _noise_sum(lattices, _peaks(lattices, rows, cols), [1.0 / (k + 1) for k in range(len(scales))],
                      rows, cols)
    lo, hi = np.inf, -np.inf
    for r0, r1, c0, c1 in blocks(rows, cols):
        values = unit(r0, r1, c0, c1)
        lo, hi = min(lo, float(values.min())), max(hi, float(values.max()))
    span = hi - lo

    def grain(r0: int, r1: int, c0: int, c1: int) -> np.ndarray:
        values = unit(r0, r1, c0, c1) - lo
        if span > 0:
            values = values / span
        return (values * relief).astype(np.float32)

    description = "grain: random relief at " + ", ".join(f"{v * 1e3:g}" for v in scales) + " mm"
    top = float(np.float32(relief)) if span > 0 else 0.0
    return grain, top, description


def _panel(spec: dict[str, Any], rows: int, cols: int, resolution: float, rng: np.random.Generator, *,
           glass: bool) -> tuple[Render, float, str]:
    """`surfaces._panel` by window, shifted to 0 and scaled as `make_surface` does (`relief` is the panel's
    own peak to valley)."""
    peel = float(spec.get("peel", 2e-7 if glass else 2e-6))
    lattices = [_lattice(rows, cols, scale, resolution, rng) for scale, _ in PEEL_SCALES]
    noise = _noise_sum(lattices, _peaks(lattices, rows, cols), [w for _, w in PEEL_SCALES], rows, cols)
    grooves: list[tuple[float, ...]] = []
    dents: list[tuple[float, ...]] = []
    windows: list[tuple[int, int, int, int]] = []   # the cells a groove or dent may change

    def cells(cx: float, cy: float, reach: float) -> tuple[int, int, int, int]:
        return (max(0, math.floor((cy - reach) / resolution) - 1), min(rows, math.ceil((cy + reach) / resolution) + 2),
                max(0, math.floor((cx - reach) / resolution) - 1), min(cols, math.ceil((cx + reach) / resolution) + 2))

    if glass:
        description = f"glass-smooth: {peel * 1e6:.2f} um RMS"
    else:
        n_cracks, n_dents = int(spec.get("cracks", 4)), int(spec.get("dents", 4))
        length, width = rows * resolution, cols * resolution
        for _ in range(n_cracks):   # surfaces._panel's draws, in its order
            cx, cy = rng.uniform(0.15, 0.85) * width, rng.uniform(0.15, 0.85) * length
            angle, half = rng.uniform(0, math.pi), rng.uniform(0.01, 0.03)
            w, depth = rng.uniform(1.5e-4, 3e-4), rng.uniform(1.5e-5, 4e-5)
            grooves.append((cx, cy, math.cos(angle), math.sin(angle), half, w, depth))
            windows.append(cells(cx, cy, half + w))
        for _ in range(n_dents):
            cx, cy = rng.uniform(0.1, 0.9) * width, rng.uniform(0.1, 0.9) * length
            radius, depth = rng.uniform(4e-4, 8e-4), rng.uniform(8e-6, 2e-5)
            dents.append((cx, cy, radius, depth))
            windows.append(cells(cx, cy, radius))
        description = f"painted panel: orange peel {peel * 1e6:.1f} um RMS, {n_cracks} cracks, {n_dents} dents"
    windows = [w for w in windows if w[1] > w[0] and w[3] > w[2]]

    def carve(heights: np.ndarray, r0: int, c0: int) -> None:
        """surfaces._panel's grooves and dents, in place on the float64 window at (r0, c0): the same
        operations on each cell, only where they can reach."""
        for (cx, cy, ux, uy, half, w, depth), (a0, a1, b0, b1) in zip(grooves, windows[:len(grooves)], strict=True):
            _carve_cells(heights, r0, c0, a0, a1, b0, b1, resolution,
                         lambda x, y, h, cx=cx, cy=cy, ux=ux, uy=uy, half=half, w=w, depth=depth:
                         _groove(x, y, h, cx, cy, ux, uy, half, w, depth))
        for (cx, cy, radius, depth), (a0, a1, b0, b1) in zip(dents, windows[len(grooves):], strict=True):
            _carve_cells(heights, r0, c0, a0, a1, b0, b1, resolution,
                         lambda x, y, h, cx=cx, cy=cy, radius=radius, depth=depth:
                         _dent(x, y, h, cx, cy, radius, depth))

    # the mean square (for the peel's RMS) and the lowest and highest of the sum outside the grooves and
    # dents, in one pass; scaling by a positive number keeps the order, so they scale to the heights'
    squares, low, high = 0.0, np.inf, -np.inf
    for r0, r1, c0, c1 in blocks(rows, cols):
        values = noise(r0, r1, c0, c1)
        squares += float(np.sum(values ** 2))
        plain = np.ones(values.shape, bool)
        for a0, a1, b0, b1 in windows:
            plain[max(a0 - r0, 0):max(a1 - r0, 0), max(b0 - c0, 0):max(b1 - c0, 0)] = False
        if plain.any():
            low, high = min(low, float(values[plain].min())), max(high, float(values[plain].max()))
    rms = math.sqrt(squares / (rows * cols))
    scale = peel / rms if rms > 0 else 0.0

    def heights(r0: int, r1: int, c0: int, c1: int) -> np.ndarray:
        values = noise(r0, r1, c0, c1)
        values *= scale
        carve(values, r0, c0)
        return values

    lo = scale * low if np.isfinite(low) else np.inf
    hi = scale * high if np.isfinite(high) else -np.inf
    for a0, a1, b0, b1 in windows:   # the grooves' and dents' cells, made once for the range
        values = heights(a0, a1, b0, b1)
        lo, hi = min(lo, float(values.min())), max(hi, float(values.max()))
    relief = hi - lo

    def panel(r0: int, r1: int, c0: int, c1: int) -> np.ndarray:
        values = heights(r0, r1, c0, c1)
        values -= lo
        unit = values / relief if relief > 0 else values
        return (unit * relief).astype(np.float32)

    return panel, (float(np.float32(relief)) if relief > 0 else 0.0), description


def _carve_cells(heights: np.ndarray, r0: int, c0: int, a0: int, a1: int, b0: int, b1: int, resolution: float,
                 cut: Any) -> None:
    """Apply `cut(x, y, h)` to the cells of rows [a0, a1) and columns [b0, b1) of the grid that lie in the
    window `heights` at (r0, c0); x and y the cells' grid coordinates (col and row x resolution)."""
    s0, s1 = max(a0, r0), min(a1, r0 + heights.shape[0])
    u0, u1 = max(b0, c0), min(b1, c0 + heights.shape[1])
    if s1 <= s0 or u1 <= u0:
        return
    y = (np.arange(s0, s1).astype(np.float64) * resolution)[:, None]
    x = (np.arange(u0, u1).astype(np.float64) * resolution)[None, :]
    cut(x, y, heights[s0 - r0:s1 - r0, u0 - c0:u1 - c0])


def _groove(x: np.ndarray, y: np.ndarray, h: np.ndarray, cx: float, cy: float, ux: float, uy: float, half: float,
            w: float, depth: float) -> None:
    along = (x - cx) * ux + (y - cy) * uy
    across = np.abs(-(x - cx) * uy + (y - cy) * ux)
    inside = (np.abs(along) <= half) & (across < w / 2)
    h[inside] -= depth * (1 - across[inside] / (w / 2))


def _dent(x: np.ndarray, y: np.ndarray, h: np.ndarray, cx: float, cy: float, radius: float, depth: float) -> None:
    r2 = (x - cx) ** 2 + (y - cy) ** 2
    inside = r2 < radius ** 2
    h[inside] -= depth * (1 - r2[inside] / radius ** 2)


def _planted(render: Render, top: float, plan: DefectPlan, rows: int, cols: int, resolution: float, x0: float,
             y0: float) -> tuple[Render, float]:
    """`render` with the plan's defects drawn into each window, and the surface's highest (see the module
    docstring)."""
    def planted(r0: int, r1: int, c0: int, c1: int) -> np.ndarray:
        heights = np.array(render(r0, r1, c0, c1), np.float32)
        plan.render(heights, x0 + c0 * resolution, y0 + r0 * resolution, resolution)
        return heights

    highest = top
    for xa, ya, xb, yb in plan.extents(resolution):
        c0, c1 = max(0, math.floor((xa - x0) / resolution)), min(cols, math.ceil((xb - x0) / resolution) + 1)
        r0, r1 = max(0, math.floor((ya - y0) / resolution)), min(rows, math.ceil((yb - y0) / resolution) + 1)
        if c1 > c0 and r1 > r0:
            highest = max(highest, float(planted(r0, r1, c0, c1).max()))
    return planted, highest
