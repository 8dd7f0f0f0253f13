"""Camera calibration files as ROS camera drivers keep them: camera_calibration_parsers' YAML, found through
camera_info_manager's URLs. No rclpy import (the CLI writes these files too).

The YAML (what `camera_calibration_parsers::writeCalibrationYml` writes and ROS's `cameracalibrator`
commits): `image_width`, `image_height`, `camera_name`, `camera_matrix` {rows 3, cols 3, data},
`distortion_model`, `distortion_coefficients` {rows 1, cols N, data}, `rectification_matrix` {3 x 3},
`projection_matrix` {3 x 4}. A file without `distortion_model` is plumb_bob and one without
`camera_name` is "unknown", as the parser reads them.

URLs (camera_info_manager's): `file:///absolute/path.yaml` and `package://PACKAGE/path.yaml` (the package's
share folder, looked up on AMENT_PREFIX_PATH as ament_index does), with `${NAME}` (the camera name) and
`${ROS_HOME}` (`$ROS_HOME`, else `~/.ros`) substituted. Unlike camera_info_manager an empty URL names
no file: the camera node then publishes the `camera.*` parameters (docs/design.md's contract), and
a file hidden in `~/.ros/camera_info/` never overrides the calibration a user passed.

Only the intrinsics live here; the roller's `extrinsics.theta` and `extrinsics.d` stay in the
parameters YAML (`touchroller_perception.calibration.write_calibration`).
"""
from __future__ import annotations

import math
import os
import re
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

from touchroller_perception.files import atomic_write_text

if TYPE_CHECKING:   # the CLI imports this module at start-up: the camera model (numpy) only when used
    from touchroller_perception.geometry import CameraModel

DEFAULT_CAMERA_NAME = "touchroller"
PLUMB_BOB = "plumb_bob"
IDENTITY = (1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0)
_CAMERA_NAME = re.compile(r"[A-Za-z0-9_]+\Z")
#: camera.* parameters a calibration file sets (theta and d are not in it)
INTRINSIC_PARAMETERS = ("camera.fx", "camera.fy", "camera.cx", "camera.cy", "camera.distortion",
                        "camera.width", "camera.height")


class CameraInfoError(ValueError):
    """A camera info URL or file that cannot be used (the message is one line)."""


