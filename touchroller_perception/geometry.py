"""The TouchRoller camera model: the paper's Eq. "bigeq" with OpenCV's 5-coefficient distortion.

Cylinder frame `touchroller_cylinder`: x along the axis, z down, origin at the centre; the
membrane is y^2 + z^2 = r^2. The camera is a pinhole rotated by `theta` about x and shifted by
`d` along z (docs/design.md):

    x_c = X,  y_c = Y cos(theta) + Z sin(theta),  z_c = -Y sin(theta) + Z cos(theta) + d
    u = fx * distort(x_c / z_c, y_c / z_c)_x + cx,  v = fy * distort(...)_y + cy

Everything is vectorised over leading axes and computed in float64. Points or pixels the model
cannot map (behind the camera, beyond the tube's ends, past the fold of the distortion
polynomial, non-finite) come back as NaN with `valid == False`, never as a wrong finite number.
"""
from __future__ import annotations

import dataclasses
import difflib
import functools
import math
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

FloatArray = NDArray[np.float64]
BoolArray = NDArray[np.bool_]

#: Parameter names of docs/design.md, in the order `to_params` writes them.
PARAMETER_NAMES = (
    "camera.fx", "camera.fy", "camera.cx", "camera.cy", "camera.distortion",
    "camera.width", "camera.height",
    "cylinder.radius", "cylinder.length", "extrinsics.theta", "extrinsics.d",
)
_FIELD_OF_PARAMETER = {
    "camera.fx": "fx", "camera.fy": "fy", "camera.cx": "cx", "camera.cy": "cy",
    "camera.distortion": "distortion", "camera.width": "width", "camera.height": "height",
    "cylinder.radius": "radius", "cylinder.length": "length",
    "extrinsics.theta": "theta", "extrinsics.d": "d",
}
#: The range (inclusive) and unit of each scalar parameter. The nodes declare these ranges
#: (touchroller_bringup.ros_params) and a CameraModel outside them is refused, so a params file read
#: without ROS (`touchroller contacts --params`, ...) is held to the same ranges: theta = 10 (degrees
#: meant, radians read) would otherwise put every contact on the wrong side of the cylinder.
PARAMETER_RANGES: dict[str, tuple[float, float, str]] = {
    "camera.fx": (1.0, 100000.0, "px"),
    "camera.fy": (1.0, 100000.0, "px"),
    "camera.cx": (-10000.0, 10000.0, "px"),
    "camera.cy": (-10000.0, 10000.0, "px"),
    "camera.width": (1, 16384, "px"),
    "camera.height": (1, 16384, "px"),
    "cylinder.radius": (0.001, 1.0, "m"),
    "cylinder.length": (0.001, 2.0, "m"),
    "extrinsics.theta": (-1.5, 1.5, "rad"),
    "extrinsics.d": (-1.0, 1.0, "m"),
}
#: Parameters whose uncertainty `contact_covariance` can propagate.
CALIBRATION_PARAMETERS = ("fx", "fy", "cx", "cy", "k1", "k2", "p1", "p2", "k3", "theta", "d", "radius")

_UNDISTORT_ITERATIONS = 30
_UNDISTORT_TOLERANCE = 1e-15   # in normalised image units (~1e-12 px)


