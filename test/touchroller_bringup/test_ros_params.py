"""Geometry parameters on a real rclpy node: descriptors, validation on set, application after set."""
from __future__ import annotations

import pytest

pytest.importorskip("rclpy")
from rclpy.node import Node  # noqa: E402
from rclpy.parameter import Parameter  # noqa: E402

from touchroller_bringup.ros_params import GEOMETRY_PARAMETERS, GeometryParameters, declare  # noqa: E402
from touchroller_perception.geometry import PARAMETER_RANGES, CameraModel  # noqa: E402


@pytest.fixture
def node(ros_context):
    node = Node("params_under_test", context=ros_context)
    yield node
    node.destroy_node()


def test_every_geometry_parameter_has_a_description_and_range(node):
    GeometryParameters(node)
    for name in GEOMETRY_PARAMETERS:
        descriptor = node.describe_parameter(name)
        assert descriptor.description, name
        if name != "camera.distortion":
            assert descriptor.floating_point_range or descriptor.integer_range, name


def test_the_declared_ranges_are_the_camera_models_own(node):
    """One range per parameter: what a node accepts and what a params file read without ROS may hold."""
    GeometryParameters(node)
    for name, (lo, hi, _unit) in PARAMETER_RANGES.items():
        descriptor = node.describe_parameter(name)
        (declared,) = descriptor.floating_point_range or descriptor.integer_range
        assert (declared.from_value, declared.to_value) == (lo, hi), name


def test_update_is_validated_then_applied(node):
    seen: list[CameraModel] = []
    geometry = GeometryParameters(node, CameraModel(theta=0.0), on_change=seen.append)
    result = node.set_parameters([Parameter("extrinsics.theta", value=0.2), Parameter("extrinsics.d", value=0.004)])
    assert all(r.successful for r in result)
    assert (geometry.model.theta, geometry.model.d) == (0.2, 0.004)
    assert seen[-1] is geometry.model

    (refused,) = node.set_parameters([Parameter("extrinsics.d", value=0.06)])   # |d| >= r
    assert not refused.successful and "outside the tube" in refused.reason
    assert geometry.model.d == 0.004
    (bad_dist,) = node.set_parameters([Parameter("camera.distortion", value=[0.1, 0.2])])
    assert not bad_dist.successful and "5 coefficients" in bad_dist.reason


def test_values_outside_the_declared_range_are_rejected_by_rclpy(node):
    GeometryParameters(node)
    (result,) = node.set_parameters([Parameter("cylinder.radius", value=5.0)])
    assert not result.successful


def test_declare_integer_parameters_get_integer_ranges(node):
    assert declare(node, "queue", 3, "queue depth", min=1, max=10) == 3
    assert node.describe_parameter("queue").integer_range[0].to_value == 10


def _node_with(ros_context, **overrides):
    return Node("declared_under_test", context=ros_context,
                parameter_overrides=[Parameter(k, value=v) for k, v in overrides.items()])


@pytest.mark.parametrize("given, taken", [("1e-6", 1e-6), (5, 5.0), (" 2.5 ", 2.5)])
def test_a_number_as_text_or_an_integer_is_taken_as_the_double_it_means(ros_context, given, taken):
    """#28: `map.resolution:=1e-6` reaches the node as the string '1e-6' (YAML 1.1); a params file's `5`
    for a double was refused by rclpy as an INTEGER."""
    node = _node_with(ros_context, x=given)
    try:
        assert declare(node, "x", 1.0, "a double", min=0.0, max=10.0) == taken
    finally:
        node.destroy_node()


@pytest.mark.parametrize("given, default, length, message", [
    ("abc", 1.0, None, "x must be a number, got the string 'abc'"),
    ([float("nan"), 0.0, 1.0, 1.0], [0.0, 0.0, 0.0, 0.0], 4, "x must be a finite number"),
    ([0.0, 0.0, 1.0], [0.0, 0.0, 0.0, 0.0], 4, "x needs 4 values, got 3"),
    (float("inf"), 1.0, None, "x must be a finite number"),
])
def test_a_value_that_cannot_be_used_is_refused_at_declaration_in_one_line(ros_context, given, default, length,
                                                                          message):
    from touchroller_bringup.errors import UserError

    node = _node_with(ros_context, x=given)
    try:
        with pytest.raises(UserError, match=message.replace("[", r"\[")):
            declare(node, "x", default, "a value", length=length)
    finally:
        node.destroy_node()


