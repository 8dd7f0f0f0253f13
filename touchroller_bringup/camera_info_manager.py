"""camera_info_manager's conventions on a node: `camera_name`, `camera_info_url` and `~/set_camera_info`.

The camera node owns its `sensor_msgs/CameraInfo` (the graph's one publisher of `camera_info`):

- `camera_name` (letters, digits, _) names the camera in the files and in `${NAME}` of the URL;
- `camera_info_url` (`file:///path.yaml`, `package://PACKAGE/path.yaml`, `${NAME}`, `${ROS_HOME}`: see
  `touchroller_bringup.camera_info_files`) names a camera_calibration_parsers YAML. When the file exists
  it is read at start-up (and when the URL or name changes): its intrinsics become the node's
  `camera.fx`, `camera.fy`, `camera.cx`, `camera.cy`, `camera.distortion`, `camera.width`,
  `camera.height`, and its CameraInfo (with its own R and P) is published. A file that does not exist yet
  is created by the first `~/set_camera_info`; a URL that names no file, or a file the camera model cannot
  hold (another distortion model, skew), is refused in one line (at start-up: the node does not start).
  Empty (the default): camera info from the `camera.*` parameters (P = [K | 0]);
- `~/set_camera_info` (`sensor_msgs/srv/SetCameraInfo`, as ROS's cameracalibrator and our calibration
  node call it) sets the intrinsics on the node and writes them to the URL's file, as camera_info_manager
  does; with an empty URL it sets them on the node only and says so (no hidden `~/.ros` file).

Setting a `camera.*` parameter by hand publishes that model (P = [K | 0]) from then on.
"""
from __future__ import annotations

import threading
from dataclasses import dataclass
from typing import Any

from rclpy.node import Node
from rclpy.parameter import Parameter
from sensor_msgs.srv import SetCameraInfo

from touchroller_bringup import names
from touchroller_bringup.camera_info_files import (
    DEFAULT_CAMERA_NAME,
    CameraCalibration,
    CameraInfoError,
    camera_name_problem,
    fill_camera_info,
    from_camera_info,
    read_camera_info,
    url_path,
    write_camera_info,
)
from touchroller_bringup.ros_params import ConfigParameters, GeometryParameters, ParameterField
from touchroller_perception.geometry import CameraModel

SERVICE = f"~/{names.SET_CAMERA_INFO}"


@dataclass(frozen=True)
class CameraInfoSettings:
    """Where the camera's calibration file is (`url`, may be empty) and the camera's name in it."""

    camera_name: str = DEFAULT_CAMERA_NAME
    url: str = ""


CAMERA_INFO_PARAMETERS: dict[str, ParameterField] = {
    "camera_name": ParameterField("camera_name", "Camera name in calibration files and ${NAME} of camera_info_url "
                                  "(letters, digits and _; camera_info_manager's rule)"),
    "camera_info_url": ParameterField("url", "camera_calibration_parsers YAML with the intrinsics: "
                                      "file:///path.yaml or package://PACKAGE/path.yaml (${NAME}, ${ROS_HOME}); read "
                                      "at start-up when it exists (setting camera.*), written by ~/set_camera_info; "
                                      "empty: camera info from camera.*"),
}