@dataclasses.dataclass(frozen=True)
class CameraModel:
    """Intrinsics, distortion, the paper's extrinsics (theta, d) and the cylinder's size."""

    fx: float = 500.0
    fy: float = 500.0
    cx: float = 319.5
    cy: float = 239.5
    distortion: tuple[float, float, float, float, float] = (0.0, 0.0, 0.0, 0.0, 0.0)
    theta: float = 0.0
    d: float = 0.0
    radius: float = 0.05
    length: float = 0.1
    width: int = 640
    height: int = 480

    def __post_init__(self) -> None:
        dist = tuple(float(k) for k in self.distortion)
        if len(dist) != 5:
            raise ValueError(f"camera.distortion needs 5 coefficients (k1, k2, p1, p2, k3), got {len(dist)}")
        object.__setattr__(self, "distortion", dist)
        for name in ("fx", "fy", "cx", "cy", "theta", "d", "radius", "length"):
            object.__setattr__(self, name, float(getattr(self, name)))
        object.__setattr__(self, "width", int(self.width))
        object.__setattr__(self, "height", int(self.height))
        values = [self.fx, self.fy, self.cx, self.cy, self.theta, self.d, self.radius, self.length, *dist]
        if not all(math.isfinite(x) for x in values):
            raise ValueError("camera model parameters must be finite")
        for name, (lo, hi, unit) in PARAMETER_RANGES.items():
            value = getattr(self, _FIELD_OF_PARAMETER[name])
            if not lo <= value <= hi:
                raise ValueError(f"{name} = {value:g} {unit} is outside its range [{lo:g}, {hi:g}] {unit}")
        if self.fx <= 0 or self.fy <= 0:
            raise ValueError(f"focal lengths must be positive (fx={self.fx}, fy={self.fy})")
        if self.radius <= 0 or self.length <= 0:
            raise ValueError(f"cylinder radius and length must be positive (r={self.radius}, L={self.length})")
        if abs(self.d) >= self.radius:
            raise ValueError(f"|extrinsics.d| = {abs(self.d)} m puts the camera outside the tube (r = {self.radius} m)")
        if self.width <= 0 or self.height <= 0:
            raise ValueError(f"image size must be positive ({self.width}x{self.height})")

    # ----------------------------------------------------------------- parameters and files
    @classmethod
    def from_params(cls, params: Mapping[str, Any]) -> CameraModel:
        """Build from docs/design.md parameter names (`camera.fx`, ...); absent names keep defaults."""
        flat = _flatten(params)
        kwargs = {field: flat[name] for name, field in _FIELD_OF_PARAMETER.items() if name in flat}
        for name, field in _FIELD_OF_PARAMETER.items():
            if field not in kwargs:
                continue
            if field == "distortion":
                value = kwargs[field]
                if isinstance(value, str | bytes) or not isinstance(value, Sequence):
                    raise TypeError(f"{name} is a list of 5 numbers (k1, k2, p1, p2, k3), got {value!r}")
                kwargs[field] = tuple(parameter_number(f"{name}[{i}]", v) for i, v in enumerate(value))
            else:
                kwargs[field] = parameter_number(name, kwargs[field], integer=field in ("width", "height"))
        return cls(**kwargs)

    def to_params(self) -> dict[str, Any]:
        return {name: (list(getattr(self, field)) if field == "distortion" else getattr(self, field))
                for name, field in _FIELD_OF_PARAMETER.items()}

    @classmethod
    def from_yaml(cls, path: str | Path) -> CameraModel:
        """Read a ROS 2 params file (`/**: ros__parameters: ...`, or any node name) or a flat mapping."""
        import yaml

        try:
            with open(path, encoding="utf-8") as stream:
                document = yaml.safe_load(stream)
        except (yaml.YAMLError, UnicodeDecodeError) as exc:
            raise ValueError(f"not a YAML parameters file ({_one_line_yaml_error(exc)})") from None
        if not isinstance(document, Mapping):
            raise ValueError("not a parameters file (expected a mapping)")
        params = _ros_parameters(document)
        _check_model_names(_flatten(params))
        return cls.from_params(params)

    def to_yaml(self, path: str | Path, extra: Mapping[str, Any] | None = None) -> None:
        """Write a ROS 2 params file that serves any node name; `extra` adds parameters (e.g. uncertainties)."""
        import yaml

        from touchroller_perception.files import atomic_write

        params: dict[str, Any] = self.to_params()
        params.update(extra or {})
        with atomic_write(path) as stream:
            yaml.safe_dump({"/**": {"ros__parameters": params}}, stream, sort_keys=False)

    def replace(self, **changes: Any) -> CameraModel:
        return dataclasses.replace(self, **changes)

    # ----------------------------------------------------------------- matrices
    @property
    def K(self) -> FloatArray:  # noqa: N802 - the usual name
        return np.array([[self.fx, 0.0, self.cx], [0.0, self.fy, self.cy], [0.0, 0.0, 1.0]])

    @property
    def R(self) -> FloatArray:  # noqa: N802
        """Rotation cylinder -> camera (paper Eq. c)."""
        c, s = math.cos(self.theta), math.sin(self.theta)
        return np.array([[1.0, 0.0, 0.0], [0.0, c, s], [0.0, -s, c]])

    @property
    def t(self) -> FloatArray:
        return np.array([0.0, 0.0, self.d])

    @property
    def camera_centre(self) -> FloatArray:
        """The pinhole in the cylinder frame: -R^T t = (0, d sin(theta), -d cos(theta))."""
        return np.array([0.0, self.d * math.sin(self.theta), -self.d * math.cos(self.theta)])

    @functools.cached_property
    def max_undistorted_radius2(self) -> float:
        """Squared normalised radius where the radial distortion folds back (inf if it never does)."""
        return _fold_radius2(*self.distortion)

    # ----------------------------------------------------------------- projection
    def project(self, points: ArrayLike) -> tuple[FloatArray, BoolArray]:
        """Cylinder-frame points (..., 3) -> pixels (..., 2) and a validity mask (...)."""
        p = np.asarray(points, dtype=np.float64)
        if p.shape[-1:] != (3,):
            raise ValueError(f"points must have shape (..., 3), got {p.shape}")
        c, s = math.cos(self.theta), math.sin(self.theta)
        x_c = p[..., 0]
        y_c = p[..., 1] * c + p[..., 2] * s
        z_c = -p[..., 1] * s + p[..., 2] * c + self.d
        with np.errstate(divide="ignore", invalid="ignore"):
            ahead = z_c > 1e-12 * self.radius
            xn = np.where(ahead, x_c / np.where(ahead, z_c, 1.0), np.nan)
            yn = np.where(ahead, y_c / np.where(ahead, z_c, 1.0), np.nan)
        uv, valid = self.project_normalised(xn, yn)
        return uv, valid & ahead

    def project_normalised(self, xn: ArrayLike, yn: ArrayLike) -> tuple[FloatArray, BoolArray]:
        """Undistorted normalised coordinates -> pixels, valid inside the distortion's monotone region."""
        xn = np.asarray(xn, dtype=np.float64)
        yn = np.asarray(yn, dtype=np.float64)
        xd, yd = _distort(xn, yn, self.distortion)
        r2 = xn * xn + yn * yn
        valid = np.isfinite(xd) & np.isfinite(yd) & (r2 < self.max_undistorted_radius2)
        valid &= _distortion_jacobian_det(xn, yn, self.distortion) > 0
        uv = np.stack([self.fx * xd + self.cx, self.fy * yd + self.cy], axis=-1)
        uv[~valid] = np.nan
        return uv, valid

    def undistort_normalised(self, uv: ArrayLike) -> tuple[FloatArray, FloatArray, BoolArray]:
        """Pixels (..., 2) -> undistorted normalised (xn, yn) and validity (Newton on the distortion)."""
        uv = np.asarray(uv, dtype=np.float64)
        if uv.shape[-1:] != (2,):
            raise ValueError(f"pixels must have shape (..., 2), got {uv.shape}")
        xd = (uv[..., 0] - self.cx) / self.fx
        yd = (uv[..., 1] - self.cy) / self.fy
        xn, yn, converged = _undistort(xd, yd, self.distortion)
        r2 = xn * xn + yn * yn
        valid = converged & (r2 < self.max_undistorted_radius2)
        valid &= _distortion_jacobian_det(xn, yn, self.distortion) > 0
        xn = np.where(valid, xn, np.nan)
        yn = np.where(valid, yn, np.nan)
        return xn, yn, valid

    def pixel_rays(self, uv: ArrayLike) -> tuple[FloatArray, FloatArray, BoolArray]:
        """Pixels -> (ray origin (3,), unnormalised directions (..., 3) in the cylinder frame, valid)."""
        xn, yn, valid = self.undistort_normalised(uv)
        c, s = math.cos(self.theta), math.sin(self.theta)
        # D = R^T (xn, yn, 1)
        directions = np.stack([xn, c * yn - s, s * yn + c], axis=-1)
        return self.camera_centre, directions, valid

    def back_project(self, uv: ArrayLike) -> tuple[FloatArray, BoolArray]:
        """Pixels (..., 2) -> points on the membrane (..., 3) where the ray meets the cylinder.

        The camera is inside the tube (|d| < r), so the quadratic for the ray parameter has one
        positive and one negative root; the positive one is taken in its cancellation-free form.
        Rays that leave through the tube's open ends (|x| > length / 2) are invalid.
        """
        origin, direction, valid = self.pixel_rays(uv)
        dy, dz = direction[..., 1], direction[..., 2]
        a = dy * dy + dz * dz                     # = 1 + yn^2 >= 1: rotation about x keeps the y-z norm
        b = 2.0 * (origin[1] * dy + origin[2] * dz)
        c0 = self.d * self.d - self.radius * self.radius   # < 0: camera inside
        root = np.sqrt(b * b - 4.0 * a * c0)
        with np.errstate(divide="ignore", invalid="ignore"):
            t = np.where(b >= 0, 2.0 * c0 / (-b - root), (-b + root) / (2.0 * a))
        points = origin + t[..., None] * direction
        # the ends are inclusive up to rounding, so a point at x = L/2 survives a round trip
        valid = valid & np.isfinite(t) & (np.abs(points[..., 0]) <= 0.5 * self.length * (1 + 1e-12))
        points[~valid] = np.nan
        return points, valid

    def in_image(self, uv: ArrayLike, margin: float = 0.0) -> BoolArray:
        """True for pixel centres inside the image (OpenCV convention: centres at integers)."""
        uv = np.asarray(uv, dtype=np.float64)
        u, v = uv[..., 0], uv[..., 1]
        with np.errstate(invalid="ignore"):
            return ((u >= -0.5 + margin) & (u <= self.width - 0.5 - margin)
                    & (v >= -0.5 + margin) & (v <= self.height - 0.5 - margin))

    # ----------------------------------------------------------------- surface coordinates
    def surface_point(self, x: ArrayLike, alpha: ArrayLike) -> FloatArray:
        """Point on the membrane at axial position x and central angle alpha (from +z towards +y)."""
        x, alpha = np.broadcast_arrays(np.asarray(x, dtype=np.float64), np.asarray(alpha, dtype=np.float64))
        return np.stack([x, self.radius * np.sin(alpha), self.radius * np.cos(alpha)], axis=-1)

    @staticmethod
    def surface_coords(points: ArrayLike) -> tuple[FloatArray, FloatArray]:
        """(x, alpha) of cylinder-frame points; alpha = atan2(y, z)."""
        p = np.asarray(points, dtype=np.float64)
        return p[..., 0], np.arctan2(p[..., 1], p[..., 2])

    # ----------------------------------------------------------------- uncertainty
    def contact_covariance(
        self,
        uv: ArrayLike,
        pixel_sigma: float = 0.5,
        calibration_sigma: Mapping[str, float] | None = None,
    ) -> FloatArray:
        """First-order covariance (..., 3, 3) of back-projected points, in m^2.

        `pixel_sigma` is the isotropic standard deviation of the detected pixel (px);
        `calibration_sigma` maps names of `CALIBRATION_PARAMETERS` to their standard deviations
        (theta in rad, d and radius in m, intrinsics in px, distortion unitless). Independent
        errors are assumed. Invalid pixels give NaN matrices.
        """
        uv = np.asarray(uv, dtype=np.float64)
        cov = np.zeros(uv.shape[:-1] + (3, 3))
        h_px = 1e-3
        for axis in range(2):
            step = np.zeros(2)
            step[axis] = h_px
            jac = (self.back_project(uv + step)[0] - self.back_project(uv - step)[0]) / (2 * h_px)
            cov += pixel_sigma**2 * _outer(jac)
        for name, sigma in (calibration_sigma or {}).items():
            if name not in CALIBRATION_PARAMETERS:
                raise ValueError(f"unknown calibration parameter {name!r}; expected one of {CALIBRATION_PARAMETERS}")
            if sigma == 0:
                continue
            h = _parameter_step(name, self)
            plus = _perturbed(self, name, +h).back_project(uv)[0]
            minus = _perturbed(self, name, -h).back_project(uv)[0]
            cov += sigma**2 * _outer((plus - minus) / (2 * h))
        return cov


