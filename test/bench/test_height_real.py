"""The height bench's own measurement code: the sphere fit finds a known sphere, the rim depth and the
geometric cap agree on an exact cap, the no-contact window keeps away from the press."""
from __future__ import annotations

import math

import numpy as np

from bench import height_real as hr


def _cap(h=200, w=240, cu=118.3, cv=97.6, radius=2.0e-3, contact_px=55.0, pixel=2.95e-5):
    vv, uu = np.mgrid[0:h, 0:w]
    rho2 = ((uu - cu) ** 2 + (vv - cv) ** 2) * pixel**2
    base = math.sqrt(radius**2 - (contact_px * pixel) ** 2)
    return np.where(rho2 < (contact_px * pixel) ** 2, np.sqrt(np.maximum(radius**2 - rho2, 0)) - base, 0.0)


def test_sphere_fit_finds_a_known_sphere():
    z = _cap()
    rms, radius, (x0, y0, _) = hr.sphere_fit(z, 115.0, 100.0, 55.0, 2.95e-5)     # started off-centre
    assert rms < 1e-7 and abs(radius - 2.0e-3) < 1e-6 and abs(x0 - 118.3) < 0.05 and abs(y0 - 97.6) < 0.05
    rms_fixed, radius_fixed, _ = hr.sphere_fit(z * 1.2, 118.3, 97.6, 55.0, 2.95e-5, fixed_radius=2.0e-3)
    assert radius_fixed == 2.0e-3 and rms_fixed > 1e-6                          # a too-deep cap does not fit R


def test_rim_depth_matches_the_geometric_cap():
    z = _cap()
    assert abs(hr.rim_depth(z, 118.3, 97.6, 55.0) / hr.geometric_cap(55.0, 2.95e-5) - 1) < 0.03


def test_flat_window_is_beyond_three_radii():
    window = hr.flat_window((480, 640), 500.0, 100.0, 40.0)
    assert window is not None
    rows, cols = window
    corners = [(u, v) for u in (cols.start, cols.stop - 1) for v in (rows.start, rows.stop - 1)]
    nearest = min(math.hypot(max(cols.start - 500, 0, 500 - cols.stop), max(rows.start - 100, 0, 100 - rows.stop))
                  for _ in corners)
    assert nearest >= 120.0
    assert hr.flat_window((200, 200), 100.0, 100.0, 60.0) is None


def test_a_further_window_and_the_no_contact_views():
    near, far = hr.flat_window((480, 640), 320.0, 100.0, 40.0), hr.flat_window((480, 640), 320.0, 100.0, 40.0,
                                                                              factor=4.5)
    assert near is not None and far is not None and far[0].start >= 100 + 4.5 * 40 > near[0].start

    def measure(flat, far_flat, drift):
        return hr.PressMeasure(0, 1.0, 1.0, 1.0, 2.0, 1.0, 1.0, 1.0, flat, (0, 0, 1), (0, 0, 1), far_flat, drift)

    views = hr.no_contact_views([measure(10.0, 3.0, 0.05), measure(2.0, math.nan, 0.0), measure(4.0, 1.0, 0.01)])
    assert views["beyond 3 radii"] == (4.0, 3) and views["beyond 4.5 radii"] == (2.0, 2)
    assert views["frames drifted > 2%"] == (10.0, 1) and views["frames drifted <= 2%"] == (3.0, 2)
