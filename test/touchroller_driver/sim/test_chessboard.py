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
