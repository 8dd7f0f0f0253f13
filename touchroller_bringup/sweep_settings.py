"""The sweep node's run-time parameters as frozen configs: the sweep `~/start` plans and the roller's mount.

`SWEEP_FIELDS` binds `SweepSettings` to the `sweep.*` parameters that apply at the next `~/start` (a running
sweep keeps the plan it started with), `MOUNT_FIELDS` binds `MountConfig` to `mount.xyz` / `mount.rpy`
(`touchroller_bringup.ros_params.ConfigParameters`). The sweep's own checks (limits, reach, passes,
duration) need the arm and the node's read-only limits: the node passes them as the binding's check hook.
"""
from __future__ import annotations

from dataclasses import dataclass

from touchroller_bringup import names
from touchroller_bringup.ros_params import ParameterField
from touchroller_driver.arm import (
    DEFAULT_CLEARANCE,
    DEFAULT_DIRECTION,
    DEFAULT_MOUNT_RPY,
    DEFAULT_MOUNT_XYZ,
    DEFAULT_START_POSE,
    SWEEP_PROFILES,
    mount_transform,
)
from touchroller_perception.transforms import Transform


@dataclass(frozen=True)
class SweepSettings:
    """What a `~/start` plans: one roll of `length` from `start_pose`, or a raster over `area`."""

    length: float = 0.11
    speed: float = 0.011
    accel: float = 0.1
    depth: float = 0.0005
    approach_speed: float = 0.005
    start_pose: tuple[float, ...] = DEFAULT_START_POSE
    area: tuple[float, ...] = (0.0, 0.0, 0.0, 0.0)
    usable_width: float = 0.06
    overlap: float = 0.25
    direction: tuple[float, ...] = DEFAULT_DIRECTION
    profile: str = "ramp"
    retract: bool = True
    clearance: float = DEFAULT_CLEARANCE


SWEEP_FIELDS: dict[str, ParameterField] = {
    "sweep.length": ParameterField("length", "Length of the roll along sweep.direction, m", 0.0, 1.0),
    "sweep.speed": ParameterField("speed", "Roll speed, m/s (paper: 11 cm in 10 s)", 1e-4, 1.0),
    "sweep.accel": ParameterField("accel", "Acceleration of every move, m/s^2", 1e-3, 5.0),
    "sweep.depth": ParameterField("depth", "How far the roller is pressed into the surface, m", 0.0, 0.01),
    "sweep.approach_speed": ParameterField("approach_speed", "Speed to the start pose, pressing and lifting, m/s",
                                           1e-4, 1.0),
    "sweep.start_pose": ParameterField(
        "start_pose", "TCP pose [x, y, z, rx, ry, rz] (base frame, m, rotation vector) where the roller just "
        "touches the surface at the start of the sweep"),
    "sweep.area": ParameterField(
        "area", "Rectangle to cover [x, y, length, width], m, in arm.base_frame: corner (x, y), length along "
        "sweep.direction, width along the roller's axis; a boustrophedon raster of passes rolled alternately "
        "forwards and back (one pass when narrower than sweep.usable_width). length 0: one roll of sweep.length "
        "from sweep.start_pose"),
    "sweep.usable_width": ParameterField("usable_width", "Width of surface one pass maps, m (the band the camera "
                                         "sees along the axis, less a margin)", 0.001, 1.0),
    "sweep.overlap": ParameterField("overlap", "Least fraction of sweep.usable_width neighbouring passes share",
                                    0.0, 0.9),
    "sweep.direction": ParameterField("direction", "Rolling direction in the base frame (horizontal)"),
    "sweep.profile": ParameterField(
        "profile", "Motion of each pass: ramp (stop above the pass, press in at rest, accelerate, roll, stop, "
        "lift: moves one at a time), blend (each pass one path at sweep.speed through its waypoints with blend "
        "radii: descending before the pass, touching down and lifting off while moving, as a UR program of movels "
        "with blend radii) or constant (the same path with sharp corners); docs/ur5.md", choices=SWEEP_PROFILES),
    "sweep.retract": ParameterField("retract", "Lift the roller off the surface at the end of the sweep"),
    "sweep.clearance": ParameterField("clearance", "Height above the start pose the roller approaches from and "
                                      "lifts back to, m", 0.0, 0.05),
}


@dataclass(frozen=True)
class MountConfig:
    """Where the roller's axis frame sits on the arm's flange: position (m) and fixed-axis roll, pitch, yaw (rad)."""

    xyz: tuple[float, ...] = DEFAULT_MOUNT_XYZ
    rpy: tuple[float, ...] = DEFAULT_MOUNT_RPY

    def __post_init__(self) -> None:
        self.transform()   # 3 finite numbers each, or ValueError in one line

    def transform(self) -> Transform:
        """T_tool_cylinder."""
        return mount_transform(self.xyz, self.rpy)


MOUNT_FIELDS: dict[str, ParameterField] = {
    "mount.xyz": ParameterField("xyz", f"Position of {names.CYLINDER_FRAME} (the roller's axis centre) in the tool "
                                "frame, m; published on /tf_static"),
    "mount.rpy": ParameterField("rpy", f"Orientation of {names.CYLINDER_FRAME} in the tool frame, fixed-axis roll, "
                                "pitch, yaw, rad (x along the roller axis, z down at the contact)"),
}
