"""Calibration library: intrinsics, theta/d from the hemisphere frame, and degenerate input."""
from __future__ import annotations

import dataclasses
import math

import cv2
import numpy as np
import pytest
import yaml
from hypothesis import given, settings
from hypothesis import strategies as st

from touchroller_perception import calibration as cal
from touchroller_perception.calibration.imprints import _order_grid
from touchroller_perception.geometry import CameraModel

TRUE_CAMERA = CameraModel(fx=512.0, fy=508.0, cx=322.0, cy=236.0,
                          distortion=(-0.08, 0.03, 0.0005, -0.0004, 0.0), theta=math.radians(2.0), d=0.0012)
BOARD = cal.Chessboard(columns=6, rows=6, square=0.01)
INTRINSICS = cal.IntrinsicsConfig(board=BOARD)
FRAME = cal.HemisphereFrame()


# --------------------------------------------------------------------------- synthetic renderings
_RAYS: dict[CameraModel, np.ndarray] = {}


def _rays(camera: CameraModel, supersample: int = 2) -> np.ndarray:
    """Undistorted normalised rays (H*s, W*s, 3) of sub-pixel samples, cached per camera."""
    if camera not in _RAYS:
        s = supersample
        offsets = (np.arange(s) + 0.5) / s - 0.5
        us = (np.arange(camera.width)[:, None] + offsets[None, :]).ravel()
        vs = (np.arange(camera.height)[:, None] + offsets[None, :]).ravel()
        uu, vv = np.meshgrid(us, vs)
        xn, yn, _ = camera.undistort_normalised(np.stack([uu, vv], axis=-1))
        _RAYS[camera] = np.stack([xn, yn, np.ones_like(xn)], axis=-1)
    return _RAYS[camera]


def render_chessboard(camera: CameraModel, board: cal.Chessboard, rvec, tvec, supersample: int = 2) -> np.ndarray:
    """The board (with one white square of margin) seen through `camera`, pose board->camera."""
    rays = _rays(camera, supersample)
    rotation = cv2.Rodrigues(np.asarray(rvec, dtype=np.float64))[0]
    t = np.asarray(tvec, dtype=np.float64)
    normal = rotation[:, 2]
    with np.errstate(invalid="ignore", divide="ignore"):
        s = (normal @ t) / (rays @ normal)
        local = (s[..., None] * rays - t) @ rotation
    bx, by = local[..., 0] / board.square, local[..., 1] / board.square
    inside = (bx >= -1) & (bx < board.columns) & (by >= -1) & (by < board.rows) & (s > 0)
    dark = ((np.floor(bx) + np.floor(by)) % 2 == 0) & inside
    value = np.where(dark, 30.0, 220.0)
    value[~np.isfinite(s)] = 220.0
    h, w = camera.height, camera.width
    image = value.reshape(h, supersample, w, supersample).mean(axis=(1, 3))
    return np.clip(image, 0, 255).astype(np.uint8)


def chessboard_views(camera: CameraModel, count: int, seed: int = 0, tilt_deg: float = 30.0) -> list[np.ndarray]:
    rng = np.random.default_rng(seed)
    images = []
    for _ in range(count):
        angles = np.radians(rng.uniform(-tilt_deg, tilt_deg, 3) * np.array([1, 1, 0.5]))
        rvec = cv2.Rodrigues(cv2.Rodrigues(angles)[0])[0].ravel()
        rotation = cv2.Rodrigues(rvec)[0]
        centre = np.array([(BOARD.columns - 1) / 2, (BOARD.rows - 1) / 2, 0]) * BOARD.square
        target = np.array([rng.uniform(-0.04, 0.04), rng.uniform(-0.03, 0.03), rng.uniform(0.12, 0.16)])
        images.append(render_chessboard(camera, BOARD, rvec, target - rotation @ centre))
    return images


