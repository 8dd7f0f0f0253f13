"""A synthetic height-map generator for the inspection bench, written for it alone: it shares no code with
the simulator (`touchroller_driver.sim`), only the findings' format.

A map is a surface at `RESOLUTION` (0.1 mm) rendered on a grid `SUPERSAMPLE` times finer and area-averaged
to the map's pixels (what a map pixel holds), plus white measurement noise. Backgrounds (metres of relief):
painted metal (fine grain), a grained surface (grains about 0.3 mm across), brushed metal (long shallow
parallel scratches along x), a plain weave (a composite's tows, 2.5 mm pitch) and a panel joint (painted
metal with a straight groove across the map, which the bench declares by a mask). Every map has a slow
waviness and a pass seam (a small step and tilt between two passes at mid-height). Planted defects:
cracks (random-walk centrelines, sometimes branched, Gaussian cross-section of full width at half depth
`width`, depth varying along the crack and tapering at its ends), dents and bumps (raised-cosine, nominal
diameter D: half depth at D/4 from the centre). The truth is a list of `Finding`s in the findings' own
conventions (a crack's length along its trunk, its median depth, its trunk and branches as polylines; a
dent's half-depth circle as its polygon).
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numpy as np
from scipy.spatial import cKDTree

from touchroller_perception.inspection import Finding

RESOLUTION = 1e-4
SUPERSAMPLE = 3
BACKGROUNDS = ("painted", "grained", "brushed", "weave", "joint")
NOISE_M = 0.5e-6          # white measurement noise per map pixel
JOINT_WIDTH_M, JOINT_DEPTH_M, JOINT_MASK_M = 6e-4, 1.5e-4, 1.5e-3


@dataclass(frozen=True)
class CrackSpec:
    width_m: float
    depth_m: float
    length_m: float


@dataclass(frozen=True)
class SyntheticMap:
    height: np.ndarray            # float32 metres, row 0 the largest y
    resolution: float
    origin: tuple[float, float]
    mask: np.ndarray | None       # True over a declared panel joint
    truth: list[Finding]
    background: str


def _blurred_noise(rng: np.random.Generator, shape: tuple[int, int], sigma_px: float | tuple[float, float],
                   rms: float) -> np.ndarray:
    """White noise blurred by a Gaussian of `sigma_px`, scaled to `rms`. A wide isotropic Gaussian (the
    waviness) is drawn on a grid `factor` times coarser and interpolated up: the same smooth field
    statistically, without a kernel of thousands of pixels."""
    sx, sy = (sigma_px, sigma_px) if isinstance(sigma_px, float | int) else sigma_px
    factor = int(min(sx, sy) // 8) if sx == sy else 1
    if factor > 1:
        coarse = (max(2, -(-shape[0] // factor)), max(2, -(-shape[1] // factor)))
        noise = rng.standard_normal(coarse).astype(np.float32)
        noise = cv2.GaussianBlur(noise, (0, 0), sigmaX=float(sx) / factor, borderType=cv2.BORDER_REFLECT)
        noise = cv2.resize(noise, (coarse[1] * factor, coarse[0] * factor), interpolation=cv2.INTER_LINEAR)
        noise = np.ascontiguousarray(noise[:shape[0], :shape[1]])
    else:
        noise = rng.standard_normal(shape).astype(np.float32)
        noise = cv2.GaussianBlur(noise, (0, 0), sigmaX=float(sx), sigmaY=float(sy), borderType=cv2.BORDER_REFLECT)
    std = float(noise.std())
    return noise * np.float32(rms / std) if std > 0 else noise


def background(kind: str, rng: np.random.Generator, shape: tuple[int, int]) -> tuple[np.ndarray, np.ndarray | None]:
    """(relief on the fine grid, the joint's mask on the fine grid or None)."""
    fine = RESOLUTION / SUPERSAMPLE
    rows, cols = shape
    ys, xs = np.mgrid[0:rows, 0:cols].astype(np.float32) * np.float32(fine)
    z = _blurred_noise(rng, shape, 15e-3 / fine / 3, 6e-6)                      # waviness, ~15 mm
    mask = None
    if kind in ("painted", "joint"):
        z += _blurred_noise(rng, shape, 0.03e-3 / fine, 0.6e-6)
    elif kind == "grained":
        z += _blurred_noise(rng, shape, 0.1e-3 / fine, 1.5e-6) + _blurred_noise(rng, shape, 0.3e-3 / fine, 1.5e-6)
    elif kind == "brushed":
        z += _blurred_noise(rng, shape, (4e-3 / fine, 0.015e-3 / fine), 1.2e-6)
        for _ in range(int(rows * fine * 1e3 * 0.6)):                          # a few deeper scratches per mm
            y0, x0 = rng.uniform(0, rows * fine), rng.uniform(0, cols * fine)
            length, width, depth = rng.uniform(3e-3, 40e-3), rng.uniform(0.02e-3, 0.1e-3), rng.uniform(1e-6, 4e-6)
            r0, r1 = max(0, int((y0 - 5 * width) / fine)), min(rows, int((y0 + 5 * width) / fine) + 2)
            band_x, band_y = xs[r0:r1], ys[r0:r1]         # the rows it reaches (beyond: < 1e-30 of its depth)
            along = np.clip(1 - np.abs(band_x - x0) / (length / 2), 0, 1) ** 0.3
            z[r0:r1] -= (depth * along * np.exp(-4 * math.log(2) * ((band_y - y0) / width) ** 2)).astype(np.float32)
    elif kind == "weave":
        pitch = 2.5e-3
        u, v = 2 * np.pi * xs / pitch, 2 * np.pi * ys / pitch
        z += (3e-6 * np.sin(u) * np.sin(v) + 1e-6 * (np.cos(2 * u) + np.cos(2 * v))).astype(np.float32)
        z += _blurred_noise(rng, shape, 0.05e-3 / fine, 0.5e-6)
    else:
        raise ValueError(f"unknown background {kind!r}")
    if kind == "joint":
        x_joint = rng.uniform(0.3, 0.7) * cols * fine
        z -= (JOINT_DEPTH_M * np.exp(-4 * math.log(2) * ((xs - x_joint) / JOINT_WIDTH_M) ** 2)).astype(np.float32)
        mask = np.abs(xs - x_joint) < JOINT_MASK_M
    seam = rows // 2                                                            # two passes meet at mid-height
    z[seam:] += np.float32(rng.uniform(-3e-6, 3e-6)) + (xs[seam:] * np.float32(rng.uniform(-5e-5, 5e-5)))
    return z, mask


def _random_walk(rng: np.random.Generator, start: np.ndarray, heading: float, length: float,
                 step: float) -> np.ndarray:
    n = max(2, int(length / step) + 1)
    turns = np.cumsum(rng.normal(0, 0.06, n - 1))
    angles = heading + turns - turns.mean() * 0.5
    steps = np.stack([np.cos(angles), np.sin(angles)], axis=1) * step
    return np.vstack([start, start + np.cumsum(steps, axis=0)])


def _line_length(points: np.ndarray) -> float:
    return float(np.hypot(*np.diff(points, axis=0).T).sum())


def _render_line(z: np.ndarray, points: np.ndarray, width: float, depths: np.ndarray, fine: float) -> None:
    """Carve a Gaussian groove of FWHM `width` along `points` (x, y metres on the fine grid's image axes:
    x along columns, y along rows), depth `depths` per point, into `z` in place."""
    reach = 2.5 * width + 2 * fine
    lo = np.floor((points.min(axis=0) - reach) / fine).astype(int)
    hi = np.ceil((points.max(axis=0) + reach) / fine).astype(int)
    c0, r0 = max(lo[0], 0), max(lo[1], 0)
    c1, r1 = min(hi[0], z.shape[1]), min(hi[1], z.shape[0])
    if c1 <= c0 or r1 <= r0:
        return
    rr, cc = np.mgrid[r0:r1, c0:c1]
    pixels = np.stack([(cc.ravel() + 0.5) * fine, (rr.ravel() + 0.5) * fine], axis=1)
    distance, index = cKDTree(points).query(pixels, distance_upper_bound=reach)
    near = np.isfinite(distance)
    carve = np.zeros(pixels.shape[0], np.float32)
    carve[near] = depths[index[near]] * np.exp(-4 * math.log(2) * (distance[near] / width) ** 2)
    z[r0:r1, c0:c1] -= carve.reshape(r1 - r0, c1 - c0)


def plant_crack(z: np.ndarray, rng: np.random.Generator, spec: CrackSpec, start: np.ndarray, heading: float,
                branches: int) -> tuple[list[np.ndarray], float]:
    """Carve a crack; returns its centrelines (trunk first, x/y metres on the fine grid's image axes) and
    its median depth along the trunk."""
    fine = RESOLUTION / SUPERSAMPLE
    step = min(fine / 2, spec.width_m / 4)
    trunk = _random_walk(rng, start, heading, spec.length_m, step)
    s = np.concatenate([[0.0], np.cumsum(np.hypot(*np.diff(trunk, axis=0).T))])
    wiggle = np.interp(s, np.linspace(0, s[-1], 12), rng.normal(0, 0.35, 12))
    taper = np.clip(np.minimum(s, s[-1] - s) / 2e-4, 0, 1)
    depths = spec.depth_m * np.exp(wiggle) * taper
    _render_line(z, trunk, spec.width_m, depths, fine)
    lines = [trunk]
    for _ in range(branches):
        k = int(rng.uniform(0.25, 0.75) * len(trunk))
        direction = trunk[min(k + 1, len(trunk) - 1)] - trunk[k]
        angle = math.atan2(direction[1], direction[0]) + rng.choice([-1, 1]) * rng.uniform(0.5, 1.0)
        branch = _random_walk(rng, trunk[k], angle, spec.length_m * rng.uniform(0.2, 0.45), step)
        bs = np.concatenate([[0.0], np.cumsum(np.hypot(*np.diff(branch, axis=0).T))])
        b_depth = depths[k] * 0.8 * np.clip((bs[-1] - bs) / 2e-4, 0, 1)
        _render_line(z, branch, spec.width_m * 0.8, b_depth, fine)
        lines.append(branch)
    inner = taper >= 1
    return lines, float(np.median(depths[inner] if inner.any() else depths))


def plant_blob(z: np.ndarray, centre: np.ndarray, diameter: float, depth: float) -> None:
    """A raised-cosine dent (depth > 0) or bump (depth < 0) of nominal `diameter` at `centre` (metres)."""
    fine = RESOLUTION / SUPERSAMPLE
    radius = diameter / 2
    c0, r0 = (np.floor((centre - radius) / fine).astype(int) - 1).clip(0)
    c1, r1 = np.minimum(np.ceil((centre + radius) / fine).astype(int) + 2, [z.shape[1], z.shape[0]])
    rr, cc = np.mgrid[r0:r1, c0:c1]
    distance = np.hypot((cc + 0.5) * fine - centre[0], (rr + 0.5) * fine - centre[1])
    bell = np.where(distance < radius, 0.5 * (1 + np.cos(np.pi * distance / radius)), 0.0)
    z[r0:r1, c0:c1] -= (depth * bell).astype(np.float32)


def _free(points: np.ndarray, taken: list[np.ndarray], clearance: float) -> bool:
    return all(cKDTree(other).query(points, distance_upper_bound=clearance)[0].min() == np.inf for other in taken)


def make_map(kind: str, seed: int, size_m: tuple[float, float] = (0.08, 0.06), cracks: int = 5, blobs: int = 4,
             crack_specs: list[CrackSpec] | None = None, branch_probability: float = 0.4) -> SyntheticMap:
    """One synthetic map: `kind` background, `cracks` random cracks (or `crack_specs`) and `blobs` dents or
    bumps, away from each other and from the map's edges."""
    rng = np.random.default_rng([seed, BACKGROUNDS.index(kind) if kind in BACKGROUNDS else 99])
    fine = RESOLUTION / SUPERSAMPLE
    cols, rows = (round(s / RESOLUTION) for s in size_m)
    z, mask_fine = background(kind, rng, (rows * SUPERSAMPLE, cols * SUPERSAMPLE))
    width_m, height_m = cols * RESOLUTION, rows * RESOLUTION
    keep_out: list[np.ndarray] = []
    if mask_fine is not None:
        xs = (np.flatnonzero(mask_fine[0]) + 0.5) * fine
        keep_out.append(np.stack([np.repeat(xs[[0, -1]], 200), np.tile(np.linspace(0, height_m, 200), 2)], axis=1))
    truth_raw: list[tuple[str, list[np.ndarray], float, float, float]] = []
    specs = crack_specs if crack_specs is not None else [
        CrackSpec(float(np.exp(rng.uniform(math.log(0.05e-3), math.log(1e-3)))),
                  float(np.exp(rng.uniform(math.log(10e-6), math.log(300e-6)))),
                  float(rng.uniform(3e-3, 0.4 * min(size_m) + 3e-3))) for _ in range(cracks)]
    for spec in specs:
        for _ in range(60):
            crack_seed = int(rng.integers(1 << 62))
            start = np.array([rng.uniform(0.1, 0.9) * width_m, rng.uniform(0.1, 0.9) * height_m])
            heading = rng.uniform(0, 2 * np.pi)
            branches = int(rng.random() < branch_probability) * int(rng.integers(1, 3))
            trial = np.zeros((8, 8), np.float32)          # dry run: the centrelines only
            lines, _ = plant_crack(trial, np.random.default_rng(crack_seed), spec, start, heading, branches)
            everything = np.vstack(lines)
            inside = ((everything > 1.5e-3) & (everything < np.array([width_m, height_m]) - 1.5e-3)).all()
            if inside and _free(everything, keep_out, 2e-3 + spec.width_m):
                break
        else:
            continue
        # the dry run's random stream again: the same centrelines
        lines, median_depth = plant_crack(z, np.random.default_rng(crack_seed), spec, start, heading, branches)
        keep_out.append(np.vstack(lines))
        truth_raw.append(("crack", lines, spec.width_m, median_depth, _line_length(lines[0])))
    for _ in range(blobs):
        diameter = float(rng.uniform(0.5e-3, 5e-3))
        depth = float(np.exp(rng.uniform(math.log(10e-6), math.log(300e-6)))) * (1 if rng.random() < 0.5 else -1)
        for _ in range(60):
            centre = np.array([rng.uniform(0.1, 0.9) * width_m, rng.uniform(0.1, 0.9) * height_m])
            ring = centre + diameter / 2 * np.stack([np.cos(np.linspace(0, 2 * np.pi, 24)),
                                                     np.sin(np.linspace(0, 2 * np.pi, 24))], axis=1)
            if _free(np.vstack([ring, centre]), keep_out, 2e-3):
                break
        else:
            continue
        plant_blob(z, centre, diameter, depth)
        keep_out.append(np.vstack([ring, centre]))
        truth_raw.append(("dent" if depth > 0 else "bump", [centre[None, :]], diameter, depth, diameter))
    height = z.reshape(rows, SUPERSAMPLE, cols, SUPERSAMPLE).mean(axis=(1, 3))
    height += rng.normal(0, NOISE_M, height.shape).astype(np.float32)
    mask = None
    if mask_fine is not None:
        mask = mask_fine.reshape(rows, SUPERSAMPLE, cols, SUPERSAMPLE).any(axis=(1, 3))
    # the grid's rows run down from the map's top edge: map y = height - grid y
    truth = [_truth(i + 1, item, height_m) for i, item in enumerate(truth_raw)]
    return SyntheticMap(height.astype(np.float32), RESOLUTION, (0.0, 0.0), mask, truth, kind)


def _to_map(points: np.ndarray, height_m: float) -> tuple[tuple[float, float], ...]:
    return tuple((float(x), float(height_m - y)) for x, y in points)


def _truth(index: int, item: tuple[str, list[np.ndarray], float, float, float], height_m: float) -> Finding:
    kind, lines, size, depth, length = item
    if kind == "crack":
        mids = np.concatenate([0.5 * (line[1:] + line[:-1]) for line in lines])
        weights = np.concatenate([np.hypot(*np.diff(line, axis=0).T) for line in lines])
        centre = (mids * weights[:, None]).sum(axis=0) / weights.sum()
        total = sum(_line_length(line) for line in lines)
        thin = [np.vstack([line[:-1:max(1, len(line) // 400)], line[-1:]]) for line in lines]
        return Finding(index, "crack", float(centre[0]), float(height_m - centre[1]), length, size, depth,
                       total * size, 1.0, polylines=tuple(_to_map(t, height_m) for t in thin))
    centre = lines[0][0]
    angles = np.linspace(0, 2 * np.pi, 33)
    ring = centre + size / 4 * np.stack([np.cos(angles), np.sin(angles)], axis=1)
    ring[-1] = ring[0]
    return Finding(index, kind, float(centre[0]), float(height_m - centre[1]), size / 2, size / 2, depth,
                   math.pi * (size / 4) ** 2, 1.0, polygon=_to_map(ring, height_m))
