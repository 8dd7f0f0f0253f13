"""Defects in a height map: the residual over the local surface, hysteresis thresholds from its robust
noise, regions, and each region classified (crack, dent, bump) and measured.

Arrays are images: row 0 is the largest y (as map.png and a GeoTIFF), `origin` is the (x, y) of the
lower-left pixel's outer corner in the map's frame, `resolution` metres per pixel; pixel (row r, column c)
has its centre at (x0 + (c + 0.5) res, y0 + (rows - r - 0.5) res).
"""
from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, replace

import cv2
import numpy as np

from touchroller_perception.inspection.background import local_surface, texture_peak
from touchroller_perception.inspection.centreline import across, path_length, smooth_path, trace
from touchroller_perception.inspection.types import (
    Finding,
    InspectionConfig,
    InspectionDiagnostics,
    InspectionResult,
    Kind,
    Point,
)

DEFAULT_CONFIG = InspectionConfig()
_BROAD = Finding(0, "crack", math.nan, math.nan, math.nan, math.nan, math.nan, math.nan, 0.0)   # counted, dropped


@dataclass(frozen=True)
class _Grid:
    resolution: float
    x0: float
    y0: float
    rows: int

    def points(self, rc: np.ndarray) -> tuple[Point, ...]:
        """(row, col) pixel coordinates -> (x, y) in the map's frame."""
        x = self.x0 + (rc[:, 1] + 0.5) * self.resolution
        y = self.y0 + (self.rows - rc[:, 0] - 0.5) * self.resolution
        return tuple((float(a), float(b)) for a, b in zip(x, y, strict=True))


@dataclass
class _Counts:
    short: int = 0
    small: int = 0
    broad: int = 0
    shallow: int = 0
    edge: int = 0


def _check(values: np.ndarray, resolution: float, origin: Sequence[float], mask: np.ndarray | None) -> None:
    if values.ndim != 2:
        raise ValueError(f"the map must be a 2-D array, got shape {values.shape}")
    if not (math.isfinite(resolution) and resolution > 0):
        raise ValueError(f"resolution must be a positive number of metres per pixel, got {resolution}")
    if len(origin) < 2 or not all(math.isfinite(float(v)) for v in origin[:2]):
        raise ValueError(f"origin must be a finite (x, y), got {origin}")
    if mask is not None and mask.shape != values.shape:
        raise ValueError(f"the mask's shape {mask.shape} is not the map's {values.shape}")


def inspect(height: np.ndarray, resolution: float, origin: Sequence[float], mask: np.ndarray | None = None,
            config: InspectionConfig = DEFAULT_CONFIG) -> InspectionResult:
    """Findings in a height map (metres, positive up; NaN where unmapped). `mask`: True where nothing
    must be reported (a declared panel joint), left out of the local surface too."""
    return _detect(np.asarray(height), resolution, origin, mask, config, depth_known=True)


def inspect_height(height: np.ndarray, resolution: float, origin: Sequence[float], mask: np.ndarray | None = None,
                   config: InspectionConfig = DEFAULT_CONFIG) -> list[Finding]:
    """`inspect(...).findings`."""
    return inspect(height, resolution, origin, mask, config).findings


def inspect_intensity(grey: np.ndarray, resolution: float, origin: Sequence[float], mask: np.ndarray | None = None,
                      config: InspectionConfig = DEFAULT_CONFIG) -> InspectionResult:
    """Findings in an intensity map (grey levels; NaN or masked where unmapped) when no height exists.

    A tactile map's grey is shading: a defect shows as a bright and a dark side (a crack as two lines, a
    dent as two half-moons), not as one sign. So the map's anomaly is unsigned: |grey - its local mean|,
    smoothed over `intensity_blur_m` (which joins the two sides into one region), and the height method
    runs on it with its thresholds from the noise, at least `min_intensity` grey levels. Places and shapes
    only: `depth_m` is NaN, widths include the shading's two sides, and a compact anomaly is a dent when
    its middle is darker than its surroundings, a bump when brighter (a shading's sign: not reliable)."""
    values = np.asarray(grey)
    _check(values, resolution, origin, mask)
    if values.size == 0:
        return _empty()
    energy, signed = _anomaly(values, resolution, mask, config)
    result = _detect(-energy, resolution, origin, mask, replace(config, min_depth_m=config.min_intensity),
                     depth_known=False)
    return InspectionResult(_signed_kinds(result.findings, signed, resolution, origin), result.diagnostics)


