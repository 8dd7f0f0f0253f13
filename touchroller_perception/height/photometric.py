"""The photometric model: from a pixel's colour change (and where it is in the image) to the membrane's slope.

Three coloured lights shine on the membrane from different directions, so a tilted patch changes the
three channels differently; against the no-contact reference the change is the slope's signature.
The features are the relative changes per channel, f_c = (I_c - R_c) / R_c (uneven light scales a
Lambertian patch's brightness, and the ratio takes most of that out), computed on the image
smoothed by `smoothing` px. The model is a least-squares polynomial:

    (gx, gy) = sum_t c_t m_t(f) p_t(u, v)

over the colour monomials m_t up to `colour_degree` (with the constant only if `offset`: a slope that
depends on position alone, which a no-contact frame then reads as a tilt); the monomials up to
`position_colour_degree` are also multiplied by the image-position monomials p(u, v) up to
`position_degree` (0: no position term), which absorbs what the ratio leaves of uneven light.
With `gain`, the reference is first scaled by the frame's overall colour drift (`frame_gain`).
gx = dz/du, gy = dz/dv (z the indentation, positive into the gel, u along image columns, v along
rows), dimensionless.

Evaluating the polynomial per pixel is exact but slow; `PhotometricModel.compile` tabulates it once
per reference and image size (`SlopeLookup`): the colour cube in `lookup_bins` steps per channel
times `lookup_cells` position cells (gx and gy as two 16-bit fixed-point numbers side by side), so a
frame costs a few array operations and one gather.

A zero-slope prior (`still_prior`: slopes shorter than a threshold read 0, longer than twice it as they are)
is a function of the slope alone, so it goes into the table too; its threshold is what the undeformed gel
reads (`PhotometricModel.still_slope`, measured by the calibration).
"""
from __future__ import annotations

import dataclasses
import io
import itertools
import json
import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import cv2
import numpy as np

FORMAT = "touchroller-photometric-1"


@dataclass(frozen=True)
class PhotometricConfig:
    """What the model is made of (all fixed before fitting)."""

    colour_degree: int = 3               # degree of the polynomial in the three colour ratios
    position_degree: int = 3             # degree in image position (0: colour alone)
    position_colour_degree: int = 2      # colour monomials up to this degree get position factors
    offset: bool = False                 # a constant term (position alone -> slope); False: no change, no slope
    gain: bool = True                    # divide out the frame's overall colour drift against the reference
    smoothing: float = 2.0               # Gaussian sigma (px) on the image before the features
    ridge: float = 1e-6                  # Tikhonov weight on the (scaled) coefficients
    lookup_bins: int = 33                # colour steps per channel (odd: one step is no change) of the compiled lookup
    lookup_cells: tuple[int, int] = (16, 12)   # position cells (along u, along v) of the compiled lookup

    def __post_init__(self) -> None:
        if not 1 <= self.colour_degree <= 6:
            raise ValueError(f"colour_degree must be 1..6, got {self.colour_degree}")
        if not 0 <= self.position_degree <= 6:
            raise ValueError(f"position_degree must be 0..6, got {self.position_degree}")
        if not 0 <= self.position_colour_degree <= self.colour_degree:
            raise ValueError("position_colour_degree must be 0..colour_degree")
        if not (np.isfinite(self.smoothing) and 0 <= self.smoothing <= 20):
            raise ValueError(f"smoothing must be 0..20 px, got {self.smoothing}")
        if not (np.isfinite(self.ridge) and self.ridge >= 0):
            raise ValueError(f"ridge must be >= 0, got {self.ridge}")
        if not 5 <= self.lookup_bins <= 129 or self.lookup_bins % 2 == 0:
            raise ValueError(f"lookup_bins must be odd, 5..129 (a step at no change), got {self.lookup_bins}")
        if len(self.lookup_cells) != 2 or not all(1 <= int(c) <= 64 for c in self.lookup_cells):
            raise ValueError(f"lookup_cells must be two counts 1..64, got {self.lookup_cells}")


