"""The Poisson integrator: exact gradients give the exact surface (sphere caps, cosines), zero gives zero,
non-finite slopes are bridged, and the two classic slips (central differences without /2, eigenvalue
indices off by one) would fail these tests."""
from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from touchroller_perception.height import divergence, forward_differences, integrate, poisson_solve
from touchroller_perception.height.integrate import (
    _footprint_operator,
    centre_divergence,
    column_heights,
    footprint_integrate,
)


def sphere_cap(h: int, w: int, cu: float, cv: float, radius: float, depth: float):
    """Height (px units) of a sphere of `radius` pressed `depth` deep, and its analytic slopes."""
    v, u = np.mgrid[0:h, 0:w].astype(np.float64)
    du, dv = u - cu, v - cv
    centre_z = radius - depth              # sphere centre above the base plane (z up = into the gel)
    inside = radius**2 - du**2 - dv**2
    z = np.where(inside > 0, np.sqrt(np.maximum(inside, 0)) - centre_z, 0.0)
    touching = z > 0
    z = np.where(touching, z, 0.0)
    s = np.sqrt(np.maximum(inside, 1e-12))
    gx = np.where(touching, -du / s, 0.0)
    gy = np.where(touching, -dv / s, 0.0)
    return z, gx, gy, ~touching


@settings(max_examples=25, deadline=None)
@given(h=st.integers(134, 180), w=st.integers(134, 180), fu=st.floats(0.45, 0.55), fv=st.floats(0.45, 0.55),
       steep=st.floats(1.1, 8.0), frac=st.floats(0.3, 0.4))
def test_sphere_cap_depth_within_one_percent(h, w, fu, fv, steep, frac):
    """Analytic slopes at pixel centres (as a photometric model gives them), contact radius >= 40 px (a real
    press: about 60; the slope's jump at the rim costs depth in proportion to 1 / contact radius),
    from shallow caps to a contact of 0.9 of the sphere's radius (a real press: about 0.87)."""
    contact = frac * min(h, w)              # contact radius (px), inside the frame
    radius = steep * contact
    depth = radius - np.sqrt(radius**2 - contact**2)
    z, gx, gy, outside = sphere_cap(h, w, fu * w, fv * h, radius, depth)
    got = integrate(gx, gy, zero=outside)
    assert abs(got.max() - z.max()) <= 0.01 * z.max()


@settings(max_examples=20, deadline=None)
@given(h=st.integers(8, 90), w=st.integers(8, 90), radius=st.floats(3.0, 100.0), depth=st.floats(0.1, 1.0))
def test_sphere_cap_exact_differences_exact(h, w, radius, depth):
    z, _, _, _ = sphere_cap(h, w, w / 2, h / 2, radius, depth * radius)
    gx = np.zeros_like(z)
    gy = np.zeros_like(z)
    gx[:, :-1] = np.diff(z, axis=1)
    gy[:-1, :] = np.diff(z, axis=0)
    got = integrate(gx, gy, sampled="forward")
    np.testing.assert_allclose(got, z - z.mean(), atol=1e-9 * max(z.max(), 1.0))


@settings(max_examples=25, deadline=None)
@given(h=st.integers(16, 80), w=st.integers(16, 80), kx=st.integers(1, 4), ky=st.integers(0, 4),
       amp=st.floats(0.5, 20.0), spacing=st.floats(1e-5, 1e-3))
def test_cosine_exact_forward_differences(h, w, kx, ky, amp, spacing):
    v, u = np.mgrid[0:h, 0:w].astype(np.float64)
    z = amp * spacing * np.cos(np.pi * kx * u / w + 0.3) * np.cos(np.pi * ky * v / h + 0.1)
    gx = np.zeros_like(z)
    gy = np.zeros_like(z)
    gx[:, :-1] = np.diff(z, axis=1) / spacing
    gy[:-1, :] = np.diff(z, axis=0) / spacing
    got = integrate(gx, gy, spacing, sampled="forward")
    np.testing.assert_allclose(got, z - z.mean(), atol=1e-9 * max(np.abs(z).max(), 1e-30) + 1e-18)


