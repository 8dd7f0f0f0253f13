"""camera_calibration_parsers' YAML and camera_info_manager's URLs, without ROS."""
from __future__ import annotations

import math
from pathlib import Path

import pytest
import yaml
from hypothesis import given
from hypothesis import strategies as st

from touchroller_bringup.camera_info_files import (
    CameraCalibration,
    CameraInfoError,
    camera_info_path_for,
    camera_name_problem,
    read_camera_info,
    resolve_url,
    url_path,
    write_camera_info,
)
from touchroller_perception.geometry import CameraModel

# what ROS's cameracalibrator commits through camera_info_manager (camera_calibration_parsers' writer)
ROS_WRITTEN = """image_width: 640
image_height: 480
camera_name: narrow_stereo
camera_matrix:
  rows: 3
  cols: 3
  data: [430.15, 0, 311.71, 0, 430.6, 221.06, 0, 0, 1]
distortion_model: plumb_bob
distortion_coefficients:
  rows: 1
  cols: 5
  data: [-0.337, 0.1114, 1e-05, -0.0002, 0]
rectification_matrix:
  rows: 3
  cols: 3
  data: [1, 0, 0, 0, 1, 0, 0, 0, 1]
projection_matrix:
  rows: 3
  cols: 4
  data: [357.5, 0, 306.4, 0, 0, 385.2, 222.0, 0, 0, 0, 1, 0]
"""


def test_a_file_ros_wrote_is_read_with_its_own_projection_and_yaml_cpp_style_numbers(tmp_path):
    path = tmp_path / "narrow_stereo.yaml"
    path.write_text(ROS_WRITTEN)
    calibration = read_camera_info(path)
    assert calibration.camera_name == "narrow_stereo" and (calibration.width, calibration.height) == (640, 480)
    assert calibration.d[2] == 1e-05            # PyYAML reads 1e-05 as a string: still the number
    assert calibration.p[0] == 357.5            # P is the file's, not [K | 0]
    params = calibration.model_parameters()
    assert params["camera.fx"] == 430.15 and params["camera.distortion"] == [-0.337, 0.1114, 1e-05, -0.0002, 0.0]


def test_missing_model_and_name_default_as_the_parser_reads_them():
    dropped = ("camera_name", "distortion_model")
    text = "\n".join(line for line in ROS_WRITTEN.splitlines() if not line.startswith(dropped))
    calibration = CameraCalibration.from_yaml(text)
    assert calibration.camera_name == "unknown" and calibration.distortion_model == "plumb_bob"


finite = st.floats(min_value=-1e6, max_value=1e6, allow_nan=False, allow_infinity=False)


@given(st.lists(finite, min_size=9, max_size=9), st.lists(finite, min_size=5, max_size=5),
       st.lists(finite, min_size=12, max_size=12), st.integers(1, 10000), st.integers(1, 10000))
def test_the_yaml_round_trips_every_number_exactly(k, d, p, width, height):
    calibration = CameraCalibration("cam_1", width, height, tuple(k), "plumb_bob", tuple(d), p=tuple(p))
    again = CameraCalibration.from_yaml(calibration.to_yaml())
    assert again == calibration
    # and the text is what camera_calibration_parsers' reader wants: numbers, not strings, for yaml-cpp too
    doc = yaml.safe_load(calibration.to_yaml())
    numbers = doc["camera_matrix"]["data"] + doc["distortion_coefficients"]["data"]
    assert all(isinstance(v, float | int) for v in numbers)


def test_write_then_read_is_the_model_and_goes_beside_the_parameters_file(tmp_path):
    model = CameraModel(fx=612.25, fy=611.5, cx=318.0, cy=241.5, distortion=(0.1, -0.02, 1e-4, 0.0, 0.003))
    path = camera_info_path_for(tmp_path / "cal.yaml")
    assert path == tmp_path / "cal.camera_info.yaml"
    write_camera_info(tmp_path / "new" / "folder" / path.name, CameraCalibration.from_model(model, "touchroller"))
    calibration = read_camera_info(tmp_path / "new" / "folder" / path.name)
    assert calibration.matches(model)
    assert CameraModel.from_params({**model.to_params(), **calibration.model_parameters()}) == model
    assert calibration.p == (612.25, 0.0, 318.0, 0.0, 0.0, 611.5, 241.5, 0.0, 0.0, 0.0, 1.0, 0.0)


