"""Declaring ROS 2 parameters once, with type, range and description (rclpy glue, no algorithms).

`declare` wraps `Node.declare_parameter` with a ParameterDescriptor carrying the description and
a floating-point or integer range, so `ros2 param describe` shows them and rclpy rejects values
outside the range. `declare_geometry_parameters` declares docs/design.md's camera/cylinder/extrinsics
parameters; `GeometryParameters` validates a whole update in the on-set callback (the model is
rebuilt from the candidate values) and applies it in the post-set callback.
"""
from __future__ import annotations

from collections.abc import Callable, Sequence
from typing import Any

from rcl_interfaces.msg import FloatingPointRange, IntegerRange, ParameterDescriptor, SetParametersResult
from rclpy.node import Node
from rclpy.parameter import Parameter

from touchroller_bringup import names
from touchroller_perception.geometry import PARAMETER_NAMES, PARAMETER_RANGES, CameraModel

_GEOMETRY_DESCRIPTIONS = {
    "camera.fx": "Focal length along u (image columns, the cylinder axis), pixels",
    "camera.fy": "Focal length along v (image rows, around the cylinder), pixels",
    "camera.cx": "Principal point u, pixels",
    "camera.cy": "Principal point v, pixels",
    "camera.distortion": "OpenCV distortion coefficients [k1, k2, p1, p2, k3]",
    "camera.width": "Image width, pixels",
    "camera.height": "Image height, pixels",
    "cylinder.radius": "Radius r of the membrane surface y^2 + z^2 = r^2, metres",
    "cylinder.length": "Length of the tube along x, metres",
    "extrinsics.theta": "Camera rotation about the cylinder axis x (paper Eq. bigeq), radians",
    "extrinsics.d": "Camera offset along z (paper Eq. bigeq), metres; |d| < radius",
}
# name -> (description, min, max); the ranges are the camera model's own (geometry.PARAMETER_RANGES)
GEOMETRY_PARAMETERS: dict[str, tuple[str, float | None, float | None]] = {
    name: (description, *(PARAMETER_RANGES[name][:2] if name in PARAMETER_RANGES else (None, None)))
    for name, description in _GEOMETRY_DESCRIPTIONS.items()
}
assert set(GEOMETRY_PARAMETERS) == set(PARAMETER_NAMES)


def descriptor(description: str, *, min: float | None = None, max: float | None = None,
               step: float | None = None, read_only: bool = False, integer: bool = False,
               additional_constraints: str = "") -> ParameterDescriptor:
    desc = ParameterDescriptor(description=description, read_only=read_only,
                               additional_constraints=additional_constraints)
    if min is not None and max is not None:
        if integer:
            desc.integer_range = [IntegerRange(from_value=int(min), to_value=int(max), step=int(step or 0))]
        else:
            desc.floating_point_range = [FloatingPointRange(from_value=float(min), to_value=float(max),
                                                            step=float(step or 0.0))]
    return desc


def declare(node: Node, name: str, default: Any, description: str, *, min: float | None = None,
            max: float | None = None, step: float | None = None, read_only: bool = False,
            additional_constraints: str = "") -> Any:
    """Declare one parameter with its descriptor and return its current value."""
    integer = isinstance(default, int) and not isinstance(default, bool)
    param = node.declare_parameter(
        name, default,
        descriptor(description, min=min, max=max, step=step, read_only=read_only, integer=integer,
                   additional_constraints=additional_constraints),
    )
    return param.value


def declare_frame_prefix(node: Node) -> str:
    """Declare the read-only `frame_prefix` every frame id the node publishes starts with, and return it.
    Its default follows the node's namespace (`names.frame_prefix`): "" in `touchroller`, "left/" in `left`."""
    default = names.frame_prefix(node.get_namespace())
    return str(declare(node, "frame_prefix", default, "Prefix of every frame id this node publishes (default: "
                       "none in the namespace touchroller, else the namespace and a slash, e.g. left/)",
                       read_only=True))


def declare_geometry_parameters(node: Node, model: CameraModel | None = None) -> None:
    """Declare docs/design.md's geometry parameters with the model's values as defaults."""
    defaults = (model or CameraModel()).to_params()
    for name, (description, lo, hi) in GEOMETRY_PARAMETERS.items():
        declare(node, name, defaults[name], description, min=lo, max=hi)


def camera_model_from_node(node: Node) -> CameraModel:
    return CameraModel.from_params({name: node.get_parameter(name).value for name in PARAMETER_NAMES})


class GeometryParameters:
    """Keeps a node's CameraModel in step with its parameters.

    On-set: the candidate model is built from the new values over the current ones; an invalid
    combination (e.g. |d| >= r, 4 distortion coefficients) is rejected with the model's reason.
    Post-set: the new model is stored and `on_change(model)` is called.
    """

    def __init__(self, node: Node, model: CameraModel | None = None,
                 on_change: Callable[[CameraModel], None] | None = None) -> None:
        declare_geometry_parameters(node, model)
        self._node = node
        self.model = camera_model_from_node(node)
        self._on_change = on_change
        node.add_on_set_parameters_callback(self._validate)
        node.add_post_set_parameters_callback(self._apply)

    def _candidate(self, parameters: Sequence[Parameter]) -> CameraModel:
        values = self.model.to_params()
        values.update({p.name: p.value for p in parameters if p.name in GEOMETRY_PARAMETERS})
        return CameraModel.from_params(values)

    def _validate(self, parameters: Sequence[Parameter]) -> SetParametersResult:
        if not any(p.name in GEOMETRY_PARAMETERS for p in parameters):
            return SetParametersResult(successful=True)
        try:
            self._candidate(parameters)
        except (TypeError, ValueError) as exc:
            return SetParametersResult(successful=False, reason=str(exc))
        return SetParametersResult(successful=True)

    def _apply(self, parameters: Sequence[Parameter]) -> None:
        if any(p.name in GEOMETRY_PARAMETERS for p in parameters):
            self.model = self._candidate(parameters)
            if self._on_change is not None:
                self._on_change(self.model)
