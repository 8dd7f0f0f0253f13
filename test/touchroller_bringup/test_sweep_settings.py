"""The sweep node's run-time configs and their parameter tables (touchroller_bringup.sweep_settings)."""
from __future__ import annotations

from dataclasses import fields

import pytest

pytest.importorskip("rclpy")
from touchroller_bringup.ros_params import parameter_values  # noqa: E402
from touchroller_bringup.sweep_settings import (  # noqa: E402
    ARM_FIELDS,
    MOUNT_FIELDS,
    SWEEP_FIELDS,
    ArmSettings,
    MountConfig,
    SweepSettings,
)
from touchroller_driver.arm import SWEEP_PROFILES  # noqa: E402


def test_every_field_is_a_parameter_and_every_parameter_a_field():
    for config, table in ((SweepSettings, SWEEP_FIELDS), (MountConfig, MOUNT_FIELDS), (ArmSettings, ARM_FIELDS)):
        assert sorted(row.field for row in table.values()) == sorted(f.name for f in fields(config))
        assert all(row.description for row in table.values())
    # what the node reads once, at start-up, cannot change under it; the sweep and the mount can
    assert all(row.read_only for row in ARM_FIELDS.values())
    assert not any(row.read_only for row in (*SWEEP_FIELDS.values(), *MOUNT_FIELDS.values()))


def test_the_parameters_hold_the_configs_values_arrays_as_lists():
    values = parameter_values(SweepSettings(area=(0.4, -0.03, 0.05, 0.1)), SWEEP_FIELDS)
    assert values["sweep.area"] == [0.4, -0.03, 0.05, 0.1] and values["sweep.profile"] == "ramp"
    assert SWEEP_FIELDS["sweep.profile"].choices == SWEEP_PROFILES


@pytest.mark.parametrize("xyz, rpy, message", [
    ((0.0, 0.0), (0.0, 0.0, 0.0), "take 3 numbers each"),
    ((0.0, 0.0, 0.1), (float("nan"), 0.0, 0.0), "must be finite"),
])
def test_a_mount_that_is_no_transform_is_refused_at_construction(xyz, rpy, message):
    with pytest.raises(ValueError, match=message):
        MountConfig(xyz, rpy)
