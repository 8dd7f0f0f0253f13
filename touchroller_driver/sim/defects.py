"""Defects the simulator plants in a scene's surface (`surface.defects`), and their truth as findings.

A scene asks for them under its surface, on any background kind:

    surface:
      kind: panel
      defects:
        seed: 0                          # the defects' own random stream (not the sensor's seed)
        area: [-0.01, 0.01, 0.01, 0.04]  # x_min, y_min, x_max, y_max in the surface frame S (m); default:
                                         # the surface less `clearance` at its edges
        cracks: 2                        # how many of each
        dents: 1
        bumps: 1
        crack_width: [1.0e-4, 5.0e-4]    # m, full width at half depth (log-uniform in the range)
        crack_depth: [2.0e-5, 1.0e-4]    # m (log-uniform), varying along the crack by `depth_variation`
        crack_length: [5.0e-3, 1.5e-2]   # m along the trunk (uniform)
        branch_probability: 0.4          # a crack has one or two side branches
        blob_diameter: [1.0e-3, 4.0e-3]  # m, the rim's diameter (uniform)
        blob_depth: [2.0e-5, 1.0e-4]     # m (log-uniform); a dent is below the surface, a bump above
        clearance: 2.0e-3                # m between defects, and from the area's edges

The limits the generator keeps to: crack widths 0.05-1 mm, depths 10-300 um, dent and bump diameters
0.5-5 mm. Geometry (its own, not the inspection bench's generator's):

* a crack is a random walk of its heading (a smoothed random turn rate, so the centreline curves but does
  not kink), sampled every quarter of the finer of its width and the grid's cell; its cross-section is a
  Gaussian of full width at half depth `width`, its depth a smooth random profile around the nominal
  (`depth_variation`, log-normal) that tapers to zero over the last half millimetre (or tenth of the
  length) at each end; a branch leaves the trunk at 25-75 % of its length, 30-60 degrees off it, 20-45 % as
  long but shorter than the trunk's shorter side there (the trunk stays the crack's longest path, as the
  detector takes it), 0.7 x as wide and deep; where lines overlap the deeper wins;
* a dent or bump is depth x (1 - (r/R)^2)^2 inside its rim R (smooth at the rim);
* each cell holds its area's mean: a groove's Gaussian is widened by the cell's box in quadrature with its
  cross-section's area kept, a dent or bump is averaged over 4 x 4 points in the cell.

The truth is in the findings' conventions (`touchroller_perception.inspection.Finding`): a crack's (x, y) is
its centrelines' length-weighted centroid, `length_m` the trunk's length, `width_m` its full width at half
depth, `depth_m` the median depth along the trunk away from the tapers, its trunk and branches as
polylines; a dent's or bump's (x, y) its centre, `length_m` = `width_m` its diameter at half depth, its
polygon the circle there, `depth_m` positive for a dent, negative for a bump. `DefectPlan.truth(T_world_S)`
puts it in the world frame (the map's `base`).

Heights here are the surface frame's relief (positive up): a planted depression may go below the surface's
base plane (negative heights).
"""
from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
from scipy.spatial import cKDTree

from touchroller_perception.inspection import Finding
from touchroller_perception.transforms import Transform

LIMITS = {"crack_width": (5e-5, 1e-3), "crack_depth": (1e-5, 3e-4), "blob_diameter": (5e-4, 5e-3),
          "blob_depth": (1e-5, 3e-4), "crack_length": (1e-3, 0.5)}
DEFAULTS: dict[str, Any] = {"seed": 0, "area": None, "cracks": 0, "dents": 0, "bumps": 0,
                            "crack_width": [1e-4, 5e-4], "crack_depth": [2e-5, 1e-4], "crack_length": [5e-3, 1.5e-2],
                            "branch_probability": 0.4, "depth_variation": 0.25,
                            "blob_diameter": [1e-3, 4e-3], "blob_depth": [2e-5, 1e-4], "clearance": 2e-3}
_FWHM = 2.0 * math.sqrt(2.0 * math.log(2.0))
_TAPER_M = 5e-4
_BLOB_HALF = math.sqrt(1.0 - math.sqrt(0.5))     # (1 - u^2)^2 = 1/2: the half-depth radius over the rim's


