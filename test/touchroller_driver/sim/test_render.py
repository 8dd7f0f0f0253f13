"""Rendering validated against theory: band width, blur length, contact positions, surface truth."""
import functools
import math

import cv2
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from touchroller_driver.sim import RollerState, SimulatedSensor, load_scene

SMALL_FLAT = {"surface.kind": "flat", "surface.width": 0.07, "surface.length": 0.04,
              "surface.resolution": 1e-4, "effects": []}


def _flat_sensor(**camera):
    overrides = dict(SMALL_FLAT)
    overrides.update({f"camera.{k}": v for k, v in camera.items()})
    return SimulatedSensor(load_scene("surface_mapping", **overrides), seed=0)


def _band_edges(image, reference, column):
    diff = np.abs(image[:, column].astype(int) - reference[:, column].astype(int)).sum(axis=1)
    rows = np.flatnonzero(diff > 0)
    assert rows.size > 0, "no contact band rendered"
    return rows[0], rows[-1]


@pytest.mark.parametrize("depth", [2e-4, 5e-4, 1e-3])
@pytest.mark.parametrize("camera", [{}, {"extrinsics.theta": 0.035, "extrinsics.d": 0.0015,
                                         "camera.distortion": [-0.08, 0.02, 0.0, 0.0, 0.0]}])
def test_band_width_matches_theory(depth, camera):
    sensor = _flat_sensor(**camera)
    reference = sensor.render(RollerState(travel=0.02, depth=-0.01))
    image = sensor.render(RollerState(travel=0.02, depth=depth))
    column = int(round(sensor.camera.cx))
    top, bottom = _band_edges(image, reference, column)
    # shading reaches one row past the indented rows (3x3 Sobel): the true edges lie half a row inside
    pts, ok = sensor.camera.back_project(np.array([[column, top + 0.5], [column, bottom - 0.5]]))
    assert ok.all()
    measured = pts[1, 1] - pts[0, 1]
    theory = 2 * math.sqrt(2 * sensor.camera.radius * depth - depth**2)   # ~ 2 sqrt(2 r delta)
    _, mpp_v = sensor.metres_per_px_at_contact()
    assert measured == pytest.approx(theory, abs=2 * mpp_v), (measured, theory)
    # and the indentation layer itself is exactly the geometric overlap
    layers = sensor.render_layers(RollerState(travel=0.02, depth=depth))
    band = np.flatnonzero(layers["indentation"][:, column] > 0)
    pts, _ = sensor.camera.back_project(np.array([[column, band[0]], [column, band[-1]]]))
    assert pts[1, 1] - pts[0, 1] == pytest.approx(theory, abs=2 * mpp_v)


@pytest.mark.parametrize("blur_px", [6.0, 10.0, 15.5])
def test_blur_length_matches_speed_times_exposure(blur_px):
    scene = load_scene("surface_mapping", **{
        "surface.kind": "stripes", "surface.period": 0.01, "surface.ridge_width": 2e-4,
        "surface.width": 0.07, "surface.length": 0.04, "surface.resolution": 5e-5,
        "sensor.lowpass_sigma": 0.0, "effects": ["blur"], "exposure": 0.02})
    sensor = SimulatedSensor(scene, seed=0)
    _, mpp_v = sensor.metres_per_px_at_contact()
    speed = blur_px * mpp_v / scene.exposure
    column = int(round(sensor.camera.cx))
    still = sensor.render_layers(RollerState(travel=0.0203, depth=5e-4, speed=0.0))["relief"][:, column]
    moving_layers = sensor.render_layers(RollerState(travel=0.0203, depth=5e-4, speed=speed))
    moving = moving_layers["relief"][:, column]
    peak = int(np.argmax(still))          # look at one ridge only
    still, moving = still[peak - 25:peak + 26], moving[peak - 25:peak + 26]
    # a ridge narrower than the blur: its blurred profile is a box whose area/peak is the blur length
    assert still.sum() / still.max() < 0.5 * blur_px
    measured = moving.sum() / moving.max()
    assert measured == pytest.approx(blur_px, abs=0.6), (measured, blur_px)
    # the relief's total is conserved (a box filter), and the image changes
    assert moving.sum() == pytest.approx(still.sum(), rel=0.02)
    assert not np.array_equal(moving_layers["image"], sensor.render(RollerState(travel=0.0203, depth=5e-4)))


