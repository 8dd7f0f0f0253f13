"""A world map (`map.png` + `map.yaml`) against the truth of a second-generator raster, in place.

No alignment: the map and the truth are compared where `base` says they lie. The map and the truth's
ideal appearance (`RasterTruth.appearance`) are resampled into the raster's own frame (u along the
passes, w across, at the map's resolution), where:

* SSIM: over the mapped part of the raster rectangle (both standardised, window 7);
* coverage: the mapped share of the rectangle;
* each pass's residual shift: the pass's central strip (+-12 mm across, 5 mm in from the ends) located
  in the truth by normalised cross-correlation of high-passed images (subpixel), as (along, across) mm;
* seams: the mean profile across the passes (the map less the truth, each standardised, averaged along
  u): at every pass border (half-way between pass lines) and every band edge (32 mm from a pass line)
  inside the rectangle, the largest dip (against a line through the profile 2-6 mm either side) and the
  step (the two sides' means), in units of the map's standard deviation;
* planted features (cracks, dents, grooves, pits): each one's 8 x 8 mm neighbourhood in the map located
  in the truth (+-1.5 mm), mm off.
"""
from __future__ import annotations

import math
import re
import warnings
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from bench._common import subpixel_peak
from bench.raster_generator.truth import RasterTruth

STRIP_HALF = 0.012
SEEN_HALF = 0.032


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
    features = _features(grey, weight, expected, origin, resolution, truth)
    shifts = [math.hypot(*r) for r in residuals if math.isfinite(r[0])]
    return MapScore(ssim, coverage, residuals, max(shifts) if shifts else math.nan,
                    max((max(dip, step) for _, dip, step in seams), default=0.0), seams, features,
                    max((f.error_mm for f in features), default=math.nan))


def _ssim(a: np.ndarray, b: np.ndarray, region: np.ndarray) -> float:
    from skimage.metrics import structural_similarity

    def grey(image: np.ndarray) -> np.ndarray:
        return np.clip(image * 40.0 + 128.0, 0, 255).astype(np.float64)

    _, full = structural_similarity(grey(a), grey(b), data_range=255.0, full=True, win_size=7)
    inner = cv2.erode(region.astype(np.uint8), np.ones((7, 7), np.uint8)) > 0
    return float(full[inner].mean()) if inner.any() else math.nan


def _seams(a: np.ndarray, b: np.ndarray, region: np.ndarray, ws: np.ndarray, truth: RasterTruth
           ) -> list[tuple[float, float, float]]:
    """(w mm, dip, step) at every pass border and band edge inside the rectangle (see the module)."""
    spec = truth.spec
    difference = np.where(region, a - b, np.nan)
    counts = region.sum(axis=1)
    with np.errstate(invalid="ignore"), warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)   # rows with nothing mapped: nan
        profile = np.where(counts >= 0.5 * max(int(counts.max()), 1), np.nanmean(difference, axis=1), np.nan)
    lines = sorted(p.w for p in truth.passes)
    borders = [0.5 * (p + q) for p, q in zip(lines, lines[1:], strict=False)]
    borders += [w + sign * SEEN_HALF for w in lines for sign in (-1, 1)]
    out = []
    for border in borders:
        if not 0.006 <= border <= spec.width - 0.006:
            continue
        near = np.abs(ws - border) <= 0.0015
        left = (ws >= border - 0.006) & (ws <= border - 0.002)
        right = (ws >= border + 0.002) & (ws <= border + 0.006)
        finite = np.isfinite(profile)
        sides = (left | right) & finite
        if (near & finite).sum() == 0 or (left & finite).sum() < 5 or (right & finite).sum() < 5:
            continue
        slope, intercept = np.polyfit(ws[sides], profile[sides], 1)
        dip = float(np.nanmax(np.abs(profile[near] - (slope * ws[near] + intercept))))
        step = float(abs(np.nanmean(profile[right]) - np.nanmean(profile[left])))
        out.append((border * 1e3, dip, step))
    return out


def _features(grey: np.ndarray, weight: np.ndarray, expected: np.ndarray, origin: tuple[float, float],
              resolution: float, truth: RasterTruth) -> list[FeatureScore]:
    """Each planted feature well inside the rectangle, located in the truth by its map neighbourhood."""
    spec = truth.spec
    half, search = int(round(0.004 / resolution)), int(round(0.0015 / resolution))
    out = []
    for feature in truth.surface.features:
        centre = np.asarray(feature.centre)
        local = centre - np.asarray(spec.corner)
        u, w = float(local @ spec.roll), float(local @ spec.across)
        if not (0.006 <= u <= spec.length - 0.006 and 0.006 <= w <= spec.width - 0.006):
            continue
        col = int(round((centre[0] - origin[0]) / resolution - 0.5))
        row = int(round((centre[1] - origin[1]) / resolution - 0.5))
        r0, r1, c0, c1 = row - half, row + half, col - half, col + half
        if r0 - search < 0 or c0 - search < 0 or r1 + search > grey.shape[0] or c1 + search > grey.shape[1]:
            continue
        if weight[r0:r1, c0:c1].mean() < 0.99:
            continue
        template = _highpass(grey[r0 - search:r1 + search, c0 - search:c1 + search])[search:-search, search:-search]
        image = _highpass(expected[r0 - search:r1 + search, c0 - search:c1 + search])
        dx, dy, peak = _locate(template, image)
        offset = (-dx * resolution * 1e3, -dy * resolution * 1e3)   # the map's content lies here relative to the truth
        out.append(FeatureScore(feature.kind, (float(centre[0]), float(centre[1])), offset,
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
