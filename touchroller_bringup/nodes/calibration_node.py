"""The TouchRoller calibration node: capture frames on request, solve, and hand the result over.

Thin ROS shell around `touchroller_perception.calibration`:

* subscribes `image_topic` (default `image_raw`, relative to the node's namespace, `touchroller` by
  default) and keeps the latest frame;
* `~/capture` stores the latest frame (a new one each time) as a view of the current `target`:
  `chessboard` (intrinsics), `hemispheres` (theta and d), `reference` (a no-contact frame,
  subtracted from the hemisphere images) or `dark` (a no-contact frame with the sensor's lights
  off: the row balance then measures imprints against the light alone);
* `~/solve` calibrates from what was captured (intrinsics first if there are chessboard views, then
  theta and d), sets the result on the running perception node through
  `<perception_node>/set_parameters_atomically` (a relative name: the perception node in the same
  namespace), writes the calibration YAML to `output_path`,
  updates its own geometry parameters, and, when it solved the intrinsics, writes them as a
  camera_calibration_parsers YAML beside it (`cal.yaml` -> `cal.camera_info.yaml`) and hands them to the
  camera node through `<camera_node>/set_camera_info` (`sensor_msgs/srv/SetCameraInfo`, as ROS's
  cameracalibrator commits a calibration): the camera node is the graph's one publisher of `camera_info`;
* `~/reset` drops all captured frames;
* `~/solve_photometric` makes the photometric model (docs/height.md) from the captured `ball` presses
  (target `ball`: one ball of radius `photometric.ball_radius` pressed per frame) and the `reference`
  frames, and writes it to `photometric.output_path`.

While chessboard views are captured, the node tells the user what they cover, as ROS
camera_calibration does: X / Y / size / skew progress bars and the image corners, in each
`~/capture` reply (one line), in the log (the bars), and on `/diagnostics` (status
"<node>: chessboard coverage", WARN until the bars are full and every image corner has been seen).

The services are `std_srvs/srv/Trigger` (`ros2 service call /touchroller/calibration/solve
std_srvs/srv/Trigger`).
"""
from __future__ import annotations

import math
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np
from rcl_interfaces.msg import SetParametersResult
from rcl_interfaces.srv import SetParametersAtomically
from rclpy.node import Node
from rclpy.parameter import Parameter
from rclpy.qos import qos_profile_sensor_data
from sensor_msgs.msg import Image
from sensor_msgs.srv import SetCameraInfo

from touchroller_bringup import names
from touchroller_bringup.camera_info_files import (
    DEFAULT_CAMERA_NAME,
    CameraCalibration,
    camera_info_path_for,
    write_camera_info,
)
from touchroller_bringup.image_conversion import image_to_array, stamp_to_ns
from touchroller_bringup.ros_diagnostics import OK, WARN, DiagnosticsPublisher, Status
from touchroller_bringup.ros_params import (
    ConfigParameters,
    GeometryParameters,
    check_start_up,
    declare,
    declare_frame_prefix,
)
from touchroller_bringup.ros_services import call_with_deadline, create_trigger_service
from touchroller_perception import calibration as cal
from touchroller_perception import height
from touchroller_perception.files import atomic_write
from touchroller_perception.geometry import CameraModel

TARGETS = ("chessboard", "hemispheres", "reference", "dark", "ball")
#: how long the solved calibration's calls to the camera and perception nodes wait for their answer
REMOTE_TIMEOUT_S = 10.0

