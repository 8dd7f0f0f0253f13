"""Slopes to height: an exact least-squares Poisson integrator (DCT, Neumann boundary).

The surface z on an H x W pixel grid is sought whose forward differences
    (Dx z)[i, j] = z[i, j + 1] - z[i, j]   (j < W - 1),   (Dy z)[i, j] = z[i + 1, j] - z[i, j]   (i < H - 1)
are closest (least squares) to the given differences. The normal equations
    (Dx^T Dx + Dy^T Dy) z = Dx^T px + Dy^T py
have the Neumann Laplacian on the left, which the type-II DCT diagonalises exactly: its eigenvalues
are (2 - 2 cos(pi k / W)) + (2 - 2 cos(pi l / H)) for k = 0..W-1, l = 0..H-1. The divergence on the
right is built with the transposes of the very operators the differences are defined by, so the
system is consistent: exact differences give back the exact surface (up to the constant the
gradients cannot see). Two classic slips are avoided here (and tested): taking central differences
without their 1/2 (a cap comes back about twice as steep) and shifting the eigenvalue index by one.

Slopes measured at pixel centres (a photometric model's dz/dx) are turned into the forward
differences the solver wants by averaging neighbouring centres (`sampled="centre"`, second-order
accurate); slopes that already are forward differences pass through (`sampled="forward"`).
Non-finite slopes carry no information: they are treated as zero slope (the solver bridges them
smoothly); the caller masks the height where it knows nothing.

A camera pixel gathers the light of its whole footprint, so its slope is the height's difference across
the pixel, averaged across it: `footprint_integrate` solves that model exactly in the transform domain
(DST/DCT), where the centre model keeps only cos(pi / wavelength in px) of a fine relief's depth;
`column_heights` is its one-dimensional form, each column on its own.
"""
from __future__ import annotations

from functools import lru_cache
from typing import Literal

import numpy as np
import scipy.fft

Sampling = Literal["centre", "forward"]


def _eigenvalues(n: int, dtype: type) -> np.ndarray:
    k = np.arange(n, dtype=np.float64)
    return (2.0 - 2.0 * np.cos(np.pi * k / n)).astype(dtype)


@lru_cache(maxsize=16)
def _inverse_operator(h: int, w: int, dtype: str) -> np.ndarray:
    """1 / the Neumann Laplacian's eigenvalues on an h x w grid (0 for the constant), read-only, cached per size."""
    denom = _eigenvalues(h, np.float64)[:, None] + _eigenvalues(w, np.float64)[None, :]
    denom[0, 0] = 1.0
    inverse = (1.0 / denom).astype(dtype)
    inverse[0, 0] = 0.0
    inverse.setflags(write=False)
    return inverse


def _finite(a: np.ndarray, dtype: type) -> np.ndarray:
    out: np.ndarray = np.asarray(a, dtype=dtype)
    if not np.isfinite(out).all():
        out = np.where(np.isfinite(out), out, 0.0).astype(dtype)
    return out


def forward_differences(gx: np.ndarray, gy: np.ndarray, spacing: float | tuple[float, float] = 1.0,
                        sampled: Sampling = "centre", dtype: type = np.float64) -> tuple[np.ndarray, np.ndarray]:
    """(px, py): z[i, j+1] - z[i, j] (H x W-1) and z[i+1, j] - z[i, j] (H-1 x W) from slopes.

    spacing: metres per pixel (one value, or (along x = columns, along y = rows)); gx, gy: slopes
    dz/dx, dz/dy (dimensionless) at the pixel centres (`centre`) or already as forward differences
    over one pixel divided by the spacing (`forward`, H x W with the last column / row ignored).
    """
    sx, sy = (spacing, spacing) if np.isscalar(spacing) else spacing  # type: ignore[misc]
    gx = _finite(gx, dtype)
    gy = _finite(gy, dtype)
    if gx.shape != gy.shape or gx.ndim != 2:
        raise ValueError(f"gx and gy must be two 2-D arrays of one shape, got {gx.shape} and {gy.shape}")
    if sampled == "centre":
        px = 0.5 * (gx[:, 1:] + gx[:, :-1]) * dtype(sx)
        py = 0.5 * (gy[1:, :] + gy[:-1, :]) * dtype(sy)
    elif sampled == "forward":
        px = gx[:, :-1] * dtype(sx)
        py = gy[:-1, :] * dtype(sy)
    else:
        raise ValueError(f"sampled must be 'centre' or 'forward', got {sampled!r}")
    return px, py


def divergence(px: np.ndarray, py: np.ndarray) -> np.ndarray:
    """Dx^T px + Dy^T py on the H x W grid (px: H x W-1, py: H-1 x W): the normal equations' right side
    (minus the usual divergence, with the boundary rows the operators' transposes give)."""
    H, W = py.shape[0] + 1, px.shape[1] + 1
    f = np.zeros((H, W), dtype=px.dtype)
    f[:, :-1] -= px
    f[:, 1:] += px
    f[:-1, :] -= py
    f[1:, :] += py
    return f