def _anomaly(values: np.ndarray, resolution: float, mask: np.ndarray | None,
             config: InspectionConfig) -> tuple[np.ndarray, np.ndarray]:
    """(unsigned anomaly |grey - local mean| smoothed, NaN where unusable; the signed residual)."""
    finite = np.isfinite(values)
    usable = finite if mask is None else finite & ~np.asarray(mask, bool)
    v = np.where(usable, values, 0.0).astype(np.float32)
    surface, _ = local_surface(v, usable, config.background_scale_m / resolution, config.background_iterations,
                               config.background_reject, config.noise_sample)   # a defect kept out of its mean
    signed = np.where(usable, v - surface, 0.0).astype(np.float32)
    blur = config.intensity_blur_m / resolution
    energy = np.abs(signed)
    if blur > 0:
        weight = cv2.GaussianBlur(usable.astype(np.float32), (0, 0), blur, borderType=cv2.BORDER_CONSTANT)
        energy = cv2.GaussianBlur(energy, (0, 0), blur, borderType=cv2.BORDER_CONSTANT) / np.maximum(weight, 1e-6)
    return np.where(usable, energy, np.nan).astype(np.float32), signed


def _signed_kinds(findings: list[Finding], signed: np.ndarray, resolution: float,
                  origin: Sequence[float]) -> list[Finding]:
    """Compact anomalies named by their middle's sign: darker a dent, brighter a bump."""
    rows, cols = signed.shape
    out = []
    for f in findings:
        if f.kind != "crack":
            col = (f.x - float(origin[0])) / resolution - 0.5
            row = rows - 0.5 - (f.y - float(origin[1])) / resolution
            half = max(1, round(0.25 * f.width_m / resolution))
            r0, r1 = max(0, round(row) - half), min(rows, round(row) + half + 1)
            c0, c1 = max(0, round(col) - half), min(cols, round(col) + half + 1)
            middle = float(signed[r0:r1, c0:c1].mean()) if r1 > r0 and c1 > c0 else 0.0
            f = replace(f, kind="bump" if middle > 0 else "dent")
        out.append(replace(f, depth_m=math.nan))
    return out


def inspect_region(height: np.ndarray, resolution: float, origin: Sequence[float],
                   region: tuple[float, float, float, float], margin_m: float | None = None,
                   mask: np.ndarray | None = None, config: InspectionConfig = DEFAULT_CONFIG,
                   intensity: bool = False) -> InspectionResult:
    """`inspect` (`inspect_intensity` with `intensity`) on a window of the map: `region` (x_min, y_min, x_max,
    y_max) plus `margin_m` around it (default three background scales: the local surface there is then
    the whole map's), keeping the findings whose centre lies in `region`. For a live map: the newly mapped
    region, inspected while the rest of the map stays as it was."""
    values = np.asarray(height)
    _check(values, resolution, origin, mask)
    margin = 3 * config.background_scale_m if margin_m is None else float(margin_m)
    x_min, y_min, x_max, y_max = (float(v) for v in region)
    rows, cols = values.shape
    x0, y0 = float(origin[0]), float(origin[1])
    c0 = max(0, math.floor((x_min - margin - x0) / resolution))
    c1 = min(cols, math.ceil((x_max + margin - x0) / resolution))
    r0 = max(0, math.floor((y0 + rows * resolution - (y_max + margin)) / resolution))
    r1 = min(rows, math.ceil((y0 + rows * resolution - (y_min - margin)) / resolution))
    if c1 <= c0 or r1 <= r0:
        return _empty()
    window = (x0 + c0 * resolution, y0 + (rows - r1) * resolution)
    how = inspect_intensity if intensity else inspect
    result = how(values[r0:r1, c0:c1], resolution, window, None if mask is None else np.asarray(mask)[r0:r1, c0:c1],
                 config)
    kept = [f for f in result.findings if x_min <= f.x <= x_max and y_min <= f.y <= y_max]
    return InspectionResult([replace(f, id=i + 1) for i, f in enumerate(kept)], result.diagnostics)


def _empty(valid: int = 0, sigma: float = 0.0, texture: float = 0.0, high: float = 0.0,
           low: float = 0.0) -> InspectionResult:
    return InspectionResult([], InspectionDiagnostics(sigma, texture, high, low, valid, 0, 0, 0, 0, 0))