@dataclass(frozen=True)
class PlantedCrack:
    lines: tuple[np.ndarray, ...]     # (n, 2) S metres: the trunk first, then its branches
    depths: tuple[np.ndarray, ...]    # depth (m) at each point of each line
    widths: tuple[float, ...]         # full width at half depth of each line (m)
    depth_m: float                    # median along the trunk away from its tapers

    @property
    def length_m(self) -> float:
        return _length(self.lines[0])


@dataclass(frozen=True)
class PlantedBlob:
    centre: tuple[float, float]       # S metres
    diameter_m: float                 # the rim's
    depth_m: float                    # > 0 a dent, < 0 a bump


@dataclass(frozen=True)
class DefectPlan:
    """The planted defects of a surface, in its frame S: drawn into any window of its grid by `render`."""

    cracks: tuple[PlantedCrack, ...] = ()
    blobs: tuple[PlantedBlob, ...] = ()

    def __bool__(self) -> bool:
        return bool(self.cracks or self.blobs)

    def render(self, height: np.ndarray, x0: float, y0: float, resolution: float) -> None:
        """Add the defects to `height` in place: a window of the surface grid whose cell (row, col) has its
        centre at S (x0 + (col + 0.5) res, y0 + (row + 0.5) res) (`surfaces.Surface`'s convention). Only
        the defects that reach the window cost anything."""
        carve = np.zeros(height.shape, np.float32)
        for crack in self.cracks:
            for line, depths, width in zip(crack.lines, crack.depths, crack.widths, strict=True):
                _groove(carve, line, depths, width, x0, y0, resolution)
        height -= carve
        for blob in self.blobs:
            _blob(height, blob, x0, y0, resolution)

    def extents(self, resolution: float) -> list[tuple[float, float, float, float]]:
        """(x_min, y_min, x_max, y_max) in S of each defect's reach on a grid of cells of `resolution` m: a
        cell wholly outside all of them is not changed by `render`."""
        boxes = []
        for crack in self.cracks:
            for line, width in zip(crack.lines, crack.widths, strict=True):
                reach = _groove_reach(width, resolution) + resolution
                boxes.append((float(line[:, 0].min()) - reach, float(line[:, 1].min()) - reach,
                              float(line[:, 0].max()) + reach, float(line[:, 1].max()) + reach))
        for blob in self.blobs:
            radius = blob.diameter_m / 2 + resolution
            boxes.append((blob.centre[0] - radius, blob.centre[1] - radius, blob.centre[0] + radius,
                          blob.centre[1] + radius))
        return boxes

    def truth(self, world_from_surface: Transform | None = None) -> list[Finding]:
        """The planted defects as findings (ids from 1: cracks, then dents and bumps), in S or, given
        T_world_S, in the world frame."""
        def place(points: np.ndarray) -> np.ndarray:
            if world_from_surface is None:
                return points
            xyz = np.column_stack([points, np.zeros(len(points))])
            return world_from_surface.apply(xyz)[:, :2]

        out: list[Finding] = []
        for crack in self.cracks:
            mids = np.concatenate([0.5 * (line[1:] + line[:-1]) for line in crack.lines])
            weights = np.concatenate([np.hypot(*np.diff(line, axis=0).T) for line in crack.lines])
            (x, y), = place(((mids * weights[:, None]).sum(axis=0) / weights.sum())[None, :])
            lines = tuple(_points(place(_thin(line))) for line in crack.lines)
            total = float(weights.sum())
            out.append(Finding(len(out) + 1, "crack", float(x), float(y), crack.length_m, crack.widths[0],
                               crack.depth_m, total * crack.widths[0], 1.0, polylines=lines))
        for blob in self.blobs:
            half = _BLOB_HALF * blob.diameter_m
            angles = np.linspace(0.0, 2 * math.pi, 33)
            ring = np.asarray(blob.centre) + 0.5 * half * np.column_stack([np.cos(angles), np.sin(angles)])
            ring[-1] = ring[0]
            (x, y), = place(np.asarray(blob.centre, np.float64)[None, :])
            out.append(Finding(len(out) + 1, "dent" if blob.depth_m > 0 else "bump", float(x), float(y), half, half,
                               blob.depth_m, math.pi * (half / 2) ** 2, 1.0, polygon=_points(place(ring))))
        return out