def _detect_blobs(image, reference, threshold=6):
    diff = np.abs(image.astype(int) - reference.astype(int)).sum(axis=2).astype(np.uint8)
    _, binary = cv2.threshold(diff, threshold, 255, cv2.THRESH_BINARY)
    count, labels, stats, centroids = cv2.connectedComponentsWithStats(binary)
    return [centroids[i] for i in range(1, count) if stats[i, cv2.CC_STAT_AREA] >= 5]


def test_rendered_contacts_back_project_to_their_3d_points():
    scene = load_scene("contact_localisation", effects=[])
    sensor = SimulatedSensor(scene, seed=0)
    frames = list(sensor.frames())
    reference = frames[0].image
    checked = 0
    for frame in frames:
        contacts = frame.truth["contacts"]
        if not contacts:
            continue
        layers = sensor.render_layers(RollerState(**{k: v for k, v in frame.truth["state"].items()
                                                     if k != "indenters"},
                                                  indenters=_indenters(frame.truth["state"])))
        D = layers["indentation"]
        blobs = _detect_blobs(frame.image, reference)
        assert len(blobs) == len(contacts)
        for contact in contacts:
            truth_uv = np.array(contact["pixel"])
            # indentation-weighted centroid of the imprint around the true pixel
            u0, v0 = np.round(truth_uv).astype(int)
            r0, r1, c0, c1 = max(v0 - 16, 0), min(v0 + 17, D.shape[0]), max(u0 - 16, 0), min(u0 + 17, D.shape[1])
            win = D[r0:r1, c0:c1]
            assert win[0].max() == 0 and win[-1].max() == 0   # the whole imprint is inside the window
            vv, uu = np.mgrid[r0:r1, c0:c1]
            centroid = np.array([(uu * win).sum(), (vv * win).sum()]) / win.sum()
            point, ok = sensor.camera.back_project(centroid)
            assert ok
            assert np.linalg.norm(point - np.array(contact["point"])) < 1e-4   # 0.1 mm
            # the image blob (shading, thresholded) is where the truth says, to a pixel or two
            nearest = min(blobs, key=lambda b: np.linalg.norm(b - truth_uv))
            point, ok = sensor.camera.back_project(nearest)
            assert np.linalg.norm(point - np.array(contact["point"])) < 5e-4   # 0.5 mm
            checked += 1
    assert checked == 2 * 3 * 3 * 3 * 3    # sides x positions x repeats x sticks x held frames


def _indenters(state):
    from touchroller_driver.sim import Indenter

    return tuple(Indenter(tuple(i["centre"]), i["radius"]) for i in state["indenters"])


def test_contact_angles_cover_the_papers_protocol():
    sensor = SimulatedSensor(load_scene("contact_localisation", effects=[]), seed=0)
    cells = set()
    for frame in sensor.frames():
        for c in frame.truth["contacts"]:
            cells.add((round(c["alpha"] / (math.pi / 12)), c["position_fraction"]))
            assert sensor.camera.in_image(np.array(c["pixel"]), margin=10)
    assert cells == {(a, p) for a in (-2, -1, 0, 1, 2) for p in (0.25, 0.5, 0.75)}


def test_hemisphere_imprints_at_their_truth_pixels():
    sensor = SimulatedSensor(load_scene("calibration_hemispheres", effects=[]), seed=1)
    frames = list(sensor.frames())
    presses = [f for f in frames if f.truth["contacts"]]
    assert len(presses) == 10
    for frame in presses[:3]:
        blobs = _detect_blobs(frame.image, frames[0].image, threshold=4)
        assert len(blobs) == 10
        for c in frame.truth["contacts"]:
            nearest = min(np.linalg.norm(b - np.array(c["pixel"])) for b in blobs)
            assert nearest < 2.0