def render_hemispheres(camera: CameraModel, frame: cal.HemisphereFrame, *, seed: int = 0, noise: float = 1.5,
                       shift_px: tuple[float, float] = (0.0, 0.0), points: np.ndarray | None = None,
                       smear_px: float = 0.0, strength: np.ndarray | None = None) -> np.ndarray:
    """A gel background with shaded imprints (lit on one side, dark on the other, per colour) at the
    projections of the frame's imprint centres. `strength`: each imprint's press depth relative to
    the nominal; a sphere's imprint grows with it in width (its contact radius, as the square root)
    and in slope (the same), so both scale."""
    rng = np.random.default_rng(seed)
    h, w = camera.height, camera.width
    vv, uu = np.mgrid[0:h, 0:w].astype(np.float64)
    base = 120.0 + 20.0 * np.exp(-((uu - w / 2) ** 2 + (vv - h / 2) ** 2) / (2 * 300.0**2))
    image = np.repeat(base[..., None], 3, axis=2)
    pts = frame.reference_points(camera.radius) if points is None else points
    uv, _ = camera.project(pts)
    sigma = 0.5 * camera.fx * 0.8 * frame.hemisphere_radius / (camera.radius + camera.d)
    lights = [(1.0, 0.0), (-0.5, 0.866), (-0.5, -0.866)]
    gains = np.ones(len(uv)) if strength is None else np.asarray(strength)
    half = int(6 * sigma) + 2
    for (cu, cv_), gain in zip(uv + np.asarray(shift_px), gains, strict=True):
        u0, v0 = max(int(cu) - half, 0), max(int(cv_) - half, 0)
        window = (slice(v0, min(int(cv_) + half, h)), slice(u0, min(int(cu) + half, w)))
        du, dv = uu[window] - cu, vv[window] - cv_
        width = sigma * math.sqrt(max(float(gain), 0.0))
        g = math.sqrt(max(float(gain), 0.0)) * np.exp(-(du**2 + dv**2) / (2 * width**2))
        for c, (lu, lv) in enumerate(lights):
            image[window + (c,)] += 60.0 * (du * lu + dv * lv) / width * g
    if smear_px > 0:
        kernel = np.ones((int(smear_px), 1), np.float32) / int(smear_px)
        image = cv2.filter2D(image, -1, kernel)
    image += rng.normal(0, noise, image.shape)
    return np.clip(image, 0, 255).astype(np.uint8)


# --------------------------------------------------------------------------- intrinsics
@pytest.fixture(scope="module")
def chessboards() -> list[np.ndarray]:
    return chessboard_views(TRUE_CAMERA, 12, seed=1)


def test_intrinsics_recover_the_camera(chessboards):
    result = cal.calibrate_intrinsics(chessboards, INTRINSICS)
    cam = result.camera
    assert result.rms < 0.2
    # the renderer's hard-edged squares bias corners by ~0.1 px; errors must match the reported sigma
    for name in ("fx", "fy", "cx", "cy"):
        assert abs(getattr(cam, name) - getattr(TRUE_CAMERA, name)) < 3 * result.sigma[name] < 3.0, name
    assert abs(cam.distortion[0] - TRUE_CAMERA.distortion[0]) < 0.02
    assert len(result.per_view_rms) == 12 and not result.rejected
    uv_true, _ = TRUE_CAMERA.replace(theta=0.0, d=0.0).project([0.02, 0.012, 0.05])
    uv_est, _ = cam.replace(theta=0.0, d=0.0).project([0.02, 0.012, 0.05])
    assert np.linalg.norm(uv_true - uv_est) < 2.0


def test_tangential_terms_are_kept_only_when_the_fit_shows_them(chessboards):
    """TRUE_CAMERA's lens has p1, p2: the fit shows them (Wald statistic above the 99 % point) and
    keeps them. A lens without them: they are left out, not fitted to the noise."""
    with_tangential = cal.calibrate_intrinsics(chessboards, INTRINSICS)
    assert with_tangential.tangential_chi2 >= INTRINSICS.tangential_chi2
    assert with_tangential.distortion_model in ("k1k2p", "full")
    plain_lens = TRUE_CAMERA.replace(distortion=(-0.08, 0.03, 0.0, 0.0, 0.0))
    without = cal.calibrate_intrinsics(chessboard_views(plain_lens, 12, seed=1), INTRINSICS)
    assert without.tangential_chi2 < INTRINSICS.tangential_chi2
    assert without.distortion_model in ("k1k2", "radial") and without.camera.distortion[2:4] == (0.0, 0.0)


def test_intrinsics_reject_a_bad_view(chessboards):
    bad = chessboard_views(TRUE_CAMERA.replace(fx=560.0, fy=560.0, distortion=(0.2, 0, 0, 0, 0)), 1, seed=7)[0]
    result = cal.calibrate_intrinsics([*chessboards[:6], bad], INTRINSICS)
    assert 6 in result.rejected and "reprojection" in result.rejected[6]
    assert abs(result.camera.fx - TRUE_CAMERA.fx) < 1.5


