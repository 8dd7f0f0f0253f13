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
