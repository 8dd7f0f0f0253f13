"""The calibration's goals on both renderers, as behaviour checks (few images: fast, generous bounds)."""
from __future__ import annotations

import math

import numpy as np
import pytest

from bench import calib_crosscheck as check
from bench import second_renderer as second
from touchroller_perception import calibration as cal


def theta_d_errors(presses: check.Presses, config: cal.ExtrinsicsConfig,
                   lights_off: bool = True) -> tuple[float, float]:
    result = cal.calibrate_extrinsics(presses.images, presses.camera.replace(theta=0.0, d=0.0), config,
                                      reference=presses.reference, dark=presses.dark if lights_off else None)
    return math.degrees(result.theta - presses.camera.theta), 1e3 * (result.d - presses.camera.d)


@pytest.fixture(scope="module")
def second_presses() -> check.Presses:
    return check.second_presses(seed=1, presses=10)


def test_second_renderer_meets_the_goals_where_the_previous_method_did_not(second_presses):
    theta, d = theta_d_errors(second_presses, cal.ExtrinsicsConfig())
    assert abs(theta) <= 0.1 and abs(d) <= 0.05
    previous = cal.ExtrinsicsConfig(detector=cal.ImprintDetectorConfig(centre="centroid", strength="absolute"))
    theta_previous, _ = theta_d_errors(second_presses, previous, lights_off=False)
    assert abs(theta_previous) > 0.1          # the failure, rebuilt


def test_simulator_meets_the_goals_with_the_same_method():
    theta, d = theta_d_errors(check.simulator_presses(seed=1, presses=10), cal.ExtrinsicsConfig())
    assert abs(theta) <= 0.1 and abs(d) <= 0.05


def test_simulator_central_variant_is_the_same_case():
    boards = check.simulator_boards(seed=1, views=8)
    size = np.array([boards.camera.width, boards.camera.height])
    assert all(np.all((c > 0.25 * size) & (c < 0.75 * size)) for c in boards.corners)
    result = cal.calibrate_intrinsics(boards.images)
    assert not result.coverage.corners_covered and result.distortion_model in ("k1k2", "radial")


def test_central_boards_rays_right_where_seen_and_the_corners_warned():
    boards = check.second_boards(seed=2, views=12)
    auto = cal.calibrate_intrinsics(boards.images)
    full = cal.calibrate_intrinsics(boards.images, cal.IntrinsicsConfig(distortion="full"))
    seen_auto, whole_auto = check.ray_errors(auto.camera, boards.camera, boards.seen)
    _, whole_full = check.ray_errors(full.camera, boards.camera, boards.seen)
    assert auto.distortion_model == "k1k2p"
    assert seen_auto <= 0.6                   # the goal is 0.5 px p95 with 20 views; 12 here
    assert whole_full > 5 * whole_auto        # the free k3 invents distortion in the corners
    assert not auto.coverage.corners_covered
    assert any("image corners not covered" in w for w in auto.warnings())


@pytest.mark.parametrize("renderer", ["simulator", "second renderer"])
def test_corners_refined_on_the_board_plane_are_nearer_the_truth_on_both_renderers(renderer):
    """The default corner path (refined on the board's plane) against the previous one (refined in
    the image), on the views of each renderer: nearer the true corners on both, not on one only."""
    boards = check.BOARDS[renderer](5, 8)

    def error(corners: str) -> float:
        found, _ = cal.chessboard_corners(boards.images, cal.IntrinsicsConfig(corners=corners))
        return float(np.sqrt(np.mean(np.concatenate([check._matched(c, boards.corners[i])
                                                      for i, c in found.items()]) ** 2)))

    assert error("fronto_parallel") < 0.9 * error("image")


def test_method_table_compares_the_methods_on_both_imprint_models():
    rows = check.method_rows({"second renderer": [check.second_presses(seed=3, presses=6)]})
    assert [r.method for r in rows] == [m[0] for m in check.METHODS]
    ours = next(r for r in rows if r.method == check.OURS)
    previous = next(r for r in rows if r.method.startswith("previous"))
    assert abs(ours.centre_bias_px[1]) < 0.05 < abs(previous.centre_bias_px[1])
    assert np.isfinite(ours.theta_err_deg.max) and ours.theta_err_deg.n == 1