#: a world height map's photometric model: the image smoothed by 1 px before the colour features, not the
#: default 2: a map cell averages some twenty frames, so it can take the noise, and relief a few pixels wide
#: keeps more of its depth (a Gaussian of 2 px keeps 0.007 of a 4-pixel wavelength's depth, one of 1 px 0.29).
#: Less smoothing keeps more of it still, and lets more noise through to the integration across the band.
MAP_PHOTOMETRIC = PhotometricConfig(smoothing=1.0)


def gaussian_kernel(sigma: float) -> np.ndarray:
    """The float32 1-D kernel `cv2.GaussianBlur` uses for a float32 image and sigma (size 8 sigma + 1, odd)."""
    size = int(round(sigma * 4 * 2 + 1)) | 1
    kernel: np.ndarray = cv2.getGaussianKernel(size, sigma, cv2.CV_32F)
    return kernel


def smooth(image: np.ndarray, sigma: float) -> np.ndarray:
    """float32 copy of an H x W x 3 image, Gaussian-smoothed by sigma px (none at 0): what
    `cv2.GaussianBlur` gives the image made float32, without that conversion's copy (8- and 16-bit
    images are filtered straight into float32)."""
    img = np.asarray(image)
    if img.ndim != 3 or img.shape[2] != 3:
        raise ValueError(f"expected an H x W x 3 colour image, got shape {img.shape}")
    if sigma <= 0:
        return img.astype(np.float32)
    if img.dtype not in (np.uint8, np.uint16, np.float32):
        img = img.astype(np.float32)
    kernel = gaussian_kernel(sigma)
    out: np.ndarray = cv2.sepFilter2D(np.ascontiguousarray(img), cv2.CV_32F, kernel, kernel,
                                      borderType=cv2.BORDER_REFLECT_101)
    return out


def frame_gain(image: np.ndarray, reference: np.ndarray, step: int = 8) -> np.ndarray:
    """3 float32: per channel, the median over the frame (a 1-in-`step` grid) of image / reference: the
    light's overall drift since the reference (a press covers a small part of the frame)."""
    a = np.asarray(image, np.float32)[::step, ::step].reshape(-1, 3)
    b = np.maximum(np.asarray(reference, np.float32)[::step, ::step].reshape(-1, 3), 1.0)
    gain = np.median(a / b, axis=0).astype(np.float32)
    return np.where(np.isfinite(gain) & (gain > 0.2) & (gain < 5.0), gain, 1.0).astype(np.float32)


def colour_features(image: np.ndarray, reference: np.ndarray, sigma: float, gain: bool = False) -> np.ndarray:
    """H x W x 3 float32 relative change per channel against the reference, both smoothed alike (with
    `gain`, against the reference times the frame's overall drift, `frame_gain`)."""
    image_s = smooth(image, sigma)
    ref_s = smooth(reference, sigma)
    if image_s.shape != ref_s.shape:
        raise ValueError(f"image {image_s.shape[:2]} and reference {ref_s.shape[:2]} differ in size")
    np.maximum(ref_s, 1.0, out=ref_s)
    if gain:
        ref_s *= frame_gain(image, reference)
    features: np.ndarray = (image_s - ref_s) / ref_s
    return features


def normalised_position(u: np.ndarray, v: np.ndarray, width: int, height: int) -> tuple[np.ndarray, np.ndarray]:
    """Image position scaled to about [-1, 1] (by the half width, both axes alike)."""
    half = 0.5 * width
    pu = (np.asarray(u, np.float64) - 0.5 * (width - 1)) / half
    pv = (np.asarray(v, np.float64) - 0.5 * (height - 1)) / half
    return pu, pv


def _exponents(degree: int, variables: int) -> list[tuple[int, ...]]:
    return [e for d in range(degree + 1) for e in itertools.combinations_with_replacement(range(variables), d)]


