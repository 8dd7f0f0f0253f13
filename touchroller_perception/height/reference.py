"""The no-contact reference from the presses' own far fields.

A photometric model reads a pixel's colour change against a no-contact reference. One no-contact frame
taken before (or after) the presses holds the light of that moment: on a real sensor the light drifts
and the gel settles between that frame and the presses, and what changed reads as slopes everywhere.
The presses themselves show the undeformed membrane in the light they are taken in, away from their
contact: `far_field_reference` is, per pixel, the median over the frames that lie beyond `factor`
contact radii of their press there (each pixel is far from most presses when the presses move about).
Where fewer than `min_frames` frames are far (presses that keep to one place), it is the given reference
times the light's change since it, carried in smoothly from the pixels around (the per-channel ratio of
built to given, a Gaussian-weighted mean of width `fill_sigma` px): the given reference alone there would
leave a step in the light at the edge, and a part of the frame read against another light than the
rest. The median of many frames also has less noise than one frame.

`reference_change` measures how well a reference matches a set of frames where they are undeformed
(the median over the frames of each one's RMS relative colour change beyond `factor` contact radii),
which needs no truth: `choose_reference` keeps the candidate that matches best, each frame weighed
against a reference built without it, provided the presses move about: every pixel must lie beyond
`factor` contact radii of at least `min_frames` of them. Presses that keep to one place leave no frame
whose far field is far from every press's influence (a press changes the colour well beyond its
contact): their median holds the presses' own halo, and the far-field measure, taken in the same
halo, cannot see it.
"""
from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import cv2
import numpy as np

from touchroller_perception.calibration.common import CalibrationError

Circle = tuple[float, float, float]     # u, v, radius (px)


def far_masks(shape: tuple[int, int], circles: Sequence[Circle], factor: float) -> np.ndarray:
    """N x H x W bool: the pixels beyond `factor` radii of each frame's contact circle."""
    h, w = shape
    vv, uu = np.mgrid[0:h, 0:w]
    out = np.empty((len(circles), h, w), bool)
    for k, (u, v, r) in enumerate(circles):
        out[k] = np.hypot(uu - u, vv - v) > factor * r
    return out


def far_field_reference(images: Sequence[np.ndarray], circles: Sequence[Circle], fallback: np.ndarray,
                        factor: float = 3.0, min_frames: int = 3, rows_per_chunk: int = 32,
                        fill_sigma: float = 128.0) -> np.ndarray:
    """H x W x 3 float32: per pixel, the median of the frames beyond `factor` contact radii of their circle
    there; where fewer than `min_frames` frames are, `fallback` (the given no-contact reference) times the
    smooth ratio of built to given around (`fill_light`)."""
    fallback = np.asarray(fallback)
    if fallback.ndim != 3 or fallback.shape[2] != 3:
        raise CalibrationError(f"the reference must be a colour image (H x W x 3), got shape {fallback.shape}")
    if len(images) != len(circles):
        raise CalibrationError(f"{len(images)} frames but {len(circles)} contact circles")
    if not (math.isfinite(factor) and factor > 0) or min_frames < 1:
        raise ValueError(f"factor must be > 0 and min_frames >= 1, got {factor}, {min_frames}")
    h, w = fallback.shape[:2]
    for image in images:
        if np.shape(image) != fallback.shape:
            raise CalibrationError(f"frame {np.shape(image)} does not match the reference {fallback.shape}")
    out = np.asarray(fallback, np.float32).copy()
    if not images:
        return out
    masks = far_masks((h, w), circles, factor)
    for v0 in range(0, h, rows_per_chunk):         # a chunk of rows at a time: N frames of float32 are large
        v1 = min(h, v0 + rows_per_chunk)
        stack = np.stack([np.asarray(image[v0:v1], np.float32) for image in images])
        far = masks[:, v0:v1]
        stack[~far] = np.nan
        count = far.sum(axis=0)
        enough = count >= min_frames
        if enough.any():
            out[v0:v1][enough] = np.nanmedian(stack[:, enough], axis=0)
    covered = masks.sum(axis=0) >= min_frames
    if covered.any() and not covered.all():
        fill_light(out, np.asarray(fallback, np.float32), covered, fill_sigma)
    return out