def _points(array: np.ndarray) -> tuple[tuple[float, float], ...]:
    return tuple((float(a), float(b)) for a, b in array)


def _thin(line: np.ndarray, most: int = 400) -> np.ndarray:
    return np.vstack([line[:-1:max(1, len(line) // most)], line[-1:]])


def _length(line: np.ndarray) -> float:
    return float(np.hypot(*np.diff(line, axis=0).T).sum())


def _groove(carve: np.ndarray, line: np.ndarray, depths: np.ndarray, width: float, x0: float, y0: float,
            resolution: float) -> None:
    """The deeper of `carve` and a Gaussian groove along `line`, area-averaged over the cells."""
    sigma = width / _FWHM
    wide = math.sqrt(sigma**2 + resolution**2 / 12.0)      # a cell's box, in quadrature
    scale = sigma / wide                                  # the cross-section's area kept
    reach = _groove_reach(width, resolution)
    rows, cols = carve.shape
    c0 = max(0, math.floor((line[:, 0].min() - reach - x0) / resolution))
    c1 = min(cols, math.ceil((line[:, 0].max() + reach - x0) / resolution))
    r0 = max(0, math.floor((line[:, 1].min() - reach - y0) / resolution))
    r1 = min(rows, math.ceil((line[:, 1].max() + reach - y0) / resolution))
    if c1 <= c0 or r1 <= r0:
        return
    rr, cc = np.mgrid[r0:r1, c0:c1]
    centres = np.column_stack([x0 + (cc.ravel() + 0.5) * resolution, y0 + (rr.ravel() + 0.5) * resolution])
    distance, index = cKDTree(line).query(centres, distance_upper_bound=reach)
    near = np.isfinite(distance)
    values = np.zeros(len(centres), np.float32)
    values[near] = depths[index[near]] * scale * np.exp(-0.5 * (distance[near] / wide) ** 2)
    window = carve[r0:r1, c0:c1]
    np.maximum(window, values.reshape(window.shape), out=window)


def _groove_reach(width: float, resolution: float) -> float:
    """How far from its centreline a groove of `width` changes cells of `resolution` (m)."""
    return 3.5 * math.sqrt((width / _FWHM) ** 2 + resolution**2 / 12.0) + resolution


def _blob(height: np.ndarray, blob: PlantedBlob, x0: float, y0: float, resolution: float) -> None:
    radius = blob.diameter_m / 2
    cx, cy = blob.centre
    rows, cols = height.shape
    c0, c1 = max(0, math.floor((cx - radius - x0) / resolution)), min(cols, math.ceil((cx + radius - x0) / resolution))
    r0, r1 = max(0, math.floor((cy - radius - y0) / resolution)), min(rows, math.ceil((cy + radius - y0) / resolution))
    if c1 <= c0 or r1 <= r0:
        return
    rr, cc = np.mgrid[r0:r1, c0:c1].astype(np.float64)
    total = np.zeros(rr.shape)
    offsets = (np.arange(4) + 0.5) / 4
    for dy in offsets:
        for dx in offsets:
            u2 = ((x0 + (cc + dx) * resolution - cx) ** 2 + (y0 + (rr + dy) * resolution - cy) ** 2) / radius**2
            total += np.where(u2 < 1.0, (1.0 - u2) ** 2, 0.0)
    height[r0:r1, c0:c1] -= (blob.depth_m * total / offsets.size**2).astype(np.float32)


# --------------------------------------------------------------------------- planning
def _range(spec: Mapping[str, Any], name: str) -> tuple[float, float]:
    value = spec[name]
    try:
        lo, hi = (float(v) for v in value)
    except (TypeError, ValueError):
        raise ValueError(f"surface.defects.{name} must be [min, max] in metres, got {value!r}") from None
    limit_lo, limit_hi = LIMITS[name]
    if not (math.isfinite(lo) and math.isfinite(hi) and limit_lo <= lo <= hi <= limit_hi):
        raise ValueError(f"surface.defects.{name} must be [min, max] with {limit_lo:g} <= min <= max <= "
                         f"{limit_hi:g} m, got {value!r}")
    return lo, hi


def _count(spec: Mapping[str, Any], name: str) -> int:
    value = spec[name]
    if isinstance(value, bool) or not isinstance(value, int) or not 0 <= value <= 1000:
        raise ValueError(f"surface.defects.{name} must be a count 0-1000, got {value!r}")
    return value


def plan_defects(spec: Mapping[str, Any] | None, extent: tuple[float, float, float, float],
                 resolution: float) -> DefectPlan:
    """The defects a scene's `surface.defects` asks for on a surface covering `extent` (x_min, y_min,
    x_max, y_max in S, m) with cells of `resolution` m. An empty plan without `defects`; ValueError, one
    line, on a bad spec. Placed apart from each other (`clearance`): a defect that finds no room after 200
    tries is left out (the plan has fewer)."""
    if not spec:
        return DefectPlan()
    if not isinstance(spec, Mapping):
        raise ValueError(f"surface.defects must be a mapping, got {spec!r}")
    unknown = sorted(set(spec) - set(DEFAULTS))
    if unknown:
        raise ValueError(f"surface.defects: unknown key(s) {', '.join(unknown)} (known: {', '.join(DEFAULTS)})")
    s = {**DEFAULTS, **spec}
    counts = {name: _count(s, name) for name in ("cracks", "dents", "bumps")}
    ranges = {name: _range(s, name) for name in LIMITS}
    clearance = float(s["clearance"])
    branchy = float(s["branch_probability"])
    variation = float(s["depth_variation"])
    if not (math.isfinite(clearance) and clearance >= 0 and 0 <= branchy <= 1 and 0 <= variation <= 1):
        raise ValueError("surface.defects: clearance must be >= 0, branch_probability and depth_variation in [0, 1]")
    area = extent if s["area"] is None else tuple(float(v) for v in s["area"])
    if len(area) != 4 or not all(math.isfinite(v) for v in area):
        raise ValueError(f"surface.defects.area must be [x_min, y_min, x_max, y_max] in m, got {s['area']!r}")
    lo = np.array([max(area[0], extent[0]), max(area[1], extent[1])]) + clearance
    hi = np.array([min(area[2], extent[2]), min(area[3], extent[3])]) - clearance
    if not (hi > lo).all():
        raise ValueError(f"surface.defects.area {list(area)} leaves no room on the surface {list(extent)} "
                         f"(less {clearance:g} m of clearance)")
    rng = np.random.default_rng(int(s["seed"]))
    placed: list[np.ndarray] = []

    def room(points: np.ndarray, reach: float) -> bool:
        if not ((points >= lo).all() and (points <= hi).all()):
            return False
        return all(cKDTree(other).query(points, distance_upper_bound=reach + clearance)[0].min() == np.inf
                   for other in placed)

    cracks: list[PlantedCrack] = []
    for _ in range(counts["cracks"]):
        width = _log_uniform(rng, ranges["crack_width"])
        depth = _log_uniform(rng, ranges["crack_depth"])
        length = float(rng.uniform(*ranges["crack_length"]))
        for _ in range(200):
            crack = _crack(rng, rng.uniform(lo, hi), width, depth, length, branchy, variation, resolution)
            everything = np.vstack(crack.lines)
            if room(everything, width):
                placed.append(everything[:: max(1, len(everything) // 2000)])
                cracks.append(crack)
                break
    blobs: list[PlantedBlob] = []
    for kind in ("dents", "bumps"):
        for _ in range(counts[kind]):
            diameter = float(rng.uniform(*ranges["blob_diameter"]))
            depth = _log_uniform(rng, ranges["blob_depth"]) * (1 if kind == "dents" else -1)
            for _ in range(200):
                centre = rng.uniform(lo, hi)
                angles = np.linspace(0, 2 * math.pi, 25)
                ring = centre + diameter / 2 * np.column_stack([np.cos(angles), np.sin(angles)])
                outline = np.vstack([ring, centre])
                if room(outline, 0.0):
                    placed.append(outline)
                    blobs.append(PlantedBlob((float(centre[0]), float(centre[1])), diameter, depth))
                    break
    return DefectPlan(tuple(cracks), tuple(blobs))


def _log_uniform(rng: np.random.Generator, bounds: Sequence[float]) -> float:
    return float(math.exp(rng.uniform(math.log(bounds[0]), math.log(bounds[1]))))


def _walk(rng: np.random.Generator, start: np.ndarray, heading: float, length: float, step: float) -> np.ndarray:
    """A centreline: the heading's turn rate is smoothed white noise (curves, no kinks)."""
    n = max(3, math.ceil(length / step) + 1)
    knots = max(4, math.ceil(length / 2e-3) + 1)         # a new turn rate every ~2 mm
    rate = np.interp(np.linspace(0, knots - 1, n - 1), np.arange(knots), rng.normal(0.0, 60.0, knots))   # rad/m
    angles = heading + np.cumsum(rate) * (length / (n - 1))
    steps = np.column_stack([np.cos(angles), np.sin(angles)]) * (length / (n - 1))
    return np.vstack([start, start + np.cumsum(steps, axis=0)])


def _profile(rng: np.random.Generator, line: np.ndarray, depth: float, variation: float,
             taper_both: bool = True) -> tuple[np.ndarray, np.ndarray]:
    """(depth per point, the points away from the tapers)."""
    s = np.concatenate([[0.0], np.cumsum(np.hypot(*np.diff(line, axis=0).T))])
    total = s[-1]
    knots = max(4, math.ceil(total / 1.5e-3) + 1)
    wobble = np.exp(variation * np.interp(s, np.linspace(0, total, knots), rng.standard_normal(knots)))
    taper_len = min(_TAPER_M, 0.1 * total)
    from_start = s if taper_both else np.full_like(s, np.inf)
    taper = np.clip(np.minimum(from_start, total - s) / taper_len, 0.0, 1.0)
    return depth * wobble * taper, taper >= 1.0


def _crack(rng: np.random.Generator, start: np.ndarray, width: float, depth: float, length: float,
           branchy: float, variation: float, resolution: float) -> PlantedCrack:
    step = 0.25 * min(width, resolution)
    trunk = _walk(rng, np.asarray(start, np.float64), rng.uniform(0, 2 * math.pi), length, step)
    trunk -= 0.5 * (trunk[-1] - trunk[0])                 # `start` is the crack's middle
    depths, inner = _profile(rng, trunk, depth, variation)
    lines, profiles, widths = [trunk], [depths], [width]
    branches = int(rng.integers(1, 3)) if rng.random() < branchy else 0
    for _ in range(branches):
        k = int(rng.uniform(0.25, 0.75) * (len(trunk) - 1))
        direction = trunk[k + 1] - trunk[k]
        angle = math.atan2(direction[1], direction[0]) + rng.choice([-1.0, 1.0]) * math.radians(rng.uniform(30, 60))
        shorter_side = min(k, len(trunk) - 1 - k) / (len(trunk) - 1) * length
        # shorter than the trunk's shorter side: the trunk stays the crack's longest path
        branch = _walk(rng, trunk[k], angle, min(length * rng.uniform(0.2, 0.45), 0.8 * shorter_side), step)
        branch_depths, _ = _profile(rng, branch, 0.7 * depths[k], variation, taper_both=False)
        lines.append(branch)
        profiles.append(branch_depths)
        widths.append(0.7 * width)
    median = float(np.median(depths[inner] if inner.any() else depths))
    return PlantedCrack(tuple(lines), tuple(profiles), tuple(widths), median)


def surface_defects(surface: Mapping[str, Any]) -> DefectPlan:
    """The plan of a scene's `surface:` block (its `defects` on the grid `make_surface` builds: the same
    width, length, resolution and offsets), without building the surface: what the truth needs."""
    width = float(surface.get("width", 0.08))
    length = float(surface.get("length", 0.11))
    resolution = float(surface.get("resolution", 5e-5))
    if not (width > 0 and length > 0 and resolution > 0):
        raise ValueError("surface: width, length and resolution must be > 0")
    cols, rows = max(1, round(width / resolution)), max(1, round(length / resolution))
    x0 = -0.5 * width + float(surface.get("x_offset", 0.0))
    y0 = float(surface.get("y_offset", 0.0))
    return plan_defects(surface.get("defects"), (x0, y0, x0 + cols * resolution, y0 + rows * resolution),
                        resolution)