@dataclass(frozen=True)
class PhotometricModel:
    """A fitted colour (+ position) -> slope polynomial for one sensor at one image size."""

    config: PhotometricConfig
    coefficients: np.ndarray     # terms x 2 (gx, gy)
    width: int
    height: int
    colour_scale: np.ndarray     # 3: features are divided by this before the monomials (conditioning)
    colour_range: np.ndarray     # 3: the lookup spans +-this relative change per channel
    pixel_size: float = float("nan")   # metres per pixel the model was calibrated at (information)
    ball_radius: float = float("nan")  # metres (information)
    # the slope the undeformed gel reads: the calibration presses' far fields (beyond a few contact radii) read
    # by this model, a quantile of the slope's length there (`PressCalibrationConfig.still_quantile`); the
    # zero-slope prior's threshold (`still_prior`, `HeightConfig.still_slope`); 0: not measured
    still_slope: float = 0.0
    # the metric the prior measures a slope's length in: a 2 x 2 matrix W (row-major, determinant 1), length |W g|;
    # the calibration's far-field slopes whitened (their covariance's ellipse, of unit area), or round (identity)
    still_shape: tuple[float, float, float, float] = (1.0, 0.0, 0.0, 1.0)

    @property
    def terms(self) -> list[tuple[tuple[int, ...], tuple[int, ...]]]:
        return model_terms(self.config)

    def design(self, features: np.ndarray, u: np.ndarray, v: np.ndarray) -> np.ndarray:
        """N x terms matrix of the monomials at N samples (features N x 3, pixel u, v)."""
        return design_matrix(self.config, features / self.colour_scale, *normalised_position(u, v, self.width,
                                                                                              self.height))

    def slopes_at(self, features: np.ndarray, u: np.ndarray, v: np.ndarray) -> np.ndarray:
        """N x 2 (gx, gy) from the polynomial itself (exact, slow: for fitting and checking)."""
        result: np.ndarray = self.design(features, u, v) @ self.coefficients
        return result

    def slopes(self, image: np.ndarray, reference: np.ndarray, first_row: int = 0,
               still_change: float = 0.0, still_slope: float = 0.0) -> tuple[np.ndarray, np.ndarray]:
        """(gx, gy) float32 per pixel from the polynomial, of an image (or a band of rows of one that starts
        at `first_row`) and the same rows of the reference; 0 where every channel's relative change is
        within `still_change`; shrunk by the zero-slope prior `still_prior` of threshold `still_slope`."""
        feats = colour_features(image, reference, self.config.smoothing, self.config.gain)
        h, w = feats.shape[:2]
        vv, uu = np.mgrid[first_row:first_row + h, 0:w]
        out = self.slopes_at(feats.reshape(-1, 3).astype(np.float64), uu.ravel(), vv.ravel())
        if still_change > 0:
            out[(np.abs(feats.reshape(-1, 3)) <= still_change).all(axis=1)] = 0.0
        if still_slope > 0:
            out = still_prior(out, still_slope, self.still_shape)
        return out[:, 0].reshape(h, w).astype(np.float32), out[:, 1].reshape(h, w).astype(np.float32)

    def compile(self, reference: np.ndarray, still_change: float = 0.0, still_slope: float = 0.0) -> SlopeLookup:
        """The fast per-frame form of this model for one reference frame (`still_change`, `still_slope`: see
        `SlopeLookup.build`)."""
        return SlopeLookup.build(self, reference, still_change, still_slope)

    # ------------------------------------------------------------------ file
    def save(self, path: str | Path) -> None:
        """One .npz (written by the caller atomically if it wants: this writes to `path` directly)."""
        buffer = io.BytesIO()
        self.save_to(buffer)
        Path(path).write_bytes(buffer.getvalue())

    def save_to(self, stream: Any) -> None:
        """Into a binary stream (a file opened "wb", BytesIO)."""
        meta = {"format": FORMAT, "config": dataclasses.asdict(self.config), "width": self.width,
                "height": self.height, "pixel_size": self.pixel_size, "ball_radius": self.ball_radius,
                "still_slope": self.still_slope, "still_shape": list(self.still_shape)}
        np.savez(stream, meta=np.array(json.dumps(meta)), coefficients=self.coefficients,
                 colour_scale=self.colour_scale, colour_range=self.colour_range)

    @classmethod
    def load(cls, path: str | Path) -> PhotometricModel:
        """Raises ValueError (one line) when the file is not a photometric model."""
        try:
            with np.load(path, allow_pickle=False) as data:
                meta = json.loads(str(data["meta"]))
                coefficients = np.asarray(data["coefficients"], np.float64)
                scale = np.asarray(data["colour_scale"], np.float64)
                colour_range = np.asarray(data["colour_range"], np.float64)
        except (OSError, KeyError, ValueError, json.JSONDecodeError) as exc:
            raise ValueError(f"{path}: not a photometric model ({exc})") from None
        if meta.get("format") != FORMAT:
            raise ValueError(f"{path}: not a photometric model (format {meta.get('format')!r})")
        cfg = dict(meta["config"])
        cfg["lookup_cells"] = tuple(cfg["lookup_cells"])
        config = PhotometricConfig(**cfg)
        model = cls(config, coefficients, int(meta["width"]), int(meta["height"]), scale, colour_range,
                    float(meta["pixel_size"]), float(meta["ball_radius"]),
                    float(meta.get("still_slope", 0.0)),   # files made before it: not measured
                    _shape(meta.get("still_shape", (1.0, 0.0, 0.0, 1.0)), path))
        if coefficients.shape != (len(model_terms(config)), 2) or scale.shape != (3,) or colour_range.shape != (3,):
            raise ValueError(f"{path}: photometric model arrays do not match its configuration")
        if not (np.isfinite(coefficients).all() and np.isfinite(scale).all() and (scale > 0).all()
                and math.isfinite(model.still_slope) and model.still_slope >= 0):
            raise ValueError(f"{path}: photometric model has non-finite or non-positive values")
        if abs(float(np.linalg.det(np.reshape(model.still_shape, (2, 2)))) - 1.0) > 1e-6:
            raise ValueError(f"{path}: the photometric model's still_shape is not of determinant 1")
        return model


