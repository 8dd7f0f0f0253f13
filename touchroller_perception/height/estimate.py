"""Height per frame: slopes from the photometric model, integrated to metres of indentation.

`HeightEstimator` is the per-frame path (a model compiled once for one reference, one pixel size and
optionally one band of rows); `band_height` is the same as one call for a band image (what a world
mapper calls: band image + its reference rows + model + pixel size -> metres). The result is the
membrane's indentation, positive into the gel, float32 metres, NaN where nothing is estimated (the
rows outside the band). What the slopes cannot give (a constant) or give badly (a slope bias over the
whole frame: light that drifted since the reference) is fixed by the flat pixels, those whose slope
is below `flat_slope`: a robust best plane through them is 0 (the undeformed membrane), or with
`level="offset"` just their median. Slopes as short as the undeformed gel reads are taken as 0 first
(`HeightConfig.still_slope`: the model's zero-slope prior, `photometric.still_prior`).

For the roller, `contact_band` gives the rows the contact can reach and the pixel size at the
contact line from the camera model (the band is integrated as a plane at that pixel size: the
membrane's curvature across the thin band is left out).
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numpy as np

from touchroller_perception.geometry import CameraModel
from touchroller_perception.height.integrate import integrate
from touchroller_perception.height.photometric import PhotometricModel, SlopeLookup


@dataclass(frozen=True)
class HeightConfig:
    flat_slope: float = 0.03         # |slope| below this counts as undeformed for the zero level
    level: str = "plane"             # "plane": a robust best plane through the flat pixels is 0; "offset": their median
    downsample: int = 1              # integrate on a grid this many times coarser (speed), then upsample
    still_change: float = 0.0        # relative colour change (every channel) within which a pixel reads slope 0
    # the zero-slope prior's threshold (`photometric.still_prior`: slopes below it read 0, above twice it as
    # they are): None the model's own (`PhotometricModel.still_slope`, what the calibration presses' undeformed
    # gel read; 0 in a model made without it), 0 off, or a slope
    still_slope: float | None = None

    def __post_init__(self) -> None:
        if self.level not in ("plane", "offset"):
            raise ValueError(f"level must be 'plane' or 'offset', got {self.level!r}")
        if not (math.isfinite(self.flat_slope) and self.flat_slope > 0):
            raise ValueError(f"flat_slope must be > 0, got {self.flat_slope}")
        if self.downsample not in (1, 2, 4):
            raise ValueError(f"downsample must be 1, 2 or 4, got {self.downsample}")
        if not (math.isfinite(self.still_change) and 0.0 <= self.still_change < 1.0):
            raise ValueError(f"still_change must be in [0, 1), got {self.still_change}")
        if self.still_slope is not None and not (math.isfinite(self.still_slope) and 0.0 <= self.still_slope <= 1.0):
            raise ValueError(f"still_slope must be None (the model's own) or a slope in [0, 1], got {self.still_slope}")

    def prior_slope(self, model: PhotometricModel) -> float:
        """The zero-slope prior's threshold for `model`: `still_slope`, or the model's own when None."""
        return float(model.still_slope if self.still_slope is None else self.still_slope)


def _spacing(pixel_size: float | tuple[float, float]) -> tuple[float, float]:
    su, sv = (pixel_size, pixel_size) if isinstance(pixel_size, int | float) else pixel_size
    if not all(math.isfinite(s) and s > 0 for s in (su, sv)):
        raise ValueError(f"pixel size must be positive metres, got {pixel_size}")
    return float(su), float(sv)


def slopes_to_height(gx: np.ndarray, gy: np.ndarray, pixel_size: float | tuple[float, float],
                     config: HeightConfig | None = None) -> np.ndarray:
    """float32 metres from slopes (dimensionless, per pixel), zero at the flat pixels' median."""
    config = config or HeightConfig()
    su, sv = _spacing(pixel_size)
    k = config.downsample
    if k > 1 and min(gx.shape) >= 4 * k:
        h, w = gx.shape
        hh, ww = h // k * k, w // k * k
        gxs = gx[:hh, :ww].reshape(hh // k, k, ww // k, k).mean(axis=(1, 3))
        gys = gy[:hh, :ww].reshape(hh // k, k, ww // k, k).mean(axis=(1, 3))
        small = _integrate_zeroed(gxs, gys, (su * k, sv * k), config)
        z = cv2.resize(small, (ww, hh), interpolation=cv2.INTER_LINEAR)
        if (hh, ww) != (h, w):
            z = np.pad(z, ((0, h - hh), (0, w - ww)), mode="edge")
        out: np.ndarray = z.astype(np.float32)
        return out
    return _integrate_zeroed(gx, gy, (su, sv), config)


def _integrate_zeroed(gx: np.ndarray, gy: np.ndarray, spacing: tuple[float, float], config: HeightConfig) -> np.ndarray:
    gx = np.asarray(gx, np.float32)
    gy = np.asarray(gy, np.float32)
    flat = cv2.magnitude(gx, gy) < np.float32(config.flat_slope)
    plane = config.level == "plane" and min(gx.shape) >= 2 and int(np.count_nonzero(flat)) >= 3
    # the plane holds the constant too: the median zero is needed only without it
    z = integrate(gx, gy, spacing, zero=None if plane or not flat.any() else flat, dtype=np.float32)
    if plane:
        z -= level_plane(z, flat)
    out: np.ndarray = z.astype(np.float32, copy=False)
    return out


def level_plane(z: np.ndarray, flat: np.ndarray, step: int = 4, iterations: int = 3) -> np.ndarray:
    """The best plane through z over the `flat` pixels (a 1-in-`step` grid of them), refitted without
    the pixels more than 2.5 robust sigmas off it (a contact's flat top is not the undeformed gel)."""
    h, w = z.shape
    sub, zs = flat[::step, ::step], z[::step, ::step]
    if np.count_nonzero(sub) < 3:
        step, sub, zs = 1, flat, z
    vs, us = np.nonzero(sub)
    u, v, zz = (us * step).astype(np.float64), (vs * step).astype(np.float64), zs[vs, us].astype(np.float64)
    keep = np.isfinite(zz)
    coef = np.zeros(3)
    design = np.stack([np.ones_like(u), u / w, v / h])          # 3 x N, scaled for conditioning
    for _ in range(iterations):
        n = int(np.count_nonzero(keep))
        if n < 3:
            break
        a = design[:, keep]
        gram = a @ a.T
        if np.linalg.cond(gram) < 1e10:
            coef = np.linalg.solve(gram, a @ zz[keep])        # least squares by the normal equations (3 x 3)
        else:                                                # the flat pixels on one line: minimum norm
            coef, *_ = np.linalg.lstsq(a.T, zz[keep], rcond=None)
        res = np.abs(zz - coef @ design)
        sigma = 1.4826 * float(np.median(res[keep])) + 1e-12
        keep = res <= 2.5 * sigma
    cols = np.float32(coef[0]) + np.float32(coef[1] / w) * np.arange(w, dtype=np.float32)
    rows = np.float32(coef[2] / h) * np.arange(h, dtype=np.float32)[:, None]
    plane: np.ndarray = cols + rows
    return plane


class HeightEstimator:
    """Per-frame height for one sensor setup: a model compiled for one reference and pixel size.

    rows: the band of image rows to estimate (the roller's contact band), or None for the whole frame.
    """

    def __init__(self, model: PhotometricModel, reference: np.ndarray, pixel_size: float | tuple[float, float],
                 rows: tuple[int, int] | None = None, config: HeightConfig | None = None) -> None:
        reference = np.asarray(reference)
        if reference.ndim != 3 or reference.shape[2] != 3:
            raise ValueError(f"the reference must be a colour image (H x W x 3), got shape {reference.shape}")
        if (reference.shape[1], reference.shape[0]) != (model.width, model.height):
            raise ValueError(f"the reference is {reference.shape[1]}x{reference.shape[0]} but the photometric "
                             f"model was calibrated on {model.width}x{model.height} images")
        self.config = config or HeightConfig()
        self.pixel_size = _spacing(pixel_size)
        h = reference.shape[0]
        if rows is not None:
            v0, v1 = int(rows[0]), int(rows[1])
            if not 0 <= v0 < v1 <= h:
                raise ValueError(f"rows {rows} are not a band of the {h}-row image")
            self.rows: tuple[int, int] = (v0, v1)
        else:
            self.rows = (0, h)
        self.lookup: SlopeLookup = model.compile(reference, self.config.still_change, self.config.prior_slope(model))
        self.shape = reference.shape[:2]

    def slopes(self, image: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(gx, gy) float32 of the band (or the whole image) from the compiled lookup."""
        return self.lookup.slopes(image, rows=slice(*self.rows))

    def band(self, image: np.ndarray) -> np.ndarray:
        """float32 metres over the band's rows only (the image may be the whole frame or just the band)."""
        gx, gy = self.slopes(image)
        return slopes_to_height(gx, gy, self.pixel_size, self.config)

    def height(self, image: np.ndarray) -> np.ndarray:
        """float32 metres, the image's size, NaN outside the band."""
        image = np.asarray(image)
        if image.shape[:2] != self.shape:
            raise ValueError(f"image {image.shape[1]}x{image.shape[0]} does not match the reference "
                             f"{self.shape[1]}x{self.shape[0]}")
        out = np.full(self.shape, np.nan, np.float32)
        out[self.rows[0]:self.rows[1]] = self.band(image)
        return out


def band_height(band_image: np.ndarray, band_reference: np.ndarray, model: PhotometricModel,
                pixel_size: float | tuple[float, float], first_row: int = 0,
                config: HeightConfig | None = None) -> np.ndarray:
    """Metres of indentation (float32, the band's size) of a band of rows starting at `first_row`.

    The model's exact polynomial (no compiled lookup: no set-up cost, slower per pixel); a caller
    with many frames keeps a `HeightEstimator` instead.
    """
    band_image = np.asarray(band_image)
    band_reference = np.asarray(band_reference)
    if band_image.shape != band_reference.shape or band_image.ndim != 3:
        raise ValueError(f"band image {band_image.shape} and reference {band_reference.shape} must be two "
                         "H x W x 3 images of one size")
    if band_image.shape[1] != model.width or not 0 <= first_row <= model.height - band_image.shape[0]:
        raise ValueError(f"a band of {band_image.shape[1]}x{band_image.shape[0]} at row {first_row} does not fit "
                         f"the model's {model.width}x{model.height} images")
    config = config or HeightConfig()
    gx, gy = model.slopes(band_image, band_reference, first_row=first_row, still_change=config.still_change,
                          still_slope=config.prior_slope(model))
    return slopes_to_height(gx, gy, pixel_size, config)


@dataclass(frozen=True)
class ContactBand:
    """The roller's contact band in the image and the pixel size at its contact line."""

    rows: tuple[int, int]          # [v0, v1)
    pixel_size: tuple[float, float]  # metres per pixel along u (the axis) and v (around it), at the contact line
    contact_row: float


def contact_band(camera: CameraModel, max_depth: float = 1.0e-3, pad: int = 4) -> ContactBand:
    """Rows whose membrane points lie within `max_depth` of the lowest membrane line (the rows a press
    of at most that depth can reach), and the pixel size at the contact line (x = 0, alpha = 0)."""
    if not (math.isfinite(max_depth) and 0 < max_depth < camera.radius):
        raise ValueError(f"max_depth must be in (0, radius), got {max_depth}")
    half = math.acos(1.0 - max_depth / camera.radius)        # angle of the band's edge
    xs = np.array([0.0, 0.0, 0.0, 1e-4, 0.0])
    alphas = np.array([-half, half, 0.0, 0.0, 1e-4 / camera.radius])
    uv, ok = camera.project(camera.surface_point(xs, alphas))
    if not ok[:3].all() or not np.isfinite(uv).all():
        raise ValueError("the contact line is not in the camera's view")
    v_lo, v_hi = sorted((float(uv[0, 1]), float(uv[1, 1])))
    v0 = max(0, int(math.floor(v_lo)) - pad)
    v1 = min(camera.height, int(math.ceil(v_hi)) + 1 + pad)
    if v1 - v0 < 2:
        raise ValueError("the contact band is less than two rows in this camera model")
    du = float(np.hypot(*(uv[3] - uv[2])))
    dv = float(np.hypot(*(uv[4] - uv[2])))
    if du <= 0 or dv <= 0:
        raise ValueError("the camera model gives no pixel size at the contact line")
    return ContactBand((v0, v1), (1e-4 / du, 1e-4 / dv), float(uv[2, 1]))


def pixel_size_at(camera: CameraModel, u: float, v: float) -> tuple[float, float]:
    """Metres per pixel along u and v on the membrane at pixel (u, v), from the camera model."""
    points, ok = camera.back_project(np.array([[u, v], [u + 1.0, v], [u, v + 1.0]]))
    if not np.all(ok):
        raise ValueError(f"pixel ({u:.1f}, {v:.1f}) does not map onto the membrane in this camera model")
    return float(np.linalg.norm(points[1] - points[0])), float(np.linalg.norm(points[2] - points[0]))