def test_the_same_checks_hold_on_set(node):
    declare(node, "bounds", [0.0, 0.0, 0.0, 0.0], "four numbers", length=4)
    for bad in ([0.0, 0.0, 1.0], [float("nan"), 0.0, 1.0, 1.0]):
        result = node.set_parameters([Parameter("bounds", value=bad)])[0]
        assert not result.successful and "bounds" in result.reason
    assert node.set_parameters([Parameter("bounds", value=[0.0, 0.0, 1.0, 1.0])])[0].successful


# -- ConfigParameters: a frozen config bound to parameters by a table ------------------------------------------
from dataclasses import dataclass  # noqa: E402

from touchroller_bringup.ros_params import ConfigParameters, ParameterField  # noqa: E402


@dataclass(frozen=True)
class _Config:
    low: float = 1.0
    high: float = 2.0
    count: int = 3
    mode: str = "a"
    flag: bool = True
    pose: tuple[float, ...] = (0.0, 0.0, 0.0)

    def __post_init__(self) -> None:
        if not self.low < self.high:
            raise ValueError(f"low must be below high, got {self.low} >= {self.high}")


_TABLE = {
    "x.low": ParameterField("low", "The low end", 0.0, 10.0),
    "x.high": ParameterField("high", "The high end", 0.0, 10.0),
    "x.count": ParameterField("count", "How many", 1, 100, read_only=True),
    "x.mode": ParameterField("mode", "The mode", choices=("a", "b"), constraints="a or b"),
    "x.flag": ("flag", "A flag", None, None),          # a table's tuple row
    "x.pose": ParameterField("pose", "Three numbers", length=3),
}


def test_every_parameter_of_the_table_is_declared_once_with_its_type_range_and_description(node):
    binding = ConfigParameters(node, _Config(low=0.5), _TABLE)
    assert binding.config == _Config(low=0.5)
    assert {n: node.get_parameter(n).value for n in _TABLE} == {
        "x.low": 0.5, "x.high": 2.0, "x.count": 3, "x.mode": "a", "x.flag": True, "x.pose": [0.0, 0.0, 0.0]}
    low = node.describe_parameter("x.low")
    assert low.description == "The low end" and not low.read_only
    (declared,) = low.floating_point_range
    assert (declared.from_value, declared.to_value) == (0.0, 10.0)
    count = node.describe_parameter("x.count")
    assert count.read_only and (count.integer_range[0].from_value, count.integer_range[0].to_value) == (1, 100)
    assert node.describe_parameter("x.mode").additional_constraints == "a or b"
    types = {n: node.get_parameter(n).type_ for n in _TABLE}
    assert types["x.low"] == Parameter.Type.DOUBLE and types["x.count"] == Parameter.Type.INTEGER
    assert types["x.pose"] == Parameter.Type.DOUBLE_ARRAY and types["x.flag"] == Parameter.Type.BOOL
    assert types["x.mode"] == Parameter.Type.STRING


def test_an_applied_change_reaches_the_callback_as_a_new_frozen_config(node):
    seen: list[_Config] = []
    binding = ConfigParameters(node, _Config, _TABLE, on_change=seen.append)
    results = node.set_parameters_atomically([Parameter("x.low", value=4.0), Parameter("x.high", value=5.0)])
    assert results.successful
    assert seen == [_Config(low=4.0, high=5.0)] and binding.config is seen[-1]
    assert node.set_parameters([Parameter("x.pose", value=[1.0, 2.0, 3.0])])[0].successful
    assert seen[-1] == _Config(low=4.0, high=5.0, pose=(1.0, 2.0, 3.0)) and isinstance(seen[-1].pose, tuple)
    declare(node, "other", 1, "a parameter of the node's own, outside the table")
    assert node.set_parameters([Parameter("other", value=2)])[0].successful   # nothing reaches the callback
    assert len(seen) == 2


@pytest.mark.parametrize("name, value, reason", [
    ("x.low", 11.0, "x.low"),                                   # outside the declared range
    ("x.low", 3.0, "low must be below high, got 3.0 >= 2.0"),   # an invalid combination: the config's own check
    ("x.mode", "c", "x.mode must be one of a, b, got 'c'"),
    ("x.pose", [1.0, 2.0], "x.pose needs 3 values, got 2"),
    ("x.count", 5, "read-only"),
])
def test_a_refused_change_leaves_the_config_and_says_why_in_one_line(node, name, value, reason):
    seen: list[_Config] = []
    binding = ConfigParameters(node, _Config, _TABLE, on_change=seen.append)
    (result,) = node.set_parameters([Parameter(name, value=value)])
    assert not result.successful and reason in result.reason and "\n" not in result.reason, result.reason
    assert binding.config == _Config() and seen == []
    assert node.get_parameter(name).value == binding.values()[name]