def _outer(j: FloatArray) -> FloatArray:
    return j[..., :, None] * j[..., None, :]


def _parameter_step(name: str, model: CameraModel) -> float:
    if name in ("fx", "fy", "cx", "cy"):
        return 1e-3
    if name in ("d", "radius"):
        return 1e-7 * max(model.radius, 1e-3) / 0.05
    return 1e-6


def _perturbed(model: CameraModel, name: str, h: float) -> CameraModel:
    names = ("k1", "k2", "p1", "p2", "k3")
    if name in names:
        dist = list(model.distortion)
        dist[names.index(name)] += h
        return model.replace(distortion=tuple(dist))
    return model.replace(**{name: getattr(model, name) + h})


# --------------------------------------------------------------------------- distortion
def _distort(xn: FloatArray, yn: FloatArray, dist: tuple[float, ...]) -> tuple[FloatArray, FloatArray]:
    k1, k2, p1, p2, k3 = dist
    r2 = xn * xn + yn * yn
    radial = 1.0 + r2 * (k1 + r2 * (k2 + r2 * k3))
    xd = xn * radial + 2.0 * p1 * xn * yn + p2 * (r2 + 2.0 * xn * xn)
    yd = yn * radial + p1 * (r2 + 2.0 * yn * yn) + 2.0 * p2 * xn * yn
    return xd, yd


