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