def model_terms(config: PhotometricConfig) -> list[tuple[tuple[int, ...], tuple[int, ...]]]:
    """(colour exponents, position exponents) of each term, in coefficient order."""
    position = _exponents(config.position_degree, 2)
    terms = []
    for ce in _exponents(config.colour_degree, 3)[0 if config.offset else 1:]:
        for pe in position if len(ce) <= config.position_colour_degree else [()]:
            terms.append((ce, pe))
    return terms


def design_matrix(config: PhotometricConfig, scaled: np.ndarray, pu: np.ndarray, pv: np.ndarray) -> np.ndarray:
    """N x terms monomials of scaled colour features (N x 3) and normalised positions (N)."""
    n = scaled.shape[0]
    colour_cache: dict[tuple[int, ...], np.ndarray] = {(): np.ones(n)}
    position_cache: dict[tuple[int, ...], np.ndarray] = {(): np.ones(n)}
    variables = (np.asarray(pu, np.float64).ravel(), np.asarray(pv, np.float64).ravel())

    def monomial(cache: dict[tuple[int, ...], np.ndarray], e: tuple[int, ...], values) -> np.ndarray:
        if e not in cache:
            cache[e] = monomial(cache, e[:-1], values) * values(e[-1])
        return cache[e]

    terms = model_terms(config)
    out = np.empty((n, len(terms)))
    for k, (ce, pe) in enumerate(terms):
        out[:, k] = monomial(colour_cache, ce, lambda j: scaled[:, j]) * monomial(position_cache, pe,
                                                                                  lambda j: variables[j])
    return out