def test_cosine_centre_slopes_within_one_percent():
    h, w, spacing = 120, 160, 3e-5
    v, u = np.mgrid[0:h, 0:w].astype(np.float64)
    a = 1e-4
    z = a * np.cos(2 * np.pi * u / 80.0) * np.cos(2 * np.pi * v / 60.0)
    gx = -a * 2 * np.pi / (80.0 * spacing) * np.sin(2 * np.pi * u / 80.0) * np.cos(2 * np.pi * v / 60.0)
    gy = -a * 2 * np.pi / (60.0 * spacing) * np.cos(2 * np.pi * u / 80.0) * np.sin(2 * np.pi * v / 60.0)
    got = integrate(gx, gy, spacing)
    assert np.ptp(got) == pytest.approx(np.ptp(z), rel=0.01)
    assert np.abs(got - (z - z.mean())).max() <= 0.01 * np.ptp(z)


def test_zero_gradient_gives_zero():
    assert np.array_equal(integrate(np.zeros((30, 40)), np.zeros((30, 40))), np.zeros((30, 40)))


@pytest.mark.parametrize("bad", [np.nan, np.inf, -np.inf])
def test_non_finite_slopes_are_bridged(bad):
    z, gx, gy, outside = sphere_cap(60, 70, 35.0, 30.0, 40.0, 3.0)
    gx[5, 5] = bad
    gy[50, 60] = bad
    got = integrate(gx, gy, zero=outside)
    assert np.isfinite(got).all()
    assert abs(got.max() - z.max()) <= 0.02 * z.max()
    all_bad = integrate(np.full((8, 9), np.nan), np.full((8, 9), np.inf))
    assert np.array_equal(all_bad, np.zeros((8, 9)))


def test_gs_sdk_slips_would_fail():
    """Central differences without /2 amount to doubled differences: the cap comes back too deep, so the
    depth tests above can tell the consistent solver from that slip."""
    z, gx, gy, outside = sphere_cap(64, 64, 32.0, 32.0, 40.0, 4.0)
    px, py = forward_differences(gx, gy)
    good = poisson_solve(px, py)
    good -= np.median(good[outside])
    assert abs(good.max() - z.max()) <= 0.01 * z.max()
    sloppy = poisson_solve(2 * px, 2 * py)      # what central differences without /2 amount to
    sloppy -= np.median(sloppy[outside])
    assert sloppy.max() > 1.5 * z.max()


def test_lines_and_shapes():
    g = np.ones((1, 5))
    np.testing.assert_allclose(integrate(g, np.zeros((1, 5))), [[-2, -1, 0, 1, 2]])
    np.testing.assert_allclose(integrate(np.zeros((4, 1)), np.full((4, 1), 2.0), spacing=0.5),
                               [[-1.5], [-0.5], [0.5], [1.5]])
    assert integrate(np.zeros((0, 3)), np.zeros((0, 3))).shape == (0, 3)
    with pytest.raises(ValueError):
        integrate(np.zeros((3, 4)), np.zeros((4, 3)))
    with pytest.raises(ValueError):
        integrate(np.zeros((3, 4)), np.zeros((3, 4)), zero=np.zeros((2, 2), bool))


@settings(max_examples=30, deadline=None)
@given(h=st.integers(2, 40), w=st.integers(2, 40), sx=st.floats(1e-5, 1e-2), sy=st.floats(1e-5, 1e-2),
       seed=st.integers(0, 1000))
def test_centre_divergence_is_the_operators_transpose(h, w, sx, sy, seed):
    """The one-pass right side equals Dx^T px + Dy^T py built from the averaged differences themselves,
    down to two-row and two-column grids (where there is no inside)."""
    rng = np.random.default_rng(seed)
    gx, gy = rng.normal(size=(h, w)), rng.normal(size=(h, w))
    want = divergence(*forward_differences(gx, gy, (sx, sy), "centre"))
    np.testing.assert_allclose(centre_divergence(gx, gy, sx, sy), want, rtol=1e-12, atol=1e-15)