def test_intrinsics_single_view_is_an_error(chessboards):
    with pytest.raises(cal.CalibrationError, match="single"):
        cal.calibrate_intrinsics(chessboards[:1], INTRINSICS)


def test_intrinsics_blurred_frames_are_named(chessboards):
    blurred = [cv2.GaussianBlur(img, (0, 0), 4.0) for img in chessboards[:4]]
    with pytest.raises(cal.CalibrationError, match="blurred"):
        cal.calibrate_intrinsics(blurred, INTRINSICS)


def test_intrinsics_without_a_board_name_what_is_missing():
    empty = [np.full((480, 640), 128, np.uint8)] * 4
    with pytest.raises(cal.CalibrationError, match="no 6x6 chessboard found"):
        cal.calibrate_intrinsics(empty, INTRINSICS)


def test_intrinsics_parallel_views_cannot_fix_the_focal_length():
    images = []
    for shift in (-0.01, 0.0, 0.01):
        images.append(render_chessboard(TRUE_CAMERA, BOARD, [0.0, 0.0, 0.0], [shift - 0.025, -0.025, 0.15]))
    with pytest.raises(cal.CalibrationError, match="focal length|disagree"):
        cal.calibrate_intrinsics(images, INTRINSICS)


# --------------------------------------------------------------------------- extrinsics
def test_hemisphere_reference_points_lie_on_the_membrane():
    points = FRAME.reference_points(0.05)
    assert points.shape == (10, 3)
    assert np.allclose(np.hypot(points[:, 1], points[:, 2]), 0.05)
    assert np.all(np.diff(points[:5, 0]) > 0) and points[5, 1] > points[0, 1]


def test_imprints_found_at_subpixel_positions_despite_one_sided_shading():
    image = render_hemispheres(TRUE_CAMERA, FRAME, seed=3)
    found = cal.find_imprints(image, FRAME)
    truth, _ = TRUE_CAMERA.project(FRAME.reference_points(TRUE_CAMERA.radius))
    assert found.reason is None
    assert np.max(np.linalg.norm(found.centres - truth, axis=1)) < 0.15


def test_extrinsics_recover_theta_and_d():
    images = [render_hemispheres(TRUE_CAMERA, FRAME, seed=s) for s in range(6)]
    prior = TRUE_CAMERA.replace(theta=0.0, d=0.0)
    result = cal.calibrate_extrinsics(images, prior)
    assert abs(math.degrees(result.theta - TRUE_CAMERA.theta)) < 0.1
    assert abs(result.d - TRUE_CAMERA.d) < 0.05e-3
    assert result.rms < 0.2 and len(result.views) == 6
    assert result.camera.fx == prior.fx and result.camera.theta == result.theta
    # the truth has no neglected terms: the full pose agrees with the two-parameter one
    assert abs(result.neglected.gamma_deg) < 0.2
    assert abs(result.neglected.tx_mm) < 0.1
    assert result.neglected.model_error_centre_mm < 0.1


def test_extrinsics_report_a_neglected_yaw():
    """A camera yawed by 1.5 deg about z: the full pose reports gamma, the two-parameter fit takes it
    as the frame's yaw (the two cannot be told apart) and theta and d stay right."""
    points = FRAME.reference_points(TRUE_CAMERA.radius)
    yaw = cal.full_pose_rotation(TRUE_CAMERA.theta, 0.0, math.radians(1.5))
    # render by moving the points so that the paper's camera sees what a yawed camera would
    moved = (TRUE_CAMERA.R.T @ (yaw @ points.T)).T
    images = [render_hemispheres(TRUE_CAMERA, FRAME, seed=s, points=moved) for s in range(4)]
    result = cal.calibrate_extrinsics(images, TRUE_CAMERA.replace(theta=0.0, d=0.0))
    assert abs(result.neglected.gamma_deg - 1.5) < 0.1
    assert all(abs(math.degrees(v.yaw) + 1.5) < 0.1 for v in result.views)
    assert abs(math.degrees(result.theta - TRUE_CAMERA.theta)) < 0.1
    assert abs(result.d - TRUE_CAMERA.d) < 0.05e-3
    assert result.rms < 0.2
    # without the frame's placement among the unknowns, the paper's two parameters cannot fit
    lenient = cal.Plausibility(max_median_rms=10.0)
    plain = cal.calibrate_extrinsics(images, TRUE_CAMERA.replace(theta=0.0, d=0.0),
                                     cal.ExtrinsicsConfig(solve_placement=False, plausibility=lenient))
    assert plain.rms > 1.0
    # and by default an RMS that large is refused as more than imprint noise explains
    if plain.rms > 3.0:
        with pytest.raises(cal.CalibrationError, match="implausible result.*median reprojection RMS"):
            cal.calibrate_extrinsics(images, TRUE_CAMERA.replace(theta=0.0, d=0.0),
                                     cal.ExtrinsicsConfig(solve_placement=False))