def _detect(values: np.ndarray, resolution: float, origin: Sequence[float], mask: np.ndarray | None,
            config: InspectionConfig, depth_known: bool) -> InspectionResult:
    _check(values, resolution, origin, mask)
    if values.size == 0:
        return _empty()
    grid = _Grid(float(resolution), float(origin[0]), float(origin[1]), values.shape[0])
    finite = np.isfinite(values)
    usable = finite if mask is None else finite & ~np.asarray(mask, bool)
    if not usable.any():
        return _empty()
    sample = values[usable]
    offset = float(np.median(sample[:: max(1, sample.size // config.noise_sample)]))
    v = (values.astype(np.float64) - offset).astype(np.float32)
    v[~finite] = 0.0
    surface, sigma = local_surface(v, usable, config.background_scale_m / resolution, config.background_iterations,
                                   config.background_reject, config.noise_sample,
                                   reject_floor=config.low_fraction * config.min_depth_m)
    residual = v - surface
    margin = math.ceil(config.edge_margin_m / resolution)
    valid = usable & np.isfinite(residual)
    if margin > 0:
        kernel = np.ones((2 * margin + 1, 2 * margin + 1), np.uint8)
        valid = cv2.erode(valid.astype(np.uint8), kernel, borderType=cv2.BORDER_CONSTANT, borderValue=0) > 0
    texture = texture_peak(residual, valid, round(2 * config.background_scale_m / resolution))
    high = max(config.min_depth_m, config.noise_multiple * sigma, config.texture_multiple * texture)
    low = config.low_fraction * high
    n_valid = int(valid.sum())
    if high <= 0 or n_valid == 0:
        return _empty(n_valid, sigma, texture, high, low)
    residual = np.where(valid, residual, np.float32(0.0))
    counts = _Counts()
    findings: list[Finding] = []
    components = 0
    edge_distance = None
    if config.edge_band_m > 0:   # px from the nearest unusable pixel or the array's border
        inside = np.pad(usable.astype(np.uint8), 1)
        edge_distance = cv2.distanceTransform(inside, cv2.DIST_L2, 5)[1:-1, 1:-1]
    gap = max(1, round(config.gap_m / resolution))
    closing = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * gap + 1, 2 * gap + 1)) if gap > 1 else None
    for sign in (1.0, -1.0):
        depth = (-sign * residual).astype(np.float32)      # the feature positive: a depression for sign +1
        grow = (depth >= low).astype(np.uint8)
        if closing is not None:
            grow = cv2.morphologyEx(grow, cv2.MORPH_CLOSE, closing)
        grow &= valid.astype(np.uint8)
        n, labels, stats, _ = cv2.connectedComponentsWithStats(grow, connectivity=8, ltype=cv2.CV_32S)
        seeded = np.zeros(n, bool)
        seeded[labels[(depth >= high) & valid]] = True
        seeded[0] = False
        for label in np.flatnonzero(seeded):
            components += 1
            c, r, w, h = (int(v) for v in stats[label, :4])
            region = labels[r:r + h, c:c + w] == label
            crack_allowed = sign > 0 or not depth_known
            finding: Finding | None = (_crack(depth, region, (r, c), grid, config, sigma, high, counts, depth_known)
                       if crack_allowed else None)
            if finding is None:
                finding = _compact(depth, region, (r, c), grid, config, sigma, high, sign, counts, depth_known)
            if finding is not None and finding is not _BROAD:
                if _along_edge(finding, region, (r, c), edge_distance, config, resolution):
                    counts.edge += 1
                    continue
                findings.append(finding)
    findings.sort(key=lambda f: (-f.y, f.x))
    findings = [replace(f, id=i + 1) for i, f in enumerate(findings)]
    diagnostics = InspectionDiagnostics(sigma, texture, high, low, n_valid, components, counts.short, counts.small,
                                        counts.broad, counts.shallow, counts.edge)
    return InspectionResult(findings, diagnostics)


def _confidence(peak: float, sigma: float, config: InspectionConfig) -> float:
    if sigma <= 0:
        return 1.0
    return float(1.0 - math.exp(-((peak / sigma) / config.noise_multiple) ** 2))


def _crack(depth: np.ndarray, region: np.ndarray, corner: tuple[int, int], grid: _Grid, config: InspectionConfig,
           sigma: float, high: float, counts: _Counts, depth_known: bool) -> Finding | None:
    """A crack when the region is long and narrow enough; None to treat it as compact. Counts (in
    `counts.short`) and drops an elongated region shorter than the minimum crack length."""
    res = grid.resolution
    skeleton = trace(np.pad(region, 1), config.min_branch_length_m / res)
    if skeleton is None:
        return None
    offset = np.array([corner[0] - 1.0, corner[1] - 1.0])
    trunk = smooth_path(skeleton.trunk + offset)
    trunk_px = path_length(trunk)
    total_px = trunk_px + sum(path_length(b) for b in skeleton.branches)
    rough_width = float(region.sum()) / max(total_px, 1.0)
    if trunk_px < config.crack_aspect * rough_width or trunk.shape[0] < 3:
        return None
    if not depth_known and (float(np.hypot(*(trunk[-1] - trunk[0]))) < 0.6 * trunk_px
                            or trunk_px * res < config.intensity_min_crack_m):
        return None     # an intensity map's ring, horseshoe or short streak: the shaded sides of a dent or bump
    profiles = across(depth, trunk, half_width_px=float(np.clip(2.5 * rough_width + 2, 4, 40)))
    good = np.isfinite(profiles.fwhm_px) & (profiles.peak > 0)
    if good.sum() < 2:
        return None
    fwhm = profiles.fwhm_px[good]
    peaks = profiles.peak[good]
    # the map's footprint (its pixel and the sensor's blur) widens a crack in quadrature and keeps its
    # cross-section's area: the width is the median full width less the footprint, the depth the median
    # area over that width (medians first: a width near the footprint's would make per-profile ratios explode)
    footprint = _footprint_px(config, res)
    measured = float(np.median(fwhm))
    width_px = math.sqrt(max(measured**2 - footprint**2, 0.25**2))
    depth_value = float(np.median(peaks * fwhm)) / width_px
    centre = profiles.centre.copy()
    centre[~good] = trunk[~good]
    centre = smooth_path(centre, 5)
    length_px = path_length(centre) + width_px
    if length_px < config.crack_aspect * width_px:
        return None
    if depth_value < high:      # a seed or two past the threshold on a shallower line: texture
        counts.shallow += 1
        return _BROAD
    if width_px * res > config.max_crack_width_m:
        counts.broad += 1
        return _BROAD
    if length_px * res < config.min_crack_length_m:
        counts.short += 1
        return None
    centre = _extend(centre, 0.5 * width_px)
    lines = [centre] + [smooth_path(b + offset) for b in skeleton.branches   # (an intensity map's are the
                        if depth_known                                       # shading's two sides: none)
                        and path_length(b) >= max(config.min_branch_length_m / res, 2 * width_px)]
    lines = [_simplify(line) for line in lines]
    mids, weights = [], []
    for line in lines:
        seg = np.hypot(*np.diff(line, axis=0).T)
        mids.append(0.5 * (line[1:] + line[:-1]))
        weights.append(seg)
    mid, weight = np.concatenate(mids), np.concatenate(weights)
    centroid = (mid * weight[:, None]).sum(axis=0) / max(weight.sum(), 1e-12)
    (x, y), = grid.points(centroid[None, :])
    total = sum(path_length(line) for line in lines)
    return Finding(0, "crack", x, y, length_px * res, width_px * res, depth_value if depth_known else math.nan,
                   total * width_px * res * res, _confidence(float(np.median(peaks)), sigma, config),
                   polylines=tuple(grid.points(line) for line in lines))


def _along_edge(finding: Finding, region: np.ndarray, corner: tuple[int, int], edge_distance: np.ndarray | None,
                config: InspectionConfig, resolution: float) -> bool:
    """An elongated finding (length >= crack_aspect x width) whose pixels lie, by their median, within
    `edge_band_m` of the map's edge (or a NaN, or the mask): the edge's artefact, not a defect."""
    if edge_distance is None or not finding.length_m >= config.crack_aspect * finding.width_m:
        return False
    r, c = corner
    distances = edge_distance[r:r + region.shape[0], c:c + region.shape[1]][region]
    return bool(distances.size) and float(np.median(distances)) * resolution <= config.edge_band_m


def _footprint_px(config: InspectionConfig, resolution: float) -> float:
    """The map's footprint (FWHM, px): its pixel's and the sensor's blur in quadrature."""
    return math.hypot(config.footprint_fwhm_px, config.blur_fwhm_m / resolution)


def _extend(path: np.ndarray, by: float) -> np.ndarray:
    """The path longer by `by` px at each end, along its end directions (the skeleton stops short)."""
    out = path.copy()
    for end, inner in ((0, min(3, len(path) - 1)), (-1, max(-4, -len(path)))):
        direction = path[end] - path[inner]
        norm = float(np.hypot(*direction))
        if norm > 0:
            out[end] = path[end] + direction / norm * by
    return out


def _simplify(path: np.ndarray, tolerance: float = 0.2) -> np.ndarray:
    if path.shape[0] <= 2:
        return path
    kept = cv2.approxPolyDP(path[:, ::-1].astype(np.float32).reshape(-1, 1, 2), tolerance, False)
    out = kept.reshape(-1, 2)[:, ::-1].astype(np.float64)
    out[0], out[-1] = path[0], path[-1]
    return out


def _compact(depth: np.ndarray, region: np.ndarray, corner: tuple[int, int], grid: _Grid, config: InspectionConfig,
             sigma: float, high: float, sign: float, counts: _Counts, depth_known: bool) -> Finding | None:
    """A dent (sign +1) or bump (sign -1): its robust peak, the region past half of it, its outline."""
    res = grid.resolution
    pad = 3
    r0, c0 = max(0, corner[0] - pad), max(0, corner[1] - pad)
    r1 = min(depth.shape[0], corner[0] + region.shape[0] + pad)
    c1 = min(depth.shape[1], corner[1] + region.shape[1] + pad)
    crop = cv2.GaussianBlur(depth[r0:r1, c0:c1], (0, 0), 0.8, borderType=cv2.BORDER_REPLICATE)
    inside = np.zeros(crop.shape, bool)
    inside[corner[0] - r0:corner[0] - r0 + region.shape[0], corner[1] - c0:corner[1] - c0 + region.shape[1]] = region
    values = np.where(inside, crop, -np.inf)
    at = np.unravel_index(int(np.argmax(values)), crop.shape)
    peak = float(crop[at])
    if not peak >= high:        # the seed was a pixel or two of noise past the threshold
        counts.shallow += 1
        return None
    if depth_known:
        n, labels = cv2.connectedComponents((crop >= 0.5 * peak).astype(np.uint8), connectivity=8)
        half = labels == labels[at]
    else:   # an intensity map: the shading's sides are apart, each a piece past half the peak
        half = (crop >= 0.5 * peak) & inside
    count = int(half.sum())
    if math.sqrt(4 * count / math.pi) * res < config.min_blob_diameter_m:
        counts.small += 1
        return None
    rr, cc = np.nonzero(half)
    w = crop[rr, cc].astype(np.float64)
    w = np.maximum(w, 0) / max(float(np.maximum(w, 0).sum()), 1e-30)
    centre = np.array([(rr * w).sum() + r0, (cc * w).sum() + c0])
    coords = np.stack([rr, cc], axis=1).astype(np.float64)
    cov = np.cov(coords.T) if count > 1 else np.zeros((2, 2))
    eig = np.sort(np.linalg.eigvalsh(cov + np.eye(2) / 12.0))[::-1]
    length, width = (4 * math.sqrt(max(float(e), 0.0)) * res for e in eig)
    contours, _ = cv2.findContours(half.astype(np.uint8), cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_SIMPLE)
    if not depth_known and len(contours) > 1:   # the pieces' hull
        contours = [cv2.convexHull(np.vstack(contours))]
    outline = max(contours, key=len).reshape(-1, 2)[:, ::-1].astype(np.float64) if contours else np.zeros((0, 2))
    if outline.shape[0] < 3:   # a line or a point: the pixels' outer square
        top, left = rr.min() - 0.5, cc.min() - 0.5
        bottom, right = rr.max() + 0.5, cc.max() + 0.5
        outline = np.array([[top, left], [top, right], [bottom, right], [bottom, left]])
    outline = outline + np.array([r0, c0])
    outline = np.vstack([outline, outline[:1]])
    if width > config.max_blob_width_m:
        counts.broad += 1
        return None
    measured_peak = peak
    if config.blur_fwhm_m > 0:
        # a compact bell blurred by the sensor: wider in quadrature, its volume kept (its peak x diameter²);
        # at most a factor 2 in diameter taken out (a dent narrower than the blur is not deconvolved further)
        measured = math.sqrt(4 * count / math.pi) * res
        true = math.sqrt(max(measured**2 - config.blur_fwhm_m**2, (measured / 2) ** 2))
        peak *= (measured / true) ** 2
        length, width = (math.sqrt(max(a**2 - config.blur_fwhm_m**2, (a / 2) ** 2)) for a in (length, width))
    (x, y), = grid.points(centre[None, :])
    kind: Kind = "dent" if sign > 0 else "bump"
    value = (peak if sign > 0 else -peak) if depth_known else math.nan
    return Finding(0, kind, x, y, length, width, value, count * res * res, _confidence(measured_peak, sigma, config),
                   polygon=grid.points(outline))