class CameraInfoManager:
    """Declares `camera_name` and `camera_info_url` on `node`, keeps the CameraInfo to publish in step with them
    and with `geometry`, and serves `~/set_camera_info`. Call `geometry_changed(model)` from the geometry's
    on_change, and `load()` once after the node's start-up checks. A URL or name it cannot use stops the node
    at start-up (UserError, one line) and is refused on set; a new one is loaded (`load()`) after set."""

    def __init__(self, node: Node, geometry: GeometryParameters) -> None:
        self._node = node
        self._geometry = geometry
        self._lock = threading.Lock()
        # checked whole on set and at start-up (UserError: the problem, one line); a new URL or name is loaded
        self.parameters = ConfigParameters(node, CameraInfoSettings(), CAMERA_INFO_PARAMETERS, check=self._check,
                                           on_change=lambda _: self.load(), refused="")
        self.calibration = CameraCalibration.from_model(geometry.model, self.camera_name)
        self.service = node.create_service(SetCameraInfo, SERVICE, self._set_camera_info)

    @property
    def camera_name(self) -> str:
        return self.parameters.config.camera_name

    @property
    def url(self) -> str:
        return self.parameters.config.url

    # ------------------------------------------------------------------ parameters
    def problem(self, url: str, camera_name: str) -> str:
        """Why this URL and name cannot be used ("" when they can): the name's syntax, a URL that names no file,
        a file that exists but is malformed or holds what the camera model cannot."""
        problem = camera_name_problem(camera_name)
        if problem:
            return problem
        try:
            path = url_path(url, camera_name)
            if path is not None and path.exists():
                calibration = read_camera_info(path)
                params = calibration.model_parameters()
                CameraModel.from_params({**self._geometry.model.to_params(), **params})
        except CameraInfoError as exc:
            return str(exc)
        except (TypeError, ValueError) as exc:   # the camera model refuses the values
            return f"camera info file of {url}: {exc}"
        return ""

    def _check(self, settings: CameraInfoSettings) -> None:
        problem = self.problem(settings.url, settings.camera_name)
        if problem:
            raise ValueError(problem)

    def load(self) -> CameraCalibration:
        """Read the URL's file when it exists and set its intrinsics on the node; the calibration published."""
        url, name = self.url, self.camera_name
        try:
            path = url_path(url, name)
        except CameraInfoError as exc:
            self._node.get_logger().error(str(exc))
            return self.calibration
        if path is None:
            return self.calibration
        if not path.exists():
            self._node.get_logger().warning(f"camera info file {path} does not exist yet: publishing the camera.* "
                                            "parameters until ~/set_camera_info writes it")
            return self.calibration
        try:
            calibration = read_camera_info(path)
            self._set_on_node(calibration)
        except CameraInfoError as exc:
            self._node.get_logger().error(str(exc))
            return self.calibration
        if calibration.camera_name != name:   # camera_info_manager's warning
            self._node.get_logger().warning(f"[{name}] does not match {calibration.camera_name} in file {path}")
        self._node.get_logger().info(f"camera info from {path}")
        return calibration

    def _set_on_node(self, calibration: CameraCalibration) -> None:
        """Set the calibration's intrinsics as camera.* parameters (atomically) and publish it as it is."""
        params = calibration.model_parameters()
        with self._lock:
            result = self._node.set_parameters_atomically([Parameter(n, value=v) for n, v in params.items()])
            if not result.successful:
                raise CameraInfoError(f"the camera model refuses the calibration: {result.reason}")
            self.calibration = calibration

    def geometry_changed(self, model: CameraModel) -> None:
        """camera.* changed: publish the new model, unless it is the calibration just loaded or set (its R, P)."""
        if not self.calibration.matches(model):
            self.calibration = CameraCalibration.from_model(model, self.camera_name)

    # ------------------------------------------------------------------ the service
    def _set_camera_info(self, request: Any, response: Any) -> Any:
        response.success, response.status_message = self.store(request.camera_info)
        if response.success:   # one severity per call site: rclpy's logger refuses a change
            self._node.get_logger().info(f"set_camera_info: {response.status_message}")
        else:
            self._node.get_logger().error(f"set_camera_info: {response.status_message}")
        return response

    def store(self, info: Any) -> tuple[bool, str]:
        """Set a sensor_msgs/CameraInfo on the node and write it to the URL's file: (success, message)."""
        name = self.camera_name
        try:
            calibration = from_camera_info(info, name)
            self._set_on_node(calibration)
        except CameraInfoError as exc:
            return False, f"not stored: {exc}"
        where = self._node.get_fully_qualified_name()
        try:
            path = url_path(self.url, name)
        except CameraInfoError as exc:   # refused when set; kept for a URL whose package went away since
            return False, f"stored on {where}, not saved: {exc}"
        if path is None:
            return True, (f"stored on {where} (camera.* parameters); not saved to a file: camera_info_url is empty "
                          "(set it to file:///path.yaml to keep calibrations)")
        try:
            write_camera_info(path, calibration)
        except OSError as exc:
            return False, f"stored on {where}, could not write {path}: {exc.strerror or exc}"
        return True, f"stored on {where} and written to {path}"

    def fill(self, msg: Any, stamp_ns: int, frame_id: str) -> Any:
        """A sensor_msgs/CameraInfo of the current calibration, stamped."""
        return fill_camera_info(msg, self.calibration, stamp_ns, frame_id)