def _distortion_jacobian(xn: FloatArray, yn: FloatArray, dist: tuple[float, ...]):
    k1, k2, p1, p2, k3 = dist
    r2 = xn * xn + yn * yn
    radial = 1.0 + r2 * (k1 + r2 * (k2 + r2 * k3))
    dradial = k1 + r2 * (2.0 * k2 + 3.0 * k3 * r2)          # d radial / d r2
    j11 = radial + 2.0 * xn * xn * dradial + 2.0 * p1 * yn + 6.0 * p2 * xn
    j12 = 2.0 * xn * yn * dradial + 2.0 * p1 * xn + 2.0 * p2 * yn
    j21 = 2.0 * xn * yn * dradial + 2.0 * p1 * xn + 2.0 * p2 * yn
    j22 = radial + 2.0 * yn * yn * dradial + 6.0 * p1 * yn + 2.0 * p2 * xn
    return j11, j12, j21, j22


def _distortion_jacobian_det(xn: FloatArray, yn: FloatArray, dist: tuple[float, ...]) -> FloatArray:
    if not any(dist):
        return np.ones(np.broadcast(xn, yn).shape)
    j11, j12, j21, j22 = _distortion_jacobian(xn, yn, dist)
    with np.errstate(invalid="ignore"):
        return np.nan_to_num(j11 * j22 - j12 * j21, nan=-1.0)