def colour_matrix(config: PhotometricConfig, scaled: np.ndarray) -> np.ndarray:
    """N x colour-terms monomials of scaled colour features alone (the order of `model_terms`)."""
    exps = _exponents(config.colour_degree, 3)[0 if config.offset else 1:]
    out = np.empty((scaled.shape[0], len(exps)))
    cache: dict[tuple[int, ...], np.ndarray] = {(): np.ones(scaled.shape[0])}
    for k, e in enumerate(exps):
        if e not in cache:   # exps are in graded order: e[:-1] came before
            cache[e] = cache[e[:-1]] * scaled[:, e[-1]]
        out[:, k] = cache[e]
    return out


def colour_coefficients(model: PhotometricModel, pu: float, pv: float) -> np.ndarray:
    """colour-terms x 2: the model's coefficients with the position factors evaluated at (pu, pv)."""
    exps = _exponents(model.config.colour_degree, 3)[0 if model.config.offset else 1:]
    row = {e: k for k, e in enumerate(exps)}
    out = np.zeros((len(exps), 2))
    for (ce, pe), c in zip(model_terms(model.config), model.coefficients, strict=True):
        factor = 1.0
        for j in pe:
            factor *= pu if j == 0 else pv
        out[row[ce]] += factor * c
    return out


def fit_model(config: PhotometricConfig, features: np.ndarray, u: np.ndarray, v: np.ndarray, targets: np.ndarray,
              width: int, height: int, weights: np.ndarray | None = None, pixel_size: float = float("nan"),
              ball_radius: float = float("nan")) -> PhotometricModel:
    """Least squares (with a small ridge) of targets (N x 2 slopes) on the model's terms at N samples."""
    features = np.asarray(features, np.float64)
    ok = np.isfinite(features).all(axis=1) & np.isfinite(targets).all(axis=1)
    if ok.sum() < 10 * len(model_terms(config)):
        raise ValueError(f"too few samples ({int(ok.sum())}) for {len(model_terms(config))} model terms")
    features, u, v, targets = features[ok], np.asarray(u)[ok], np.asarray(v)[ok], np.asarray(targets, np.float64)[ok]
    scale = np.maximum(np.percentile(np.abs(features), 99, axis=0), 1e-3)
    colour_range = np.maximum(np.percentile(np.abs(features), 99.9, axis=0) * 1.1, 1e-3)
    model = PhotometricModel(config, np.zeros((len(model_terms(config)), 2)), int(width), int(height), scale,
                             colour_range, float(pixel_size), float(ball_radius))
    X = model.design(features, u, v)
    if weights is not None:
        w = np.sqrt(np.asarray(weights, np.float64)[ok])[:, None]
        X, targets = X * w, targets * w
    norms = np.maximum(np.linalg.norm(X, axis=0), 1e-12)
    A = X / norms
    gram = A.T @ A + config.ridge * np.eye(A.shape[1])
    coefficients = np.linalg.solve(gram, A.T @ targets) / norms[:, None]
    return dataclasses.replace(model, coefficients=coefficients)


def _shape(value: Any, path: str | Path) -> tuple[float, float, float, float]:
    try:
        shape = tuple(float(x) for x in value)
    except (TypeError, ValueError):
        raise ValueError(f"{path}: not a photometric model (still_shape {value!r})") from None
    if len(shape) != 4 or not all(math.isfinite(x) for x in shape):
        raise ValueError(f"{path}: not a photometric model (still_shape {value!r})")
    return shape[0], shape[1], shape[2], shape[3]