@pytest.mark.parametrize("strength", ["auto", "relative"])
def test_row_balance_removes_the_frame_shift_along_y(strength):
    """Frames shifted along y turn the picture like theta; the deeper (nearer) row leaves the stronger
    (wider and steeper) imprint, which the row balance uses to take the shift out, measured by the
    imprints' extent (the default without a lights-off frame) or their energy."""
    images = []
    for k, shift in enumerate((-1.2e-3, -0.6e-3, 0.0, 0.4e-3, 1.0e-3, 1.4e-3)):
        layout = FRAME.layout()
        points = FRAME.reference_points(TRUE_CAMERA.radius, shift_y=shift)
        plate_z = TRUE_CAMERA.radius + FRAME.hemisphere_radius - FRAME.press_depth
        depth = FRAME.press_depth - (layout[:, 1] + shift) ** 2 / (2 * plate_z)
        images.append(render_hemispheres(TRUE_CAMERA, FRAME, seed=k, points=points, strength=depth / FRAME.press_depth))
    prior = TRUE_CAMERA.replace(theta=0.0, d=0.0)
    result = cal.calibrate_extrinsics(images, prior, cal.ExtrinsicsConfig(
        detector=cal.ImprintDetectorConfig(strength=strength)))
    plain = cal.calibrate_extrinsics(images, prior, cal.ExtrinsicsConfig(balance_rows=False))
    assert abs(math.degrees(plain.theta - TRUE_CAMERA.theta)) > 0.15      # mean shift 0.17 mm = 0.19 deg
    assert abs(math.degrees(result.theta - TRUE_CAMERA.theta)) < 0.05
    assert result.row_balance.applied and result.row_balance.slope_deg > 0


def test_extrinsics_reject_an_outlier_view():
    images = [render_hemispheres(TRUE_CAMERA, FRAME, seed=s) for s in range(5)]
    images.append(render_hemispheres(TRUE_CAMERA, FRAME, seed=9, shift_px=(0.0, 12.0)))   # frame slipped
    result = cal.calibrate_extrinsics(images, TRUE_CAMERA.replace(theta=0.0, d=0.0))
    assert 5 in result.rejected and "outlier" in result.rejected[5]
    assert abs(math.degrees(result.theta - TRUE_CAMERA.theta)) < 0.1


def test_extrinsics_single_view_is_an_error():
    with pytest.raises(cal.CalibrationError, match="single"):
        cal.calibrate_extrinsics([render_hemispheres(TRUE_CAMERA, FRAME)], TRUE_CAMERA)


def test_extrinsics_too_few_imprints_is_named():
    small = cal.HemisphereFrame(rows=2, columns=3)
    images = [render_hemispheres(TRUE_CAMERA, small, seed=s) for s in range(3)]
    with pytest.raises(cal.CalibrationError, match="too few imprints: found 6"):
        cal.calibrate_extrinsics(images, TRUE_CAMERA)


def test_extrinsics_collinear_imprints_are_named():
    line = np.stack([np.linspace(-0.02, 0.02, 10), np.zeros(10), np.full(10, 0.05)], axis=-1)
    images = [render_hemispheres(TRUE_CAMERA, FRAME, seed=s, points=line) for s in range(3)]
    with pytest.raises(cal.CalibrationError, match="collinear"):
        cal.calibrate_extrinsics(images, TRUE_CAMERA)


def test_a_one_row_frame_is_collinear():
    with pytest.raises(cal.CalibrationError, match="collinear"):
        cal.HemisphereFrame(rows=1, columns=5)


def test_extrinsics_blurred_frames_are_named():
    images = [render_hemispheres(TRUE_CAMERA, FRAME, seed=s, smear_px=25) for s in range(3)]
    with pytest.raises(cal.CalibrationError, match="blurred"):
        cal.calibrate_extrinsics(images, TRUE_CAMERA)


def test_extrinsics_with_a_no_contact_reference_frame():
    reference = render_hemispheres(TRUE_CAMERA, FRAME, points=np.empty((0, 3)), noise=0.0)
    images = [render_hemispheres(TRUE_CAMERA, FRAME, seed=s) for s in range(3)]
    result = cal.calibrate_extrinsics(images, TRUE_CAMERA.replace(theta=0.0, d=0.0), reference=reference)
    assert abs(math.degrees(result.theta - TRUE_CAMERA.theta)) < 0.1