def _undistort(xd: FloatArray, yd: FloatArray, dist: tuple[float, ...]):
    """Invert the distortion by Newton's method; returns (xn, yn, converged)."""
    finite = np.isfinite(xd) & np.isfinite(yd)
    if not any(dist):
        return np.where(finite, xd, np.nan), np.where(finite, yd, np.nan), finite
    xd0 = np.where(finite, xd, 0.0)
    yd0 = np.where(finite, yd, 0.0)
    xn, yn = xd0.copy(), yd0.copy()
    with np.errstate(all="ignore"):
        for _ in range(_UNDISTORT_ITERATIONS):
            fx_, fy_ = _distort(xn, yn, dist)
            ex, ey = fx_ - xd0, fy_ - yd0
            j11, j12, j21, j22 = _distortion_jacobian(xn, yn, dist)
            det = j11 * j22 - j12 * j21
            dx = (j22 * ex - j12 * ey) / det
            dy = (-j21 * ex + j11 * ey) / det
            xn = xn - dx
            yn = yn - dy
            if np.all(~np.isfinite(dx) | (np.abs(dx) + np.abs(dy) < _UNDISTORT_TOLERANCE)):
                break
        fx_, fy_ = _distort(xn, yn, dist)
        residual = np.abs(fx_ - xd0) + np.abs(fy_ - yd0)
    converged = finite & np.isfinite(xn) & np.isfinite(yn) & (residual < 1e-12)
    return xn, yn, converged