def poisson_solve(px: np.ndarray, py: np.ndarray, workers: int = 1) -> np.ndarray:
    """The least-squares surface (mean zero) whose forward differences best match px, py."""
    H, W = py.shape[0] + 1, px.shape[1] + 1
    if px.shape != (H, W - 1):
        raise ValueError(f"px must be H x (W-1) = {H} x {W - 1}, got {px.shape}")
    # (Dx^T Dx + Dy^T Dy) z = Dx^T px + Dy^T py: the operator is positive semi-definite
    return _solve(divergence(px, py), workers)


def _solve(f: np.ndarray, workers: int) -> np.ndarray:
    """z (mean zero) with (Dx^T Dx + Dy^T Dy) z = f, in f's dtype (f is overwritten)."""
    dtype = f.dtype.type
    hat = scipy.fft.dctn(f, type=2, norm="ortho", workers=workers, overwrite_x=True)
    hat *= _inverse_operator(f.shape[0], f.shape[1], f.dtype.str)
    z = scipy.fft.idctn(hat, type=2, norm="ortho", workers=workers, overwrite_x=True)
    return np.asarray(z, dtype=dtype)


def centre_divergence(gx: np.ndarray, gy: np.ndarray, sx: float, sy: float) -> np.ndarray:
    """`divergence(*forward_differences(gx, gy, (sx, sy), "centre"))` in one pass over the slopes (H, W >= 2):
    with px[:, j] = (gx[:, j] + gx[:, j+1]) sx / 2, Dx^T px is sx / 2 (gx[:, j-1] - gx[:, j+1]) inside,
    -px[:, 0] at the first column and px[:, -1] at the last (and alike along y)."""
    dtype = gx.dtype.type
    hx, hy = dtype(0.5 * sx), dtype(0.5 * sy)
    f = np.empty(gx.shape, dtype=gx.dtype)
    np.subtract(gx[:, :-2], gx[:, 2:], out=f[:, 1:-1])
    f[:, 1:-1] *= hx
    np.add(gx[:, 0], gx[:, 1], out=f[:, 0])
    f[:, 0] *= -hx
    np.add(gx[:, -2], gx[:, -1], out=f[:, -1])
    f[:, -1] *= hx
    inner = gy[:-2] - gy[2:]
    inner *= hy
    f[1:-1] += inner
    f[0] -= hy * (gy[0] + gy[1])
    f[-1] += hy * (gy[-2] + gy[-1])
    return f


def integrate(gx: np.ndarray, gy: np.ndarray, spacing: float | tuple[float, float] = 1.0,
              sampled: Sampling = "centre", zero: np.ndarray | None = None, dtype: type = np.float64,
              workers: int = 1) -> np.ndarray:
    """Height (units of `spacing`) from slopes dz/dx, dz/dy on an H x W grid.

    zero: optional boolean mask of pixels known to be at height 0 (the undeformed membrane); the
    constant the slopes cannot give is chosen so that their median is 0. Without it the result has
    mean 0. A grid of one row or column integrates along its length alone.
    """
    gx_arr = np.asarray(gx)
    if gx_arr.ndim != 2 or gx_arr.shape != np.shape(gy):
        raise ValueError(f"gx and gy must be two 2-D arrays of one shape, got {gx_arr.shape} and {np.shape(gy)}")
    H, W = gx_arr.shape
    if H == 0 or W == 0:
        return np.zeros((H, W), dtype=dtype)
    if H == 1 or W == 1:
        z = _integrate_line(gx, gy, spacing, sampled, dtype)
    elif sampled == "centre":
        sx, sy = (spacing, spacing) if np.ndim(spacing) == 0 else spacing  # type: ignore[misc]
        z = _solve(centre_divergence(_finite(gx, dtype), _finite(gy, dtype), float(sx), float(sy)),  # type: ignore[arg-type]
                   workers)
    else:
        px, py = forward_differences(gx, gy, spacing, sampled, dtype)
        z = poisson_solve(px, py, workers=workers)
    if zero is not None:
        zero = np.asarray(zero, dtype=bool)
        if zero.shape != z.shape:
            raise ValueError(f"zero mask must be {z.shape}, got {zero.shape}")
        if zero.any():
            z -= dtype(np.median(z[zero]))
    return z


def _integrate_line(gx: np.ndarray, gy: np.ndarray, spacing: float | tuple[float, float], sampled: Sampling,
                    dtype: type) -> np.ndarray:
    sx, sy = (spacing, spacing) if np.isscalar(spacing) else spacing  # type: ignore[misc]
    H, W = np.shape(gx)
    g, s = (_finite(gx, dtype).ravel(), sx) if H == 1 else (_finite(gy, dtype).ravel(), sy)
    if g.size == 1:
        return np.zeros((H, W), dtype=dtype)
    d = 0.5 * (g[1:] + g[:-1]) if sampled == "centre" else g[:-1]
    z: np.ndarray = np.concatenate([[0.0], np.cumsum(d * dtype(s))]).astype(dtype)
    z -= z.mean()
    return z.reshape(H, W)


