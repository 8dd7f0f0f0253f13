"""The camera model of docs/design.md: projection, back-projection and the hard cases."""
from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import assume, given, settings
from hypothesis import strategies as st

from touchroller_perception.geometry import PARAMETER_RANGES, CameraModel

thetas = st.floats(-math.radians(60), math.radians(60))
offsets = st.floats(-0.9, 0.9)          # d as a fraction of r
small_k = st.floats(-0.3, 0.3)
tangential = st.floats(-0.005, 0.005)


def model_of(theta: float, d_frac: float, dist=(0.0,) * 5, **kw) -> CameraModel:
    return CameraModel(theta=theta, d=d_frac * 0.05, distortion=dist, **kw)


def image_grid(model: CameraModel, n: int = 25) -> np.ndarray:
    u, v = np.meshgrid(np.linspace(0, model.width - 1, n), np.linspace(0, model.height - 1, n))
    return np.stack([u, v], axis=-1).reshape(-1, 2)


def test_equation_bigeq_by_hand():
    """Eq. bigeq: lambda u = X fx - Y u0 sin(t) + Z u0 cos(t) + u0 d, etc. (no distortion)."""
    m = CameraModel(fx=480.0, fy=470.0, cx=300.0, cy=250.0, theta=0.2, d=0.01)
    X, Y, Z = 0.013, -0.02, math.sqrt(0.05**2 - 0.02**2)
    s, c = math.sin(0.2), math.cos(0.2)
    lam = -Y * s + Z * c + 0.01
    u = (X * 480.0 - Y * 300.0 * s + Z * 300.0 * c + 300.0 * 0.01) / lam
    v = (Y * (470.0 * c - 250.0 * s) + Z * (470.0 * s + 250.0 * c) + 250.0 * 0.01) / lam
    uv, valid = m.project([X, Y, Z])
    assert valid
    np.testing.assert_allclose(uv, [u, v], rtol=0, atol=1e-9)


def test_centre_pixel_sees_the_bottom_of_the_roller():
    m = CameraModel()
    p, valid = m.back_project([m.cx, m.cy])
    assert valid
    np.testing.assert_allclose(p, [0.0, 0.0, m.radius], atol=1e-15)


def test_theta_turns_the_view_around_the_axis():
    """With d = 0 the pinhole is on the axis: the principal ray meets the membrane at alpha = -theta."""
    m = CameraModel(theta=0.3)
    p, _ = m.back_project([m.cx, m.cy])
    x, alpha = m.surface_coords(p)
    assert x == pytest.approx(0.0, abs=1e-15)
    assert alpha == pytest.approx(-0.3, abs=1e-12)


def test_agrees_with_opencv_projectpoints():
    cv2 = pytest.importorskip("cv2")
    dist = (-0.25, 0.08, 0.001, -0.0015, -0.01)
    m = CameraModel(theta=0.25, d=0.012, distortion=dist)
    pts = m.surface_point(np.linspace(-0.03, 0.03, 7), np.linspace(-0.4, 0.2, 7))
    rvec, _ = cv2.Rodrigues(m.R)
    expected, _ = cv2.projectPoints(pts, rvec, m.t, m.K, np.array(dist))
    uv, valid = m.project(pts)
    assert valid.all()
    np.testing.assert_allclose(uv, expected.reshape(-1, 2), atol=1e-7)


@settings(max_examples=60, deadline=None)
@given(theta=thetas, d_frac=offsets, k1=small_k, k2=st.floats(-0.1, 0.1), p1=tangential, p2=tangential)
def test_back_project_then_project_is_identity(theta, d_frac, k1, k2, p1, p2):
    m = model_of(theta, d_frac, (k1, k2, p1, p2, 0.0))
    uv = image_grid(m)
    points, valid = m.back_project(uv)
    assume(valid.any())
    # lands on the membrane
    radius = np.hypot(points[valid, 1], points[valid, 2])
    np.testing.assert_allclose(radius, m.radius, rtol=0, atol=1e-12)
    uv2, valid2 = m.project(points[valid])
    assert valid2.all()
    np.testing.assert_allclose(uv2, uv[valid], rtol=0, atol=1e-7)
    # and the other way round, in metres
    points2, valid3 = m.back_project(uv2)
    assert valid3.all()
    assert np.max(np.linalg.norm(points2 - points[valid], axis=-1)) < 1e-9


@settings(max_examples=60, deadline=None)
@given(theta=thetas, d_frac=offsets, x=st.floats(-0.05, 0.05), alpha=st.floats(-math.pi, math.pi))
def test_project_then_back_project_is_identity_where_valid(theta, d_frac, x, alpha):
    m = model_of(theta, d_frac)
    point = m.surface_point(x, alpha)
    uv, valid = m.project(point)
    if not valid:
        assert np.isnan(uv).all()       # invalid is NaN, never a wrong finite pixel
        return
    back, valid_back = m.back_project(uv)
    assert valid_back
    assert np.linalg.norm(back - point) < 1e-9