# parameter -> (default, description, min, max)
SETTINGS: dict[str, tuple[Any, str, float | None, float | None]] = {
    "image_topic": (names.IMAGE, "Image topic the captures are taken from (relative: in the node's namespace)",
                    None, None),
    "target": ("hemispheres", f"What ~/capture stores: {', '.join(TARGETS)}", None, None),
    "perception_node": (names.PERCEPTION_NODE, "Node whose geometry parameters ~/solve sets (relative: in "
                        "the node's namespace; '' = none)", None, None),
    "camera_node": (names.CAMERA_NODE, "Camera node whose <camera_node>/set_camera_info receives solved intrinsics "
                    "(relative: in the node's namespace; '' = none)", None, None),
    "output_path": ("touchroller_calibration.yaml", "Calibration YAML written by ~/solve ('' = none); solved "
                    "intrinsics also go to NAME.camera_info.yaml beside it (camera_calibration_parsers' YAML)",
                    None, None),
    "row_balance": (True, "Correct each press for the frame's shift along y from the rows' imprint strengths "
                          "(applied only when the presses show it)", None, None),
    "intrinsics.distortion": ("auto", "Distortion model: auto (k1, k2, p1, p2, plus k3 when held-out views need "
                                      f"it) or one of {', '.join(cal.DISTORTION_MODELS)}", None, None),
    "intrinsics.corners": ("fronto_parallel", "Chessboard corners: fronto_parallel (refined on the board's plane "
                                              "with the lens of a first fit) or image (as found in the image)",
                           None, None),
    "photometric.ball_radius": (0.002, "Radius of the ball pressed for ~/solve_photometric, m", 1e-4, 0.05),
    "photometric.output_path": ("touchroller_photometric.npz", "Photometric model written by ~/solve_photometric",
                                None, None),
    "imprints.centre": ("symmetric", "Imprint centres: symmetric (corrected for light from one side), shading "
                        "(also for the slopes a low light leaves in shadow) or centroid",
                        None, None),
    "imprints.strength": ("auto", "Imprint strengths for the row balance: auto (relative given a dark capture, "
                                  "else size), relative (energy relative to the light), size (extent, which no "
                                  "light level changes) or absolute", None, None),
}
# parameter -> (Chessboard field, description, min, max); a change re-detects the captured chessboards
BOARD_PARAMETERS: dict[str, tuple[str, str, float, float]] = {
    "board.columns": ("columns", "Chessboard inner corners along a row", 2, 100),
    "board.rows": ("rows", "Chessboard inner corners along a column", 2, 100),
    "board.square": ("square", "Chessboard square side, m", 1e-4, 1.0),
}
# parameter -> (HemisphereFrame field, description, min, max)
FRAME_PARAMETERS: dict[str, tuple[str, str, float, float]] = {
    "frame.rows": ("rows", "Hemisphere frame rows (across the roller axis)", 2, 100),
    "frame.columns": ("columns", "Hemisphere frame columns (along the roller axis)", 2, 100),
    "frame.pitch_x": ("pitch_x", "Hemisphere centre distance along the axis, m", 1e-4, 0.1),
    "frame.pitch_y": ("pitch_y", "Hemisphere centre distance across the axis, m", 1e-4, 0.1),
    "frame.hemisphere_radius": ("hemisphere_radius", "Hemisphere radius, m", 1e-5, 0.01),
    "frame.press_depth": ("press_depth", "Depth the hemispheres press into the membrane at the contact line, m",
                          0.0, 0.01),
}
#: string parameters and the values they accept
CHOICES: dict[str, tuple[str, ...]] = {
    "target": TARGETS,
    "intrinsics.distortion": ("auto", *cal.DISTORTION_MODELS),
    "intrinsics.corners": cal.CORNER_METHODS,
    "imprints.centre": cal.CENTRE_ESTIMATORS,
    "imprints.strength": cal.STRENGTH_MEASURES,
}