@functools.lru_cache(maxsize=256)
def _fold_radius2(k1: float, k2: float, p1: float, p2: float, k3: float) -> float:
    """Smallest s = r^2 > 0 where d/dr [r (1 + k1 r^2 + k2 r^4 + k3 r^6)] = 0, i.e. the radial fold.

    1 + 3 k1 s + 5 k2 s^2 + 7 k3 s^3 = 0 is solved for w = 1/s, where it is monic
    (w^3 + 3 k1 w^2 + 5 k2 w + 7 k3 = 0), so tiny or denormal coefficients cannot overflow;
    the smallest positive s is 1 / (largest positive real w).
    """
    roots = np.roots([1.0, 3.0 * k1, 5.0 * k2, 7.0 * k3])
    positive = [float(r.real) for r in roots if abs(r.imag) <= 1e-12 * max(1.0, abs(r)) and r.real > 0]
    largest = max(positive, default=0.0)
    return 1.0 / largest if largest > 1e-300 else math.inf    # a vanishing root: the fold is at infinity


# --------------------------------------------------------------------------- YAML helpers
def _one_line_yaml_error(exc: Exception) -> str:
    """`found unexpected end of stream at line 2, column 1` rather than PyYAML's multi-line report."""
    problem = getattr(exc, "problem", None)
    mark = getattr(exc, "problem_mark", None)
    if problem and mark is not None:
        return f"{problem} at line {mark.line + 1}, column {mark.column + 1}"
    return " ".join(str(exc).split()) or type(exc).__name__


def parameter_number(name: str, value: Any, integer: bool = False) -> float:
    """A parameter's value as a number: int or float, or a string that reads as one (YAML 1.1 reads `1e-6`,
    without a dot, as a string); a boolean or anything else is a TypeError naming the parameter."""
    if isinstance(value, str):
        try:
            value = float(value.strip())
        except ValueError:
            raise TypeError(f"{name} must be a number, got the string {value!r}") from None
    if isinstance(value, bool) or not isinstance(value, int | float | np.integer | np.floating):
        raise TypeError(f"{name} must be a number, got {type(value).__name__} {value!r}")
    if integer:
        if not float(value).is_integer():
            raise TypeError(f"{name} must be a whole number, got {value!r}")
        return int(value)
    return float(value)


def _check_model_names(flat: Mapping[str, Any]) -> None:
    """A file read for the camera model must name it: one with none of its parameters, or with a misspelt
    one (`extrinsics.thetta`), would otherwise give the defaults silently."""
    if not any(name in flat for name in _FIELD_OF_PARAMETER):
        raise ValueError(f"no camera-model parameters in it (expected some of {', '.join(_FIELD_OF_PARAMETER)})")
    for name in flat:
        if name in _FIELD_OF_PARAMETER:
            continue
        # extrinsics.* and cylinder.* belong to the model alone; camera.* also holds driver settings
        near = difflib.get_close_matches(name, list(_FIELD_OF_PARAMETER), n=1, cutoff=0.85)
        if name.startswith(("extrinsics.", "cylinder.")) or near:
            hint = f" (did you mean {near[0]}?)" if near else ""
            raise ValueError(f"unknown camera-model parameter {name}{hint}")


def _flatten(params: Mapping[str, Any], prefix: str = "") -> dict[str, Any]:
    flat: dict[str, Any] = {}
    for key, value in params.items():
        name = f"{prefix}{key}"
        if isinstance(value, Mapping):
            flat.update(_flatten(value, name + "."))
        else:
            flat[name] = value
    return flat


def _ros_parameters(document: Mapping[str, Any]) -> dict[str, Any]:
    """The `ros__parameters` of a params file (first node entry that has them), else the document."""
    for value in document.values():
        if isinstance(value, Mapping) and "ros__parameters" in value:
            return dict(value["ros__parameters"])
        if isinstance(value, Mapping):  # namespaced: /ns: node: ros__parameters
            for inner in value.values():
                if isinstance(inner, Mapping) and "ros__parameters" in inner:
                    return dict(inner["ros__parameters"])
    return dict(document)
