"""Surfaces made tile by tile on demand: a square metre at 0.1 mm is 100 million cells (400 MB of float32,
more for the low-passed copy the renderer reads), yet a frame reads a few hundred thousand of them.

`TiledSurface` has `Surface`'s grid convention (`height[row, col]`, rows along Y, cell centres at
x0 + (col + 0.5) res, y0 + (row + 0.5) res; the base plane 0 outside the grid) and its reading methods
(`sample`, `remap`, `lowpassed`, `max_height`, `width`, `length`), but holds only a bounded cache of
`tile_cells` x `tile_cells` tiles (`TileCacheConfig.max_tiles`, least recently used dropped), each made
when first read by a `render(row0, row1, col0, col1)` function that computes any window of the grid. The
low-passed surface the renderer reads is tiled too: each of its tiles is the Gaussian blur of the
surface's window around it (a margin of the kernel's radius; the grid's edges replicated as
`Surface.lowpassed` does), so it equals the whole surface blurred.

Which surface kinds can be rendered by window, and what they contain, is `touchroller_driver.sim.surfaces`
(`make_surface` returns a `TiledSurface` when the spec asks for `lazy: true` or the grid is too large to
hold); this module only stores and samples.
"""
from __future__ import annotations

import math
from collections import OrderedDict
from collections.abc import Callable
from dataclasses import dataclass

import cv2
import numpy as np

Render = Callable[[int, int, int, int], np.ndarray]


@dataclass(frozen=True)
class TileCacheConfig:
    """tile_cells: the side of a tile, grid cells. max_tiles: the most tiles held at once (per surface)."""

    tile_cells: int = 256
    max_tiles: int = 96

    def __post_init__(self) -> None:
        if not (isinstance(self.tile_cells, int) and self.tile_cells >= 8):
            raise ValueError(f"tile_cells must be an integer >= 8, got {self.tile_cells}")
        if not (isinstance(self.max_tiles, int) and self.max_tiles >= 4):
            raise ValueError(f"max_tiles must be an integer >= 4, got {self.max_tiles}")


