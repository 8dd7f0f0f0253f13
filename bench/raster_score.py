"""A world map (`map.png` + `map.yaml`) against the truth of a second-generator raster, in place.

No alignment: the map and the truth are compared where `base` says they lie. The map and the truth's
ideal appearance (`RasterTruth.appearance`) are resampled into the raster's own frame (u along the
passes, w across, at the map's resolution), where:

* SSIM: over the mapped part of the raster rectangle (both standardised, window 7);
* coverage: the mapped share of the rectangle;
* each pass's residual shift: the pass's central strip (+-12 mm across, 5 mm in from the ends) located
  in the truth by normalised cross-correlation of high-passed images (subpixel), as (along, across) mm;
* seams: lines along the passes, at every pass border (half-way between pass lines) and every band edge
  (32 mm from a pass line) inside the rectangle. The mean profile across the passes of the map and of
  the truth (each standardised, averaged along u) are compared locally: on the profile 2-8 mm either
  side of the border, the map's profile is fitted as a level on each side, a common slope, and a short
  filter of the truth's profile (taps +-0.2 mm: the texture's local gain, blur and subpixel phase; held
  towards the whole width's gain where the truth's profile barely varies, as on glass); the dip is the
  largest departure of the map's profile from that fit within 1.5 mm of the border (where nothing was
  fitted), the step the difference of the two sides' levels, both in units of the map's
  standard deviation. Texture the map and the truth share is explained by the fit and is no seam; a
  line (or a step) the truth does not have at the border is not, because the fit never saw it. The same
  measure at lines 4 mm or more from any border (`seam_floor`, its 95th percentile) says how much the
  map's texture alone departs from the truth's: a border is a seam only where it stands out of that;
* planted features (cracks, dents, grooves, pits), each centred 6 mm or more inside the rectangle: its
  neighbourhood in the map (8 x 8 mm, or for a crack or groove 5 mm wide and as long as holds both its
  ends with 1.5 mm to spare, turned along it) located in the truth (+-1.5 mm), mm off, where the map covers the
  whole window. On a smooth surface a feature is the only
  texture in its window, so the window must hold a crack's ends: a crack running through the window
  pins its placement across itself but not along.
"""
from __future__ import annotations

import math
import re
import warnings
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from bench._common import subpixel_peak
from bench.raster_generator.surfaces import Feature
from bench.raster_generator.truth import RasterTruth

STRIP_HALF = 0.012
SEEN_HALF = 0.032
SEAM_NEAR = 0.0015            # m either side of a border where a line is looked for
SEAM_SIDES = (0.002, 0.008)   # m from the border: the profile the texture fit sees on each side
SEAM_TAPS = 2                 # the truth's profile filtered over +-2 rows (+-0.2 mm at 0.1 mm)
SEAM_CLEAR = 0.004            # m: the floor's lines lie at least this far from every border
FEATURE_HALF = 0.004          # m: a feature's window reaches this far either side of its centre, at least
FEATURE_END_MARGIN = 0.0015   # m: a crack's window reaches this far beyond its ends
CRACK_HALF_ACROSS = 0.0025    # m: and this far either side of it (10 to 30 crack widths)
SEAM_RIDGE = 0.03             # map stds: the truth's profile varying less than this leaves the taps at the gain


@dataclass(frozen=True)
class MapRun:
    """What `touchroller map` said of a recording (its summary line, and any WARN line)."""

    latency_ms: float | None
    latency_estimated: bool
    latency_sigma_ms: float | None
    warned: bool
    mapped_frames: int | None
    passes: int | None
    summary: str
    seconds: float


def parse_map_output(stdout: str, stderr: str, seconds: float) -> MapRun:
    """The latency and counts from `touchroller map`'s summary line ("... camera latency estimated 35.2 ms",
    optionally "+- 1.1 ms"); `warned`: a WARN or warning line about the latency anywhere in its output."""
    lines = [line for line in stdout.splitlines() if "camera latency" in line]
    summary = lines[-1] if lines else (stdout.strip().splitlines() or [""])[-1]
    found = re.search(r"camera latency\s+(\w+)\s+(?:[a-z ]*?)(-?[0-9.]+)\s*ms", summary)
    latency = float(found.group(2)) if found else None
    estimated = bool(found and found.group(1) == "estimated")
    sigma = re.search(r"(?:\+-|±|sigma|sd)\s*([0-9.]+)\s*ms", summary)
    frames = re.search(r"(\d+) frames mapped in (\d+) pass", summary)
    warned = any(("WARN" in line or "warning" in line.lower()) and "latency" in line.lower()
                 for line in (stdout + "\n" + stderr).splitlines())
    return MapRun(latency, estimated, float(sigma.group(1)) if sigma else None, warned,
                  int(frames.group(1)) if frames else None, int(frames.group(2)) if frames else None,
                  summary.strip(), seconds)


