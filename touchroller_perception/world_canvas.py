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

from touchroller_perception.tiles import TileConfig, TileStore

# ------------------------------------------------------------------------------------------------ canvas
LAYERS = ("band", "flat", "weight")   # sum(w band), sum(w field), sum(w)
MAPPED_WEIGHT = 0.05                  # a cell with more weight than this counts as mapped


class WorldCanvas:
    """Weighted sums on a grid of the world plane, kept as tiles (`touchroller_perception.tiles`): layer
    "band" sum(w band), "flat" sum(w field), "weight" sum(w) (0, 1, 2 where planes are given in order),
    and any further layer a caller adds (`add_layer`). Cell (row r, column c) covers world x in origin_x
    + [c, c + 1] * res, y in origin_y + [r, r + 1] * res (rows grow with y; images flip it).

    The canvas is the rectangle of tiles that bands reached (or `bounds`, fixed): growing only changes
    which tiles it spans, never copies a sum; tiles are made when first touched, and beyond the store's
    cache they live on disk. `used()` is the rectangle of cells bands were ever added to: everything
    outside it is zero. Cells are also addressed absolutely (`offset`: the absolute (row, column) of the
    canvas's cell (0, 0)), as the store and the pyramid views see them.

    Registration's prior (the map as it was when a pass began) is kept copy-on-write: `begin_prior()`
    marks the moment, and a tile is copied aside just before the first band after it changes it."""

    def __init__(self, resolution: float, bounds: tuple[float, float, float, float] | None,
                 tiles: TileConfig | None = None, grow_px: int = 512) -> None:
        self.resolution = resolution
        self.grow_px = grow_px
        self.store = TileStore(tiles)
        self.tile = self.store.tile
        for name in LAYERS:
            self.store.add_layer(name, np.float32)
        self.fixed = bounds is not None
        if bounds is not None:
            x0, y0, x1, y1 = bounds
            self._size = (math.ceil((y1 - y0) / resolution), math.ceil((x1 - x0) / resolution))
            self.anchor = (float(x0), float(y0))
        else:
            self._size = (0, 0)
            self.anchor = (0.0, 0.0)
        self.offset = (0, 0)   # absolute (row, column) of the canvas's cell (0, 0)
        self._origin = self.anchor
        self._used: list[int] | None = None   # [row0, row1, column0, column1], absolute
        self.weight_max = 0.0                 # the largest sum of weights anywhere
        self._saved: dict[tuple[int, int], bool] | None = None   # tiles copied aside for the prior (existed?)
        self.prior_level = 1.0

    @property
    def shape(self) -> tuple[int, int]:
        return self._size

    @property
    def origin(self) -> tuple[float, float]:
        """World (x, y) of the lower-left corner of the canvas's cell (0, 0)."""
        return self._origin

    @origin.setter
    def origin(self, xy: tuple[float, float]) -> None:
        """Move the whole map (its absolute grid's `anchor` with it)."""
        dx, dy = xy[0] - self._origin[0], xy[1] - self._origin[1]
        self.anchor = (self.anchor[0] + dx, self.anchor[1] + dy)
        self._origin = (float(xy[0]), float(xy[1]))

    def add_layer(self, name: str, dtype: type | np.dtype | str = np.float32, fill: float = 0.0) -> None:
        """A further layer on the same tiles (e.g. a height sum); `add_named` adds to it."""
        self.store.add_layer(name, dtype, fill)

    def used(self) -> tuple[int, int, int, int] | None:
        """(row0, row1, column0, column1): the cells bands were added to (the rest is zero); None: none."""
        if self._used is None:
            return None
        ro, co = self.offset
        r0, r1, c0, c1 = self._used
        return r0 - ro, r1 - ro, c0 - co, c1 - co

    def to_grid(self, xy: np.ndarray) -> np.ndarray:
        """World (x, y) -> fractional (column, row) where pixel centres are whole numbers."""
        return (np.asarray(xy) - np.asarray(self.origin)) / self.resolution - 0.5

    def ensure(self, c0: int, r0: int, c1: int, r1: int) -> tuple[int, int]:
        """Make columns [c0, c1) and rows [r0, r1) exist (growing, unless fixed); returns the shift of
        the old indices (the new index of old (0, 0)): whole tiles (nothing is copied)."""
        rows, cols = self._size
        if self.fixed or (rows and cols and c0 >= 0 and r0 >= 0 and c1 <= cols and r1 <= rows):
            return 0, 0
        t = self.tile
        if not rows or not cols:   # the first band: the absolute grid's cell (0, 0) a little below it
            pad = self.grow_px // 2
            anchor_c, anchor_r = c0 - pad, r0 - pad
            self.anchor = (self.origin[0] + anchor_c * self.resolution, self.origin[1] + anchor_r * self.resolution)
            a = (r0 - anchor_r, r1 - anchor_r, c0 - anchor_c, c1 - anchor_c)
            shift_base = (-anchor_c, -anchor_r)   # old canvas index (c, r) -> absolute (c - anchor_c, ...)
            tiles = (a[0] // t, (a[1] - 1) // t + 1, a[2] // t, (a[3] - 1) // t + 1)
        else:
            ro, co = self.offset
            shift_base = (co, ro)
            a = (r0 + ro, r1 + ro, c0 + co, c1 + co)
            tiles = (min(a[0], ro) // t, (max(a[1], ro + rows) - 1) // t + 1,
                     min(a[2], co) // t, (max(a[3], co + cols) - 1) // t + 1)
        ty0, ty1, tx0, tx1 = tiles
        self.offset = (ty0 * t, tx0 * t)
        self._size = ((ty1 - ty0) * t, (tx1 - tx0) * t)
        self._origin = (self.anchor[0] + tx0 * t * self.resolution, self.anchor[1] + ty0 * t * self.resolution)
        return shift_base[0] - self.offset[1], shift_base[1] - self.offset[0]

    def _clip(self, h: int, w: int, c0: int, r0: int) -> tuple[int, int, int, int] | None:
        rows, cols = self._size
        a0, b0 = max(r0, 0), max(c0, 0)
        a1, b1 = min(r0 + h, rows), min(c0 + w, cols)
        if a1 <= a0 or b1 <= b0:
            return None
        return a0, a1, b0, b1

    def add(self, planes: Sequence[np.ndarray | None] | np.ndarray, c0: int, r0: int) -> None:
        """Add (h, w) patches to the layers band, flat, weight (None: leave that layer; or a (3, h, w)
        stack of all three), their lowest cell at (column c0, row r0), clipped to the map. Raises
        `StorageFull` (nothing added) when its new tiles would not fit on the disk."""
        self.add_named(dict(zip(LAYERS, planes, strict=True)), c0, r0)

    def add_named(self, planes: dict[str, np.ndarray | None], c0: int, r0: int) -> None:
        """`add` by layer name (any layer of the canvas)."""
        first = next((p for p in planes.values() if p is not None), None)
        if first is None:
            return
        h, w = first.shape
        box = self._clip(h, w, c0, r0)
        if box is None:
            return
        a0, a1, b0, b1 = box
        ro, co = self.offset
        store = self.store
        windows = store.windows(a0 + ro, a1 + ro, b0 + co, b1 + co)   # the tiles, once for every layer
        names = [name for name, plane in planes.items() if plane is not None]
        store.reserve([(name, w[0], w[1]) for name in names for w in windows])   # all or nothing
        if self._saved is not None:
            self._save_for_prior([(w[0], w[1]) for w in windows])
        for name in names:
            plane = planes[name]
            assert plane is not None
            largest = store.add_windows(name, plane[a0 - r0:a1 - r0, b0 - c0:b1 - c0], windows,
                                        track_max=name == "weight")
            if largest > self.weight_max:
                self.weight_max = largest
        self._mark(a0 + ro, a1 + ro, b0 + co, b1 + co)

    def _mark(self, a0: int, a1: int, b0: int, b1: int) -> None:
        used = self._used
        if used is None:
            self._used = [a0, a1, b0, b1]
        else:
            used[0], used[1] = min(used[0], a0), max(used[1], a1)
            used[2], used[3] = min(used[2], b0), max(used[3], b1)

    def clear(self, name: str) -> None:
        """Set a layer to zero everywhere (its tiles kept)."""
        tiles = sorted(self.store.tiles(name))
        if self._saved is not None:
            self._save_for_prior(tiles)
        for ix, iy in tiles:
            tile = self.store.get(name, ix, iy, write=True)
            if tile is not None:
                tile[...] = 0

    def read(self, name: str, box: tuple[int, int, int, int]) -> np.ndarray:
        """A layer over rows [row0, row1) and columns [column0, column1) of the canvas (a copy)."""
        r0, r1, c0, c1 = box
        ro, co = self.offset
        return self.store.read(name, r0 + ro, r1 + ro, c0 + co, c1 + co)

    def value(self, level: float, min_weight: float = 1e-3) -> tuple[np.ndarray, np.ndarray]:
        """(flat-field-corrected map as float32 grey, weight), rows growing with y, the whole canvas."""
        grey, weight = np.zeros(self.shape, np.float32), np.zeros(self.shape, np.float32)
        box = self.used()
        if box is not None:
            r0, r1, c0, c1 = box
            grey[r0:r1, c0:c1], weight[r0:r1, c0:c1] = self.value_in(level, box, min_weight)
        return grey, weight

    def value_in(self, level: float, box: tuple[int, int, int, int],
                 min_weight: float = 1e-3) -> tuple[np.ndarray, np.ndarray]:
        """`value` over rows [row0, row1) and columns [column0, column1) of the canvas."""
        return _value(self.read("band", box), self.read("flat", box), self.read("weight", box), level, min_weight)

    def view(self, level: float) -> IntensityView:
        """The flat-field-corrected map at grey `level` as a `tiles.LayerView` (absolute cells)."""
        return IntensityView(self, level)

    def ratio_view(self, numerator: str, denominator: str = "weight", scale: float = 1.0,
                   min_denominator: float = 1e-3, weight: str = "weight") -> RatioView:
        """A layer kept as a weighted sum (e.g. sum(w height) beside sum(w)) as a `tiles.LayerView`: value =
        scale numerator / denominator where the denominator is at least `min_denominator`, weights the
        layer `weight` there (the canvas's own by default; a file leaves cells of weight below
        `min_denominator`, or `MAPPED_WEIGHT` with the canvas's, out) (absolute cells); what
        `geotiff.write_geotiff(..., kind="float")` writes."""
        return RatioView(self, numerator, denominator, scale, min_denominator, weight)

    def mapped_extent(self) -> tuple[int, int, int, int] | None:
        """(row0, row1, column0, column1) of the canvas around the mapped cells (weight above
        `MAPPED_WEIGHT`), read a tile at a time; None: nothing mapped."""
        box = self.used()
        if box is None:
            return None
        ro, co = self.offset
        rows: list[int] = []
        cols: list[int] = []
        t = self.tile
        for ix, iy in self.store.tiles("weight"):
            tile = self.store.get("weight", ix, iy)
            assert tile is not None
            mapped = tile > MAPPED_WEIGHT
            any_rows, any_cols = np.flatnonzero(mapped.any(axis=1)), np.flatnonzero(mapped.any(axis=0))
            if len(any_rows):
                rows += [iy * t + int(any_rows[0]) - ro, iy * t + int(any_rows[-1]) + 1 - ro]
                cols += [ix * t + int(any_cols[0]) - co, ix * t + int(any_cols[-1]) + 1 - co]
        if not rows:
            return None
        h, w = self.shape
        return max(min(rows), 0), min(max(rows), h), max(min(cols), 0), min(max(cols), w)

    # -- the prior: copy-on-write --------------------------------------------------------------------
    def begin_prior(self, level: float) -> None:
        """From now on `prior_read` gives the sums as they are now (and `prior_level` the grey level)."""
        for name in LAYERS:
            self.store.drop_layer(f"prior_{name}")
            self.store.add_layer(f"prior_{name}", np.float32)
        self._saved = {}
        self.prior_level = level
        self.prior_weight_max = self.weight_max

    def _save_for_prior(self, tiles: Sequence[tuple[int, int]]) -> None:
        assert self._saved is not None
        for ix, iy in tiles:
            if (ix, iy) in self._saved:
                continue
            exists = self.store.has("weight", ix, iy)
            if exists:
                for name in LAYERS:
                    source = self.store.get(name, ix, iy)
                    if source is not None:
                        target = self.store.get(f"prior_{name}", ix, iy, create=True, write=True)
                        assert target is not None
                        target[...] = source
            self._saved[(ix, iy)] = exists

    def prior_value(self, r0: int, c0: int, h: int, w: int) -> tuple[np.ndarray, np.ndarray]:
        """(value, weight) of canvas cells [r0, r0 + h) x [c0, c0 + w) as they were at `begin_prior`
        (zero weight where nothing was mapped then), at the grey level of then."""
        ro, co = self.offset
        a0, b0 = r0 + ro, c0 + co
        sums = [self.store.read(name, a0, a0 + h, b0, b0 + w) for name in LAYERS]
        if self._saved:
            t = self.tile
            for ix, iy in self.store.spans(a0, a0 + h, b0, b0 + w):
                existed = self._saved.get((ix, iy))
                if existed is None:
                    continue
                y0, y1 = max(a0, iy * t), min(a0 + h, (iy + 1) * t)
                x0, x1 = max(b0, ix * t), min(b0 + w, (ix + 1) * t)
                for k, name in enumerate(LAYERS):
                    part = sums[k][y0 - a0:y1 - a0, x0 - b0:x1 - b0]
                    if existed:
                        part[...] = self.store.read(f"prior_{name}", y0, y1, x0, x1)
                    else:
                        part[...] = 0
        return _value(sums[0], sums[1], sums[2], self.prior_level)


def _value(band: np.ndarray, flat: np.ndarray, weight: np.ndarray, level: float,
           min_weight: float = 1e-3, in_place: bool = False) -> tuple[np.ndarray, np.ndarray]:
    """(grey, weight): level * band / flat where the weight and the flat field are known, else 0.
    `in_place`: written over `band` and `weight` (the caller's own copies: two fewer arrays to allocate
    and fill for the same values)."""
    known = (weight > min_weight) & (flat > 1e-6)
    if not in_place:
        grey = np.divide(band * np.float32(level), flat, out=np.zeros_like(band), where=known)
        return grey, np.where(known, weight, np.float32(0.0))
    unknown = ~known
    np.multiply(band, np.float32(level), out=band)
    np.divide(band, flat, out=band, where=known)
    np.copyto(band, np.float32(0.0), where=unknown)
    np.copyto(weight, np.float32(0.0), where=unknown)
    return band, weight


class RatioView:
    """`WorldCanvas.ratio_view`: one layer over another, with the canvas's weights and extent."""

    mapped_weight = MAPPED_WEIGHT

    def __init__(self, canvas: WorldCanvas, numerator: str, denominator: str, scale: float,
                 min_denominator: float, weight: str = "weight") -> None:
        self.canvas, self.numerator, self.denominator = canvas, numerator, denominator
        self.scale, self.min_denominator, self.weight = scale, min_denominator, weight
        self.tile, self.resolution, self.origin = canvas.tile, canvas.resolution, canvas.anchor
        if weight != "weight":   # a cell counts where its own weight is at least min_denominator
            self.mapped_weight = float(np.nextafter(np.float32(min_denominator), np.float32(0)))

    def read(self, r0: int, r1: int, c0: int, c1: int) -> tuple[np.ndarray, np.ndarray]:
        store = self.canvas.store
        top = store.read(self.numerator, r0, r1, c0, c1).astype(np.float32, copy=False)
        bottom = store.read(self.denominator, r0, r1, c0, c1).astype(np.float32, copy=False)
        known = bottom >= np.float32(self.min_denominator)
        value = np.divide(top * np.float32(self.scale), bottom, out=np.zeros_like(top), where=known)
        weights = bottom if self.weight == self.denominator else store.read(self.weight, r0, r1, c0, c1)
        weight = np.where(known, weights, np.float32(0))
        return value, weight

    def extent(self) -> tuple[int, int, int, int] | None:
        return IntensityView(self.canvas, 1.0).extent()


class IntensityView:
    """The canvas's flat-field-corrected map as a `tiles.LayerView`: cells absolute (the store's)."""

    mapped_weight = MAPPED_WEIGHT

    def __init__(self, canvas: WorldCanvas, level: float) -> None:
        self.canvas, self.level = canvas, level
        self.tile, self.resolution, self.origin = canvas.tile, canvas.resolution, canvas.anchor

    def read(self, r0: int, r1: int, c0: int, c1: int) -> tuple[np.ndarray, np.ndarray]:
        store = self.canvas.store
        band, flat, weight = (store.read(name, r0, r1, c0, c1) for name in LAYERS)   # copies: ours to overwrite
        return _value(band, flat, weight, self.level, in_place=True)

    def extent(self) -> tuple[int, int, int, int] | None:
        """The absolute cells a file of the map holds: a fixed map's bounds, else around what was mapped."""
        canvas = self.canvas
        box = (0, canvas.shape[0], 0, canvas.shape[1]) if canvas.fixed else canvas.mapped_extent()
        if box is None or box[1] <= box[0] or box[3] <= box[2]:
            return None
        ro, co = canvas.offset
        return box[0] + ro, box[1] + ro, box[2] + co, box[3] + co


# ------------------------------------------------------------------------------------------------ placing
@dataclass(frozen=True)
class _Placement:
    """Where a band landed on the map: for an axis-aligned roller (`axes` not None: transpose, flip rows,
    flip columns) the oriented band at (c0, r0) blended by the 2x2 bilinear `kernel`; else the affine
    `matrix` (band -> patch) of a (w, h) patch at (c0, r0). An axis-aligned placement may hold its `matrix` and
    `size` too (the same cells as the blend's), for what is interpolated rather than blended."""

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


class _Prior:
    """The map's value and weight at a pass's start (what registration compares the pass's frames with),
    read from the canvas's copy-on-write prior (`WorldCanvas.begin_prior`)."""

    def __init__(self, canvas: WorldCanvas, level: float) -> None:
        self.canvas = canvas
        canvas.begin_prior(level)
        self.weight_max = canvas.prior_weight_max

    def moved(self, dc: int, dr: int) -> _Prior:
        """The canvas grew (its cells moved by (dc, dr)): the prior reads absolute cells, so it is the same."""
        return self

    def patch(self, r0: int, c0: int, h: int, w: int) -> tuple[np.ndarray, np.ndarray] | None:
        """(value, weight) of the canvas's cells [r0, r0 + h) x [c0, c0 + w) as they were at the pass's
        start (zero weight where nothing was mapped then, also cells the canvas has grown by since)."""
        return self.canvas.prior_value(r0, c0, h, w)