class TiledSurface:
    """See the module docstring. `max_height` is the highest height of the surface (for a low-passed
    surface: its parent's, an upper bound)."""

    def __init__(self, rows: int, cols: int, resolution: float, x0: float, y0: float, render: Render,
                 max_height: float, description: str = "", config: TileCacheConfig | None = None) -> None:
        if rows < 1 or cols < 1 or not resolution > 0:
            raise ValueError(f"a tiled surface needs rows, cols >= 1 and resolution > 0, got {rows}, {cols}, "
                             f"{resolution}")
        self.rows, self.cols = int(rows), int(cols)
        self.resolution, self.x0, self.y0 = float(resolution), float(x0), float(y0)
        self.description = description
        self.config = config or TileCacheConfig()
        self._render = render
        self._max_height = float(max_height)
        self._cache: OrderedDict[tuple[int, int], np.ndarray] = OrderedDict()
        self.tiles_made = 0      # tiles rendered (a tile dropped and read again is rendered again)
        self.peak_tiles = 0      # the most tiles held at once

    # -- Surface's interface ------------------------------------------------------------------------
    @property
    def shape(self) -> tuple[int, int]:
        return self.rows, self.cols

    @property
    def width(self) -> float:
        return self.cols * self.resolution

    @property
    def length(self) -> float:
        return self.rows * self.resolution

    @property
    def max_height(self) -> float:
        return self._max_height

    @property
    def height(self) -> np.ndarray:
        """The whole grid (allocates it: for small surfaces, tests and truth files)."""
        return self.window(0, self.rows, 0, self.cols)

    @property
    def tiles_held(self) -> int:
        return len(self._cache)

    def lowpassed(self, sigma: float) -> TiledSurface:
        """The relief as the membrane can follow it: Gaussian low-pass with `sigma` metres, tile by tile."""
        if sigma <= 0:
            return self
        sigma_px = sigma / self.resolution
        radius = (round(sigma_px * 4 * 2 + 1) | 1) // 2   # OpenCV's kernel size for float images
        margin = radius + 1

        def render(r0: int, r1: int, c0: int, c1: int) -> np.ndarray:
            a0, a1 = max(r0 - margin, 0), min(r1 + margin, self.rows)
            b0, b1 = max(c0 - margin, 0), min(c1 + margin, self.cols)
            around = self.window(a0, a1, b0, b1)
            blurred = cv2.GaussianBlur(around, (0, 0), sigmaX=sigma_px, sigmaY=sigma_px,
                                       borderType=cv2.BORDER_REPLICATE)
            return blurred[r0 - a0:r1 - a0, c0 - b0:c1 - b0]

        return TiledSurface(self.rows, self.cols, self.resolution, self.x0, self.y0, render, self._max_height,
                            self.description, self.config)

    def remap(self, mx: np.ndarray, my: np.ndarray) -> np.ndarray:
        """`cv2.remap(height, mx, my, INTER_LINEAR, BORDER_CONSTANT 0)` of the whole grid, reading only the
        window the coordinates (float32 column and row, pixel centres whole) fall in."""
        mx = np.asarray(mx, np.float32)
        my = np.asarray(my, np.float32)
        inside = (mx > -2) & (mx < self.cols + 1) & (my > -2) & (my < self.rows + 1)
        if not inside.any():
            return np.zeros(mx.shape, np.float32)
        xs, ys = mx[inside], my[inside]
        # the window within the grid: a neighbour outside it is outside the grid, 0 either way
        c0 = max(math.floor(float(xs.min())) - 1, 0)
        c1 = min(math.ceil(float(xs.max())) + 2, self.cols)
        r0 = max(math.floor(float(ys.min())) - 1, 0)
        r1 = min(math.ceil(float(ys.max())) + 2, self.rows)
        if c1 <= c0 or r1 <= r0:
            return np.zeros(mx.shape, np.float32)
        window = self.window(r0, r1, c0, c1)
        # shifting by a whole number no larger than the coordinates that matter is exact in float32 (and
        # so is remap's fixed-point fraction of them): the same result as on the whole grid
        return cv2.remap(window, mx - np.float32(c0), my - np.float32(r0), cv2.INTER_LINEAR,
                         borderMode=cv2.BORDER_CONSTANT, borderValue=0.0)

    def sample(self, X: np.ndarray, Y: np.ndarray) -> np.ndarray:  # noqa: N803 - world coordinates
        """Bilinear heights at world points (0 outside the grid), as `Surface.sample`."""
        mx = ((np.asarray(X, np.float64) - self.x0) / self.resolution - 0.5).astype(np.float32)
        my = ((np.asarray(Y, np.float64) - self.y0) / self.resolution - 0.5).astype(np.float32)
        shape = mx.shape
        flat_x, flat_y = mx.ravel(), my.ravel()
        out = np.empty(flat_x.size, np.float32)
        cols = 1024   # cv2.remap wants both sides < 32767: rows of 1024 points, a block of rows at a time
        step = cols * 64
        for start in range(0, flat_x.size, step):
            bx, by = flat_x[start:start + step], flat_y[start:start + step]
            n = bx.size
            padded = -(-n // cols) * cols
            px = np.full(padded, -1e6, np.float32)
            py = np.full(padded, -1e6, np.float32)
            px[:n], py[:n] = bx, by
            out[start:start + n] = self.remap(px.reshape(-1, cols), py.reshape(-1, cols)).ravel()[:n]
        return out.reshape(shape)

    # -- tiles --------------------------------------------------------------------------------------
    def window(self, r0: int, r1: int, c0: int, c1: int) -> np.ndarray:
        """Heights of rows [r0, r1) and columns [c0, c1) (0 outside the grid), float32."""
        out = np.zeros((max(r1 - r0, 0), max(c1 - c0, 0)), np.float32)
        t = self.config.tile_cells
        a0, a1 = max(r0, 0), min(r1, self.rows)
        b0, b1 = max(c0, 0), min(c1, self.cols)
        if a1 <= a0 or b1 <= b0:
            return out
        for ti in range(a0 // t, (a1 - 1) // t + 1):
            for tj in range(b0 // t, (b1 - 1) // t + 1):
                tile = self._tile(ti, tj)
                tr0, tc0 = ti * t, tj * t
                s0, s1 = max(a0, tr0), min(a1, tr0 + tile.shape[0])
                u0, u1 = max(b0, tc0), min(b1, tc0 + tile.shape[1])
                out[s0 - r0:s1 - r0, u0 - c0:u1 - c0] = tile[s0 - tr0:s1 - tr0, u0 - tc0:u1 - tc0]
        return out

    def _tile(self, ti: int, tj: int) -> np.ndarray:
        key = (ti, tj)
        tile = self._cache.get(key)
        if tile is not None:
            self._cache.move_to_end(key)
            return tile
        t = self.config.tile_cells
        r0, c0 = ti * t, tj * t
        r1, c1 = min(r0 + t, self.rows), min(c0 + t, self.cols)
        tile = np.ascontiguousarray(self._render(r0, r1, c0, c1), np.float32)
        if tile.shape != (r1 - r0, c1 - c0):
            raise AssertionError(f"a surface tile rendered as {tile.shape}, not {(r1 - r0, c1 - c0)}")
        self.tiles_made += 1
        self._cache[key] = tile
        while len(self._cache) > self.config.max_tiles:
            self._cache.popitem(last=False)
        self.peak_tiles = max(self.peak_tiles, len(self._cache))
        return tile


# ------------------------------------------------------------------------------------------------ windows
_CUBIC_A = -0.75   # OpenCV's bicubic


def _cubic_taps(n_dst: int, n_src: int, start: int, stop: int) -> tuple[np.ndarray, np.ndarray]:
    """Source indices (n, 4) and weights (n, 4) of destination samples [start, stop) of a bicubic resize
    of n_src samples to n_dst, as cv2.resize(INTER_CUBIC) takes them (half-pixel centres, the edges
    replicated)."""
    scale = 1.0 / (n_dst / n_src)
    f = (np.arange(start, stop, dtype=np.float64) + 0.5) * scale - 0.5
    s = np.floor(f)
    t = f - s
    a = _CUBIC_A
    t1, u = t + 1.0, 1.0 - t
    w0 = ((a * t1 - 5 * a) * t1 + 8 * a) * t1 - 4 * a
    w1 = ((a + 2) * t - (a + 3)) * t * t + 1
    w2 = ((a + 2) * u - (a + 3)) * u * u + 1
    w3 = 1.0 - w0 - w1 - w2
    index = np.clip(s.astype(np.int64)[:, None] + np.arange(-1, 3), 0, n_src - 1)
    return index, np.stack([w0, w1, w2, w3], axis=1).astype(np.float32)


def cubic_window(small: np.ndarray, rows: int, cols: int, r0: int, r1: int, c0: int, c1: int) -> np.ndarray:
    """Rows [r0, r1) and columns [c0, c1) of cv2.resize(small, (cols, rows), INTER_CUBIC) (float32, to its
    rounding), without making the rest."""
    ir, wr = _cubic_taps(rows, small.shape[0], r0, r1)
    ic, wc = _cubic_taps(cols, small.shape[1], c0, c1)
    lo, hi = int(ir.min()), int(ir.max()) + 1
    part = np.asarray(small[lo:hi], np.float32)
    across = part[:, ic[:, 0]] * wc[:, 0]
    for k in range(1, 4):
        across += part[:, ic[:, k]] * wc[:, k]
    ir = ir - lo
    out = across[ir[:, 0]] * wr[:, 0, None]
    for k in range(1, 4):
        out += across[ir[:, k]] * wr[:, k, None]
    return out


def blocks(rows: int, cols: int, size: int = 1024) -> list[tuple[int, int, int, int]]:
    """(r0, r1, c0, c1) of blocks of at most size x size covering a rows x cols grid (for passes over a
    surface too large to hold)."""
    return [(r, min(r + size, rows), c, min(c + size, cols)) for r in range(0, rows, size)
            for c in range(0, cols, size)]
