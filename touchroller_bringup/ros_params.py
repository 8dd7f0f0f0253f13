"""Declaring ROS 2 parameters once, with type, range and description (rclpy glue, no algorithms).

`declare` wraps `Node.declare_parameter` with a ParameterDescriptor carrying the description and
a floating-point or integer range, so `ros2 param describe` shows them and rclpy rejects values
outside the range. `GeometryParameters` binds docs/design.md's camera/cylinder/extrinsics parameters to
the node's CameraModel (a `ConfigParameters`, below): a whole update is validated in the on-set callback
(the model is rebuilt from the candidate values) and applied in the post-set callback.

Every parameter declared through `declare` is checked in one place, at declaration (the value a params
file or `name:=value` gave) and in an on-set callback `declare` adds once per node: its type (a number
written as a string, `1e-6` as YAML 1.1 reads it, or an integer for a double, is taken as the number; a
boolean is never a number), finiteness (NaN or infinity is refused for every double), its range and,
for arrays, its length. A node then validates the whole set once its own callbacks are added
(`check_start_up`): a combination it refuses stops it at start-up, in one line, exit 2 (through
`ros_main.run_node`), instead of running on values it cannot use.

`ConfigParameters` binds a frozen config dataclass to parameters by a table (parameter name ->
`ParameterField`: config field, description, range, choices, read-only): it declares them all through
`declare` (the type is the field's), checks a change in the on-set callback by building the candidate
config with `dataclasses.replace` (the config's own `__post_init__`, then an optional `check` hook of the
node's) and, in the post-set callback, keeps the new config and hands it to `on_change`.
"""
from __future__ import annotations

import math
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, fields, replace
from types import UnionType
from typing import Any, Generic, TypeVar, Union, get_args, get_origin, get_type_hints

from rcl_interfaces.msg import FloatingPointRange, IntegerRange, ParameterDescriptor, SetParametersResult
from rclpy.node import Node
from rclpy.parameter import Parameter

from touchroller_bringup import names
from touchroller_bringup.errors import UserError
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


@dataclass(frozen=True)
class _Spec:
    """What `declare` checks of one parameter's value beyond rclpy's own type and range checks."""

    number: bool            # a double (or double array): finite numbers only
    length: int | None      # arrays: exactly this many elements
    min: float | None
    max: float | None


def declare(node: Node, name: str, default: Any, description: str, *, min: float | None = None,
            max: float | None = None, step: float | None = None, read_only: bool = False,
            additional_constraints: str = "", length: int | None = None) -> Any:
    """Declare one parameter with its descriptor and return its current value. The given value is checked
    (see the module docstring): UserError, one line naming the parameter, when it cannot be used."""
    integer = isinstance(default, int) and not isinstance(default, bool)
    number = isinstance(default, float) or (isinstance(default, list) and bool(default)
                                            and all(isinstance(v, float) for v in default))
    spec = _Spec(number, length, min, max)
    _coerce_override(node, name, default)
    given = getattr(node, "_parameter_overrides", {}).get(name)
    problem = _problem(name, given.value, replace(spec, min=None, max=None)) \
        if given is not None and given.value is not None else ""
    if problem:   # before rclpy's own checks (the range is rclpy's: "NAME out of range")
        raise UserError(problem)
    _specs(node)[name] = spec
    param = node.declare_parameter(
        name, default,
        descriptor(description, min=min, max=max, step=step, read_only=read_only, integer=integer,
                   additional_constraints=additional_constraints),
    )
    problem = _problem(name, param.value, spec)
    if problem:
        raise UserError(problem)
    return param.value


def _specs(node: Node) -> dict[str, _Spec]:
    """The node's declared specs; the first call adds the on-set callback that checks them."""
    specs = getattr(node, "_touchroller_specs", None)
    if specs is None:
        specs = {}
        node._touchroller_specs = specs  # type: ignore[attr-defined]

        def validate(parameters: Sequence[Parameter]) -> SetParametersResult:
            for p in parameters:
                spec = specs.get(p.name)
                problem = _problem(p.name, p.value, spec) if spec is not None else ""
                if problem:
                    return SetParametersResult(successful=False, reason=problem)
            return SetParametersResult(successful=True)
        node.add_on_set_parameters_callback(validate)
    return specs