@dataclass(frozen=True)
class FeatureScore:
    kind: str
    centre: tuple[float, float]
    offset_mm: tuple[float, float]    # (dx, dy) in base, map minus truth
    error_mm: float
    peak: float                       # NCC peak


@dataclass(frozen=True)
class MapScore:
    ssim: float
    coverage_percent: float
    pass_residual_mm: list[tuple[float, float]]   # (along, across) per pass
    worst_residual_mm: float
    seam_worst: float                 # largest dip or step at a border, in map standard deviations
    seams: list[tuple[float, float, float]]       # (w mm, dip, step) per border
    features: list[FeatureScore]
    worst_feature_mm: float
    seam_floor: float = math.nan      # the same measure's 95th percentile at lines away from any border


def read_map(yaml_path: Path) -> tuple[np.ndarray, np.ndarray, tuple[float, float], float]:
    """(grey float32, weight, origin (x, y), resolution) of a world map, rows growing with y."""
    from touchroller_bringup.map_files import read_world_map

    grey, alpha, meta = read_world_map(yaml_path)
    return (grey[::-1].astype(np.float32), (alpha[::-1] > 0).astype(np.float32),
            (float(meta["origin"][0]), float(meta["origin"][1])), float(meta["resolution"]))


def _standard(image: np.ndarray, mask: np.ndarray) -> np.ndarray:
    values = image[mask] if mask.any() else image.reshape(-1)
    std = float(values.std()) or 1.0
    return ((image - float(values.mean())) / std).astype(np.float32)


def _highpass(image: np.ndarray) -> np.ndarray:
    image = image.astype(np.float32)
    return cv2.subtract(image, cv2.GaussianBlur(image, (0, 0), 3.0))


def _locate(template: np.ndarray, image: np.ndarray) -> tuple[float, float, float]:
    """Where `template` best matches in `image` (dx, dy px from the centred position), and the NCC peak."""
    scores = cv2.matchTemplate(image, template, cv2.TM_CCOEFF_NORMED)
    _, best, _, (bx, by) = cv2.minMaxLoc(scores)

    mx, my = (image.shape[1] - template.shape[1]) / 2, (image.shape[0] - template.shape[0]) / 2
    return bx + subpixel_peak(scores[by, :], bx) - mx, by + subpixel_peak(scores[:, bx], by) - my, float(best)