@settings(max_examples=15, deadline=None)
@given(theta=st.floats(-5.0, 5.0), d=st.floats(-3e-3, 3e-3), gamma=st.floats(-3.0, 3.0),
       beta=st.floats(-3.0, 3.0), t=st.tuples(*[st.floats(-2e-3, 2e-3)] * 2))
def test_solve_view_recovers_exact_poses(theta, d, gamma, beta, t):
    """Noise-free correspondences: the full pose comes back exactly; with beta = gamma = t = 0 so does (theta, d)."""
    points = FRAME.reference_points(0.05)
    camera = TRUE_CAMERA.replace(theta=0.0, d=0.0)
    rotation = cal.full_pose_rotation(math.radians(theta), math.radians(beta), math.radians(gamma))
    translation = np.array([t[0], t[1], d])
    uv, _ = cv2.projectPoints(points, cv2.Rodrigues(rotation)[0], translation, camera.K, np.array(camera.distortion))
    view = cal.solve_view(camera, FRAME, uv.reshape(-1, 2))
    assert view.full_rms < 1e-3
    assert math.degrees(view.full_theta) == pytest.approx(theta, abs=1e-3)
    assert math.degrees(view.gamma) == pytest.approx(gamma, abs=1e-3)
    assert view.t[2] == pytest.approx(d, abs=1e-6)
    exact = camera.replace(theta=math.radians(theta), d=d)
    uv2, _ = exact.project(points)
    view2 = cal.solve_view(camera, FRAME, uv2)
    assert view2.rms < 1e-6
    assert math.degrees(view2.theta) == pytest.approx(theta, abs=1e-6)
    assert view2.d == pytest.approx(d, abs=1e-9)
    assert abs(view2.shift_x) < 1e-9 and abs(view2.yaw) < 1e-7


# --------------------------------------------------------------------------- outputs
def test_written_calibration_round_trips(tmp_path):
    images = [render_hemispheres(TRUE_CAMERA, FRAME, seed=s) for s in range(3)]
    result = cal.calibrate_extrinsics(images, TRUE_CAMERA.replace(theta=0.0, d=0.0))
    path = tmp_path / "cal.yaml"
    cal.write_calibration(str(path), result.camera, extrinsics=result)
    loaded = CameraModel.from_yaml(path)
    assert loaded.theta == pytest.approx(result.theta) and loaded.d == pytest.approx(result.d)
    params = yaml.safe_load(path.read_text())["/**"]["ros__parameters"]
    assert params["calibration.sigma.theta"] > 0


def test_camera_info_fields():
    info = cal.camera_info_fields(TRUE_CAMERA)
    assert info["k"][0] == TRUE_CAMERA.fx and info["k"][5] == TRUE_CAMERA.cy
    assert info["p"][2] == TRUE_CAMERA.cx and info["p"][3] == 0.0
    assert info["d"] == list(TRUE_CAMERA.distortion) and info["distortion_model"] == "plumb_bob"


def test_intrinsics_radial_model_holds_the_tangential_terms(chessboards):
    result = cal.calibrate_intrinsics(chessboards, cal.IntrinsicsConfig(board=BOARD, distortion="radial"))
    assert result.camera.distortion[2] == 0.0 and result.camera.distortion[3] == 0.0
    # the true lens has a little tangential distortion, which the radial model has to absorb
    assert abs(result.camera.fx - TRUE_CAMERA.fx) < 3 * result.sigma["fx"] + 1.0
    with pytest.raises(cal.CalibrationError, match="distortion must be auto or one of"):
        cal.IntrinsicsConfig(board=BOARD, distortion="fisheye")


@settings(max_examples=30, deadline=None)
@given(angle=st.floats(-8.0, 8.0), shift=st.tuples(st.floats(-50, 50), st.floats(-30, 30)),
       seed=st.integers(0, 10_000), scale=st.floats(0.5, 2.0))
def test_grid_order_ignores_detection_order_and_small_rotations(angle, shift, seed, scale):
    layout = FRAME.layout() / FRAME.pitch_x * 40.0 * scale          # pixels, row-major like the frame
    c, s = math.cos(math.radians(angle)), math.sin(math.radians(angle))
    pixels = layout @ np.array([[c, s], [-s, c]]) + np.array([320.0, 240.0]) + np.asarray(shift)
    permutation = np.random.default_rng(seed).permutation(len(pixels))
    order, reason = _order_grid(pixels[permutation], FRAME.rows, FRAME.columns, 0.08)
    assert reason is None
    assert np.array_equal(pixels[permutation][order], pixels)