def test_cached_operator_is_not_mutated_by_a_solve():
    """The eigenvalue cache is shared between calls: two solves of one size give the same answer."""
    rng = np.random.default_rng(3)
    gx, gy = rng.normal(size=(30, 40)), rng.normal(size=(30, 40))
    first = integrate(gx, gy, 1e-4, dtype=np.float32)
    second = integrate(gx, gy, 1e-4, dtype=np.float32)
    np.testing.assert_array_equal(first, second)
    np.testing.assert_allclose(integrate(gx, gy, 1e-4), first, rtol=1e-4, atol=1e-9)


def _waves(shape: tuple[int, int], wavelengths: tuple[float, ...], seed: int = 0,
           along_rows: bool = False) -> tuple[np.ndarray, ...]:
    """A sum of cosines of the given wavelengths (px) in random directions (or along the rows) and phases, and
    per pixel: the height
    at its centre, and its slopes as a camera's pixel gathers them, the mean over its footprint (the difference
    across the pixel, averaged across it)."""
    rng = np.random.default_rng(seed)
    v, u = np.mgrid[0:shape[0], 0:shape[1]].astype(np.float64)
    z, gx, gy = np.zeros(shape), np.zeros(shape), np.zeros(shape)
    for wavelength in wavelengths:
        angle, phase = (0.0 if along_rows else rng.uniform(0, np.pi)), rng.uniform(0, 2 * np.pi)
        kx, ky = 2 * np.pi / wavelength * np.cos(angle), 2 * np.pi / wavelength * np.sin(angle)
        z += np.cos(kx * u + ky * v + phase)
        # the mean over the pixel [u - 1/2, u + 1/2] x [v - 1/2, v + 1/2] of dz/du, and of dz/dv
        across_x = np.cos(kx * (u + 0.5) + ky * v + phase) - np.cos(kx * (u - 0.5) + ky * v + phase)
        across_y = np.cos(kx * u + ky * (v + 0.5) + phase) - np.cos(kx * u + ky * (v - 0.5) + phase)
        gx += across_x * np.sinc(ky / 2 / np.pi)   # np.sinc(t) = sin(pi t) / (pi t): the box's mean across
        gy += across_y * np.sinc(kx / 2 / np.pi)
    return z, gx, gy


def _gain(read: np.ndarray, true: np.ndarray) -> float:
    inner = (slice(12, -12), slice(12, -12))   # the boundary's own error left out
    a, b = read[inner] - read[inner].mean(), true[inner] - true[inner].mean()
    return float(a.ravel() @ b.ravel() / (b.ravel() @ b.ravel()))


@pytest.mark.parametrize("wavelength", [3.0, 4.0, 6.0, 20.0])
def test_footprint_slopes_integrate_to_the_height_at_every_wavelength_the_pixels_hold(wavelength):
    """A pixel's colour tells its mean slope over its area: the height's difference across it. Integrated as
    such, a relief of any wavelength down to 3 px comes back whole; integrated as the slope at the pixel's centre
    (the centre model, `height.integrate`), a relief along the pixels' rows keeps cos(pi / wavelength) of its
    depth: half at 3 px."""
    z, gx, gy = _waves((72, 96), (wavelength,) * 3)
    spacing = 1e-4
    read = footprint_integrate(gx / spacing, gy / spacing, (spacing, spacing))   # slopes dz/dx: z per metre
    assert read.dtype == np.float32
    assert _gain(read, z) == pytest.approx(1.0, abs=0.01)
    inner = (slice(12, -12), slice(12, -12))
    error = (read - read[inner].mean()) - (z - z[inner].mean())
    assert float(np.sqrt(np.mean(error[inner] ** 2))) < 0.02 * float(z[inner].std())
    z, gx, gy = _waves((72, 96), (wavelength,), along_rows=True)
    assert _gain(footprint_integrate(gx, gy, (1.0, 1.0)), z) == pytest.approx(1.0, abs=0.01)
    assert _gain(integrate(gx, gy, 1.0), z) == pytest.approx(np.cos(np.pi / wavelength), abs=0.01)