@dataclass(frozen=True)
class CameraCalibration:
    """One camera's sensor_msgs/CameraInfo calibration fields and its name, as the YAML holds them."""

    camera_name: str
    width: int
    height: int
    k: tuple[float, ...]                 # 3 x 3, row-major
    distortion_model: str
    d: tuple[float, ...]
    r: tuple[float, ...] = IDENTITY      # 3 x 3
    p: tuple[float, ...] = ()            # 3 x 4; () = [K | 0]

    def __post_init__(self) -> None:
        if not self.p:
            k = self.k
            object.__setattr__(self, "p", (k[0], k[1], k[2], 0.0, k[3], k[4], k[5], 0.0, k[6], k[7], k[8], 0.0))
        for name, size in (("k", 9), ("r", 9), ("p", 12)):
            values = tuple(float(v) for v in getattr(self, name))
            if len(values) != size:
                raise CameraInfoError(f"{name.upper()} needs {size} numbers, got {len(values)}")
            object.__setattr__(self, name, values)
        object.__setattr__(self, "d", tuple(float(v) for v in self.d))
        object.__setattr__(self, "width", int(self.width))
        object.__setattr__(self, "height", int(self.height))

    @classmethod
    def from_model(cls, model: CameraModel, camera_name: str) -> CameraCalibration:
        """The calibration of the model's intrinsics: plumb_bob, R identity, P = [K | 0]."""
        return cls(camera_name, model.width, model.height, tuple(float(v) for v in model.K.reshape(-1)),
                   PLUMB_BOB, tuple(float(v) for v in model.distortion))

    def model_parameters(self) -> dict[str, Any]:
        """The camera.* parameters of this calibration (docs/design.md's names); CameraInfoError, one line,
        when the TouchRoller camera model cannot hold it (another distortion model, skew, a bad number)."""
        if self.distortion_model != PLUMB_BOB:
            raise CameraInfoError(f"distortion model {self.distortion_model!r} is not supported: the TouchRoller "
                                  f"camera model is OpenCV's 5-coefficient {PLUMB_BOB}")
        if len(self.d) != 5:
            raise CameraInfoError(f"{PLUMB_BOB} needs 5 distortion coefficients (k1, k2, p1, p2, k3), "
                                  f"got {len(self.d)}")
        values = (*self.k, *self.d, *self.r, *self.p)
        if not all(math.isfinite(v) for v in values):
            raise CameraInfoError("the calibration holds a number that is not finite")
        fx, skew, cx, zero1, fy, cy, zero2, zero3, one = self.k
        if skew != 0.0 or (zero1, zero2, zero3, one) != (0.0, 0.0, 0.0, 1.0):
            raise CameraInfoError("camera_matrix must be [fx 0 cx; 0 fy cy; 0 0 1] (the camera model has no skew)")
        if fx <= 0 or fy <= 0 or self.width <= 0 or self.height <= 0:
            raise CameraInfoError(f"fx, fy and the image size must be positive, got fx={fx:g} fy={fy:g} "
                                  f"{self.width}x{self.height}")
        return {"camera.fx": fx, "camera.fy": fy, "camera.cx": cx, "camera.cy": cy, "camera.distortion": list(self.d),
                "camera.width": self.width, "camera.height": self.height}

    def matches(self, model: CameraModel) -> bool:
        """Whether the model's intrinsics are this calibration's (so its own R and P still apply)."""
        try:
            mine = self.model_parameters()
        except CameraInfoError:
            return False
        theirs = model.to_params()
        return all(mine[n] == (list(theirs[n]) if n == "camera.distortion" else theirs[n]) for n in mine)

    def to_yaml(self) -> str:
        """camera_calibration_parsers' YAML (floats written so that yaml-cpp and PyYAML read them back exactly)."""
        def matrix(name: str, rows: int, cols: int, data: Sequence[float]) -> list[str]:
            numbers = ", ".join(_number(v) for v in data)
            return [f"{name}:", f"  rows: {rows}", f"  cols: {cols}", f"  data: [{numbers}]"]

        return "\n".join([f"image_width: {self.width}", f"image_height: {self.height}",
                          f"camera_name: {self.camera_name}", *matrix("camera_matrix", 3, 3, self.k),
                          f"distortion_model: {self.distortion_model}",
                          *matrix("distortion_coefficients", 1, len(self.d), self.d),
                          *matrix("rectification_matrix", 3, 3, self.r),
                          *matrix("projection_matrix", 3, 4, self.p), ""])

    @classmethod
    def from_yaml(cls, text: str, source: str = "camera info") -> CameraCalibration:
        """Parse camera_calibration_parsers' YAML; CameraInfoError naming `source` and the field, one line."""
        import yaml

        try:
            doc = yaml.safe_load(text)
        except yaml.YAMLError as exc:
            raise CameraInfoError(f"{source}: not YAML ({' '.join(str(exc).split())})") from None
        if not isinstance(doc, Mapping):
            raise CameraInfoError(f"{source}: not a camera calibration file (expected a mapping with image_width, "
                                  "camera_matrix, ...)")

        def integer(name: str) -> int:
            value = doc.get(name)
            if isinstance(value, bool) or not isinstance(value, int):
                raise CameraInfoError(f"{source}: {name} must be an integer, got {value!r}")
            return value

        def matrix(name: str, rows: int | None, cols: int | None) -> tuple[float, ...]:
            node = doc.get(name)
            if not isinstance(node, Mapping):
                raise CameraInfoError(f"{source}: {name} is missing (a mapping with rows, cols and data)")
            shape = (node.get("rows"), node.get("cols"))
            want = (rows if rows is not None else shape[0], cols if cols is not None else shape[1])
            if not all(isinstance(n, int) and not isinstance(n, bool) and n >= 0 for n in shape) or shape != want:
                raise CameraInfoError(f"{source}: {name} must be {want[0]} x {want[1]}, got rows {shape[0]!r} cols "
                                      f"{shape[1]!r}")
            data = node.get("data")
            if not isinstance(data, list) or len(data) != shape[0] * shape[1]:
                raise CameraInfoError(f"{source}: {name}.data must be a list of {shape[0] * shape[1]} numbers")
            values = []
            for v in data:   # yaml-cpp may write 1e-05, which PyYAML reads as a string
                try:
                    if isinstance(v, bool) or not isinstance(v, int | float | str):
                        raise TypeError
                    values.append(float(v))
                except (TypeError, ValueError):
                    raise CameraInfoError(f"{source}: {name}.data holds {v!r}, not a number") from None
            return tuple(values)

        model = doc.get("distortion_model", PLUMB_BOB)
        return cls(str(doc.get("camera_name", "unknown")), integer("image_width"), integer("image_height"),
                   matrix("camera_matrix", 3, 3), str(model), matrix("distortion_coefficients", 1, None),
                   matrix("rectification_matrix", 3, 3), matrix("projection_matrix", 3, 4))


def _number(value: float) -> str:
    """repr (the shortest exact form) with a decimal point before an exponent: PyYAML reads 1e-05 as a string."""
    text = repr(float(value))
    mantissa, e, exponent = text.partition("e")
    if e and "." not in mantissa:
        mantissa += ".0"
    if e and exponent[0] not in "+-":
        exponent = "+" + exponent
    return mantissa + e + exponent


# -- names and URLs ---------------------------------------------------------------------------------

def camera_name_problem(name: str) -> str:
    """Why `name` is not a camera name camera_info_manager accepts ("" when it is)."""
    if not _CAMERA_NAME.match(str(name)):
        return f"camera_name {name!r} must be letters, digits and _ only (camera_info_manager's rule)"
    return ""