@settings(max_examples=40, deadline=None)
@given(theta=thetas, d_frac=st.floats(-0.89, 0.89), u=st.floats(0, 639), v=st.floats(0, 479))
def test_back_project_is_continuous_in_theta_and_d(theta, d_frac, u, v):
    m = model_of(theta, d_frac)
    p0, ok0 = m.back_project([u, v])
    assume(ok0)
    for change in ({"theta": theta + 1e-7}, {"d": m.d + 1e-9}):
        p1, ok1 = m.replace(**change).back_project([u, v])
        assume(ok1)
        assert np.linalg.norm(p1 - p0) < 1e-6


def test_grazing_rays_beyond_the_tube_ends_are_invalid():
    m = CameraModel(fx=150.0, fy=150.0)            # wide lens: the image corners look out of the tube's ends
    uv = np.array([[0.0, 240.0], [639.0, 240.0], [319.5, 239.5]])
    points, valid = m.back_project(uv)
    assert valid.tolist() == [False, False, True]
    assert np.isnan(points[:2]).all()


def test_strong_distortion_past_the_fold_is_invalid_not_wrong():
    m = CameraModel(distortion=(-0.9, 0.0, 0.0, 0.0, 0.0))    # folds at r^2 = 1/2.7
    assert m.max_undistorted_radius2 == pytest.approx(1 / 2.7)
    corners = np.array([[0.0, 0.0], [639.0, 479.0]])
    points, valid = m.back_project(corners)
    assert not valid.any() and np.isnan(points).all()
    far = m.surface_point(0.049, 1.2)                           # past the fold when projected
    uv, ok = m.project(far)
    assert not ok and np.isnan(uv).all()


@pytest.mark.parametrize("bad", [np.nan, np.inf, -np.inf])
def test_non_finite_pixels_are_invalid(bad):
    m = CameraModel(distortion=(-0.2, 0.05, 0.0, 0.0, 0.0))
    points, valid = m.back_project([[bad, 100.0], [100.0, 100.0]])
    assert valid.tolist() == [False, True]
    assert np.isnan(points[0]).all() and np.isfinite(points[1]).all()


def test_points_behind_the_camera_are_invalid():
    m = CameraModel()
    uv, valid = m.project([[0.0, 0.0, -0.05], [0.0, 0.0, 0.05]])
    assert valid.tolist() == [False, True]


def test_float32_input_is_computed_in_float64():
    m = CameraModel(theta=0.1, d=0.01)
    uv = np.array([[100.25, 200.75]], dtype=np.float32)
    p32, _ = m.back_project(uv)
    p64, _ = m.back_project(uv.astype(np.float64))
    assert p32.dtype == np.float64
    np.testing.assert_array_equal(p32, p64)


@pytest.mark.parametrize("kwargs, message", [
    ({"d": 0.05}, "outside the tube"),
    ({"fx": 0.0}, "camera.fx = 0 px is outside its range"),
    ({"distortion": (0.1, 0.2)}, "5 coefficients"),
    ({"theta": float("nan")}, "finite"),
])
def test_invalid_models_are_refused_with_a_reason(kwargs, message):
    with pytest.raises(ValueError, match=message):
        CameraModel(**kwargs)


def test_params_and_yaml_round_trip(tmp_path):
    m = CameraModel(fx=510.0, theta=-0.05, d=0.003, distortion=(0.1, -0.02, 0.001, 0.0, 0.003))
    assert CameraModel.from_params(m.to_params()) == m
    path = tmp_path / "cal.yaml"
    m.to_yaml(path)
    text = path.read_text()
    assert text.startswith("/**:\n  ros__parameters:")
    assert CameraModel.from_yaml(path) == m


def test_yaml_accepts_nested_names_and_named_nodes(tmp_path):
    path = tmp_path / "cal.yaml"
    path.write_text("perception:\n  ros__parameters:\n    camera: {fx: 600.0}\n    extrinsics: {theta: 0.1}\n")
    m = CameraModel.from_yaml(path)
    assert (m.fx, m.theta, m.fy) == (600.0, 0.1, 500.0)


def test_covariance_grows_with_pixel_noise_and_calibration_error():
    m = CameraModel(theta=0.1, d=0.005)
    uv = np.array([[320.0, 240.0], [100.0, 400.0]])
    c1 = m.contact_covariance(uv, pixel_sigma=0.5)
    c2 = m.contact_covariance(uv, pixel_sigma=1.0)
    np.testing.assert_allclose(c2, 4 * c1, rtol=1e-6)
    c3 = m.contact_covariance(uv, pixel_sigma=0.5, calibration_sigma={"theta": math.radians(1.0)})
    assert np.all(np.trace(c3, axis1=-2, axis2=-1) > np.trace(c1, axis1=-2, axis2=-1))
    # one degree of theta moves the centre contact by about r * 1deg = 0.87 mm around the axis
    spread = math.sqrt(np.trace(c3[0] - c1[0]))
    assert spread == pytest.approx(0.05 * math.radians(1.0), rel=0.05)