def test_surface_truth_matches_what_the_contact_line_sees():
    scene = load_scene("surface_mapping", **{"surface.width": 0.07, "surface.length": 0.03,
                                             "surface.resolution": 1e-4, "effects": []})
    sensor = SimulatedSensor(scene, seed=3)
    truth = sensor.surface_map_truth(0.0, 0.03)
    assert truth.mm_per_px_rows == pytest.approx(0.1, rel=0.01)
    row = int(round(sensor.contact_row()))
    for travel in (0.008, 0.017):
        relief = sensor.render_layers(RollerState(travel=travel, depth=5e-4))["relief"][row]
        k = int(round((travel - truth.y_start) / (truth.mm_per_px_rows * 1e-3)))
        np.testing.assert_allclose(relief, truth.height[k], atol=0.05 * sensor.surface.max_height)
        assert np.corrcoef(relief, truth.height[k + 15])[0, 1] < 0.9   # a different row differs


def test_thickness_variation_moves_the_membrane():
    base = load_scene("contact_localisation", effects=[])
    uneven = load_scene("contact_localisation", effects=[], **{"sensor.thickness_variation": 3e-4})
    a, b = SimulatedSensor(base, seed=0), SimulatedSensor(uneven, seed=0)
    fa = [f for f in a.frames() if f.truth["contacts"]][0]
    fb = [f for f in b.frames() if f.truth["contacts"]][0]
    radii = [np.hypot(*c["point"][1:]) for c in fb.truth["contacts"]]
    assert max(abs(r - 0.05) for r in radii) > 1e-5
    assert all(np.hypot(*c["point"][1:]) == pytest.approx(0.05) for c in fa.truth["contacts"])
    assert not np.array_equal(fa.image, fb.image)


def test_paper_variant_has_a_calibration_error():
    scene = load_scene("contact_localisation", variant="paper")
    assert scene.paper_camera.theta - scene.camera.theta == pytest.approx(math.radians(1.0), rel=1e-4)
    assert scene.paper_camera.d - scene.camera.d == pytest.approx(5e-4)


# --------------------------------------------------------------------------- properties
@settings(max_examples=12, deadline=None)
@given(depth=st.floats(1e-4, 1.5e-3), theta=st.floats(-0.05, 0.05), d=st.floats(-3e-3, 3e-3),
       k1=st.floats(-0.15, 0.05), fy=st.floats(380.0, 600.0))
def test_band_truth_matches_rendered_band_for_any_camera(depth, theta, d, k1, fy):
    sensor = _flat_sensor(**{"extrinsics.theta": theta, "extrinsics.d": d, "camera.fy": fy,
                             "camera.distortion": [k1, 0.0, 0.0, 0.0, 0.0]})
    layers = sensor.render_layers(RollerState(travel=0.02, depth=depth))
    column = int(round(sensor.camera.cx))
    band = np.flatnonzero(layers["indentation"][:, column] > 0)
    truth = sensor.band_truth(depth)
    if not (0 <= truth["v_top"] and truth["v_bottom"] <= sensor.camera.height - 1):
        return   # band leaves the image: nothing to compare at this column
    assert band[0] == pytest.approx(truth["v_top"], abs=1.0)
    assert band[-1] == pytest.approx(truth["v_bottom"], abs=1.0)
    image = layers["image"]
    assert image.dtype == np.uint8 and image.shape == (480, 640, 3)
    assert np.all(layers["indentation"] >= 0) and np.isfinite(layers["indentation"]).all()


@pytest.mark.parametrize("bad", [
    RollerState(travel=math.nan), RollerState(depth=math.inf), RollerState(speed=-math.inf),
])
def test_non_finite_states_are_rejected(bad):
    sensor = _flat_sensor()
    with pytest.raises(ValueError, match="non-finite"):
        sensor.render(bad)