def fill_light(built: np.ndarray, given: np.ndarray, covered: np.ndarray, sigma: float, step: int = 8) -> None:
    """In place: the pixels of `built` not `covered` become `given` times the ratio built / given carried in
    from the covered pixels (a normalised Gaussian of `sigma` px, on a 1-in-`step` grid; the covered pixels'
    median ratio where none is near)."""
    h, w = covered.shape
    safe = np.maximum(given, 1.0)
    ratio = np.where(covered[..., None], built / safe, 0.0).astype(np.float32)
    weight = covered.astype(np.float32)
    size = (max(1, w // step), max(1, h // step))
    small_r = cv2.resize(ratio, size, interpolation=cv2.INTER_AREA)
    small_w = cv2.resize(weight, size, interpolation=cv2.INTER_AREA)
    s = max(sigma / step, 0.5)
    blur_r = cv2.GaussianBlur(small_r, (0, 0), s, borderType=cv2.BORDER_REPLICATE)
    blur_w = cv2.GaussianBlur(small_w, (0, 0), s, borderType=cv2.BORDER_REPLICATE)
    median = np.median((built / safe)[covered], axis=0).astype(np.float32)
    near = blur_w > 1e-3
    light = np.where(near[..., None], blur_r / np.maximum(blur_w, 1e-3)[..., None], median)
    light = cv2.resize(light.astype(np.float32), (w, h), interpolation=cv2.INTER_LINEAR)
    built[~covered] = given[~covered] * light[~covered]


def reference_change(images: Sequence[np.ndarray], circles: Sequence[Circle], references: Sequence[np.ndarray],
                     factor: float = 3.0, step: int = 4) -> float:
    """The median over the frames of each frame's RMS relative colour change (all channels) against its
    reference (`references[k]` for frame k) beyond `factor` contact radii (a 1-in-`step` grid)."""
    values = []
    for image, (u, v, r), ref in zip(images, circles, references, strict=True):
        a = np.asarray(image, np.float32)[::step, ::step]
        b = np.maximum(np.asarray(ref, np.float32)[::step, ::step], 1.0)
        h, w = a.shape[:2]
        vv, uu = np.mgrid[0:h, 0:w] * step
        far = np.hypot(uu - u, vv - v) > factor * r
        if far.any():
            values.append(float(np.sqrt(np.mean(((a - b) / b)[far] ** 2))))
    return float(np.median(values)) if values else math.inf


@dataclass(frozen=True)
class ReferenceChoice:
    """Which reference the calibration uses, and how well each candidate matched the presses' far fields."""

    source: str                 # "given" or "presses"
    reference: np.ndarray       # H x W x 3 (float32 when built from the presses)
    given_change: float         # median RMS relative colour change of the far fields against the given reference
    presses_change: float       # ... against one built from the other presses (leave one out); nan: not weighed
    coverage: float = 1.0       # fraction of the pixels beyond `factor` radii of at least `min_frames` presses


def choose_reference(images: Sequence[np.ndarray], circles: Sequence[Circle], given: np.ndarray, source: str,
                     factor: float = 3.0, min_frames: int = 3, folds: int = 4) -> ReferenceChoice:
    """The reference a calibration uses: `source` "given" keeps the given one, "presses" builds it from the
    presses' far fields (`far_field_reference`), "auto" builds it and keeps it if the presses' far fields
    match it better than the given one (`reference_change`; each press against a reference built from the
    presses of the other `folds` - 1 parts, press k in part k mod folds, so no press matches itself), if every
    pixel lies beyond `factor` contact radii of at least `min_frames` presses (else the given one)."""
    if source not in ("given", "presses", "auto"):
        raise ValueError(f"reference source must be 'given', 'presses' or 'auto', got {source!r}")
    given = np.asarray(given)
    if source == "given":
        return ReferenceChoice("given", given, math.nan, math.nan)
    built = far_field_reference(images, circles, given, factor, min_frames)
    if source == "presses":
        return ReferenceChoice("presses", built, math.nan, math.nan)
    coverage = float(np.mean(far_masks(given.shape[:2], circles, factor).sum(axis=0) >= min_frames))
    if coverage < 1.0:          # the presses keep to a part of the image: see the module's docstring
        return ReferenceChoice("given", given, math.nan, math.nan, coverage)
    n = len(images)
    folds = max(2, min(folds, n))
    held: list[np.ndarray] = [given] * n
    for k in range(folds):
        others = [i for i in range(n) if i % folds != k]
        ref = far_field_reference([images[i] for i in others], [circles[i] for i in others], given, factor,
                                  min_frames)
        for i in range(k, n, folds):
            held[i] = ref
    given_change = reference_change(images, circles, [given] * n, factor)
    presses_change = reference_change(images, circles, held, factor)
    if presses_change < given_change:
        return ReferenceChoice("presses", built, given_change, presses_change)
    return ReferenceChoice("given", given, given_change, presses_change)
