"""How much of a requested rectangle a world map covers.

The rectangle is the sweep's `sweep.area` = (x, y, length, width) in the map's frame: corner (x, y), `length`
along the horizontal rolling direction, `width` to its left (the side `touchroller_driver.arm.plan_raster`
spreads the passes to). The map is a nav2-style grid: `mapped` row 0 the top (largest y), `origin` the world
(x, y) of the lower-left pixel's corner, `resolution` m per pixel, no yaw.
"""
from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

#: most sample points used to measure one rectangle (a finer map is sampled, not read whole)
MAX_SAMPLES = 4_000_000


@dataclass(frozen=True)
class AreaRectangle:
    """A rectangle in the map's plane: `corner`, `length` along the unit `heading`, `width` to its left."""

    corner: tuple[float, float]
    heading: tuple[float, float]
    length: float
    width: float

    @classmethod
    def from_sweep_area(cls, area: Sequence[float],
                        direction: Sequence[float] = (1.0, 0.0, 0.0)) -> AreaRectangle | None:
        """The rectangle of `sweep.area` rolled along `sweep.direction`; None for no area (length 0) or a
        direction without a horizontal part. ValueError for an area that is not 4 finite numbers."""
        values = [float(v) for v in area]
        if len(values) != 4 or not all(math.isfinite(v) for v in values):
            raise ValueError(f"an area is [x, y, length, width] (4 finite numbers, m), got {list(area)}")
        hx, hy = (float(direction[0]), float(direction[1])) if len(direction) >= 2 else (math.nan, math.nan)
        norm = math.hypot(hx, hy)
        if values[2] <= 0 or values[3] < 0 or not (math.isfinite(norm) and norm > 1e-9):
            return None
        return cls((values[0], values[1]), (hx / norm, hy / norm), values[2], values[3])

    @property
    def across(self) -> tuple[float, float]:
        """The unit vector the width runs along (the heading turned a quarter to the left)."""
        return (-self.heading[1], self.heading[0])

    @property
    def area(self) -> float:
        return self.length * self.width

    def corners(self) -> np.ndarray:
        """(4, 2) world corners: corner, + length, + length + width, + width."""
        c, h, a = np.asarray(self.corner), np.asarray(self.heading), np.asarray(self.across)
        return np.stack([c, c + self.length * h, c + self.length * h + self.width * a, c + self.width * a])


def mapped_fraction(mapped: np.ndarray, resolution: float, origin: Sequence[float], rectangle: AreaRectangle) -> float:
    """Fraction (0..1) of the rectangle's area that lies on mapped pixels (outside the map counts as
    unmapped), measured on a grid of points at most a pixel apart (coarser only beyond MAX_SAMPLES points);
    NaN for a rectangle of no area."""
    mask = np.asarray(mapped, dtype=bool)
    if mask.ndim != 2 or not (math.isfinite(resolution) and resolution > 0):
        raise ValueError("mapped must be a 2-D mask and resolution a positive number")
    if not rectangle.area > 0:
        return math.nan
    step = max(resolution, math.sqrt(rectangle.area / MAX_SAMPLES))
    n_s, n_t = max(1, math.ceil(rectangle.length / step)), max(1, math.ceil(rectangle.width / step))
    s = (np.arange(n_s) + 0.5) * (rectangle.length / n_s)
    t = (np.arange(n_t) + 0.5) * (rectangle.width / n_t)
    heading, across = np.asarray(rectangle.heading), np.asarray(rectangle.across)
    x = rectangle.corner[0] + s[:, None] * heading[0] + t[None, :] * across[0]
    y = rectangle.corner[1] + s[:, None] * heading[1] + t[None, :] * across[1]
    col = np.floor((x - float(origin[0])) / resolution).astype(np.int64)
    row = mask.shape[0] - 1 - np.floor((y - float(origin[1])) / resolution).astype(np.int64)
    inside = (col >= 0) & (col < mask.shape[1]) & (row >= 0) & (row < mask.shape[0])
    hit = np.zeros(x.shape, dtype=bool)
    hit[inside] = mask[row[inside], col[inside]]
    return float(hit.mean())
