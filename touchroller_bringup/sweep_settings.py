"""The sweep node's parameters as frozen configs: its arm, the sweep `~/start` plans and the roller's mount.

`ARM_FIELDS` binds `ArmSettings` to the read-only parameters read at start-up (the arm, its limits, the
simulated clock, the robot's frames); `SWEEP_FIELDS` binds `SweepSettings` to the `sweep.*` parameters that
apply at the next `~/start` (a running sweep keeps the plan it started with), `MOUNT_FIELDS` binds
`MountConfig` to `mount.xyz` / `mount.rpy` (`touchroller_bringup.ros_params.ConfigParameters`). The sweep's
own checks (limits, reach, passes, duration) need the arm and the node's read-only limits: the node passes
them as the binding's check hook.
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

ARM_BACKENDS = ("ur_rtde", "ur_driver", "sim")   # arm.backend; use_sim true is sim whatever it says
UR5_REACH_M = 0.85   # a UR5's reach from its base (the datasheet's 850 mm)


@dataclass(frozen=True)
class ArmSettings:
    """What the sweep node reads once, at start-up: which arm, its hard limits, the simulated clock, frames."""

    use_sim: bool = True
    robot_ip: str = "192.168.1.10"
    backend: str = "ur_rtde"
    robot_timeout: float = 10.0
    max_speed: float = 0.1
    max_accel: float = 0.5
    reach: float = UR5_REACH_M
    max_duration: float = 1800.0
    sim_rate: float = 1.0
    sim_lockstep: bool = True
    sim_max_lead: float = 0.05
    publish_rate: float = 50.0
    base_frame: str = names.BASE_FRAME
    tool_frame: str = names.TOOL_FRAME
    publish_tf: bool = True


def _read_only(field: str, description: str, lo: float | None = None, hi: float | None = None,
               constraints: str = "") -> ParameterField:
    return ParameterField(field, description, lo, hi, read_only=True, constraints=constraints)


ARM_FIELDS: dict[str, ParameterField] = {
    "use_sim": _read_only("use_sim", "Use the simulated arm instead of a UR5 (read at start-up)"),
    "robot_ip": _read_only("robot_ip", "IP address of the UR controller (ur_rtde)"),
    # the node refuses an unknown backend when it makes the arm (not for an arm it is given)
    "arm.backend": _read_only("backend", "The arm when use_sim is false: ur_rtde (its own control script through "
                              "ur_rtde) or ur_driver (URScript through a running ur_robot_driver, docs/ur5.md); sim: "
                              "the simulated arm", constraints="one of: " + ", ".join(ARM_BACKENDS)),
    "robot_timeout": _read_only("robot_timeout", "Longest a ur_rtde interface may take to connect (the control "
                                "interface uploads its script), s; a UR that greets and then stays silent is given up "
                                "after it", 0.5, 120.0),
    "arm.max_speed": _read_only("max_speed", "Hard limit on any commanded tool speed, m/s", 1e-4, 1.0),
    "arm.max_accel": _read_only("max_accel", "Hard limit on any commanded tool acceleration, m/s^2", 1e-3, 5.0),
    "arm.reach": _read_only("reach", "Farthest any commanded tool position may be from the base frame's origin, m "
                            "(UR5: 0.85); a sweep or raster reaching beyond is refused", 0.05, 3.0),
    "sweep.max_duration": _read_only("max_duration", "Longest a sweep or raster may take (all its moves, from where "
                                     "the arm is), s; a longer one is refused", 1.0, 86400.0),
    "sim.rate": _read_only("sim_rate", "use_sim: simulated seconds per wall-clock second of the simulated clock "
                           "(published on /clock; the simulated camera renders on it)", 0.1, 20.0),
    "sim.lockstep": _read_only("sim_lockstep", "use_sim: the simulated clock waits for the frames: never more than "
                               "sim.max_lead s past a frame the camera has not published, the perception node has not "
                               "finished or a recorder has not written (camera_info, image_done, image_raw/recorded), "
                               "so a loaded machine makes the simulation slower, not different"),
    "sim.max_lead": _read_only("sim_max_lead", "use_sim and sim.lockstep: how far the simulated clock may run ahead "
                               "of the oldest frame perception has not finished (and of the camera's next frame), s; "
                               "frames in flight are about max_lead x fps", 0.0, 10.0),
    "sweep.publish_rate": _read_only("publish_rate", "Rate of the arm loop: TCP pose, /tf and progress messages, with "
                                     "use_sim the simulated clock's tick, watchdog kicks (>= 10 Hz), Hz", 10.0, 500.0),
    "arm.base_frame": _read_only("base_frame", "Frame of the published TCP pose and parent of the tool frame on /tf "
                                 "(the UR base, the robot driver's name: frame_prefix does not apply)"),
    "arm.tool_frame": _read_only("tool_frame", "The arm's flange frame (UR: tool0, the robot driver's name: "
                                 "frame_prefix does not apply; a second simulated arm in another namespace gets its "
                                 "own); the TCP pose is its pose"),
    "publish_tf": _read_only("publish_tf", "Publish arm.base_frame -> arm.tool_frame on /tf from the arm's pose; false "
                             "when a robot driver (e.g. ur_robot_driver) already does"),
}


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