@lru_cache(maxsize=8)
def _footprint_operator(h: int, w: int) -> tuple[np.ndarray, np.ndarray]:
    """(Hx / (Hx^2 + Hy^2), Hy / (Hx^2 + Hy^2)) on the h x w DCT-II coefficients (row l, column k; 0 at (0, 0)):
    a pixel's mean slope over its footprint, of the height's cosine (l, k), is Hx (along the columns) or Hy
    (along the rows) times the sine of the same frequency (DST-II): the height's difference across the pixel
    (2 sin(w / 2) at w = pi k / w), averaged across it (the box's sin(w / 2) / (w / 2))."""
    wx = np.pi * np.arange(w) / w
    wy = np.pi * np.arange(h) / h

    def box(a: np.ndarray) -> np.ndarray:
        half = 0.5 * a
        out = np.ones_like(a)
        out[1:] = np.sin(half[1:]) / half[1:]
        return out

    hx = (-2.0 * np.sin(0.5 * wx))[None, :] * box(wy)[:, None]
    hy = (-2.0 * np.sin(0.5 * wy))[:, None] * box(wx)[None, :]
    denominator = hx * hx + hy * hy
    denominator[0, 0] = 1.0
    ox, oy = (hx / denominator).astype(np.float32), (hy / denominator).astype(np.float32)
    ox.setflags(write=False)
    oy.setflags(write=False)
    return ox, oy


def footprint_integrate(gx: np.ndarray, gy: np.ndarray, spacing: tuple[float, float]) -> np.ndarray:
    """The height (float32, mean zero, on the pixel centres) whose mean slopes over each pixel's footprint best
    match gx, gy (least squares, Neumann boundary): a pixel integrates the light over its area, so its colour
    tells the height's difference across it, not the slope at its centre. Exact for such slopes at every
    frequency the grid holds (the centre model's integration keeps cos(w / 2) of them: half at a 3-pixel
    wavelength)."""
    h, w = gx.shape
    ox, oy = _footprint_operator(h, w)
    if h < 2 or w < 2:
        raise ValueError(f"footprint_integrate needs at least 2 x 2 slopes, got {h} x {w}")
    # non-finite slopes carry nothing: zero slope there (as `height.integrate`)
    px = np.nan_to_num(np.asarray(gx, np.float32) * np.float32(spacing[0]), nan=0.0, posinf=0.0, neginf=0.0)
    py = np.nan_to_num(np.asarray(gy, np.float32) * np.float32(spacing[1]), nan=0.0, posinf=0.0, neginf=0.0)
    sx = scipy.fft.dct(scipy.fft.dst(px, type=2, norm="ortho", axis=1, overwrite_x=True), type=2, norm="ortho",
                       axis=0, overwrite_x=True)
    sy = scipy.fft.dct(scipy.fft.dst(py, type=2, norm="ortho", axis=0, overwrite_x=True), type=2, norm="ortho",
                       axis=1, overwrite_x=True)
    hat = np.zeros((h, w), np.float32)
    # DST-II's coefficient k - 1 is the cosine's k (its last, k = w, is the pixel-to-pixel alternation no cosine
    # of the grid has)
    np.multiply(ox[:, 1:], sx[:, :-1], out=hat[:, 1:])
    hat[1:, :] += oy[1:, :] * sy[:-1, :]
    z: np.ndarray = scipy.fft.idctn(hat, type=2, norm="ortho", overwrite_x=True)
    return z.astype(np.float32, copy=False)


def column_heights(gy: np.ndarray, spacing: float, slopes: str = "footprint") -> np.ndarray:
    """Each column's height (float32, up to a constant per column) from its own slopes along the rows, gy, alone,
    its closure removed (the column's mean slope: both ends at one height). `slopes` as `WorldHeightConfig.slopes`:
    "footprint", the 1-D form of `footprint_integrate` (a relief along the rows comes back as that solver gives it:
    whole); "centre", the slopes summed down the column."""
    g = np.asarray(gy, np.float32) - np.asarray(gy, np.float32).mean(axis=0, keepdims=True)
    if slopes == "centre":
        column: np.ndarray = np.cumsum(g, axis=0, dtype=np.float32)
        column *= np.float32(spacing)
        return column
    h = g.shape[0]
    if h < 2:
        return np.zeros_like(g)
    coefficients = scipy.fft.dst(g * np.float32(spacing), type=2, norm="ortho", axis=0, overwrite_x=True)
    inverse = np.zeros(h, np.float32)
    inverse[1:] = -0.5 / np.sin(0.5 * np.pi * np.arange(1, h) / h)   # 1 / the difference across a pixel
    hat = np.zeros_like(coefficients)
    np.multiply(coefficients[:-1], inverse[1:, None], out=hat[1:])     # DST-II's l - 1 is the cosine's l
    out: np.ndarray = scipy.fft.idct(hat, type=2, norm="ortho", axis=0, overwrite_x=True)
    return out.astype(np.float32, copy=False)