def score_map(yaml_path: Path, truth: RasterTruth) -> MapScore:
    grey, weight, origin, resolution = read_map(yaml_path)
    expected = truth.appearance(origin, grey.shape, resolution)
    spec = truth.spec
    margin = 0.004
    us = np.arange(-margin, spec.length + margin, resolution) + 0.5 * resolution
    ws = np.arange(-margin, spec.width + margin, resolution) + 0.5 * resolution
    uu, ww = np.meshgrid(us, ws)
    xy = spec.to_base(uu, ww)
    map_x = ((xy[..., 0] - origin[0]) / resolution - 0.5).astype(np.float32)
    map_y = ((xy[..., 1] - origin[1]) / resolution - 0.5).astype(np.float32)

    def resample(image: np.ndarray, interpolation: int = cv2.INTER_LINEAR) -> np.ndarray:
        return cv2.remap(image, map_x, map_y, interpolation, borderMode=cv2.BORDER_CONSTANT, borderValue=0.0)

    value, mapped, ideal = resample(grey), resample(weight, cv2.INTER_NEAREST) > 0, resample(expected)
    inside = (uu >= 0) & (uu <= spec.length) & (ww >= 0) & (ww <= spec.width)
    coverage = 100.0 * float((mapped & inside).sum()) / max(float(inside.sum()), 1.0)
    region = mapped & inside
    a, b = _standard(value, region), _standard(ideal, region)
    ssim = _ssim(a, b, region)
    residuals = []
    for p in truth.passes:
        rows = (ws >= p.w - STRIP_HALF) & (ws <= p.w + STRIP_HALF)
        cols = (us >= 0.005) & (us <= spec.length - 0.005)
        if region[np.ix_(rows, cols)].mean() < 0.5:   # the pass was (mostly) not mapped: no shift to measure
            residuals.append((math.nan, math.nan))
            continue
        strip_a = np.where(region, a, 0.0)[np.ix_(rows, cols)]
        strip_b = b[np.ix_(rows, cols)]
        edge = 20   # +-2 mm at 0.1 mm
        dx, dy, _ = _locate(_highpass(strip_a[edge:-edge, edge:-edge]), _highpass(strip_b))
        residuals.append((-dx * resolution * 1e3, -dy * resolution * 1e3))   # map minus truth
    seams = _seams(a, b, region, ws, truth)
    floor = _seam_floor(a, b, region, ws, truth)
    features = _features(grey, weight, expected, origin, resolution, truth)
    shifts = [math.hypot(*r) for r in residuals if math.isfinite(r[0])]
    return MapScore(ssim, coverage, residuals, max(shifts) if shifts else math.nan,
                    max((max(dip, step) for _, dip, step in seams), default=0.0), seams, features,
                    max((f.error_mm for f in features), default=math.nan), floor)


def _ssim(a: np.ndarray, b: np.ndarray, region: np.ndarray) -> float:
    from skimage.metrics import structural_similarity

    def grey(image: np.ndarray) -> np.ndarray:
        return np.clip(image * 40.0 + 128.0, 0, 255).astype(np.float64)

    _, full = structural_similarity(grey(a), grey(b), data_range=255.0, full=True, win_size=7)
    inner = cv2.erode(region.astype(np.uint8), np.ones((7, 7), np.uint8)) > 0
    return float(full[inner].mean()) if inner.any() else math.nan


