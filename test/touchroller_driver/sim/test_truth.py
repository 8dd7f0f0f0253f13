"""Ground-truth files: YAML-safe values, cameras as params files, chessboard truth."""
import math

import cv2
import numpy as np
import yaml

from touchroller_driver.sim import SimulatedSensor, load_scene
from touchroller_driver.sim.truth import plain, write_ground_truth
from touchroller_perception.geometry import CameraModel


def test_plain_makes_numpy_yaml_safe():
    value = plain({"a": np.float32(1.5), "b": np.arange(3), "c": (np.int64(2), np.bool_(True)), "d": math.nan})
    text = yaml.safe_dump(value)
    back = yaml.safe_load(text)
    assert back["a"] == 1.5 and back["b"] == [0, 1, 2] and back["c"] == [2, True] and math.isnan(back["d"])


def test_chessboard_truth_file(tmp_path):
    sensor = SimulatedSensor(load_scene("calibration_chessboard", effects=[], **{"motion.views": 3}), seed=0)
    frames = [f.truth for f in sensor.frames()]
    write_ground_truth(tmp_path, sensor, frames, dropped=[])
    doc = yaml.safe_load((tmp_path / "ground_truth.yaml").read_text())
    assert doc["board"]["pattern_size"] == [7, 7]
    assert len(doc["board"]["object_points"]) == 49
    assert len(doc["frames"]) == 3 and len(doc["frames"][0]["board"]["corners_px"]) == 49
    truth = CameraModel.from_yaml(tmp_path / "camera_truth.yaml")
    assert truth == sensor.camera
    # the truth corners are the truth camera's projection of the board (OpenCV agrees)
    rvec = np.array(doc["frames"][0]["board"]["rvec"])
    tvec = np.array(doc["frames"][0]["board"]["tvec"])
    uv, _ = cv2.projectPoints(np.array(doc["board"]["object_points"]), rvec, tvec, truth.K,
                              np.array(truth.distortion))
    np.testing.assert_allclose(uv.reshape(-1, 2), doc["frames"][0]["board"]["corners_px"], atol=1e-6)