def resolve_url(url: str, camera_name: str, environ: Mapping[str, str] | None = None) -> str:
    """`url` with ${NAME} and ${ROS_HOME} substituted; CameraInfoError for another ${...}."""
    env = os.environ if environ is None else environ

    def substitute(match: re.Match[str]) -> str:
        key = match.group(1)
        if key == "NAME":
            return camera_name
        if key == "ROS_HOME":
            return env.get("ROS_HOME") or str(Path(env.get("HOME", "~")).expanduser() / ".ros")
        raise CameraInfoError(f"camera_info_url {url!r}: unknown substitution ${{{key}}} (only ${{NAME}} and "
                              "${ROS_HOME})")

    return re.sub(r"\$\{([^}]*)\}", substitute, url)


def url_path(url: str, camera_name: str, environ: Mapping[str, str] | None = None) -> Path | None:
    """The file a camera_info_url names (None for ""); CameraInfoError, one line, when it names none."""
    text = str(url).strip()
    if not text:
        return None
    resolved = resolve_url(text, camera_name, environ)
    lower = resolved.lower()
    if lower.startswith("file://"):
        path = resolved[len("file://"):]
        if not path.startswith("/"):
            raise CameraInfoError(f"camera_info_url {url!r}: a file URL needs an absolute path (file:///path.yaml)")
        return Path(path)
    if lower.startswith("package://"):
        package, _, rest = resolved[len("package://"):].partition("/")
        if not package or not rest:
            raise CameraInfoError(f"camera_info_url {url!r}: expected package://PACKAGE/path.yaml")
        return package_share(package, environ) / rest
    raise CameraInfoError(f"camera_info_url {url!r} is not a file:///path.yaml or package://PACKAGE/path.yaml URL")


def package_share(package: str, environ: Mapping[str, str] | None = None) -> Path:
    """`<prefix>/share/<package>` of the first AMENT_PREFIX_PATH prefix that registers the package (ament_index's
    lookup); CameraInfoError when none does."""
    env = os.environ if environ is None else environ
    for prefix in (p for p in env.get("AMENT_PREFIX_PATH", "").split(os.pathsep) if p):
        if (Path(prefix) / "share" / "ament_index" / "resource_index" / "packages" / package).is_file():
            return Path(prefix) / "share" / package
    raise CameraInfoError(f"package {package!r} of the camera_info_url is not found on AMENT_PREFIX_PATH "
                          "(source the workspace that installs it)")


def read_camera_info(path: str | os.PathLike[str]) -> CameraCalibration:
    """A camera_calibration_parsers YAML file; CameraInfoError, one line, when it is missing or malformed."""
    try:
        text = Path(path).read_text(encoding="utf-8")
    except FileNotFoundError:
        raise CameraInfoError(f"camera info file {path} does not exist") from None
    except (OSError, UnicodeDecodeError) as exc:
        raise CameraInfoError(f"cannot read camera info file {path}: {getattr(exc, 'strerror', None) or exc}") from None
    return CameraCalibration.from_yaml(text, f"camera info file {path}")


def write_camera_info(path: str | os.PathLike[str], calibration: CameraCalibration) -> None:
    """Write the YAML whole or not at all, making missing folders (as camera_info_manager does)."""
    Path(path).parent.mkdir(parents=True, exist_ok=True)
    atomic_write_text(path, calibration.to_yaml())


def camera_info_path_for(parameters_path: str | os.PathLike[str]) -> Path:
    """Where our calibration writes the camera_calibration_parsers YAML beside a parameters file:
    cal.yaml -> cal.camera_info.yaml."""
    path = Path(parameters_path)
    return path.with_name(f"{path.stem}.camera_info.yaml")


# -- sensor_msgs/CameraInfo (duck-typed: no message import here) -----------------------------------

def fill_camera_info(msg: Any, calibration: CameraCalibration, stamp_ns: int, frame_id: str) -> Any:
    """Set a sensor_msgs/CameraInfo's header and calibration fields; returns `msg`."""
    msg.header.stamp.sec, msg.header.stamp.nanosec = divmod(int(stamp_ns), 1_000_000_000)
    msg.header.frame_id = frame_id
    msg.width, msg.height = calibration.width, calibration.height
    msg.distortion_model = calibration.distortion_model
    msg.d = list(calibration.d)
    msg.k, msg.r, msg.p = list(calibration.k), list(calibration.r), list(calibration.p)
    return msg


def from_camera_info(msg: Any, camera_name: str) -> CameraCalibration:
    """The calibration a sensor_msgs/CameraInfo carries (a set_camera_info request's)."""
    try:
        return CameraCalibration(camera_name, int(msg.width), int(msg.height), tuple(msg.k), str(msg.distortion_model),
                                 tuple(msg.d), tuple(msg.r), tuple(msg.p))
    except (TypeError, ValueError) as exc:
        raise CameraInfoError(f"camera info: {exc}") from None