def test_thicker_gel_smooths_more():
    from touchroller_driver.sim.render import lowpass_sigma

    thin = lowpass_sigma({"lowpass_sigma": "auto", "lowpass_per_thickness": 0.075, "elastomer_thickness": 1e-3})
    thick = lowpass_sigma({"lowpass_sigma": "auto", "lowpass_per_thickness": 0.075, "elastomer_thickness": 4e-3})
    assert thick == pytest.approx(4 * thin)
    relief = {}
    for t in (1e-3, 4e-3):
        scene = load_scene("surface_mapping", effects=[], **{"sensor.elastomer_thickness": t,
                                                            "surface.width": 0.07, "surface.length": 0.03,
                                                            "surface.resolution": 5e-5})
        sensor = SimulatedSensor(scene, seed=0)
        relief[t] = sensor.render_layers(RollerState(travel=0.015, depth=5e-4))["relief"]
    assert np.abs(np.diff(relief[4e-3], axis=1)).sum() < 0.5 * np.abs(np.diff(relief[1e-3], axis=1)).sum()


def test_tactile_truth_is_what_the_contact_line_shows():
    scene = load_scene("surface_mapping", **{"surface.width": 0.07, "surface.length": 0.03,
                                             "surface.resolution": 5e-5, "effects": []})
    sensor = SimulatedSensor(scene, seed=5)
    truth = sensor.surface_map_truth(0.0, 0.03)
    row = int(round(sensor.contact_row()))
    travel = 0.0151
    image = sensor.render(RollerState(travel=travel, depth=5e-4))
    grey = cv2.cvtColor(image, cv2.COLOR_BGR2GRAY)[row - 3:row + 4].astype(float)
    k = int(round((travel - truth.y_start) / (truth.mm_per_px_rows * 1e-3)))
    expected = truth.tactile[k - 3:k + 4].astype(float)
    assert np.corrcoef(grey.ravel(), expected.ravel())[0, 1] > 0.9
    assert np.corrcoef(grey.ravel(), truth.tactile[k + 40:k + 47].astype(float).ravel())[0, 1] < 0.5


def test_pixels_past_the_tube_ends_are_dark():
    sensor = SimulatedSensor(load_scene("surface_mapping", **dict(SMALL_FLAT, **{"camera.cylinder.length": 0.04})),
                             seed=0)
    image = sensor.render(RollerState(travel=0.02, depth=5e-4))
    pts, ok = sensor.camera.back_project(np.array([[5.0, 240.0], [320.0, 240.0]]))
    assert not ok[0] and ok[1]
    assert image[240, 5].max() == 0 and image[240, 320].min() > 50
    assert not np.isnan(sensor.render_layers(RollerState(travel=0.02, depth=5e-4))["indentation"]).any()


@settings(max_examples=25, deadline=None)
@given(travel=st.floats(-0.05, 0.2), x_along=st.floats(-0.05, 0.05), depth=st.floats(-0.01, 3e-3),
       speed=st.floats(-0.2, 0.2))
def test_any_finite_state_renders_a_valid_frame(travel, x_along, depth, speed):
    sensor = _fabric_sensor()
    state = RollerState(travel=travel, x_along=x_along, depth=depth, speed=speed)
    layers = sensor.render_layers(state)
    assert layers["image"].shape == (480, 640, 3) and layers["image"].dtype == np.uint8
    assert np.isfinite(layers["indentation"]).all() and (layers["indentation"] >= 0).all()
    if depth + sensor.surface.max_height <= 0:
        assert np.array_equal(layers["image"], sensor._static)


@functools.cache
def _fabric_sensor():
    return SimulatedSensor(load_scene("surface_mapping", effects=["blur", "background"],
                                      **{"surface.width": 0.07, "surface.length": 0.03,
                                         "surface.resolution": 1e-4}), seed=0)


def test_other_image_sizes():
    sensor = SimulatedSensor(load_scene("surface_mapping", **dict(SMALL_FLAT, **{
        "camera.width": 320, "camera.height": 240, "camera.fx": 250, "camera.fy": 250,
        "camera.cx": 159.5, "camera.cy": 119.5})), seed=0)
    image = sensor.render(RollerState(travel=0.02, depth=5e-4))
    assert image.shape == (240, 320, 3)
    _, mpp_v = sensor.metres_per_px_at_contact()
    assert mpp_v == pytest.approx(2e-4, rel=0.01)