def _problem(name: str, value: Any, spec: _Spec) -> str:
    """Why `value` cannot be `name`'s value ("" when it can)."""
    values = list(value) if isinstance(value, list | tuple) or hasattr(value, "tolist") else [value]
    if spec.length is not None and len(values) != spec.length:
        return f"{name} needs {spec.length} values, got {len(values)}: {list(values)}"
    if spec.number:
        for v in values:
            if isinstance(v, bool) or not isinstance(v, int | float):
                return f"{name} must be a number, got {v!r}"
            if not math.isfinite(v):
                return f"{name} must be a finite number, got {v}"
            if spec.min is not None and spec.max is not None and not spec.min <= v <= spec.max:
                return f"{name} = {v:g} is outside [{spec.min:g}, {spec.max:g}]"
    return ""


def _number(text: str) -> float | None:
    try:
        return float(text.strip())
    except ValueError:
        return None


def _coerce_override(node: Node, name: str, default: Any) -> None:
    """The value a params file or `name:=value` gives, as the number it means: `1e-6` (a string to YAML 1.1),
    an integer for a double, integers for a double array. A boolean or other text stays as given (rclpy
    then refuses its type, naming the parameter)."""
    overrides = getattr(node, "_parameter_overrides", None)
    if not isinstance(overrides, dict) or name not in overrides:
        return
    value = overrides[name].value
    coerced: Any = None
    if isinstance(default, float):
        if isinstance(value, str):
            coerced = _number(value)
            if coerced is None:
                raise UserError(f"{name} must be a number, got the string {value!r}")
        elif isinstance(value, int) and not isinstance(value, bool):
            coerced = float(value)
    elif isinstance(default, list) and default and all(isinstance(v, float) for v in default) \
            and isinstance(value, list | tuple) and value and not any(isinstance(v, bool) for v in value):
        if all(isinstance(v, int | float) for v in value) and not all(isinstance(v, float) for v in value):
            coerced = [float(v) for v in value]
    if coerced is not None:
        overrides[name] = Parameter(name, value=coerced)


def frame_id_problem(name: str, value: Any) -> str:
    """Why `value` is not a usable frame id for parameter `name` ("" when it is)."""
    try:
        names.check_frame_id(str(value), name)
    except names.InvalidName as exc:
        return str(exc)
    return ""


def check_start_up(node: Node, validate: Callable[[Sequence[Parameter]], SetParametersResult],
                   names_: Sequence[str] | None = None) -> None:
    """Run an on-set validator over the node's declared values (all, or `names_`) once: the values a node
    starts with pass the same checks as a later change. UserError (one line) when they do not."""
    chosen = names_ if names_ is not None else list(node._parameters)   # noqa: SLF001 - rclpy's declared set
    result = validate([node.get_parameter(n) for n in chosen])
    if not result.successful:
        raise UserError(f"{node.get_name()}: {result.reason}")


def declare_frame_prefix(node: Node) -> str:
    """Declare the read-only `frame_prefix` every frame id the node publishes starts with, and return it.
    Its default follows the node's namespace (`names.frame_prefix`): "" in `touchroller`, "left/" in `left`."""
    default = names.frame_prefix(node.get_namespace())
    value = str(declare(node, "frame_prefix", default, "Prefix of every frame id this node publishes (default: "
                        "none in the namespace touchroller, else the namespace and a slash, e.g. left/)",
                        read_only=True))
    try:
        return names.check_frame_prefix(value)
    except names.InvalidName as exc:
        raise UserError(str(exc)) from None


@dataclass(frozen=True)
class ParameterField:
    """One row of a node's parameter table: the ROS parameter sets config field `field`.

    The parameter is declared with `description`, the range [`min`, `max`] (both or neither), read-only or
    not, and `choices` (a text parameter: its values, said in the descriptor's additional constraints and
    checked on set); `length`: an array's length, checked on set; `constraints`: the descriptor's additional
    constraints in other words than "one of: ..."."""

    field: str
    description: str
    min: float | None = None
    max: float | None = None
    read_only: bool = False
    choices: tuple[str, ...] = ()
    length: int | None = None
    constraints: str = ""