def test_covariance_matches_monte_carlo():
    m = CameraModel(theta=0.2, d=0.01, distortion=(-0.1, 0.02, 0.0, 0.0, 0.0))
    uv = np.array([250.0, 300.0])
    rng = np.random.default_rng(0)
    samples, _ = m.back_project(uv + rng.normal(0.0, 0.3, size=(20000, 2)))
    empirical = np.cov(samples.T)
    predicted = m.contact_covariance(uv, pixel_sigma=0.3)
    # sampling error of a covariance element is ~ sqrt(var_i var_j / N): 4 of those is the tolerance
    scale = np.sqrt(np.outer(np.diag(empirical), np.diag(empirical)) / len(samples))
    assert np.all(np.abs(predicted - empirical) <= 0.02 * np.abs(empirical) + 4 * scale)


def test_unknown_calibration_parameter_is_refused():
    with pytest.raises(ValueError, match="unknown calibration parameter"):
        CameraModel().contact_covariance([[1.0, 2.0]], calibration_sigma={"phi": 1.0})


@pytest.mark.parametrize("dist, fold", [
    ((0.0, 5e-324, 0.0, 0.0, 0.0), math.inf),          # denormal coefficient found by hypothesis
    ((-0.9, 0.0, 0.0, 0.0, 0.0), 1 / 2.7),
    ((0.0, -0.2, 0.0, 0.0, 0.0), 1.0),                 # 1 - 1.0 s^2 = 0
    ((0.1, 0.01, 0.0, 0.0, 0.0), math.inf),
])
def test_distortion_fold_radius(dist, fold):
    assert CameraModel(distortion=dist).max_undistorted_radius2 == pytest.approx(fold)


@pytest.mark.parametrize("name", sorted(PARAMETER_RANGES))
def test_each_parameter_is_held_to_the_range_the_nodes_declare(name):
    """A params file read without ROS (`touchroller contacts --params`) meets the nodes' ranges: theta = 10
    (degrees meant, radians read) put every contact on the other side of the cylinder."""
    lo, hi, unit = PARAMETER_RANGES[name]
    CameraModel.from_params({name: lo if name != "extrinsics.d" else -0.01})   # in range: taken
    beyond = hi * 2 + 1
    with pytest.raises(ValueError, match=rf"{name} = .* {unit} is outside its range \[{lo:g}, {hi:g}\]"):
        CameraModel.from_params({name: int(beyond) if isinstance(lo, int) else beyond})


def test_theta_in_degrees_from_a_params_file_is_refused(tmp_path):
    path = tmp_path / "cal.yaml"
    path.write_text("/**:\n  ros__parameters:\n    extrinsics.theta: 10\n")
    with pytest.raises(ValueError, match=r"extrinsics.theta = 10 rad is outside its range \[-1.5, 1.5\] rad"):
        CameraModel.from_yaml(path)


@pytest.mark.parametrize("content", [b"a: [\n", b"\x00\xff\xfe binary", b"key: value\n\tbad: tab\n"])
def test_a_file_that_is_not_yaml_is_one_line(tmp_path, content):
    path = tmp_path / "cal.yaml"
    path.write_bytes(content)
    with pytest.raises(ValueError, match="not a YAML parameters file") as raised:
        CameraModel.from_yaml(path)
    assert "\n" not in str(raised.value)


def test_a_params_file_is_replaced_whole_or_not_at_all(tmp_path):
    """A write that fails half-way (here a value YAML cannot represent, as a full disk would) left a
    truncated calibration file."""
    path = tmp_path / "cal.yaml"
    CameraModel(theta=0.1).to_yaml(path)
    before = path.read_text()
    with pytest.raises(Exception, match="cannot represent"):
        CameraModel(theta=0.2).to_yaml(path, extra={"calibration.note": object()})
    assert path.read_text() == before and [p.name for p in tmp_path.iterdir()] == ["cal.yaml"]


@pytest.mark.parametrize(("text", "message"), [
    (":::\n", "no camera-model parameters"),
    ("other.key: 1\n", "no camera-model parameters"),
    ("camera.fx: 400.0\nextrinsics.thetta: 0.01\n", "unknown camera-model parameter extrinsics.thetta "
                                                     r"\(did you mean extrinsics.theta\?\)"),
    ("/**:\n  ros__parameters:\n    camera.fx: 400.0\n    camera.fxx: 410.0\n", "did you mean camera.fx"),
    ("camera.fx: 400.0\ncylinder.diameter: 0.1\n", "unknown camera-model parameter cylinder.diameter"),
])
def test_a_params_file_that_does_not_name_the_model_rightly_is_refused(tmp_path, text, message):
    path = tmp_path / "p.yaml"
    path.write_text(text)
    with pytest.raises(ValueError, match=message):
        CameraModel.from_yaml(path)


def test_a_params_file_with_driver_settings_and_extras_beside_the_model_is_read(tmp_path):
    path = tmp_path / "p.yaml"
    path.write_text("camera.fx: 400.0\ncamera.latency: 0.03\ncalibration.sigma.theta: 0.001\nmap.metric: 0.1\n")
    assert CameraModel.from_yaml(path).fx == 400.0
