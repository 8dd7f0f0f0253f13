"""The world map's canvas and how a band lands on it: weighted sums on a grid of the world plane
(`WorldCanvas`), a band's placement (a quarter-turned band moved by one bilinear 2x2 blend, or a general
affine), and the map as earlier passes left it for registration (`_Prior`). Used by
`touchroller_perception.world_map`; no rclpy here."""
from __future__ import annotations

import dataclasses
import math
from collections.abc import Sequence
from dataclasses import dataclass

import cv2
import numpy as np


# ------------------------------------------------------------------------------------------------ canvas
class WorldCanvas:
    """Weighted sums on a grid of the world plane: layer 0 sum(w band), 1 sum(w field), 2 sum(w), each a
    plane of `layers` (3, rows, columns). Cell (row r, column c) covers world x in origin_x + [c, c + 1] *
    res, y in origin_y + [r, r + 1] * res (rows grow with y; images flip it). Grows by at least `grow_px`
    (or half its size) on the side that needs it, unless fixed by `bounds`.

    A growing map's `layers` is a window of a larger zeroed allocation (room on every side, within
    `max_pixels`): growing into that room moves the window, without copying the sums or allocating again,
    and the pages of the room are not touched (not made resident) until bands land there. `used()` is the
    rectangle of cells bands were ever added to: everything outside it is zero."""

    def __init__(self, resolution: float, bounds: tuple[float, float, float, float] | None,
                 max_pixels: int, grow_px: int = 512, layers: int = 3) -> None:
        self.depth = layers   # planes per cell: the intensity's three, then any a caller adds (height)
        self.resolution = resolution
        self.max_pixels = max_pixels
        self.grow_px = grow_px
        self.fixed = bounds is not None
        if bounds is not None:
            x0, y0, x1, y1 = bounds
            cols, rows = math.ceil((x1 - x0) / resolution), math.ceil((y1 - y0) / resolution)
            self.origin = (float(x0), float(y0))
        else:
            cols, rows = 0, 0
            self.origin = (0.0, 0.0)
        self._backing = np.zeros((self.depth, rows, cols), np.float32)
        self._offset = (0, 0)   # (row, column) of the window's cell (0, 0) in the allocation
        self.layers = self._backing
        self._used: list[int] | None = None   # [row0, row1, column0, column1] in the allocation

    @property
    def shape(self) -> tuple[int, int]:
        return self.layers.shape[1], self.layers.shape[2]

    def used(self) -> tuple[int, int, int, int] | None:
        """(row0, row1, column0, column1): the cells bands were added to (the rest is zero); None: none."""
        if self._used is None:
            return None
        ro, co = self._offset
        r0, r1, c0, c1 = self._used
        return r0 - ro, r1 - ro, c0 - co, c1 - co

    def to_grid(self, xy: np.ndarray) -> np.ndarray:
        """World (x, y) -> fractional (column, row) where pixel centres are whole numbers."""
        return (np.asarray(xy) - np.asarray(self.origin)) / self.resolution - 0.5

    def _window(self, row0: int, col0: int, rows: int, cols: int) -> None:
        """Make the canvas rows x cols cells whose cell (0, 0) is the old one's (row0, col0): within the
        allocation if it has room, else in a new one with room on every side (the sums copied)."""
        ro, co = self._offset[0] + row0, self._offset[1] + col0
        _, total_rows, total_cols = self._backing.shape
        if not (ro >= 0 and co >= 0 and ro + rows <= total_rows and co + cols <= total_cols):
            room = max(rows, cols)
            while room > 0 and (rows + 2 * room) * (cols + 2 * room) > self.max_pixels:
                room //= 2
            backing = np.zeros((self.depth, rows + 2 * room, cols + 2 * room), np.float32)
            old_rows, old_cols = self.shape
            if self._used is not None:   # only the cells bands reached can be non-zero
                r0, r1, c0, c1 = self.used()  # type: ignore[misc]
                backing[:, room - row0 + r0:room - row0 + r1, room - col0 + c0:room - col0 + c1] = \
                    self.layers[:, r0:r1, c0:c1]
                self._used = [room - row0 + r0, room - row0 + r1, room - col0 + c0, room - col0 + c1]
            elif old_rows and old_cols:
                backing[:, room - row0:room - row0 + old_rows, room - col0:room - col0 + old_cols] = self.layers
            self._backing, ro, co = backing, room, room
        self._offset = (ro, co)
        self.layers = self._backing[:, ro:ro + rows, co:co + cols]

    def ensure(self, c0: int, r0: int, c1: int, r1: int) -> tuple[int, int]:
        """Make columns [c0, c1) and rows [r0, r1) exist (growing, unless fixed); returns the shift of
        the old indices (the new index of old (0, 0)). Raises MemoryError past max_pixels."""
        rows, cols = self.shape
        if self.fixed or (rows and cols and c0 >= 0 and r0 >= 0 and c1 <= cols and r1 <= rows):
            return 0, 0
        if not rows or not cols:   # the first band: start around it with room to grow (within max_pixels)
            pad = self.grow_px // 2
            while pad > 0 and (r1 - r0 + 2 * pad) * (c1 - c0 + 2 * pad) > self.max_pixels:
                pad //= 2
            if (r1 - r0 + 2 * pad) * (c1 - c0 + 2 * pad) > self.max_pixels:
                raise MemoryError(f"one band needs more than {self.max_pixels} pixels at {self.resolution} m/px")
            new_c0, new_r0 = c0 - pad, r0 - pad
            self._backing = np.zeros((self.depth, 0, 0), np.float32)
            self._offset, self._used = (0, 0), None
            self._window(0, 0, r1 - r0 + 2 * pad, c1 - c0 + 2 * pad)
            self.origin = (self.origin[0] + new_c0 * self.resolution, self.origin[1] + new_r0 * self.resolution)
            return -new_c0, -new_r0
        need = (max(0, -c0), max(0, c1 - cols), max(0, -r0), max(0, r1 - rows))   # left, right, bottom, top
        sizes = (cols, cols, rows, rows)
        grow = [max(n, self.grow_px, size // 2) if n else 0 for n, size in zip(need, sizes, strict=True)]
        left, right, bottom, top = grow
        if (rows + bottom + top) * (cols + left + right) > self.max_pixels:
            left, right, bottom, top = need
            if (rows + bottom + top) * (cols + left + right) > self.max_pixels:
                raise MemoryError(f"the map would exceed {self.max_pixels} pixels at {self.resolution} m/px "
                                  "(set bounds or a coarser resolution)")
        self._window(-bottom, -left, rows + bottom + top, cols + left + right)
        self.origin = (self.origin[0] - left * self.resolution, self.origin[1] - bottom * self.resolution)
        return left, bottom

    def add(self, planes: Sequence[np.ndarray | None] | np.ndarray, c0: int, r0: int, first: int = 0) -> None:
        """Add (h, w) patches to the layers from `first` on (None: leave that layer; or a (n, h, w) stack),
        their lowest cell at (column c0, row r0), clipped to the map."""
        rows, cols = self.shape
        h, w = next(p for p in planes if p is not None).shape
        a0, b0 = max(r0, 0), max(c0, 0)
        a1, b1 = min(r0 + h, rows), min(c0 + w, cols)
        if a1 <= a0 or b1 <= b0:
            return
        # cv2.add: 2x numpy's speed on these views
        for layer, plane in zip(self.layers[first:first + len(planes)], planes, strict=True):
            if plane is not None:
                view = layer[a0:a1, b0:b1]
                cv2.add(view, plane[a0 - r0:a1 - r0, b0 - c0:b1 - c0], dst=view)
        self._mark(a0, a1, b0, b1)

    def _mark(self, a0: int, a1: int, b0: int, b1: int) -> None:
        ro, co = self._offset
        used = self._used
        if used is None:
            self._used = [a0 + ro, a1 + ro, b0 + co, b1 + co]
        else:
            if a0 + ro < used[0]:
                used[0] = a0 + ro
            if a1 + ro > used[1]:
                used[1] = a1 + ro
            if b0 + co < used[2]:
                used[2] = b0 + co
            if b1 + co > used[3]:
                used[3] = b1 + co

    def value(self, level: float, min_weight: float = 1e-3) -> tuple[np.ndarray, np.ndarray]:
        """(flat-field-corrected map as float32 grey, weight), rows growing with y."""
        grey, weight = np.zeros(self.shape, np.float32), np.zeros(self.shape, np.float32)
        box = self.used()
        if box is not None:
            r0, r1, c0, c1 = box
            grey[r0:r1, c0:c1], weight[r0:r1, c0:c1] = self.value_in(level, box, min_weight)
        return grey, weight

    def value_in(self, level: float, box: tuple[int, int, int, int],
                 min_weight: float = 1e-3) -> tuple[np.ndarray, np.ndarray]:
        """`value` over rows [row0, row1) and columns [column0, column1) of the canvas."""
        r0, r1, c0, c1 = box
        band, flat, weight = self.layers[:3, r0:r1, c0:c1]
        known = (weight > min_weight) & (flat > 1e-6)
        grey = np.divide(band * np.float32(level), flat, out=np.zeros_like(band), where=known)
        return grey, np.where(known, weight, np.float32(0.0))


# ------------------------------------------------------------------------------------------------ placing
@dataclass(frozen=True)
class _Placement:
    """Where a band landed on the map: for an axis-aligned roller (`axes` not None: transpose, flip rows,
    flip columns) the oriented band at (c0, r0) blended by the 2x2 bilinear `kernel`; else the affine
    `matrix` (band -> patch) of a (w, h) patch at (c0, r0)."""

    c0: int
    r0: int
    axes: tuple[bool, bool, bool] | None
    kernel: np.ndarray | None = None
    matrix: np.ndarray | None = None
    size: tuple[int, int] = (0, 0)

    def moved(self, dc: int, dr: int) -> _Placement:
        return dataclasses.replace(self, c0=self.c0 + dc, r0=self.r0 + dr)


def _axes(matrix: np.ndarray) -> tuple[bool, bool, bool] | None:
    """(transpose, flip rows, flip columns) when the affine's 2x2 part is a signed permutation to within
    1e-6 (an error of 1e-3 px across a 640-column band), else None."""
    # plain floats: this runs for every frame placed, and numpy's calls on a 2x2 cost more than its arithmetic
    (a, b, _), (c, d, _) = matrix.tolist()
    ra, rb, rc, rd = round(a), round(b), round(c), round(d)
    if max(abs(a - ra), abs(b - rb), abs(c - rc), abs(d - rd)) > 1e-6:
        return None
    if not (abs(ra) + abs(rb) == abs(rc) + abs(rd) == abs(ra) + abs(rc) == abs(rb) + abs(rd) == 1):
        return None   # not one non-zero in each row and each column
    if ra == 0:   # map column from the band's row, map row from its column
        return True, rc < 0, rb < 0
    return False, rd < 0, ra < 0


Axes = tuple[bool, bool, bool]   # (transpose, flip rows, flip columns)


def _axis_aligned(matrix: np.ndarray, shape: tuple[int, int]) -> tuple[Axes, int, int, np.ndarray] | None:
    """For an affine band (column j, row i) -> map (column, row) that only turns a band of `shape` (rows,
    columns) by quarter turns and flips (`_axes`): (axes, column c0 and row r0 of the lowest cell of
    `_blend(_orient(plane, axes), kernel)`, kernel) with which that equals the bilinear warp of the plane;
    None for any other affine."""
    axes = _axes(matrix)
    if axes is None:
        return None
    transpose, flip_rows, flip_cols = axes
    rows, cols = (shape[1], shape[0]) if transpose else shape
    ox = float(matrix[0, 2]) - (cols - 1 if flip_cols else 0)
    oy = float(matrix[1, 2]) - (rows - 1 if flip_rows else 0)
    c0, r0 = math.floor(ox), math.floor(oy)
    fx, fy = ox - c0, oy - r0
    kernel = np.array([[fy * fx, fy * (1 - fx)], [(1 - fy) * fx, (1 - fy) * (1 - fx)]], np.float32)
    return axes, c0, r0, kernel


def _orient(plane: np.ndarray, axes: tuple[bool, bool, bool]) -> np.ndarray:
    """The band plane turned to the map's axes, with a zero border of one pixel (for the bilinear blend)."""
    transpose, flip_rows, flip_cols = axes
    out = cv2.transpose(plane) if transpose else plane
    if flip_rows or flip_cols:
        out = cv2.flip(out, -1 if flip_rows and flip_cols else (0 if flip_rows else 1))
    return cv2.copyMakeBorder(out, 1, 1, 1, 1, cv2.BORDER_CONSTANT, value=0)


def _orient_into(plane: np.ndarray, axes: tuple[bool, bool, bool], out: np.ndarray) -> None:
    """`_orient(plane, axes)` without its border, written into `out` (e.g. the inside of a bordered buffer)."""
    transpose, flip_rows, flip_cols = axes
    code = -1 if flip_rows and flip_cols else (0 if flip_rows else 1)
    if transpose:
        written = cv2.transpose(plane, dst=out)
        if flip_rows or flip_cols:
            written = cv2.flip(out, code, dst=out)
    elif flip_rows or flip_cols:
        written = cv2.flip(plane, code, dst=out)
    else:
        np.copyto(out, plane)
        written = out
    if not np.shares_memory(written, out):   # OpenCV made a new array instead of writing into `out`
        raise AssertionError("_orient_into: the output was not written in place")


def _blend(padded: np.ndarray, kernel: np.ndarray) -> np.ndarray:
    """An oriented, bordered plane moved by its subpixel phase: (h + 1, w + 1)."""
    out = cv2.filter2D(padded, -1, kernel, anchor=(0, 0), borderType=cv2.BORDER_CONSTANT)
    return out[:-1, :-1]


@dataclass(frozen=True)
class _Prior:
    """The map's value and weight at a pass's start (what registration compares the pass's frames with):
    the canvas then was `rows` x `columns`, its cells (r, c) now at (r + r_shift, c + c_shift); computed
    only over rows [row0, row0 + value rows) and columns [column0, ...) (zero elsewhere)."""

    value: np.ndarray
    weight: np.ndarray
    row0: int
    col0: int
    rows: int
    cols: int
    r_shift: int = 0
    c_shift: int = 0

    def moved(self, dc: int, dr: int) -> _Prior:
        return dataclasses.replace(self, r_shift=self.r_shift + dr, c_shift=self.c_shift + dc)

    def patch(self, r0: int, c0: int, h: int, w: int) -> tuple[np.ndarray, np.ndarray] | None:
        """(value, weight) of the canvas's cells [r0, r0 + h) x [c0, c0 + w) as they were at the pass's
        start (zero weight where nothing was mapped then, also cells the canvas has grown by since)."""
        pr0, pc0 = r0 - self.r_shift, c0 - self.c_shift
        lr0, lc0 = pr0 - self.row0, pc0 - self.col0
        rows, cols = self.value.shape
        if lr0 >= 0 and lc0 >= 0 and lr0 + h <= rows and lc0 + w <= cols:
            return self.value[lr0:lr0 + h, lc0:lc0 + w], self.weight[lr0:lr0 + h, lc0:lc0 + w]
        value, weight = np.zeros((h, w), np.float32), np.zeros((h, w), np.float32)
        a0, a1 = max(lr0, 0), min(lr0 + h, rows)
        b0, b1 = max(lc0, 0), min(lc0 + w, cols)
        if a1 > a0 and b1 > b0:
            value[a0 - lr0:a1 - lr0, b0 - lc0:b1 - lc0] = self.value[a0:a1, b0:b1]
            weight[a0 - lr0:a1 - lr0, b0 - lc0:b1 - lc0] = self.weight[a0:a1, b0:b1]
        return value, weight
