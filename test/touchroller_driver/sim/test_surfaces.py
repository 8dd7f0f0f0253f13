"""Surfaces: procedural fabrics, shipped texture images, the grid convention."""
import numpy as np
import pytest

from touchroller_driver.sim.surfaces import FABRIC_PATTERNS, fabric, make_surface, texture_path

SPEC = {"width": 0.01, "length": 0.012, "resolution": 5e-5, "relief": 3e-4}


@pytest.mark.parametrize("pattern", FABRIC_PATTERNS)
def test_fabrics_span_their_relief_and_are_not_periodic(pattern):
    surface = make_surface({"kind": "fabric", "pattern": pattern, **SPEC}, np.random.default_rng(0))
    h = surface.height
    assert h.shape == (240, 200) and h.dtype == np.float32
    assert h.min() == pytest.approx(0.0, abs=1e-9) and h.max() == pytest.approx(3e-4, rel=1e-5)
    # yarn texture: strong variation at the yarn pitch ...
    assert h.std() > 0.1 * 3e-4
    # ... but not a perfect lattice: shifting by one (or two) yarn periods does not reproduce it
    period = round(8e-4 / 5e-5) * (2 if pattern != "knit" else 1)
    assert np.abs(h[period:] - h[:-period]).mean() > 0.05 * h.std()


def test_fabrics_depend_on_the_seed():
    a = fabric("plain_weave", 100, 100, 5e-5, 8e-4, np.random.default_rng(1))
    b = fabric("plain_weave", 100, 100, 5e-5, 8e-4, np.random.default_rng(1))
    c = fabric("plain_weave", 100, 100, 5e-5, 8e-4, np.random.default_rng(2))
    assert np.array_equal(a, b) and not np.array_equal(a, c)


@pytest.mark.parametrize("name", ["brick.png", "grass.png", "gravel.png"])
def test_shipped_textures_load_as_relief(name):
    assert texture_path(name).is_file()
    surface = make_surface({"kind": "image", "image": name, **SPEC}, np.random.default_rng(0))
    assert surface.height.max() == pytest.approx(3e-4, rel=1e-5) and surface.height.std() > 1e-5


def test_sampling_follows_the_grid_and_is_flat_outside():
    surface = make_surface({"kind": "stripes", "period": 1e-3, "ridge_width": 2e-4, **SPEC},
                           np.random.default_rng(0))
    assert surface.x0 == pytest.approx(-0.005) and surface.y0 == 0.0
    X = np.array([0.0, 0.0, 0.0, 0.02])
    Y = np.array([0.5 * 5e-5, 5e-4 + 0.5 * 5e-5, 1.0e-3 + 0.5 * 5e-5, 0.001])
    np.testing.assert_allclose(surface.sample(X, Y), [3e-4, 0.0, 3e-4, 0.0], atol=1e-12)
    big = surface.sample(np.zeros(70_000), np.full(70_000, 2.5e-5))    # more points than cv2.remap's limit
    assert big.shape == (70_000,) and np.allclose(big, 3e-4)


def test_lowpass_smooths_and_keeps_mean():
    surface = make_surface({"kind": "fabric", **SPEC}, np.random.default_rng(0))
    smooth = surface.lowpassed(2e-4)
    assert smooth.height.std() < surface.height.std()
    assert smooth.height.mean() == pytest.approx(surface.height.mean(), rel=0.02)
    assert surface.lowpassed(0.0) is surface


@pytest.mark.parametrize("spec, message", [
    ({"kind": "velvet"}, "surface.kind"),
    ({"kind": "fabric", "pattern": "lace"}, "surface.pattern"),
    ({"kind": "flat", "width": -1.0}, "must be > 0"),
    ({"kind": "image", "image": "no_such_texture.png"}, "no texture"),
])
def test_bad_surfaces_are_clear_errors(spec, message):
    with pytest.raises(ValueError, match=message):
        make_surface(spec, np.random.default_rng(0))