@pytest.mark.parametrize("edit, message", [
    (lambda d: d.pop("camera_matrix"), "camera_matrix is missing"),
    (lambda d: d["camera_matrix"].update(rows=2), "camera_matrix must be 3 x 3"),
    (lambda d: d["projection_matrix"]["data"].pop(), "projection_matrix.data must be a list of 12 numbers"),
    (lambda d: d["distortion_coefficients"]["data"].__setitem__(0, "k1"), "holds 'k1', not a number"),
    (lambda d: d.update(image_width="640"), "image_width must be an integer"),
])
def test_a_malformed_file_is_one_line_naming_the_field(tmp_path, edit, message):
    doc = yaml.safe_load(ROS_WRITTEN)
    edit(doc)
    path = tmp_path / "bad.yaml"
    path.write_text(yaml.safe_dump(doc))
    with pytest.raises(CameraInfoError, match=message) as info:
        read_camera_info(path)
    assert "\n" not in str(info.value) and str(path) in str(info.value)


@pytest.mark.parametrize("edit, message", [
    (dict(distortion_model="equidistant", d=(0.1, 0.0, 0.0, 0.0)), "'equidistant' is not supported"),
    (dict(d=(0.1, 0.0, 0.0, 0.0)), "5 distortion coefficients"),
    (dict(k=(500.0, 2.0, 320.0, 0.0, 500.0, 240.0, 0.0, 0.0, 1.0)), "no skew"),
    (dict(k=(math.nan, 0.0, 320.0, 0.0, 500.0, 240.0, 0.0, 0.0, 1.0)), "not finite"),
])
def test_what_the_camera_model_cannot_hold_is_refused(edit, message):
    base = dict(camera_name="c", width=640, height=480, k=(500.0, 0.0, 320.0, 0.0, 500.0, 240.0, 0.0, 0.0, 1.0),
                distortion_model="plumb_bob", d=(0.0,) * 5)
    with pytest.raises(CameraInfoError, match=message):
        CameraCalibration(**{**base, **edit}).model_parameters()


def test_urls_resolve_as_camera_info_manager_resolves_them(tmp_path):
    env = {"ROS_HOME": str(tmp_path / "ros"), "HOME": "/home/u"}
    assert url_path("file://${ROS_HOME}/camera_info/${NAME}.yaml", "left", env) == \
        tmp_path / "ros" / "camera_info" / "left.yaml"
    assert resolve_url("file://${ROS_HOME}/x.yaml", "c", {"HOME": "/home/u"}) == "file:///home/u/.ros/x.yaml"
    assert url_path("FILE:///tmp/a.yaml", "c", env) == Path("/tmp/a.yaml")
    assert url_path("", "c", env) is None
    share = tmp_path / "prefix"
    (share / "share" / "ament_index" / "resource_index" / "packages").mkdir(parents=True)
    (share / "share" / "ament_index" / "resource_index" / "packages" / "my_cams").touch()
    assert url_path("package://my_cams/calib/${NAME}.yaml", "left", {"AMENT_PREFIX_PATH": str(share)}) == \
        share / "share" / "my_cams" / "calib" / "left.yaml"


@pytest.mark.parametrize("url, message", [
    ("/tmp/cam.yaml", "is not a file:///path.yaml or package://PACKAGE/path.yaml URL"),
    ("http://example.com/cam.yaml", "is not a file:///path.yaml"),
    ("file://cam.yaml", "needs an absolute path"),
    ("package://nowhere_pkg/cam.yaml", "package 'nowhere_pkg' of the camera_info_url is not found"),
    ("package://only_a_package", "expected package://PACKAGE/path.yaml"),
    ("file:///tmp/${USER}.yaml", r"unknown substitution \$\{USER\}"),
])
def test_a_bad_url_is_one_line(url, message):
    with pytest.raises(CameraInfoError, match=message) as info:
        url_path(url, "c", {"AMENT_PREFIX_PATH": ""})
    assert "\n" not in str(info.value)


def test_camera_names_follow_camera_info_manager():
    assert camera_name_problem("left_cam_2") == ""
    assert "letters, digits and _" in camera_name_problem("left-cam")
    assert camera_name_problem("")
