"""The Poisson integrator: exact gradients give the exact surface (sphere caps, cosines), zero gives zero,
non-finite slopes are bridged, and the two classic slips (central differences without /2, eigenvalue
indices off by one) would fail these tests."""
from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from touchroller_perception.height import divergence, forward_differences, integrate, poisson_solve
from touchroller_perception.height.integrate import centre_divergence


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