#: a table row: a ParameterField, or the tuple (field, description, min, max[, read_only]) the tables write
TableRow = ParameterField | tuple[Any, ...]
C = TypeVar("C")


def parameter_field(row: TableRow) -> ParameterField:
    return row if isinstance(row, ParameterField) else ParameterField(*row)


def _kind(annotation: Any) -> tuple[type, type | None]:
    """(ROS-side kind, element kind): bool/int/float/str, or tuple/list with their element's kind. An optional
    field (`int | None`) is its type's: a parameter always holds a value."""
    origin = get_origin(annotation)
    if origin in (UnionType, Union):
        present = [a for a in get_args(annotation) if a is not type(None)]
        if len(present) == 1:
            return _kind(present[0])
    if origin in (tuple, list):
        elements = {a for a in get_args(annotation) if a is not Ellipsis}
        if len(elements) != 1 or next(iter(elements)) not in (bool, int, float, str):
            raise TypeError(f"no ROS parameter type for {annotation!r}")
        return origin, next(iter(elements))
    if annotation in (bool, int, float, str):
        return annotation, None
    raise TypeError(f"no ROS parameter type for {annotation!r}")


def _scalar(name: str, value: Any, kind: type) -> Any:
    """`value` as a `kind` field value; TypeError (one line) when it is not one (a boolean is no number)."""
    if kind is bool:
        if not isinstance(value, bool):
            raise TypeError(f"{name} must be true or false, got {value!r}")
        return value
    if kind is str:
        if not isinstance(value, str):
            raise TypeError(f"{name} must be text, got {value!r}")
        return value
    if isinstance(value, bool) or not isinstance(value, int | float) \
            or (kind is int and not float(value).is_integer()):
        raise TypeError(f"{name} must be {'an integer' if kind is int else 'a number'}, got {value!r}")
    return kind(value)


def parameter_values(config: Any, table: Mapping[str, TableRow]) -> dict[str, Any]:
    """The values of `config`'s fields as the table's parameters hold them (an array as a list; a field's
    type decides: a float field's 1 is 1.0)."""
    hints = get_type_hints(type(config))
    out: dict[str, Any] = {}
    for name, row in table.items():
        field = parameter_field(row).field
        kind, element = _kind(hints[field])
        value = getattr(config, field)
        out[name] = [element(v) for v in value] if element is not None else kind(value)
    return out


#: the geometry parameters' table: each sets the CameraModel field its name ends with (camera.fx -> fx)
GEOMETRY_FIELDS: dict[str, ParameterField] = {
    name: ParameterField(name.split(".", 1)[1], description, lo, hi)
    for name, (description, lo, hi) in GEOMETRY_PARAMETERS.items()
}