def test_sigma_rows_count_trials_within_two_sigma():
    presses = {"second renderer": [check.second_presses(seed=4, presses=6)]}
    boards = check.second_boards(seed=4, views=8)
    intrinsics = {"second renderer": [cal.calibrate_intrinsics(boards.images)]}
    rows, whole = check.sigma_rows(presses, intrinsics)
    assert [r.parameter for r in rows] == list(check.SIGMA_PARAMETERS)
    assert all(r.trials == 1 and r.within_2_sigma in (0.0, 1.0) and r.median_abs_z >= 0 for r in rows)
    assert [w.renderer for w in whole] == ["second renderer"] and whole[0].theta_err_deg.n == 1


def test_sigma_verdict_is_the_binomial_spread_around_95_percent():
    def verdict(within: float, trials: int) -> check.SigmaVerdict:
        rows = (check.SigmaRow("r", "theta", trials, within, 0.7),)
        return check.CrosscheckResult(1, 20, (), (), rows).sigma_verdict()

    assert verdict(0.95, 100).met and verdict(0.92, 100).met
    assert not verdict(0.85, 100).met            # sigmas too small
    assert not verdict(1.0, 100).met             # too large: 100 of 100 is unlikely for right sigmas
    assert verdict(1.0, 20).met                  # but not with 20 trials


def test_floor_row_solves_from_the_true_corners_with_the_measured_noise():
    boards = [check.second_boards(seed=2, views=8)]
    auto = [cal.calibrate_intrinsics(boards[0].images)]
    row = check.floor_row("second renderer", boards, auto, [2])
    assert row.model.startswith(check.FLOOR) and "px per axis" in row.model
    noise = float(row.model.split("(")[1].split()[0])
    assert 0.005 < noise < 0.1                   # the detector's corner error, measured against the truth
    assert 0 < row.seen_p95_px.max < 3.0


def test_renderer_truth_is_the_true_camera():
    presses = second.render_presses(0, 1)
    assert presses.camera == second.TRUE_CAMERA and len(presses.truth[0].centres_px) == 10


def test_centre_errors_are_each_found_imprint_against_its_truth_and_skip_presses_without_a_frame():
    presses = check.second_presses(seed=0, presses=2)
    blank = check.Presses(presses.reference, [*presses.images, presses.reference],
                          [*presses.centres_px, presses.centres_px[0]], presses.camera)
    errors = check.centre_errors(blank, "shading")
    assert errors.shape == (20, 2) and float(np.abs(errors).max()) < 0.5
    none = check.Presses(presses.reference, [presses.reference], [presses.centres_px[0]], presses.camera)
    assert check.centre_errors(none, "shading").shape == (0, 2)

def test_corner_noise_is_not_inflated_by_a_few_misdetected_corners():
    rng = np.random.default_rng(0)
    errors = rng.normal(0.0, 0.02, (2000, 2))
    errors[:6] += 4.0                            # a few corners put between the true ones
    assert abs(check.corner_noise(errors) - 0.02) < 0.002
    assert np.sqrt(np.mean(errors**2)) > 0.1     # what a root mean square would have said


def test_a_principal_point_error_is_a_rotation_and_theta_absorbs_only_the_one_across_the_roller():
    truth = second.TRUE_CAMERA
    seen = np.zeros((truth.height, truth.width), bool)
    seen[120:360, 160:480] = True
    along_u = check.ray_decomposition(truth.replace(cx=truth.cx + 1.0), truth, seen)
    assert 0.9 < along_u.seen_p95 < 1.1
    assert along_u.less_rotation_p95 < 0.1       # a shifted principal point turns the rays
    assert along_u.less_theta_p95 > 0.9          # about y: not what theta (about x) absorbs
    along_v = check.ray_decomposition(truth.replace(cy=truth.cy + 1.0), truth, seen)
    assert along_v.less_theta_p95 < 0.1 and abs(along_v.rotation_deg[0]) > 0.1
    shape = check.ray_decomposition(truth.replace(distortion=(-0.15, *truth.distortion[1:])), truth, seen)
    assert shape.less_rotation_p95 > 0.5 * shape.seen_p95   # the distortion's shape is no rotation