def _profiles(a: np.ndarray, b: np.ndarray, region: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The map's and the truth's mean profile across the passes (averaged along u over the mapped cells;
    nan on rows less than half as mapped as the best row)."""
    counts = region.sum(axis=1)
    with np.errstate(invalid="ignore"), warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)   # rows with nothing mapped: nan
        enough = counts >= 0.5 * max(int(counts.max()), 1)
        return (np.where(enough, np.nanmean(np.where(region, a, np.nan), axis=1), np.nan),
                np.where(enough, np.nanmean(np.where(region, b, np.nan), axis=1), np.nan))


def _borders(ws: np.ndarray, truth: RasterTruth) -> list[float]:
    """Every pass border and band edge (m across) inside the rectangle, clear of its edges."""
    lines = sorted(p.w for p in truth.passes)
    borders = [0.5 * (p + q) for p, q in zip(lines, lines[1:], strict=False)]
    borders += [w + sign * SEEN_HALF for w in lines for sign in (-1, 1)]
    return [b for b in borders if 0.006 <= b <= truth.spec.width - 0.006]


def seam_at(ws: np.ndarray, profile: np.ndarray, truth_profile: np.ndarray, border: float, gain: float = 1.0
            ) -> tuple[float, float] | None:
    """(dip, step) of `profile` at `border` (see the module: the truth's texture fitted on both sides, the
    near rows left out of the fit; the filter held towards `gain` times the truth where the truth's profile
    says too little to fit it); None where too little of either side or the border row is mapped."""
    near = np.abs(ws - border) <= SEAM_NEAR
    distance = np.abs(ws - border)
    sides = (distance >= SEAM_SIDES[0]) & (distance <= SEAM_SIDES[1])
    left, right = sides & (ws < border), sides & (ws > border)
    rows = np.flatnonzero(distance <= SEAM_SIDES[1])
    rows = rows[(rows >= SEAM_TAPS) & (rows < len(ws) - SEAM_TAPS)]
    taps = np.stack([truth_profile[rows + j] for j in range(-SEAM_TAPS, SEAM_TAPS + 1)], axis=1)
    finite = np.isfinite(profile[rows]) & np.isfinite(taps).all(axis=1)
    fit = finite & sides[rows]
    columns = taps.shape[1] + 3
    if (finite & near[rows]).sum() == 0 or (fit & left[rows]).sum() < columns or (fit & right[rows]).sum() < columns:
        return None
    offset = (ws[rows] - border) * 1e3    # mm: the slope's column stays of order one
    design = np.column_stack([left[rows], right[rows], offset, np.where(finite[:, None], taps, 0.0)])
    # the taps are held (ridge) towards `gain` times the truth (the whole width's fit): where the truth's
    # profile is nearly flat (glass) a free filter would take any value, and a speck of texture near the
    # border times such a tap would read as a line
    weight = math.sqrt(fit.sum()) * SEAM_RIDGE
    ridge = np.zeros((taps.shape[1], columns))
    ridge[:, 3:] = weight * np.eye(taps.shape[1])
    prior = np.zeros(taps.shape[1])
    prior[SEAM_TAPS] = weight * gain
    coefficients, *_ = np.linalg.lstsq(np.vstack([design[fit], ridge]),
                                       np.concatenate([profile[rows][fit], prior]), rcond=None)
    level_left, level_right, slope = coefficients[:3]
    texture = design[:, 3:] @ coefficients[3:]
    baseline = 0.5 * (level_left + level_right) + slope * offset
    departure = np.abs(profile[rows] - texture - baseline)[finite & near[rows]]
    return float(departure.max()), float(abs(level_right - level_left))


def profile_gain(profile: np.ndarray, truth_profile: np.ndarray) -> float:
    """The map's profile against the truth's over the whole width: the least-squares gain of the two less
    their means (1 where the truth's profile is flat or nothing is mapped)."""
    finite = np.isfinite(profile) & np.isfinite(truth_profile)
    if finite.sum() < 2:
        return 1.0
    p, q = profile[finite] - profile[finite].mean(), truth_profile[finite] - truth_profile[finite].mean()
    power = float(np.dot(q, q))
    return float(np.dot(p, q)) / power if power > 1e-12 else 1.0


def _seams(a: np.ndarray, b: np.ndarray, region: np.ndarray, ws: np.ndarray, truth: RasterTruth
           ) -> list[tuple[float, float, float]]:
    """(w mm, dip, step) at every pass border and band edge inside the rectangle (see the module)."""
    profile, truth_profile = _profiles(a, b, region)
    gain = profile_gain(profile, truth_profile)
    out = []
    for border in _borders(ws, truth):
        found = seam_at(ws, profile, truth_profile, border, gain)
        if found is not None:
            out.append((border * 1e3, *found))
    return out


def _seam_floor(a: np.ndarray, b: np.ndarray, region: np.ndarray, ws: np.ndarray, truth: RasterTruth) -> float:
    """The seam measure's 95th percentile (the larger of dip and step) at lines every 0.5 mm at least
    `SEAM_CLEAR` from every border and band edge: what the map's texture alone reads (nan: no such line)."""
    profile, truth_profile = _profiles(a, b, region)
    borders = np.array(_borders(ws, truth) or [-1.0])
    lines = np.arange(0.006, truth.spec.width - 0.006 + 1e-9, 5e-4)
    lines = lines[np.abs(lines[:, None] - borders[None, :]).min(axis=1) >= SEAM_CLEAR]
    gain = profile_gain(profile, truth_profile)
    values = [max(found) for line in lines if (found := seam_at(ws, profile, truth_profile, line, gain)) is not None]
    return float(np.percentile(values, 95)) if values else math.nan


def _feature_frame(feature: Feature) -> tuple[np.ndarray, float, float]:
    """The frame a feature is scored in: its unit direction (x, y) in base (x for a dent), and the half
    extents (m) along and across it of its window: 4 mm either side of its centre, or, for a crack or
    groove, as far as its ends and 1.5 mm beyond, and 2.5 mm either side (less than a dent's, so that a
    long crack's window still fits the mapped area near its ends). A crack longer than the window would leave the match
    free to slide along it, as nothing in the window pins it there; and on a window not turned along the
    crack, the correlation's ridge runs diagonally through the pixel grid, where the pixel nearest the
    ridge line wins over the one its ends point to."""
    if feature.kind not in ("crack", "groove"):
        return np.array([1.0, 0.0]), FEATURE_HALF, FEATURE_HALF
    d = np.asarray(feature.end, float) - np.asarray(feature.start, float)
    length = float(np.hypot(*d))
    direction = d / length if length > 0 else np.array([1.0, 0.0])
    return direction, max(FEATURE_HALF, 0.5 * length + FEATURE_END_MARGIN), CRACK_HALF_ACROSS


def _turned(image: np.ndarray, centre: tuple[float, float], direction: np.ndarray, size: tuple[int, int]
            ) -> np.ndarray:
    """`image` resampled on a (rows, cols) = `size` grid centred on `centre` (col, row) whose columns run
    along `direction` and rows across it (rows growing with y, as the map's)."""
    (c, s), (rows, cols) = direction, size
    dst_c, dst_r = (cols - 1) / 2, (rows - 1) / 2
    # src = centre + R (dst - dst centre), with R's columns the direction and its normal
    matrix = np.array([[c, -s, centre[0] - c * dst_c + s * dst_r],
                       [s, c, centre[1] - s * dst_c - c * dst_r]])
    return cv2.warpAffine(image, matrix, (cols, rows), flags=cv2.INTER_CUBIC | cv2.WARP_INVERSE_MAP,
                          borderMode=cv2.BORDER_CONSTANT, borderValue=0.0)


def _inside(feature: Feature, spec: Any) -> bool:
    """The feature's centre is 6 mm or more inside the rectangle."""
    local = np.asarray(feature.centre) - np.asarray(spec.corner)
    u, w = float(local @ spec.roll), float(local @ spec.across)
    return 0.006 <= u <= spec.length - 0.006 and 0.006 <= w <= spec.width - 0.006


def _features(grey: np.ndarray, weight: np.ndarray, expected: np.ndarray, origin: tuple[float, float],
              resolution: float, truth: RasterTruth) -> list[FeatureScore]:
    """Each planted feature well inside the rectangle, located in the truth by its map neighbourhood (a
    window holding the whole feature, turned along a crack: see `_feature_frame`)."""
    search = int(round(0.0015 / resolution))
    out = []
    for feature in truth.surface.features:
        if not _inside(feature, truth.spec):
            continue
        direction, half_along, half_across = _feature_frame(feature)
        along, across = int(round(half_along / resolution)), int(round(half_across / resolution))
        centre = ((feature.centre[0] - origin[0]) / resolution - 0.5,
                  (feature.centre[1] - origin[1]) / resolution - 0.5)
        size = (2 * (across + search) + 1, 2 * (along + search) + 1)
        if _turned(weight, centre, direction, size)[search:-search, search:-search].mean() < 0.99:
            continue   # not mapped throughout (a window off the map reads weight 0)
        template = _highpass(_turned(grey, centre, direction, size))[search:-search, search:-search]
        image = _highpass(_turned(expected, centre, direction, size))
        du, dw, peak = _locate(template, image)
        dx, dy = du * direction + dw * np.array([-direction[1], direction[0]])   # back to base x, y
        offset = (-dx * resolution * 1e3, -dy * resolution * 1e3)   # the map's content lies here relative to the truth
        out.append(FeatureScore(feature.kind, (float(feature.centre[0]), float(feature.centre[1])), offset,
                                float(math.hypot(*offset)), peak))
    return out


def main(argv: list[str] | None = None) -> int:
    """`python -m bench.raster_score RASTER_FOLDER map.yaml`: a map against a generated raster's truth."""
    import argparse
    import json as json_module
    import sys

    from bench._common import to_json
    from bench.raster_generator.truth import load_truth

    parser = argparse.ArgumentParser(description=main.__doc__)
    parser.add_argument("raster", type=Path, help="the generator's output folder (truth.json, surface.npy)")
    parser.add_argument("map_yaml", type=Path, help="the map.yaml `touchroller map` wrote")
    args = parser.parse_args(argv)
    try:
        truth = load_truth(args.raster)
        score = score_map(args.map_yaml, truth)
    except (OSError, ValueError, KeyError) as error:
        print(f"error: {error}", file=sys.stderr)
        return 1
    print(json_module.dumps(json_module.loads(to_json(score)), indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