def test_compare_cameras_measures_how_far_contacts_move():
    same = cal.compare_cameras(TRUE_CAMERA, TRUE_CAMERA)
    assert same["image_max_mm"] == 0.0 and same["dtheta_deg"] == 0.0
    turned = cal.compare_cameras(TRUE_CAMERA, TRUE_CAMERA.replace(theta=TRUE_CAMERA.theta + math.radians(1.0)))
    # a camera near the axis turned by 1 deg moves the seen membrane point by about r * 1 deg = 0.87 mm
    assert turned["dtheta_deg"] == pytest.approx(1.0)
    assert 0.75 < turned["contact_band_mean_mm"] < 1.0


# --------------------------------------------------------------------------- evidence and uncertainty
def test_row_balance_is_not_applied_when_the_presses_do_not_show_it():
    """Presses that hardly differ give no slope to fit: the paper's plain mean, and the reason."""
    images = [render_hemispheres(TRUE_CAMERA, FRAME, seed=s) for s in range(5)]
    result = cal.calibrate_extrinsics(images, TRUE_CAMERA.replace(theta=0.0, d=0.0))
    assert not result.row_balance.applied and "hardly differ" in result.row_balance.reason
    assert result.theta == pytest.approx(result.theta_plain_mean)
    assert "paper's plain mean" in result.summary()
    off = cal.calibrate_extrinsics(images, TRUE_CAMERA.replace(theta=0.0, d=0.0),
                                   cal.ExtrinsicsConfig(balance_rows=False))
    assert off.row_balance.reason == "switched off"


def test_sigma_carries_the_intrinsics_uncertainty():
    """d scales with the focal length and theta moves with cy: their sigmas reach theta and d."""
    images = [render_hemispheres(TRUE_CAMERA, FRAME, seed=s) for s in range(4)]
    prior = TRUE_CAMERA.replace(theta=0.0, d=0.0)
    alone = cal.calibrate_extrinsics(images, prior)
    sigma = {"fx": 1.0, "fy": 1.0, "cx": 0.5, "cy": 0.5}
    with_intrinsics = cal.calibrate_extrinsics(images, prior, intrinsics_sigma=sigma)
    assert with_intrinsics.theta == alone.theta and with_intrinsics.d == alone.d
    # cy by 0.5 px turns theta by about 0.5 / fy rad; fx, fy by 1 px move d by about (r + d) / f
    assert math.degrees(with_intrinsics.theta_sigma) == pytest.approx(math.degrees(0.5 / TRUE_CAMERA.fy), rel=0.3)
    assert with_intrinsics.d_sigma == pytest.approx((TRUE_CAMERA.radius + TRUE_CAMERA.d) / TRUE_CAMERA.fx, rel=0.3)
    assert alone.d_sigma < 0.2 * with_intrinsics.d_sigma
    written = cal.calibration_sigma(None, with_intrinsics)
    assert written == {"theta": with_intrinsics.theta_sigma, "d": with_intrinsics.d_sigma}


def test_intrinsics_result_says_what_the_views_cover(chessboards):
    result = cal.calibrate_intrinsics(chessboards, INTRINSICS)
    assert result.distortion_model in cal.AUTO_CANDIDATES
    assert sum(score.chosen for score in result.model_scores) == 1
    assert result.coverage.views == len(result.per_view_rms)
    assert "coverage:" in result.summary() and result.warnings() == result.coverage.warnings()