def test_boards_in_the_middle_do_not_buy_k3_by_chance():
    """Seed 27's central views: held out, k3 looked better by a fraction of a standard error, and the
    fitted k3 put the imprints' rays off beyond the boards (d 0.13 mm off). The corners were never
    seen, so k3 is not offered; within the boards the rays are as good."""
    boards = check.second_boards(seed=27, views=20)
    auto = cal.calibrate_intrinsics(boards.images)
    assert not auto.coverage.corners_covered
    assert auto.distortion_model == "k1k2p" and auto.camera.distortion[4] == 0.0
    full = cal.calibrate_intrinsics(boards.images, cal.IntrinsicsConfig(distortion="full"))
    seen_auto, whole_auto = check.ray_errors(auto.camera, boards.camera, boards.seen)
    seen_full, whole_full = check.ray_errors(full.camera, boards.camera, boards.seen)
    assert seen_auto <= seen_full + 0.05 and whole_auto < whole_full


def test_one_side_lit_presses_calibrate_with_the_defaults():
    """Issue #26: a GelSight-type membrane lit from one side at a low 15 deg, the frame centred within
    0.2 mm and pressed 0.15 mm deeper or shallower (imprints grow with the local press depth). With
    strengths relative to the whole reference (no lights-off frame) the rows' strengths followed the
    light and the uneven gel as much as the placement and the row balance moved theta 0.19 deg off;
    the imprints' extent follows the placement, and theta is within 0.1 deg with the defaults."""
    import dataclasses

    rendered = second.render_presses(0, 10, look=dataclasses.replace(second.Look(), light_elevation_deg=15.0),
                                     placement=second.Placement(shift=2e-4, depth_jitter=1.5e-4))
    result = cal.calibrate_extrinsics(rendered.images, rendered.camera.replace(theta=0.0, d=0.0),
                                      reference=rendered.reference)
    assert abs(math.degrees(result.theta - rendered.camera.theta)) <= 0.1
    assert abs(result.d - rendered.camera.d) <= 0.05e-3
    balance = next(c for c in result.choices if c.term == "row balance")
    assert balance.presses == 10 and result.row_balance.applied == balance.kept


@pytest.mark.parametrize("azimuth", [90.0, 270.0])
def test_sigma_of_one_side_lit_presses_includes_the_model_error(azimuth):
    """Issue #26: an LED at 15 deg along the rolling direction, frame centred, a lights-off frame.
    The shadows pull every imprint centre towards the light and the rows' two strength measures
    disagree: theta is off by ~0.04 deg in every press alike, twice and more the presses' jackknife
    sigma, which sees only their scatter. The model error (`theta_model_sigma`: the centres' shadow
    pull moved through the pose solves, and the other strength measure's theta) is in the sigma,
    and the truth lies within 2 sigma."""
    import dataclasses

    rendered = second.render_presses(0, 10, look=dataclasses.replace(second.Look(), light_azimuth_deg=azimuth,
                                                                     light_elevation_deg=15.0),
                                     placement=second.Placement(shift=2e-4, depth_jitter=1.5e-4))
    result = cal.calibrate_extrinsics(rendered.images, rendered.camera.replace(theta=0.0, d=0.0),
                                      reference=rendered.reference, dark=rendered.dark)
    error = abs(result.theta - rendered.camera.theta)
    assert error > 2 * result.theta_press_sigma
    assert result.theta_model_sigma > result.theta_press_sigma
    assert result.theta_sigma == pytest.approx(math.hypot(result.theta_press_sigma, result.theta_model_sigma))
    assert error <= 2 * result.theta_sigma
    assert 0 < result.d_model_sigma < result.d_sigma