def still_prior(slopes: np.ndarray, threshold: float,
                shape: tuple[float, float, float, float] | None = None) -> np.ndarray:
    """A zero-slope prior (a firm threshold on the slope's length, its direction kept): slopes (... x 2,
    gx and gy last) shorter than `threshold` read 0, those longer than twice it read as they are, and in
    between the length rises linearly from 0 to 2 threshold (continuous; every slope is scaled by one
    factor). The length is |W g| with `shape` W (2 x 2 row-major, determinant 1; None: the plain length):
    the undeformed gel's slopes whitened, so the threshold is an ellipse of its readings. The threshold is
    what the undeformed gel reads (`PhotometricModel.still_slope`): a colour change that small cannot be
    told from one of a flat membrane, and a soft threshold (every slope shortened by it) would also flatten
    the steep ones. Non-finite slopes stay as they are."""
    dtype = np.float32 if np.asarray(slopes).dtype == np.float32 else np.float64
    out: np.ndarray = np.array(slopes, dtype=dtype)
    if threshold <= 0:
        return out
    t = float(threshold)
    if shape is None or tuple(shape) == (1.0, 0.0, 0.0, 1.0):
        magnitude = np.hypot(out[..., 0], out[..., 1])
    else:
        a, b, c, d = (float(x) for x in shape)
        magnitude = np.hypot(a * out[..., 0] + b * out[..., 1], c * out[..., 0] + d * out[..., 1])
    with np.errstate(divide="ignore", invalid="ignore"):
        factor = np.where(magnitude >= 2.0 * t, 1.0,
                          np.clip(magnitude - t, 0.0, None) * 2.0 / np.where(magnitude > 0, magnitude, 1.0))
    factor = np.where(np.isfinite(magnitude), factor, 1.0)
    out *= factor[..., None].astype(dtype)
    return out


SLOPE_UNIT = 1.0 / 8192.0   # the lookup's fixed-point slope step: int16 spans slopes of +-4 (76 deg)