class ConfigParameters(Generic[C]):
    """A frozen config dataclass bound to ROS parameters by a table (parameter name -> `ParameterField`).

    Every parameter of the table is declared once (`declare`): its type is the config field's (bool, int,
    float, str, or a tuple/list of one of them: an array), its default the start config's value, with the
    row's description, range, choices and read-only flag. The start config is then built from the declared
    values (a params file's, `name:=value`'s) and checked like a change; a refusal raises UserError,
    `refused` followed by the reason, in one line.

    On-set (a change to any of the table's parameters): the candidate config is
    `dataclasses.replace(config, ...)` with the new values, so the config's own `__post_init__` checks the
    whole combination, then `check(candidate)` (the node's own checks, e.g. a sweep's plan); an exception of
    `errors` refuses the change with its message as the one-line reason. Post-set: `config` becomes the
    candidate (the hook is not run twice) and `on_change(config)` is called. Parameters outside the table
    are left to the node."""

    def __init__(self, node: Node, config: C | type[C], table: Mapping[str, TableRow], *,
                 on_change: Callable[[C], None] | None = None, check: Callable[[C], None] | None = None,
                 errors: tuple[type[BaseException], ...] = (TypeError, ValueError),
                 refused: str | None = None) -> None:
        start = config() if isinstance(config, type) else config
        self.type: type[C] = type(start)
        self.table = {name: parameter_field(row) for name, row in table.items()}
        hints = get_type_hints(self.type)
        names_ = {f.name for f in fields(self.type)}   # type: ignore[arg-type]
        self._kinds: dict[str, tuple[type, type | None]] = {}
        for name, row in self.table.items():
            if row.field not in names_:
                raise TypeError(f"{name}: {self.type.__name__} has no field {row.field!r}")
            self._kinds[name] = _kind(hints[row.field])
        self._node = node
        self._on_change = on_change
        self._check = check
        self._errors = errors
        defaults = self.values(start)
        for name, row in self.table.items():
            constraints = row.constraints or ("one of: " + ", ".join(row.choices) if row.choices else "")
            declare(node, name, defaults[name], row.description, min=row.min, max=row.max, read_only=row.read_only,
                    additional_constraints=constraints, length=row.length)
        self.config: C = start
        try:
            self.config = self._candidate({name: node.get_parameter(name).value for name in self.table})
        except errors as exc:
            raise UserError(f"{node.get_name() + ': ' if refused is None else refused}{_one_line(exc)}") from None
        node.add_on_set_parameters_callback(self._validate)
        node.add_post_set_parameters_callback(self._apply)

    def values(self, config: C | None = None) -> dict[str, Any]:
        """The parameters' values of `config` (default: the current one), as ROS holds them (arrays as lists)."""
        return parameter_values(self.config if config is None else config, self.table)

    def _field_value(self, name: str, value: Any) -> Any:
        kind, element = self._kinds[name]
        row = self.table[name]
        if element is None:
            value = _scalar(name, value, kind)
            if row.choices and value not in row.choices:
                raise ValueError(f"{name} must be one of {', '.join(row.choices)}, got {value!r}")
            return value
        if isinstance(value, str | bytes) or not hasattr(value, "__iter__"):
            raise TypeError(f"{name} must be a list, got {value!r}")
        # the length is `declare`'s to check (its own on-set callback), after the config's own checks
        return kind(_scalar(f"{name}[{i}]", v, element) for i, v in enumerate(value))

    def _candidate(self, changes: Mapping[str, Any], *, check: bool = True) -> C:
        candidate = replace(self.config, **{self.table[name].field: self._field_value(name, value)   # type: ignore[type-var]
                                            for name, value in changes.items()})
        if check and self._check is not None:
            self._check(candidate)
        return candidate

    def _changes(self, parameters: Sequence[Parameter]) -> dict[str, Any]:
        return {p.name: p.value for p in parameters if p.name in self.table}

    def _validate(self, parameters: Sequence[Parameter]) -> SetParametersResult:
        changes = self._changes(parameters)
        if changes:
            try:
                self._candidate(changes)
            except self._errors as exc:
                return SetParametersResult(successful=False, reason=_one_line(exc))
        return SetParametersResult(successful=True)

    def _apply(self, parameters: Sequence[Parameter]) -> None:
        changes = self._changes(parameters)
        if changes:   # accepted by _validate: the check hook (e.g. a sweep's whole plan) is not run again
            self.config = self._candidate(changes, check=False)
            if self._on_change is not None:
                self._on_change(self.config)


def _one_line(exc: BaseException) -> str:
    return " ".join(str(exc).split()) or type(exc).__name__


class GeometryParameters:
    """Keeps a node's CameraModel in step with its parameters: a `ConfigParameters` of GEOMETRY_FIELDS.

    On-set: the candidate model is the current one with the new values (`dataclasses.replace`); an invalid
    combination (e.g. |d| >= r, 4 distortion coefficients) is rejected with the model's reason.
    Post-set: the new model is stored and `on_change(model)` is called.
    """

    def __init__(self, node: Node, model: CameraModel | None = None,
                 on_change: Callable[[CameraModel], None] | None = None) -> None:
        self.binding = ConfigParameters(node, model or CameraModel(), GEOMETRY_FIELDS, on_change=on_change)

    @property
    def model(self) -> CameraModel:
        return self.binding.config