def test_sigma_propagates_the_intrinsics_covariance_including_distortion():
    """The intrinsics' covariance reaches theta and d through the pose solves' gradient: the same as
    the sigmas alone for a covariance built from them, and a distortion term (which the sigmas of a
    parameters file before did not carry) moves d as far as re-solving with it moved does."""
    from touchroller_perception.calibration.extrinsics import intrinsics_covariance_from_sigma

    images = [render_hemispheres(TRUE_CAMERA, FRAME, seed=s) for s in range(4)]
    prior = TRUE_CAMERA.replace(theta=0.0, d=0.0)
    sigma = {"fx": 1.0, "fy": 1.0, "cx": 0.5, "cy": 0.5}
    by_sigma = cal.calibrate_extrinsics(images, prior, intrinsics_sigma=sigma)
    by_covariance = cal.calibrate_extrinsics(images, prior,
                                             intrinsics_covariance=intrinsics_covariance_from_sigma(sigma))
    assert by_covariance.theta_sigma == pytest.approx(by_sigma.theta_sigma, rel=1e-6)
    assert by_covariance.d_sigma == pytest.approx(by_sigma.d_sigma, rel=1e-6)
    step = 0.02
    k1_only = np.zeros((9, 9))
    k1_only[4, 4] = step**2
    with_k1 = cal.calibrate_extrinsics(images, prior, intrinsics_covariance=k1_only)
    k1, *rest = prior.distortion
    moved = cal.calibrate_extrinsics(images, prior.replace(distortion=(k1 + step, *rest)))
    intrinsic_part = math.sqrt(with_k1.d_sigma**2 - with_k1.d_press_sigma**2 - with_k1.d_model_sigma**2)
    assert abs(moved.d - with_k1.d) > 3 * with_k1.d_press_sigma
    assert intrinsic_part == pytest.approx(abs(moved.d - with_k1.d), rel=0.2)


def test_press_sigma_is_the_jackknife_over_presses():
    """Without the row balance the jackknife of the mean is the standard error of the mean; with it,
    the intercept redone with each press left out."""
    images = [render_hemispheres(TRUE_CAMERA, FRAME, seed=s) for s in range(5)]
    result = cal.calibrate_extrinsics(images, TRUE_CAMERA.replace(theta=0.0, d=0.0))
    assert not result.row_balance.applied
    thetas = np.array([v.theta for v in result.views])
    ds = np.array([v.d for v in result.views])
    assert result.theta_press_sigma == pytest.approx(thetas.std(ddof=1) / math.sqrt(thetas.size), rel=1e-9)
    assert result.d_press_sigma == pytest.approx(ds.std(ddof=1) / math.sqrt(ds.size), rel=1e-9)
    assert result.theta_sigma == pytest.approx(math.hypot(result.theta_press_sigma, result.theta_model_sigma))


# --------------------------------------------------------------------------- views judged against the set (#26)
def _uneven_points() -> np.ndarray:
    """The frame's imprint centres moved by a pattern no pose explains (+-0.16 mm along the axis,
    alternating): every view ~1.2 px RMS, as on a sensor whose imprints are a little off everywhere."""
    points = FRAME.reference_points(TRUE_CAMERA.radius).copy()
    points[:, 0] += 0.16e-3 * np.where(np.arange(FRAME.count) % 2 == 0, 1.0, -1.0)
    return points


def test_a_set_uniformly_worse_than_the_simulators_is_used_with_a_warning():
    """Every view ~1.2 px RMS: no view stands out from the others, so all are used (a fixed 1 px limit
    refused them all), with a warning saying how much worse than the simulators and what it costs."""
    images = [render_hemispheres(TRUE_CAMERA, FRAME, seed=s, points=_uneven_points()) for s in range(6)]
    result = cal.calibrate_extrinsics(images, TRUE_CAMERA.replace(theta=0.0, d=0.0))
    assert len(result.views) == 6 and not result.rejected
    assert all(0.8 < v.rms < 2.0 for v in result.views)
    assert abs(math.degrees(result.theta - TRUE_CAMERA.theta)) < 0.1
    assert any("what this project's simulators give" in w and "sigma" in w for w in result.warnings)
    assert "warning: the views' median reprojection RMS" in result.summary()


def test_a_view_far_above_the_others_rms_is_dropped_only_when_that_predicts_better():
    """One press whose imprints are moved by the pattern above (1.6 px RMS among 0.02 px) stands out
    from the set and is a candidate outlier; but its theta and d agree with the others, so leaving it
    out predicts the other presses no better, and it is kept: the choice says so."""
    images = [render_hemispheres(TRUE_CAMERA, FRAME, seed=s) for s in range(6)]
    images.append(render_hemispheres(TRUE_CAMERA, FRAME, seed=7, points=_uneven_points()))
    result = cal.calibrate_extrinsics(images, TRUE_CAMERA.replace(theta=0.0, d=0.0))
    rejection = next(c for c in result.choices if c.term == "view rejection")
    assert rejection.reason == "1 outlier(s)" and not rejection.kept and abs(rejection.margin_px) < 0.01
    assert 6 in {v.index for v in result.views}
    assert abs(math.degrees(result.theta - TRUE_CAMERA.theta)) < 0.1


