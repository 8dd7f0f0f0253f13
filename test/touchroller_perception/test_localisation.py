"""Localisation of detected contacts on the cylinder."""
from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from touchroller_perception.contacts import Contact
from touchroller_perception.geometry import CameraModel
from touchroller_perception.localisation import SurfaceLookup, localise

#: A 640x480 webcam behind a wide-angle lens (barrel distortion), as the Table II scene uses.
WIDE_CAMERA = CameraModel(fx=400.0, fy=400.0, distortion=(-0.2, 0.0, 0.0, 0.0, 0.0))

# Half-size camera keeps the rendered Table II fast in tests.
SMALL_CAMERA = CameraModel(fx=200.0, fy=200.0, cx=159.5, cy=119.5, distortion=(-0.2, 0, 0, 0, 0),
                           width=320, height=240, theta=0.02, d=0.002)


def _contact(u, v):
    return Contact(u=float(u), v=float(v), area=100.0, confidence=1.0, score=20.0)


def test_localise_inverts_the_projection_and_gives_a_covariance():
    camera = WIDE_CAMERA.replace(theta=0.05, d=0.003)
    truth = camera.surface_point(np.array([-0.02, 0.0, 0.03]), np.array([0.3, -0.1, 0.0]))
    uv, ok = camera.project(truth)
    assert ok.all()
    located = localise(camera, [_contact(u, v) for u, v in uv], pixel_sigma=0.5)
    for loc, point in zip(located, truth, strict=True):
        assert loc.valid
        np.testing.assert_allclose(loc.point, point, atol=1e-9)
        eig = np.linalg.eigvalsh(loc.covariance)
        assert eig.min() > -1e-15 and 0 < eig.max() < (1e-3) ** 2   # sub-mm for half a pixel
    # a pixel far outside the image maps nowhere: NaN and invalid, never a wrong point
    [outside] = localise(camera, [_contact(1e6, 1e6)])
    assert not outside.valid and np.isnan(outside.point).all()
    assert localise(camera, []) == []


def test_surface_lookup_matches_the_exact_back_projection():

    camera = SMALL_CAMERA
    lookup = SurfaceLookup(camera)
    rng = np.random.default_rng(0)
    uv = rng.uniform([0, 0], [camera.width - 1, camera.height - 1], size=(500, 2))
    uv = np.vstack([uv, [[-3.0, 5.0], [camera.width - 0.7, 10.0], [np.nan, 1.0], [1e6, 1e6]]])
    exact, exact_ok = camera.back_project(uv)
    fast, fast_ok = lookup.back_project(uv)
    np.testing.assert_array_equal(fast_ok, exact_ok)
    # this half-size wide-angle camera is the hard case (4x the curvature per pixel): 50 um at the corners
    assert np.nanmax(np.linalg.norm(fast - exact, axis=1)) < 5e-5
    np.testing.assert_allclose(np.hypot(fast[fast_ok, 1], fast[fast_ok, 2]), camera.radius)
    contacts = [_contact(u, v) for u, v in uv[:3]]
    via_lookup = localise(camera, contacts, covariance=False, lookup=lookup)
    assert all(np.isnan(c.covariance).all() for c in via_lookup)
    with pytest.raises(ValueError, match="another camera"):
        localise(camera.replace(theta=0.1), contacts, lookup=lookup)
    # a 640x480 wide-angle camera: sub-micrometre typically, tens of um only in the extreme corners
    sensor = WIDE_CAMERA.replace(theta=0.03, d=0.0015)
    uv = rng.uniform([0, 0], [sensor.width - 1, sensor.height - 1], size=(500, 2))
    fast, _ = SurfaceLookup(sensor).back_project(uv)
    error = np.linalg.norm(fast - sensor.back_project(uv)[0], axis=1)
    assert np.nanmedian(error) < 1e-7 and np.nanmax(error) < 3e-5


@settings(max_examples=8, deadline=None)
@given(theta=st.floats(-0.3, 0.3), d=st.floats(-0.01, 0.01), k1=st.floats(-0.25, 0.1),
       focal=st.floats(150.0, 400.0), seed=st.integers(0, 10))
def test_property_surface_lookup_stays_far_below_the_error_budget(theta, d, k1, focal, seed):

    camera = CameraModel(fx=focal, fy=focal, cx=159.5, cy=119.5, width=320, height=240, theta=theta, d=d,
                         distortion=(k1, 0.0, 0.0, 0.0, 0.0))
    uv = np.random.default_rng(seed).uniform([0, 0], [319, 239], size=(200, 2))
    exact, exact_ok = camera.back_project(uv)
    fast, fast_ok = SurfaceLookup(camera).back_project(uv)
    # pixels without four valid neighbours fall back to the exact model, so validity always agrees
    np.testing.assert_array_equal(fast_ok, exact_ok)
    if exact_ok.any():
        assert np.max(np.linalg.norm(fast[exact_ok] - exact[exact_ok], axis=1)) < 1e-4   # 0.1 mm; goal 0.25