def test_the_check_hook_refuses_what_the_config_alone_allows(node):
    checked: list[_Config] = []

    def check(config: _Config) -> None:
        checked.append(config)
        if config.high - config.low > 5.0:
            raise ValueError(f"the span {config.high - config.low:g} is wider than 5")

    seen: list[_Config] = []
    ConfigParameters(node, _Config, _TABLE, on_change=seen.append, check=check)
    (result,) = node.set_parameters([Parameter("x.high", value=9.0)])
    assert not result.successful and result.reason == "the span 8 is wider than 5"
    checked.clear()
    assert node.set_parameters([Parameter("x.high", value=6.0)])[0].successful and seen[-1].high == 6.0
    assert checked == [seen[-1]]   # once, on set (a sweep's plan is not made again after it was accepted)


def test_start_up_values_get_the_checks_a_change_gets(ros_context):
    from touchroller_bringup.errors import UserError

    node = _node_with(ros_context, **{"x.low": 3.0})
    try:
        with pytest.raises(UserError, match=r"^declared_under_test: low must be below high, got 3.0 >= 2.0$"):
            ConfigParameters(node, _Config, _TABLE)
    finally:
        node.destroy_node()
    node = _node_with(ros_context, **{"x.mode": "c"})
    try:
        with pytest.raises(UserError, match=r"^x refused: x.mode must be one of a, b, got 'c'$"):
            ConfigParameters(node, _Config, _TABLE, refused="x refused: ")
    finally:
        node.destroy_node()
    node = _node_with(ros_context, **{"x.low": 0.5, "x.count": 7})
    try:
        assert ConfigParameters(node, _Config, _TABLE, refused="x refused: ").config == _Config(low=0.5, count=7)
    finally:
        node.destroy_node()


@dataclass(frozen=True)
class _Optional:
    most: int | None = 10


def test_an_optional_field_is_declared_with_its_types_parameter(node):
    binding = ConfigParameters(node, _Optional, {"most": ParameterField("most", "At most", 1, 100)})
    assert node.get_parameter("most").type_ == Parameter.Type.INTEGER
    assert node.set_parameters([Parameter("most", value=20)])[0].successful and binding.config == _Optional(20)


def test_choices_are_said_in_the_descriptor_unless_the_row_words_them(node):
    ConfigParameters(node, _Config, {"x.mode": ParameterField("mode", "The mode", choices=("a", "b")),
                                     "x.high": ParameterField("high", "The high end", constraints="above x.low")})
    assert node.describe_parameter("x.mode").additional_constraints == "one of: a, b"
    assert node.describe_parameter("x.high").additional_constraints == "above x.low"


def test_the_config_stays_in_step_with_the_parameters_whatever_is_set(ros_context):
    """Property: after any run of changes, refused or not, atomic or one by one, the binding's config is the
    config of the node's parameter values, and it is valid (low < high)."""
    from hypothesis import HealthCheck, given, settings
    from hypothesis import strategies as st

    from touchroller_bringup.ros_params import parameter_values

    node = Node("params_in_step", context=ros_context)
    binding = ConfigParameters(node, _Config, _TABLE)
    value = st.one_of(st.floats(allow_nan=True, allow_infinity=True, width=32), st.integers(-3, 12))
    change = st.tuples(st.sampled_from(["x.low", "x.high"]), value)

    @settings(max_examples=60, deadline=None, suppress_health_check=[HealthCheck.too_slow])
    @given(st.lists(st.tuples(st.lists(change, min_size=1, max_size=2), st.booleans()), max_size=4))
    def run(steps):
        for changes, atomic in steps:
            parameters = [Parameter(n, value=float(v)) for n, v in changes]
            if atomic:
                node.set_parameters_atomically(parameters)
            else:
                node.set_parameters(parameters)
            assert parameter_values(binding.config, _TABLE) == {n: node.get_parameter(n).value for n in _TABLE}
            assert binding.config.low < binding.config.high

    try:
        run()
    finally:
        node.destroy_node()