class CalibrationNode(Node):
    def __init__(self, node_name: str = names.CALIBRATION_NODE, **node_kwargs: Any) -> None:
        node_kwargs.setdefault("namespace", names.DEFAULT_NAMESPACE)
        super().__init__(node_name, **node_kwargs)
        self.frame_prefix = declare_frame_prefix(self)
        self.geometry = GeometryParameters(self)
        for name, (default, description, lo, hi) in SETTINGS.items():
            declare(self, name, default, description, min=lo, max=hi)
        # the chessboard and the hemisphere frame: frozen configs bound to their tables (checked whole on set)
        self.board_parameters = ConfigParameters(self, cal.Chessboard(), BOARD_PARAMETERS,
                                                 on_change=lambda _: self._redetect_boards())
        self.frame_parameters = ConfigParameters(self, cal.HemisphereFrame(), FRAME_PARAMETERS)
        self.add_on_set_parameters_callback(self._validate)
        self.add_post_set_parameters_callback(self._apply)
        check_start_up(self, self._validate)   # the start-up values pass the checks a change does

        self.captures: dict[str, list[np.ndarray]] = {t: [] for t in TARGETS}
        self.board_corners: list[np.ndarray] = []      # corners of each captured chessboard view
        self.latest: tuple[int, np.ndarray] | None = None
        self._captured_stamps: set[int] = set()
        self.last_result: str = ""
        self.remote_result: SetParametersResult | None = None
        self.camera_result: tuple[bool, str] | None = None   # what the camera node answered to set_camera_info
        self.image_sub = None
        self._subscribe(str(self.get_parameter("image_topic").value))
        for name, action in ((names.CAPTURE, self.capture), (names.SOLVE, self.solve), (names.RESET, self.reset),
                             (names.SOLVE_PHOTOMETRIC, self.solve_photometric)):
            create_trigger_service(self, f"~/{name}", action)
        self._remote_client = None
        self._camera_client = None
        self.diagnostics = DiagnosticsPublisher(self, f"{self.get_name()}: chessboard coverage")
        self.diagnostics.add(self._coverage_status)

    # ------------------------------------------------------------------ parameters
    def _validate(self, parameters: Sequence[Parameter]) -> SetParametersResult:
        problem = self._problem(parameters)
        return SetParametersResult(successful=not problem, reason=problem)

    def _problem(self, parameters: Sequence[Parameter]) -> str:
        """Why these values cannot be used ("" when they can): choices, names and the output path (the board
        and the hemisphere frame are checked by their ConfigParameters)."""
        from rclpy.validate_node_name import validate_node_name
        from rclpy.validate_topic_name import validate_topic_name

        for p in parameters:
            if p.name in CHOICES and p.value not in CHOICES[p.name]:
                return f"{p.name} must be one of {', '.join(CHOICES[p.name])}, got {p.value!r}"
            try:
                if p.name == "image_topic":
                    if not str(p.value).strip():
                        return "image_topic must not be empty"
                    validate_topic_name(str(p.value))
                elif p.name in ("perception_node", "camera_node") and str(p.value):
                    validate_node_name(str(p.value).rsplit("/", 1)[-1])
            except Exception as exc:  # noqa: BLE001 - rclpy's InvalidTopicNameException and friends
                return f"{p.name} {p.value!r} is not a valid ROS name: {' '.join(str(exc).split())}"
            if p.name == "output_path" and str(p.value):
                path = Path(str(p.value))
                if path.exists() and not path.is_file():
                    return f"output_path {path} exists and is not a regular file; give a YAML file name"
        return ""

    def _apply(self, parameters: Sequence[Parameter]) -> None:
        for p in parameters:
            if p.name == "image_topic":
                self._subscribe(str(p.value))
            elif p.name == "perception_node":
                self._remote_client = None
            elif p.name == "camera_node":
                self._camera_client = None

    def _subscribe(self, topic: str) -> None:
        if self.image_sub is not None:
            self.destroy_subscription(self.image_sub)
        # sensor-data QoS (best effort, depth 5) matches reliable and best-effort publishers
        self.image_sub = self.create_subscription(Image, topic, self._on_image, qos_profile_sensor_data)

    def _intrinsics_config(self) -> cal.IntrinsicsConfig:
        distortion = str(self.get_parameter("intrinsics.distortion").value)
        return cal.IntrinsicsConfig(board=self.board_parameters.config, distortion=distortion,
                                    corners=str(self.get_parameter("intrinsics.corners").value))

    def _extrinsics_config(self) -> cal.ExtrinsicsConfig:
        detector = cal.ImprintDetectorConfig(centre=str(self.get_parameter("imprints.centre").value),
                                             strength=str(self.get_parameter("imprints.strength").value))
        return cal.ExtrinsicsConfig(frame=self.frame_parameters.config, detector=detector,
                                    balance_rows=bool(self.get_parameter("row_balance").value))

    # ------------------------------------------------------------------ images and services
    def _on_image(self, msg: Image) -> None:
        try:
            image = image_to_array(msg)
        except ValueError as exc:
            self.get_logger().warning(f"dropping malformed image: {exc}", throttle_duration_sec=5.0)
            return
        stamp = stamp_to_ns(msg.header.stamp)
        self.latest = (stamp, np.array(image, copy=True))

    def capture(self) -> tuple[bool, str]:
        target = str(self.get_parameter("target").value)
        topic = self.get_parameter("image_topic").value
        if self.latest is None:
            return False, f"no image received on {topic} yet"
        stamp, image = self.latest
        if stamp in self._captured_stamps:
            return False, f"no new image on {topic} since the last capture"
        problem = self._check(target, image)
        if problem:
            return False, f"not captured: {problem}"
        self._captured_stamps.add(stamp)
        self.captures[target].append(image)
        message = f"captured {target} image {len(self.captures[target])}"
        if target == "chessboard":
            coverage = self.coverage()
            self.get_logger().info("\n".join([message, *coverage.lines(), *coverage.warnings()]))
            message += f"; {coverage.one_line()}"
        return True, message

    def coverage(self) -> cal.BoardCoverage:
        """What the captured chessboard views cover (bars, image corners, map)."""
        board = self.board_parameters.config
        views = self.captures["chessboard"]
        size = (views[0].shape[1], views[0].shape[0]) if views else (self.geometry.model.width,
                                                                      self.geometry.model.height)
        return cal.board_coverage(self.board_corners, board.columns, board.rows, size)

    def _coverage_status(self) -> Status:
        if not self.board_corners:
            return Status(OK, "no chessboard views captured", {"views": 0})
        coverage = self.coverage()
        values: dict[str, Any] = {"views": coverage.views}
        values.update({bar.name: round(bar.progress, 3) for bar in coverage.bars})
        values.update({"image_corners_seen": sum(coverage.corners_seen), "reach": round(coverage.reach, 3)})
        warnings = coverage.warnings()
        return Status(WARN if warnings else OK, "; ".join(warnings) or "views cover the image", values)

    def _redetect_boards(self) -> None:
        board = self.board_parameters.config
        found = (cal.find_chessboard(image, board).corners for image in self.captures["chessboard"])
        self.board_corners = [corners for corners in found if corners is not None]

    def _check(self, target: str, image: np.ndarray) -> str | None:
        """Why the frame is useless as a view of `target` (checked at capture, so the user can press
        again at once), or None. A usable chessboard's corners are kept for the coverage."""
        try:
            if target == "chessboard":
                detection = cal.find_chessboard(image, self.board_parameters.config)
                if detection.corners is not None:
                    self.board_corners.append(detection.corners)
                return detection.reason
            if target == "hemispheres":
                detection = cal.find_imprints(image, self.frame_parameters.config, self._extrinsics_config().detector,
                                              reference=self._reference())
                if detection.found == 0:
                    return "no imprints: is the roller pressed on the frame?"
                return detection.reason
            if target == "ball":
                reference = self._reference()
                if reference is None:
                    return "capture a no-contact reference first (target 'reference')"
                height.find_press(image, reference)
        except ValueError as exc:   # CalibrationError is one
            return str(exc)
        return None

    def _reference(self, target: str = "reference") -> np.ndarray | None:
        references = self.captures[target]
        return np.median(np.stack(references), axis=0).astype(np.uint8) if references else None

    def reset(self) -> tuple[bool, str]:
        for frames in self.captures.values():
            frames.clear()
        self.board_corners.clear()
        self._captured_stamps.clear()
        return True, "dropped all captured images"

    def solve(self) -> tuple[bool, str]:
        chessboards, presses = self.captures["chessboard"], self.captures["hemispheres"]
        if not chessboards and not presses:
            return False, ("nothing captured: set target to 'chessboard' or 'hemispheres' and call ~/capture "
                           "once per view")
        camera = self.geometry.model
        intrinsics: cal.IntrinsicsResult | None = None
        extrinsics: cal.ExtrinsicsResult | None = None
        try:
            if chessboards:
                intrinsics = cal.calibrate_intrinsics(chessboards, self._intrinsics_config(), prior=camera)
                camera = intrinsics.camera
            if presses:
                extrinsics = cal.calibrate_extrinsics(
                    presses, camera, self._extrinsics_config(), reference=self._reference(),
                    dark=self._reference("dark"),
                    intrinsics_sigma=self._intrinsics_sigma(intrinsics),
                    intrinsics_covariance=intrinsics.covariance if intrinsics is not None else None)
                camera = extrinsics.camera
        except cal.CalibrationError as exc:
            return False, f"calibration failed: {exc}"
        notes = [r.summary() for r in (intrinsics, extrinsics) if r is not None]
        if intrinsics is not None:
            notes += [f"warning: {w}" for w in intrinsics.warnings()]
            self.get_logger().info("\n".join([f"solved with distortion model {intrinsics.distortion_model}",
                                               *intrinsics.coverage.lines()]))
            for warning in intrinsics.warnings():
                self.get_logger().warning(warning)
        if extrinsics is not None:     # the terms chosen by held-out prediction, and their margins
            self.get_logger().info("\n".join([f"extrinsics: {extrinsics.method}",
                                               *(f"term {c.line()}" for c in extrinsics.choices)]))
            for warning in extrinsics.warnings:
                self.get_logger().warning(warning)
        notes.append(self._write(camera, intrinsics, extrinsics))
        notes.append(self._send(camera, intrinsics is not None))
        if intrinsics is not None:
            notes.append(self._send_camera_info(camera))
        self.set_parameters([Parameter(name, value=value) for name, value in _changed(camera, intrinsics is not None)])
        self.last_result = "; ".join(n for n in notes if n)
        return True, self.last_result

    def solve_photometric(self) -> tuple[bool, str]:
        """The photometric model (colour -> slope) from the captured ball presses and reference: each press
        labelled by `find_press`, its pixel size from the node's camera model, written to
        photometric.output_path (docs/height.md)."""
        reference, balls = self._reference(), self.captures["ball"]
        if reference is None or not balls:
            return False, ("nothing to solve: capture a no-contact frame (target 'reference') and ball presses "
                           "(target 'ball')")
        camera = self.geometry.model
        try:
            presses = []
            for k, image in enumerate(balls):
                u, v, r = height.find_press(image, reference)
                presses.append(height.BallPress(image, u, v, r, height.pixel_size_at(camera, u, v), str(k),
                                                float(camera.radius)))
            result = height.calibrate_photometric(
                presses, reference, float(self.get_parameter("photometric.ball_radius").value))
        except ValueError as exc:
            return False, f"photometric calibration failed: {exc}"
        path = str(self.get_parameter("photometric.output_path").value)
        note = ""
        if path:
            try:
                with atomic_write(path, "wb") as stream:
                    result.model.save_to(stream)
                note = f"; wrote {path}"
            except OSError as exc:
                note = f"; could not write {path}: {exc.strerror}"
        self.last_result = result.summary() + note
        return True, self.last_result

    def _intrinsics_sigma(self, intrinsics: cal.IntrinsicsResult | None) -> dict[str, float]:
        """The intrinsics' sigmas: from this solve, else from the calibration file an earlier solve wrote."""
        if intrinsics is not None:
            return intrinsics.sigma
        path = str(self.get_parameter("output_path").value)
        if not path or not Path(path).exists():
            return {}
        try:
            extras = cal.read_calibration_extras(path)
        except (OSError, ValueError):
            return {}
        prefix = "calibration.sigma."
        return {k[len(prefix):]: float(v) for k, v in extras.items() if k.startswith(prefix)}

    # ------------------------------------------------------------------ outputs
    def _write(self, camera: CameraModel, intrinsics: Any, extrinsics: Any) -> str:
        path = str(self.get_parameter("output_path").value)
        if not path:
            return ""
        written = [path]
        try:
            keep = cal.read_calibration_extras(path) if intrinsics is None and Path(path).exists() else {}
            cal.write_calibration(path, camera, intrinsics=intrinsics, extrinsics=extrinsics, keep=keep)
            if intrinsics is not None:   # the intrinsics as ROS camera drivers read them (camera_info_url)
                info_path = camera_info_path_for(path)
                write_camera_info(info_path, CameraCalibration.from_model(camera, DEFAULT_CAMERA_NAME))
                written.append(str(info_path))
        except (OSError, ValueError) as exc:
            return f"could not write {path}: {exc}"
        return f"wrote {' and '.join(written)}"

    def _send_camera_info(self, camera: CameraModel) -> str:
        """The solved intrinsics to `<camera_node>/set_camera_info` (the camera node publishes camera_info)."""
        name = str(self.get_parameter("camera_node").value).strip().rstrip("/")
        if not name:
            return ""
        service = self.resolve_service_name(f"{name}/{names.SET_CAMERA_INFO}")
        if self._camera_client is None or self._camera_client.srv_name != service:
            self._camera_client = self.create_client(SetCameraInfo, service)
        if not self._camera_client.service_is_ready():
            return f"{service} is not available: camera_info not updated"
        request = SetCameraInfo.Request()
        for field, value in cal.camera_info_fields(camera).items():
            setattr(request.camera_info, field, value)
        self.camera_result = None
        call_with_deadline(self, self._camera_client, request, REMOTE_TIMEOUT_S, self._on_camera_result)
        return f"sending the intrinsics to {service}"

    def _on_camera_result(self, response: Any | None, why: str) -> None:
        self.camera_result = (False, why or "no response") if response is None else (response.success,
                                                                                      response.status_message)
        if self.camera_result[0]:   # one severity per call site: rclpy's logger refuses a change
            self.get_logger().info(f"set_camera_info: {self.camera_result[1]}")
        else:
            self.get_logger().error(f"set_camera_info: {self.camera_result[1]}")

    def _send(self, camera: CameraModel, with_intrinsics: bool) -> str:
        name = str(self.get_parameter("perception_node").value).strip().rstrip("/")
        if not name:
            return ""
        service = self.resolve_service_name(f"{name}/set_parameters_atomically")
        name = service.removesuffix("/set_parameters_atomically")   # the node's full name, for messages
        if self._remote_client is None or self._remote_client.srv_name != service:
            self._remote_client = self.create_client(SetParametersAtomically, service)
        if not self._remote_client.service_is_ready():
            return f"{service} is not available: parameters not set on {name}"
        request = SetParametersAtomically.Request()
        request.parameters = [Parameter(n, value=v).to_parameter_msg() for n, v in _changed(camera, with_intrinsics)]
        self.remote_result = None
        call_with_deadline(self, self._remote_client, request, REMOTE_TIMEOUT_S,
                           lambda response, why: self._on_remote_result(response, why, name))
        return f"setting {len(request.parameters)} parameters on {name}"

    def _on_remote_result(self, response: Any | None, why: str, name: str) -> None:
        self.remote_result = response.result if response is not None else SetParametersResult(
            successful=False, reason=why or "no response")
        verdict = "rejected the calibration" if response is not None else "did not take the calibration"
        if self.remote_result.successful:
            self.get_logger().info(f"{name} accepted the calibration")
        else:   # one severity per call site: rclpy's logger refuses a change
            self.get_logger().error(f"{name} {verdict}: {self.remote_result.reason}")


def _changed(camera: CameraModel, with_intrinsics: bool) -> list[tuple[str, Any]]:
    params = camera.to_params()
    names = ["extrinsics.theta", "extrinsics.d"]
    if with_intrinsics:
        names += ["camera.fx", "camera.fy", "camera.cx", "camera.cy", "camera.distortion",
                  "camera.width", "camera.height"]
    return [(n, [float(v) for v in params[n]] if n == "camera.distortion" else params[n]) for n in names
            if not (isinstance(params[n], float) and not math.isfinite(params[n]))]


def main(args: list[str] | None = None) -> None:
    from touchroller_bringup.ros_main import run_node

    run_node(CalibrationNode, args)


if __name__ == "__main__":
    main()
