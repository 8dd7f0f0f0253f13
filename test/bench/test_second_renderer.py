"""The second renderer: its own geometry agrees with ours, its imprints and boards are as described."""
from __future__ import annotations

import math

import numpy as np
import pytest

from bench import second_renderer as second
from touchroller_perception.calibration import HemisphereFrame


def test_opencv_projection_agrees_with_the_camera_model():
    """The renderer projects with OpenCV, not CameraModel: both must put the membrane in the same place."""
    camera = second.TRUE_CAMERA
    points = HemisphereFrame().reference_points(camera.radius, 0.7e-3, -0.4e-3, math.radians(1.0))
    ours, valid = camera.project(points)
    assert valid.all()
    assert np.abs(second.project_points(camera, points) - ours).max() < 1e-6


def test_membrane_coordinates_invert_the_projection():
    camera = second.TRUE_CAMERA
    x, s = second.membrane_coordinates(camera)
    for u, v in ((320, 240), (5, 7), (630, 470)):
        alpha = s[v, u] / camera.radius
        point = np.array([[x[v, u], camera.radius * math.sin(alpha), camera.radius * math.cos(alpha)]])
        assert np.abs(second.project_points(camera, point)[0] - (u, v)).max() < 1e-6


def test_hertz_imprint_is_continuous_at_the_rim_and_deeper_when_pressed_harder():
    radius, approach = 1e-3, 4e-4
    a = math.sqrt(radius * approach)
    rho = np.array([a * (1 - 1e-9), a * (1 + 1e-9)])
    w, slope = second.hertz_displacement(rho, approach, radius)
    assert w[0] == pytest.approx(approach / 2, rel=1e-6) and w[1] == pytest.approx(w[0], rel=1e-6)
    assert slope[1] == pytest.approx(slope[0], rel=1e-3) and slope[0] == pytest.approx(-approach / a, rel=1e-6)
    shallow, _ = second.hertz_displacement(np.array([0.0, 2 * a]), approach / 2, radius)
    deep, _ = second.hertz_displacement(np.array([0.0, 2 * a]), approach, radius)
    assert np.all(deep > shallow)


def test_the_row_nearer_the_contact_line_presses_deeper():
    renderer = second.PressRenderer(seed=0)
    _, truth = renderer.press((0.0, 0.8e-3), 0.0, 5e-4)       # frame moved towards +y: the -y row is nearer
    assert truth.approach[:5].min() > truth.approach[5:].max()
    _, centred = renderer.press((0.0, 0.0), 0.0, 5e-4)
    assert np.allclose(centred.approach[:5], centred.approach[5:])


def test_boards_stay_in_the_central_half():
    boards = second.render_chessboards(0, 2, supersample=2)
    camera = boards.camera
    for corners in boards.corners_px:
        assert np.all(corners[:, 0] > camera.width / 4) and np.all(corners[:, 0] < 3 * camera.width / 4)
        assert np.all(corners[:, 1] > camera.height / 4) and np.all(corners[:, 1] < 3 * camera.height / 4)
    seen = second.seen_mask(boards)
    assert seen.any() and not seen[:camera.height // 4].any() and not seen[:, :camera.width // 4].any()