@pytest.mark.parametrize("azimuth", [0.0, 90.0, 180.0, 270.0])
def test_directional_light_lights_every_imprint_from_its_side(azimuth):
    """`sensor.directional_light_deg`: one white LED from that azimuth (0: +u along the axis, 90: +v
    around it). Each imprint's slope that faces the light is brighter than the opposite one, the
    same in every colour, and the light is stronger on the membrane's side towards it."""
    scene = load_scene("calibration_hemispheres", effects=[],
                       **{"motion.presses": 1, "sensor.directional_light_deg": azimuth})
    sensor = SimulatedSensor(scene, seed=0)
    frames = list(sensor.frames())
    reference = frames[0].image.astype(np.float64)
    press = next(f for f in frames if f.truth["contacts"])
    change = press.image.astype(np.float64) - reference
    assert np.allclose(change[..., 0] / 0.72, change[..., 1] / 0.72, atol=2.0)   # white: channels alike
    towards = np.array([math.cos(math.radians(azimuth)), math.sin(math.radians(azimuth))])
    for contact in press.truth["contacts"]:
        u, v = np.rint(contact["pixel"]).astype(int)
        lit = change[v + int(round(3 * towards[1])), u + int(round(3 * towards[0]))].mean()
        dark = change[v - int(round(3 * towards[1])), u - int(round(3 * towards[0]))].mean()
        assert lit > dark + 5.0
    grey = reference.mean(axis=2)
    rows, cols = grey.shape
    near = grey[rows // 2 + int(60 * towards[1]), cols // 2 + int(60 * towards[0])]
    far = grey[rows // 2 - int(60 * towards[1]), cols // 2 - int(60 * towards[0])]
    assert near > far


def test_a_pressed_ball_indents_the_membrane_as_a_sphere_cap():
    """The membrane under a ball pressed d deep lies on the ball: each point pushed in along its normal by
    D sits on the sphere, the deepest by d, and along the axis D is the cap sqrt(R^2 - x^2) - (R - d)
    (not the distance inside the ball towards its centre, R - |P - C|, a ball of radius R - d)."""
    from touchroller_driver.sim import Indenter

    sensor = SimulatedSensor(load_scene("ball_presses", effects=[]), seed=0)
    radius, depth, alpha = 4e-3, 6e-4, 0.03
    membrane = sensor.membrane_point(0.002, alpha)
    dist = float(np.hypot(membrane[1], membrane[2])) + radius - depth
    centre = np.array([0.002, dist * math.sin(alpha), dist * math.cos(alpha)])
    state = RollerState(depth=-1.0, indenters=(Indenter(tuple(centre), radius),))
    D = sensor.render_layers(state)["indentation"].astype(np.float64)
    points = sensor._points.astype(np.float64)
    inside = D > 1e-5
    assert inside.sum() > 200
    normal = points[inside] * np.array([0.0, 1.0, 1.0])
    normal /= np.linalg.norm(normal, axis=1, keepdims=True)
    moved = points[inside] - D[inside][:, None] * normal
    assert np.abs(np.linalg.norm(moved - centre, axis=1) - radius).max() < 2e-7
    assert D.max() == pytest.approx(depth, abs=5e-6)
    # along the axis through the press (the membrane points at the ball's angle): the cap
    angles = np.arctan2(points[..., 1], points[..., 2])
    line = inside & (np.abs(angles - alpha) < 2e-3)
    x = points[line][:, 0] - centre[0]
    arc = (angles[line] - alpha) * np.hypot(membrane[1], membrane[2])   # <= 0.1 mm off the line: in rho
    assert line.sum() > 10 and np.abs(x).max() > 1.2e-3
    cap = np.sqrt(radius**2 - x**2 - arc**2) - (radius - depth)
    assert np.abs(D[line] - cap).max() < 2e-6
