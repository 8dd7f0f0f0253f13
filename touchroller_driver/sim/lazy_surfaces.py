"""The surface kinds `make_surface` can also make tile by tile (`TiledSurface`): the same heights as its
eager grid (to float32 rounding), from the same random draws, computed window by window.

* `flat`: zeros.
* `stripes`: ridges across the rolling direction, a closed form of the row.
* `grain`: the eager sum of band-limited noises (`surfaces._smooth_noise`: a random lattice resized
  bicubically, divided by its peak), shifted to 0 and scaled to `relief`. The lattices are drawn up front
  (the same draws, in the same order); the peaks and the sum's range, which the eager surface takes over
  the whole grid, come from one pass over it in blocks (time in proportion to the area, memory of one
  block); each tile is then the lattices resized over its window only (`tiled_surface.cubic_window`).

Kinds that need the whole grid at once (fabrics, images, panels and glass with their planted cracks and
dents) stay eager.
"""
from __future__ import annotations

from typing import Any

import numpy as np

from touchroller_driver.sim.tiled_surface import TileCacheConfig, TiledSurface, blocks, cubic_window

LAZY_KINDS = ("flat", "stripes", "grain")
#: the largest lattice of a lazy grain, cells (a square metre at 0.1 mm with 0.3 mm grain: 11 million)
MAX_LATTICE_CELLS = 200_000_000


def lazy_surface(spec: dict[str, Any], rows: int, cols: int, resolution: float, relief: float, x0: float,
                 y0: float, rng: np.random.Generator) -> TiledSurface:
    """The surface of `spec` (kind in LAZY_KINDS) as a TiledSurface; `surface.tile_cells` and
    `surface.max_tiles` set its cache (TileCacheConfig)."""
    kind = spec.get("kind", "flat")
    defaults = TileCacheConfig()
    config = TileCacheConfig(int(spec.get("tile_cells", defaults.tile_cells)),
                             int(spec.get("max_tiles", defaults.max_tiles)))
    if kind == "flat":
        return TiledSurface(rows, cols, resolution, x0, y0, lambda r0, r1, c0, c1: np.zeros((r1 - r0, c1 - c0),
                                                                                           np.float32),
                            0.0, "flat plane", config)
    if kind == "stripes":
        period = float(spec.get("period", 5e-3))
        ridge = float(spec.get("ridge_width", 3e-4))

        def stripes(r0: int, r1: int, c0: int, c1: int) -> np.ndarray:
            y = (np.arange(r0, r1) + 0.5) * resolution
            profile = (np.mod(y, period) < ridge).astype(np.float32)
            return np.repeat((profile * relief).astype(np.float32)[:, None], c1 - c0, axis=1)

        any_ridge = bool(np.any(np.mod((np.arange(rows) + 0.5) * resolution, period) < ridge))
        top = float(np.float32(relief)) if any_ridge else 0.0
        return TiledSurface(rows, cols, resolution, x0, y0, stripes, top, f"ridges every {period * 1e3:.1f} mm",
                            config)
    if kind == "grain":
        return _grain(spec, rows, cols, resolution, relief, x0, y0, rng, config)
    raise ValueError(f"surface.kind {kind!r} cannot be made tile by tile (lazy): only {', '.join(LAZY_KINDS)}")


def _grain(spec: dict[str, Any], rows: int, cols: int, resolution: float, relief: float, x0: float, y0: float,
           rng: np.random.Generator, config: TileCacheConfig) -> TiledSurface:
    scales = [float(v) for v in spec.get("scales", [3e-4, 1e-3, 4e-3])]
    lattices = []
    for scale in scales:   # surfaces._smooth_noise's draws, in its order
        scale_px = max(scale / resolution, 1.0)
        shape = (max(2, int(rows / scale_px) + 3), max(2, int(cols / scale_px) + 3))
        if shape[0] * shape[1] > MAX_LATTICE_CELLS:
            raise ValueError(f"surface: grain at {scale * 1e3:g} mm over {rows}x{cols} cells needs a lattice of "
                             f"{shape[0]}x{shape[1]}; raise surface.resolution or the grain's scale")
        lattices.append(rng.standard_normal(shape).astype(np.float32))
    peaks = [0.0] * len(lattices)
    for r0, r1, c0, c1 in blocks(rows, cols):
        for k, lattice in enumerate(lattices):
            peaks[k] = max(peaks[k], float(np.abs(cubic_window(lattice, rows, cols, r0, r1, c0, c1)).max()))

    def unit(r0: int, r1: int, c0: int, c1: int) -> np.ndarray:
        total = np.zeros((r1 - r0, c1 - c0))
        for k, (lattice, peak) in enumerate(zip(lattices, peaks, strict=True)):
            big = cubic_window(lattice, rows, cols, r0, r1, c0, c1)
            total += (big / peak if peak > 0 else big).astype(np.float64) / (k + 1)
        return total

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
    return TiledSurface(rows, cols, resolution, x0, y0, grain, top, description, config)