def test_footprint_integration_treats_non_finite_slopes_as_flat_and_needs_two_by_two():
    z, gx, gy = _waves((40, 50), (8.0, 11.0))
    gx[5, 7], gy[20, 30] = np.nan, np.inf
    read = footprint_integrate(gx, gy, (1.0, 1.0))
    assert np.isfinite(read).all() and abs(float(read.mean())) < 1e-5
    with pytest.raises(ValueError, match="2 x 2"):
        footprint_integrate(np.zeros((1, 5)), np.zeros((1, 5)), (1.0, 1.0))


@pytest.mark.parametrize("wavelength", [3.0, 5.0, 40.0])
def test_a_columns_own_height_reads_a_relief_along_the_rows_as_the_band_solver_does(wavelength):
    """The slow variation along the axis comes from each column's own slopes (`axis_sigma`): where a relief varies
    only along the rows (a groove along the roller's axis), that is all the frame gives, and it must read the
    relief whole, as the 2-D solver does, or the groove is read shallow."""
    # whole periods down the columns (120 rows), varying along the rows alone: the column's ends at one height,
    # as the band's undeformed rows are
    z, gx, gy = _waves((30, 120), (wavelength,), along_rows=True)
    z, gx, gy = z.T.copy(), gy.T.copy(), gx.T.copy()
    column = column_heights(gy, 1.0)
    assert _gain(column, z) == pytest.approx(1.0, abs=0.01)   # summed as a trapezoid: cos(pi / wavelength)
    solved = footprint_integrate(gx, gy, (1.0, 1.0))
    inner = slice(12, -12)
    assert np.allclose(column[inner] - column[inner].mean(), solved[inner] - solved[inner].mean(), atol=0.02)
    # a slope common to the whole column (the closure) is no height
    assert np.abs(column_heights(np.full((50, 4), 0.3), 1.0)).max() < 1e-5
    # the centre reading sums the slopes: the earlier behaviour, kept
    assert np.allclose(column_heights(gy, 2.0, "centre"), 2.0 * np.cumsum(gy - gy.mean(axis=0), axis=0), atol=1e-5)


@settings(max_examples=40, deadline=None)
@given(h=st.integers(2, 40), w=st.integers(2, 40), seed=st.integers(0, 2**32 - 1),
       spoil=st.sampled_from([None, np.nan, np.inf, -np.inf]))
def test_footprint_integration_gives_back_any_height_from_its_own_slopes_and_never_a_non_finite_one(h, w, seed, spoil):
    """Any height on any grid of at least 2 x 2: its footprint slopes (the solver's own model, applied in the
    transform domain) integrate back to it, less its mean; a non-finite slope anywhere still gives a finite
    height of the grid's shape."""
    import scipy.fft


    rng = np.random.default_rng(seed)
    z = rng.normal(0.0, 1.0, (h, w))
    ox, oy = _footprint_operator(h, w)
    denominator = np.where(ox**2 + oy**2 > 0, ox**2 + oy**2, 1.0)
    hx, hy = ox / denominator, oy / denominator          # the model's operators back from their pseudo-inverse
    c = scipy.fft.dctn(z, type=2, norm="ortho")
    sx, sy = np.zeros((h, w)), np.zeros((h, w))
    sx[:, :-1] = (hx * c)[:, 1:]                         # DST-II's k - 1 is the cosine's k
    sy[:-1, :] = (hy * c)[1:, :]
    gx = scipy.fft.idst(scipy.fft.idct(sx, type=2, norm="ortho", axis=0), type=2, norm="ortho", axis=1)
    gy = scipy.fft.idst(scipy.fft.idct(sy, type=2, norm="ortho", axis=1), type=2, norm="ortho", axis=0)
    read = footprint_integrate(gx, gy, (1.0, 1.0))
    assert read.shape == (h, w) and read.dtype == np.float32
    np.testing.assert_allclose(read, z - z.mean(), atol=1e-4 * max(1.0, float(np.abs(z).max())))   # float32
    if spoil is not None:
        gx[rng.integers(h), rng.integers(w)] = spoil
        gy[rng.integers(h), rng.integers(w)] = spoil
        assert np.isfinite(footprint_integrate(gx, gy, (1.0, 1.0))).all()