def test_never_zero_views_when_the_papers_plain_method_solves():
    """When the rejections leave fewer views than needed, the paper's plain method (every view that
    solved, the plain mean) is used and the result says so, instead of refusing."""
    images = [render_hemispheres(TRUE_CAMERA, FRAME, seed=s) for s in range(5)]
    images.append(render_hemispheres(TRUE_CAMERA, FRAME, seed=9, shift_px=(0.0, 12.0)))   # frame slipped
    result = cal.calibrate_extrinsics(images, TRUE_CAMERA.replace(theta=0.0, d=0.0), cal.ExtrinsicsConfig(min_views=6))
    assert len(result.views) == 6
    assert "paper's plain method" in result.method and any("plain method" in w for w in result.warnings)
    assert result.theta == pytest.approx(np.mean([v.theta for v in result.views]))


def test_outlier_rejection_is_kept_by_held_out_prediction():
    """The slipped frame's press is rejected because leaving it out predicts the other presses better."""
    images = [render_hemispheres(TRUE_CAMERA, FRAME, seed=s) for s in range(5)]
    images.append(render_hemispheres(TRUE_CAMERA, FRAME, seed=9, shift_px=(0.0, 12.0)))
    result = cal.calibrate_extrinsics(images, TRUE_CAMERA.replace(theta=0.0, d=0.0))
    rejection = next(c for c in result.choices if c.term == "view rejection")
    assert rejection.kept and rejection.margin_px > rejection.needed * rejection.spread_px
    assert "view rejection: kept, held-out margin" in result.summary()


# --------------------------------------------------------------------------- plausibility (#26)
def test_intrinsics_of_another_camera_are_refused_not_applied():
    """fx 500 px given for a camera of 512/508 px is mild; 380 px gives d many mm off: refused, with why."""
    images = [render_hemispheres(TRUE_CAMERA, FRAME, seed=s) for s in range(4)]
    with pytest.raises(cal.CalibrationError, match=r"implausible result.*d = .*intrinsics"):
        cal.calibrate_extrinsics(images, TRUE_CAMERA.replace(theta=0.0, d=0.0, fx=380.0, fy=380.0))


def test_intrinsics_for_another_image_size_are_refused():
    images = [render_hemispheres(TRUE_CAMERA, FRAME, seed=s) for s in range(3)]
    with pytest.raises(cal.CalibrationError, match="intrinsics are for 320x240 images, the presses are 640x480"):
        cal.calibrate_extrinsics(images, TRUE_CAMERA.replace(theta=0.0, d=0.0, width=320, height=240))


# --------------------------------------------------------------------------- model error in the sigma (#26)
def _view(index: int, theta: float, rows: tuple[float, float], other: tuple[float, float]):
    from touchroller_perception.calibration.extrinsics import ViewPose

    return ViewPose(index=index, theta=theta, d=1.5e-3, rms=0.05, shift_x=0.0, yaw=0.0, full_theta=theta, beta=0.0,
                    gamma=0.0, t=(0.0, 0.0, 1.5e-3), full_rms=0.05, rvec=(0.0, 0.0, 0.0), row_strengths=rows,
                    other_row_strengths=other)


def test_strength_model_error_is_how_far_the_other_measure_moves_the_balanced_theta():
    """Five presses whose theta follows the row asymmetry; the other strength measure reads every
    press's asymmetry 0.1 higher (a row that measures larger in every press by one measure only): its
    balance line meets a = 0 elsewhere, by slope x 0.1, and that is the model error. Measures that
    agree give 0, and so does a set without the other measure."""
    from touchroller_perception.calibration.extrinsics import _strength_model_error, _with_row_asymmetry

    asymmetry = np.array([-0.3, -0.1, 0.0, 0.2, 0.4])
    slope, theta0 = math.radians(1.0), math.radians(2.0)
    views = _with_row_asymmetry([_view(i, theta0 - slope * a, (1.0 - a / 2, 1.0 + a / 2),
                                       (1.0 - (a + 0.1) / 2, 1.0 + (a + 0.1) / 2))
                                 for i, a in enumerate(asymmetry)])
    assert _strength_model_error(views) == pytest.approx(slope * 0.1, rel=1e-6)
    agreeing = [dataclasses.replace(v, other_row_strengths=v.row_strengths) for v in views]
    assert _strength_model_error(agreeing) == pytest.approx(0.0, abs=1e-12)
    without = [dataclasses.replace(v, other_row_strengths=(math.nan, math.nan)) for v in views]
    assert _strength_model_error(without) == 0.0