@pytest.mark.parametrize("azimuth", [90.0, 270.0])
def test_a_few_presses_lit_low_from_one_side_without_a_lights_off_frame(azimuth):
    """Issue #26's test: 6 presses of a frame moved by hand (+-1 mm), lit by one LED at 15 deg along
    the rolling direction, no lights-off frame, the defaults: theta within 0.1 deg. Strengths relative
    to the whole reference (the former default) put 0.2-0.3 deg into theta here: the reference holds a
    background the light does not make (ambient light, the uneven gel), brighter under one row."""
    import dataclasses

    rendered = second.render_presses(0, 6, look=dataclasses.replace(second.Look(), light_azimuth_deg=azimuth,
                                                                     light_elevation_deg=15.0),
                                     placement=second.Placement(depth_jitter=1.5e-4))
    start = rendered.camera.replace(theta=0.0, d=0.0)

    def theta_error(config: cal.ExtrinsicsConfig) -> float:
        result = cal.calibrate_extrinsics(rendered.images, start, config, reference=rendered.reference)
        return abs(math.degrees(result.theta - rendered.camera.theta))

    assert theta_error(cal.ExtrinsicsConfig()) <= 0.1
    assert theta_error(cal.ExtrinsicsConfig(detector=cal.ImprintDetectorConfig(strength="relative"))) > 0.15


@pytest.mark.parametrize("azimuth", [90.0, 270.0])
def test_simulator_lit_from_one_side_calibrates_with_the_defaults(azimuth):
    """The simulator's one white LED along the rolling direction (the light's asymmetry lies along the
    rows): the row balance is kept (the frame moves 1.5 mm between presses), theta within 0.1 deg."""
    from touchroller_driver.sim import SimulatedSensor, load_scene

    sensor = SimulatedSensor(load_scene("calibration_hemispheres", **{"sensor.directional_light_deg": azimuth}), seed=0)
    frames = list(sensor.frames())
    reference = np.median(np.stack([f.image for f in frames if f.truth.get("phase") == "reference"]), axis=0)
    presses = [f.image for f in frames if f.truth.get("phase") == "press"]
    result = cal.calibrate_extrinsics(presses, sensor.camera.replace(theta=0.0, d=0.0),
                                      reference=reference.astype(np.uint8))
    assert abs(math.degrees(result.theta - sensor.camera.theta)) <= 0.1
    assert abs(result.d - sensor.camera.d) <= 0.05e-3
    assert result.row_balance.applied and result.choices[0].kept


def _centre_bias(images, reference, truths, centre: str) -> np.ndarray:
    errors = [cal.find_imprints(image, cal.HemisphereFrame(), cal.ImprintDetectorConfig(centre=centre),
                                reference).centres - truth for image, truth in zip(images, truths, strict=True)]
    return np.concatenate(errors).mean(axis=0)


@pytest.mark.parametrize("azimuth", [0.0, 90.0, 180.0, 270.0])
def test_imprint_centres_do_not_move_with_the_lights_direction(azimuth):
    """Presses lit from one side at each of four azimuths, on both renderers: the centroid moves
    0.3-0.5 px away from the light, the shading centre stays within 0.1 px of the truth. The
    simulator indents its balls as sphere caps, whose slopes facing away from its 25-degree light are
    partly in shadow: the shading-symmetric centre alone ("symmetric") is pulled towards the light
    by more than 0.1 px there, the shadow-censored fit after it ("shading") is not."""
    import dataclasses

    from touchroller_driver.sim import SimulatedSensor, load_scene

    sensor = SimulatedSensor(load_scene("calibration_hemispheres", **{"motion.presses": 2,
                                                                      "sensor.directional_light_deg": azimuth}), seed=0)
    frames = list(sensor.frames())
    reference = np.median(np.stack([f.image for f in frames if f.truth.get("phase") == "reference"]),
                          axis=0).astype(np.uint8)
    pressed = [f for f in frames if f.truth.get("phase") == "press"]
    rendered = second.render_presses(0, 2, look=dataclasses.replace(second.Look(), light_azimuth_deg=azimuth))
    towards = np.array([math.cos(math.radians(azimuth)), math.sin(math.radians(azimuth))])
    simulated = [np.array([c["pixel"] for c in f.truth["contacts"]]) for f in pressed]
    for images, ref, truths in (
            ([f.image for f in pressed], reference, simulated),
            (rendered.images, rendered.reference, [t.centres_px for t in rendered.truth])):
        assert float(_centre_bias(images, ref, truths, "centroid") @ towards) < -0.3
        assert float(np.abs(_centre_bias(images, ref, truths, "shading")).max()) < 0.1
    # the shadow is what the censored fit is for: without it the simulator's centres move with the light
    assert float(_centre_bias([f.image for f in pressed], reference, simulated, "symmetric") @ towards) > 0.1
