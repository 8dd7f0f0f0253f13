"""The bare-camera chessboard scene (intrinsic calibration)."""
import numpy as np

from touchroller_driver.sim import SimulatedSensor, load_scene


def test_chessboard_corners_in_view():
    sensor = SimulatedSensor(load_scene("calibration_chessboard", effects=[], **{"motion.views": 4}), seed=0)
    frames = list(sensor.frames())
    assert len(frames) == 4
    for frame in frames:
        corners = np.array(frame.truth["board"]["corners_px"])
        assert corners.shape == (49, 2)
        assert sensor.camera.in_image(corners, margin=5).all()
        # an inner corner: the four pixels diagonally around it alternate dark/bright
        u, v = np.round(corners[24]).astype(int)
        grey = frame.image[:, :, 0].astype(int)
        a, b = grey[v - 3, u - 3] + grey[v + 3, u + 3], grey[v - 3, u + 3] + grey[v + 3, u - 3]
        assert abs(a - b) > 150


def central_frames(views: int = 4, **overrides):
    scene = load_scene("calibration_chessboard", "central", **{"motion.views": views, **overrides})
    sensor = SimulatedSensor(scene, seed=1)
    return sensor, list(sensor.frames())


def test_central_variant_keeps_the_boards_in_the_central_half():
    sensor, frames = central_frames()
    corners = np.concatenate([np.array(f.truth["board"]["corners_px"]) for f in frames])
    size = np.array([sensor.camera.width, sensor.camera.height])
    assert np.all(corners > 0.25 * size) and np.all(corners < 0.75 * size)


def test_pixels_integrate_over_their_area_so_corners_are_where_the_truth_says():
    """Point-sampling the board's edges (one ray per pixel) moved OpenCV's subpixel corners by ~0.1 px
    RMS on small boards; a pixel integrates the light that falls on it."""
    from touchroller_perception import calibration as cal

    def corner_error(frames) -> float:
        errors = []
        for frame in frames:
            found = cal.find_chessboard(frame.image, cal.Chessboard())
            truth = np.array(frame.truth["board"]["corners_px"])
            nearest = np.linalg.norm(found.corners[:, None] - truth[None], axis=-1).argmin(axis=1)
            errors.append(found.corners - truth[nearest])
        return float(np.sqrt(np.mean(np.concatenate(errors) ** 2)))

    _, frames = central_frames()
    _, point_sampled = central_frames(**{"motion.supersample": 1})
    assert corner_error(frames) < 0.04 < corner_error(point_sampled)