@dataclass(frozen=True)
class SlopeLookup:
    """A model tabulated for one reference frame: per frame, slopes are one gather from `table`.

    Colour ratios are quantised to `bins` steps over +-colour_range per channel (nearest step); each
    pixel belongs to one of cells_u x cells_v position cells, whose polynomial is evaluated at the
    cell's centre. `scale`, `offset` fold the reference and the quantisation into one multiply-add per
    channel: q_c = rint(I_c * scale_c + offset_c) (`offset` is one value per channel). The table holds
    gx, gy as two int16 in units of `SLOPE_UNIT` (clipped to +-4, steeper than any membrane the
    calibration saw) packed into one uint32, so one gather gives both.
    """

    model: PhotometricModel
    table: np.ndarray        # cells * bins^3 uint32: gx, gy as two int16 (SLOPE_UNIT) packed (one gather per pixel)
    scale: np.ndarray        # H x W x 3 float32
    offset: np.ndarray       # H x W x 3 float32
    cell_base: np.ndarray    # H x W int32: cell index * bins^3
    reference: np.ndarray    # H x W x 3 float32, smoothed (the raw one for the frame gain: `raw`)
    raw: np.ndarray          # H x W x 3 uint8/float: the reference as given

    @classmethod
    def build(cls, model: PhotometricModel, reference: np.ndarray, still_change: float = 0.0,
              still_slope: float = 0.0) -> SlopeLookup:
        """still_change: a colour step whose relative change is within this in every channel reads slope 0
        (the frame matches the reference there: a zero-slope prior where nothing touches, at no cost per
        frame); 0 keeps only the step at no change, which the polynomial maps to 0 anyway. still_slope: the
        table's slopes shrunk by `still_prior` of this threshold in the model's `still_shape` (0: off), also
        at no cost per frame."""
        if not (np.isfinite(still_change) and 0.0 <= still_change < 1.0):
            raise ValueError(f"still_change must be a relative colour change in [0, 1), got {still_change}")
        if not (math.isfinite(still_slope) and still_slope >= 0.0):
            raise ValueError(f"still_slope must be a slope >= 0, got {still_slope}")
        cfg = model.config
        ref = smooth(reference, cfg.smoothing)
        h, w = ref.shape[:2]
        b = cfg.lookup_bins
        cu, cv = (int(c) for c in cfg.lookup_cells)
        step = 2.0 * model.colour_range / (b - 1)                  # relative change per bin; (b-1)/2 is 0
        np.maximum(ref, 1.0, out=ref)
        # f = I / R - 1, q = (f + range) / step  ->  q = I * (1 / (R step)) + (range - 1 * step^-1 ...)
        scale = (1.0 / (ref * step.astype(np.float32))).astype(np.float32)
        offset = np.broadcast_to(((model.colour_range - 1.0) / step).astype(np.float32) + 0.5, ref.shape)
        offset = np.ascontiguousarray(offset, dtype=np.float32)
        vv, uu = np.mgrid[0:h, 0:w]
        cell = (np.minimum(vv * cv // h, cv - 1) * cu + np.minimum(uu * cu // w, cu - 1)).astype(np.int32)
        levels = (np.arange(b) - (b - 1) // 2)[:, None] * step[None, :]   # b x 3, level (b-1)/2 exactly 0
        grid = np.stack(np.meshgrid(levels[:, 0], levels[:, 1], levels[:, 2], indexing="ij"), axis=-1).reshape(-1, 3)
        colour = colour_matrix(cfg, grid / model.colour_scale)
        coefficients = []
        for j in range(cv):
            for i in range(cu):
                pu, pv = normalised_position(np.array((i + 0.5) * w / cu - 0.5), np.array((j + 0.5) * h / cv - 0.5),
                                             w, h)
                coefficients.append(colour_coefficients(model, float(pu), float(pv)))
        # one product for all cells: bins^3 x (cells * 2), then cell-major
        values = colour @ np.concatenate(coefficients, axis=1)
        if still_change > 0:
            values[(np.abs(grid) <= still_change).all(axis=1)] = 0.0
        if still_slope > 0:     # a function of the slope alone: the table's entries, each cell's gx, gy
            values = still_prior(values.reshape(len(grid), -1, 2), still_slope,
                                 model.still_shape).reshape(values.shape)
        tables = values.reshape(len(grid), cu * cv, 2).transpose(1, 0, 2).reshape(-1, 2)
        fixed = np.clip(np.rint(tables / SLOPE_UNIT), -32767, 32767).astype(np.int16)
        table = np.ascontiguousarray(fixed).view(np.uint32).ravel()
        return cls(model, table, scale, offset, (cell * b**3).astype(np.int32), ref, np.asarray(reference))

    def slopes(self, image: np.ndarray, rows: slice | None = None) -> tuple[np.ndarray, np.ndarray]:
        """(gx, gy) float32 of an image, or of its `rows` (the image may be just those rows)."""
        cfg = self.model.config
        sl = slice(None) if rows is None else rows
        scale, offset, base = self.scale[sl], self.offset[sl], self.cell_base[sl]
        img = np.asarray(image)
        if img.shape[0] != scale.shape[0]:
            img = img[sl]
        if img.shape[:2] != scale.shape[:2] or img.ndim != 3 or img.shape[2] != 3:
            raise ValueError(f"image {img.shape} does not match the reference {self.scale.shape}")
        smoothed = smooth(img, cfg.smoothing)
        # q = I * scale / gain + offset per channel: the gain (f = I / (R g) - 1 divides the image by the
        # frame's drift) and the constant offset go in one affine colour transform
        inverse_gain = (1.0 / frame_gain(img, self.raw[sl] if img.shape[0] != self.raw.shape[0] else self.raw)
                        if cfg.gain else np.ones(3, np.float32))
        affine = np.zeros((3, 4), np.float32)
        affine[[0, 1, 2], [0, 1, 2]] = inverse_gain
        affine[:, 3] = offset.reshape(-1, 3)[0] if offset.size else 0.0
        q = cv2.transform(cv2.multiply(smoothed, scale), affine)
        b = cfg.lookup_bins
        np.clip(q, 0, b - 1, out=q)    # q >= 0: truncation of (x + 0.5) is rounding to the nearest step
        np.trunc(q, out=q)
        # the cell's index: q0 b^2 + q1 b + q2 (< 2^24 for b <= 129, exact in float32), plus the cell's base
        index = cv2.transform(q, np.array([[b * b, b, 1.0]], np.float32)).astype(np.int32)
        index += base
        pairs = self.table.take(index).view(np.int16).reshape(*index.shape, 2)
        both = pairs.astype(np.float32)
        both *= np.float32(SLOPE_UNIT)
        gx, gy = cv2.split(both)
        return gx, gy
