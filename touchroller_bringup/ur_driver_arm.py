"""A UR arm driven through a running Universal Robots ROS 2 driver (ur_robot_driver), behind `Arm`.

For labs whose robot runs the official driver (ros2_control, MoveIt) all day: instead of ur_rtde's own
control script (`touchroller_driver.ur5`), each linear move is one URScript program published on the
driver's `urscript_interface/script_command` (std_msgs/String), the tool pose is read from the TF its
robot_state_publisher publishes (`base -> tool0`, chained through whatever the driver's tree holds), and
the robot's state from its `io_and_status_controller`: `safety_mode` (ur_dashboard_msgs/SafetyMode),
`robot_mode` (ur_dashboard_msgs/RobotMode) and `robot_program_running` (std_msgs/Bool), all three
published on change with transient-local QoS, so a late subscriber gets the current value at once (the
program state changes from a default false: nothing on it means false).

What the driver gives and what it does not, and so how this back end works:

- A program sent on `script_command` replaces whatever program runs on the robot, including the driver's
  own External Control program (ros2_control and MoveIt stop commanding the robot until
  `io_and_status_controller/resend_robot_program` or the pendant's play button starts it again), and the
  driver reports nothing about it (an invalid program is silently not run). So a move is known to run
  only from the tool pose: a movel that does not move the tool within `start_timeout`, or a tool that
  stands still short of the target for `stall_timeout`, is a fault; the driver's External Control
  program starting while our move runs (it ends our program) is a fault.
- `robot_program_running` is the External Control program's state, not ours: false while our moves run.
- Each move is one movel to a checked target (`ArmLimits` before anything is published; a NaN never
  reaches the robot); a pass of `sweep.profile` blend/constant is one program of movels with blend radii
  (`path_program`), every waypoint and corner checked first. If this process hangs or dies, the robot
  finishes at most the current segment (or pass) and stops there: nothing of ours is queued behind it,
  and there is no watchdog to kick.
- `stop()` sends `stopl(a)` when a program of ours may still be moving the robot, and never interrupts
  a program it did not start (an idle sweep node leaves MoveIt's External Control program alone).
- `fault()`: a safety mode other than NORMAL/REDUCED (protective, safeguard or emergency stop, ...), a
  robot mode other than RUNNING, no fresh `base -> tool0` on TF for `driver_timeout` (a lost or silent
  driver), a move that does not start or stalls, the External Control program taking the robot back.
  A fault stays until `reset_fault()`, which clears only what can be cleared: an emergency stop must
  be released on the pendant, a protective stop is unlocked through the driver's dashboard client
  (`unlock_service`, std_srvs/Trigger) when it offers that, and the reset succeeds only once the driver
  reports the robot healthy again.

The arm has its own rclpy node and executor thread (in the context it is given), so its subscriptions
are served while the sweep node's executor is busy; every `Arm` call still comes from one thread.
Tested against a fake driver only (test/touchroller_bringup/fake_ur_driver.py): see docs/ur5.md.
"""
from __future__ import annotations

import math
import re
import threading
import time
from collections import deque
from collections.abc import Sequence
from dataclasses import dataclass, field, fields
from typing import Any

import numpy as np
from numpy.typing import ArrayLike
from rclpy.node import Node
from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy
from std_msgs.msg import Bool, String
from std_srvs.srv import Trigger

from touchroller_bringup.ros_params import ParameterField
from touchroller_bringup.tf import TransformListener
from touchroller_driver.arm import ArmError, ArmLimits, as_pose, check_path_start
from touchroller_driver.path import blend_radii, fraction_along_path
from touchroller_perception.transforms import TransformBuffer, TransformError

# ur_dashboard_msgs/msg/SafetyMode and RobotMode values (the messages' constants, here so that the
# names can be reported without the messages)
SAFETY_MODES = {1: "NORMAL", 2: "REDUCED", 3: "PROTECTIVE_STOP", 4: "RECOVERY", 5: "SAFEGUARD_STOP",
                6: "SYSTEM_EMERGENCY_STOP", 7: "ROBOT_EMERGENCY_STOP", 8: "VIOLATION", 9: "FAULT",
                10: "VALIDATE_JOINT_ID", 11: "UNDEFINED_SAFETY_MODE", 12: "AUTOMATIC_MODE_SAFEGUARD_STOP",
                13: "SYSTEM_THREE_POSITION_ENABLING_STOP"}
HEALTHY_SAFETY_MODES = frozenset({1, 2})
PROTECTIVE_STOP = 3
EMERGENCY_STOPS = frozenset({6, 7})
ROBOT_MODES = {-1: "NO_CONTROLLER", 0: "DISCONNECTED", 1: "CONFIRM_SAFETY", 2: "BOOTING", 3: "POWER_OFF",
               4: "POWER_ON", 5: "IDLE", 6: "BACKDRIVE", 7: "RUNNING", 8: "UPDATING_FIRMWARE"}
ROBOT_RUNNING = 7

#: the io_and_status_controller's publishers: SystemDefaultsQoS made transient local (latched)
LATCHED_QOS = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=1, reliability=ReliabilityPolicy.RELIABLE,
                         durability=DurabilityPolicy.TRANSIENT_LOCAL)
SCRIPT_QOS = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=10, reliability=ReliabilityPolicy.RELIABLE,
                        durability=DurabilityPolicy.VOLATILE)
#: a fully qualified or relative ROS name: segments of letters, digits and _, not starting with a digit
_ROS_NAME = re.compile(r"/?[A-Za-z_][A-Za-z0-9_]*(/[A-Za-z_][A-Za-z0-9_]*)*")
MOVE_PROGRAM = "touchroller_move"
STOP_PROGRAM = "touchroller_stop"


@dataclass(frozen=True)
class URDriverConfig:
    """Where the driver's interfaces are and how long its silence is tolerated (see the module docstring)."""

    script_topic: str = "/urscript_interface/script_command"
    program_running_topic: str = "/io_and_status_controller/robot_program_running"
    safety_mode_topic: str = "/io_and_status_controller/safety_mode"
    robot_mode_topic: str = "/io_and_status_controller/robot_mode"
    unlock_service: str = "/dashboard_client/unlock_protective_stop"   # "" : never unlock, say so
    base_frame: str = "base"
    tool_frame: str = "tool0"
    driver_timeout: float = 0.5      # s without a fresh base -> tool0 on TF: the driver is lost
    connect_timeout: float = 5.0     # s connect() waits for the driver's topics
    reset_timeout: float = 3.0       # s the whole of reset_fault() may take (within the sweep node's 5 s answer)
    start_timeout: float = 1.0       # s a published movel has to start moving the tool
    stall_timeout: float = 1.0       # s the tool may stand still short of the movel's target
    arrive_tolerance: float = 2e-4   # m from the target at which a movel counts as done (once settled)
    settle_time: float = 0.1         # s the tool must stand still there (the next program must not cut it short)
    still_tolerance: float = 2e-5    # m the tool must move to count as moving (above encoder noise)
    stop_deceleration: float = 0.5   # m/s^2 of stopl

    def __post_init__(self) -> None:
        self.validate()

    def validate(self) -> None:
        """ValueError (one line) naming the first bad value."""
        for name in ("script_topic", "program_running_topic", "safety_mode_topic", "robot_mode_topic",
                     "unlock_service"):
            value = getattr(self, name)
            if not isinstance(value, str) or not (_ROS_NAME.fullmatch(value) or (name == "unlock_service"
                                                                                  and value == "")):
                empty = " or empty" if name == "unlock_service" else ""
                raise ValueError(f"ur_driver.{name} must be a ROS topic or service name{empty} (letters, digits, "
                                 f"_ and /, e.g. /io_and_status_controller/safety_mode), got {value!r}")
        for name in ("base_frame", "tool_frame"):
            value = getattr(self, name)
            if not isinstance(value, str) or not value.strip() or any(c.isspace() for c in value):
                raise ValueError(f"ur_driver.{name} must be a non-empty frame id without spaces, got {value!r}")
        if self.base_frame == self.tool_frame:
            raise ValueError(f"ur_driver.base_frame and ur_driver.tool_frame are both {self.base_frame!r}")
        for name in ("driver_timeout", "connect_timeout", "reset_timeout", "start_timeout", "stall_timeout",
                     "arrive_tolerance", "settle_time", "still_tolerance", "stop_deceleration"):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, (int, float)) or not (math.isfinite(value)
                                                                                     and value > 0):
                raise ValueError(f"ur_driver.{name} must be a finite number > 0, got {value!r}")
        if self.still_tolerance >= self.arrive_tolerance:
            raise ValueError(f"ur_driver.still_tolerance ({self.still_tolerance} m) must be below "
                             f"ur_driver.arrive_tolerance ({self.arrive_tolerance} m)")


# parameter name -> (URDriverConfig field, description, min, max); read at start-up (read-only)
_UR_DRIVER_ROWS: dict[str, tuple[str, str, float | None, float | None]] = {
    "ur_driver.script_topic": ("script_topic", "arm.backend ur_driver: the driver's urscript_interface topic "
                               "(std_msgs/String) the movel/stopl programs are published on", None, None),
    "ur_driver.program_running_topic": ("program_running_topic", "arm.backend ur_driver: the driver's External "
                                        "Control program state (std_msgs/Bool, latched)", None, None),
    "ur_driver.safety_mode_topic": ("safety_mode_topic", "arm.backend ur_driver: the robot's safety mode "
                                    "(ur_dashboard_msgs/SafetyMode, latched)", None, None),
    "ur_driver.robot_mode_topic": ("robot_mode_topic", "arm.backend ur_driver: the robot mode "
                                   "(ur_dashboard_msgs/RobotMode, latched)", None, None),
    "ur_driver.unlock_service": ("unlock_service", "arm.backend ur_driver: the dashboard client's "
                                 "std_srvs/Trigger that unlocks a protective stop on ~/reset_fault (empty: never; "
                                 "unlock on the pendant)", None, None),
    "ur_driver.base_frame": ("base_frame", "arm.backend ur_driver: the driver's base frame (TF; no frame_prefix)",
                             None, None),
    "ur_driver.tool_frame": ("tool_frame", "arm.backend ur_driver: the driver's flange frame (TF; no "
                             "frame_prefix)", None, None),
    "ur_driver.driver_timeout": ("driver_timeout", "arm.backend ur_driver: seconds without a fresh base -> tool "
                                 "transform before the driver counts as lost (a fault)", 0.01, 60.0),
    "ur_driver.connect_timeout": ("connect_timeout", "arm.backend ur_driver: seconds connecting waits for the "
                                  "driver's TF, modes and script subscriber", 0.1, 120.0),
    "ur_driver.reset_timeout": ("reset_timeout", "arm.backend ur_driver: seconds ~/reset_fault may take in all "
                                "(unlock, then the driver reporting the robot healthy); below the sweep node's "
                                "5 s service answer", 0.1, 4.5),
    "ur_driver.start_timeout": ("start_timeout", "arm.backend ur_driver: seconds a sent movel has to start "
                                "moving the tool (else a fault: remote control off, script refused)", 0.05, 60.0),
    "ur_driver.stall_timeout": ("stall_timeout", "arm.backend ur_driver: seconds the tool may stand still short "
                                "of a movel's target (else a fault)", 0.05, 60.0),
    "ur_driver.arrive_tolerance": ("arrive_tolerance", "arm.backend ur_driver: distance to the target at which a "
                                   "movel is done, m", 1e-6, 0.01),
    "ur_driver.settle_time": ("settle_time", "arm.backend ur_driver: seconds the tool must stand still within "
                              "arrive_tolerance of the target before the next move is sent", 0.01, 5.0),
    "ur_driver.still_tolerance": ("still_tolerance", "arm.backend ur_driver: least tool motion that counts as "
                                  "moving, m (above the encoders' noise)", 1e-7, 0.005),
    "ur_driver.stop_deceleration": ("stop_deceleration", "arm.backend ur_driver: stopl's tool deceleration, "
                                    "m/s^2", 0.01, 10.0),
}
#: the `ur_driver.*` parameters, bound to URDriverConfig; read-only: the arm is made once, at start-up
UR_DRIVER_PARAMETERS: dict[str, ParameterField] = {name: ParameterField(*row, read_only=True)
                                                   for name, row in _UR_DRIVER_ROWS.items()}
assert {row.field for row in UR_DRIVER_PARAMETERS.values()} == {f.name for f in fields(URDriverConfig)}


def make_ur_driver_arm(node: Node, limits: ArmLimits) -> URDriverArm:
    """The sweep node's factory for `arm.backend: ur_driver`: declares `ur_driver.*` on `node` (a
    ConfigParameters of UR_DRIVER_PARAMETERS) and builds the arm in the node's context (it connects later,
    from the sweep node's worker thread). UserError (one line, naming the node and the parameter) for a bad
    value."""
    from touchroller_bringup.ros_params import ConfigParameters

    config = ConfigParameters(node, URDriverConfig(), UR_DRIVER_PARAMETERS).config
    return URDriverArm(config, limits=limits, context=node.context)


def format_number(value: float) -> str:
    """A finite float as URScript reads it: positional, no exponent, exact to the float's shortest repr."""
    if not math.isfinite(value):
        raise ArmError(f"non-finite value {value} in a URScript program")
    return str(np.format_float_positional(float(value), trim="0"))


def movel_program(target: ArrayLike, speed: float, accel: float) -> str:
    """One movel as a URScript program (checked values only: see `URDriverArm.move_linear`)."""
    pose = as_pose(target)
    if not (math.isfinite(speed) and speed > 0 and math.isfinite(accel) and accel > 0):
        raise ArmError(f"movel needs a finite speed and acceleration > 0, got v={speed}, a={accel}")
    values = ", ".join(format_number(v) for v in pose)
    return (f"def {MOVE_PROGRAM}():\n  movel(p[{values}], a={format_number(accel)}, v={format_number(speed)})\n"
            "end\n")


def path_program(waypoints: ArrayLike, speed: float, accel: float, blend: float) -> str:
    """A path as one URScript program: a movel to every waypoint with its blend radius (`blend_radii`: 0
    at both ends, so the robot stops only at the last), checked values only (see `URDriverArm.move_path`)."""
    points = np.asarray(waypoints, np.float64)
    if points.ndim != 2 or points.shape[1] != 6 or len(points) < 1:
        raise ArmError(f"a path is waypoints (N, 6), got an array of shape {points.shape}")
    if not (math.isfinite(speed) and speed > 0 and math.isfinite(accel) and accel > 0
            and math.isfinite(blend) and blend >= 0):
        raise ArmError(f"movel needs a finite speed and acceleration > 0 and a blend >= 0, got v={speed}, "
                       f"a={accel}, r={blend}")
    lines = []
    for pose, radius in zip(points, blend_radii(points, blend), strict=True):
        values = ", ".join(format_number(v) for v in as_pose(pose))
        lines.append(f"  movel(p[{values}], a={format_number(accel)}, v={format_number(speed)}, "
                     f"r={format_number(float(radius))})\n")
    return f"def {MOVE_PROGRAM}():\n{''.join(lines)}end\n"


def stopl_program(deceleration: float) -> str:
    if not (math.isfinite(deceleration) and deceleration > 0):
        raise ArmError(f"stopl needs a finite deceleration > 0, got {deceleration}")
    return f"def {STOP_PROGRAM}():\n  stopl({format_number(deceleration)})\nend\n"


@dataclass
class _Move:
    start: np.ndarray
    target: np.ndarray
    sent: float                  # monotonic time the program was published
    programs_started: int        # the External Control program's starts seen when it was sent
    path: np.ndarray | None = None   # a path's waypoints (N, 6): progress is along them
    sent_ns: int = field(default_factory=time.time_ns)   # wall time sent: the publisher's stamps are wall time


class URDriverArm:
    """`touchroller_driver.arm.Arm` through ur_robot_driver's topics (see the module docstring)."""

    #: the driver's robot_state_publisher publishes base -> tool0: a node driving this arm must not publish it
    #: too (tool0 would have two parents)
    publishes_tool_tf = True

    def __init__(self, config: URDriverConfig | None = None, *, limits: ArmLimits | None = None,
                 context: Any = None, node_name: str = "touchroller_ur_driver_arm") -> None:
        self.config = config or URDriverConfig()
        self.limits = limits or ArmLimits()
        self._context = context
        self._node_name = node_name
        self._node: Node | None = None
        self._executor: Any = None
        self._spinner: threading.Thread | None = None
        self._spinning = threading.Event()
        self._aborted = threading.Event()   # abort(): a wait under way gives up; cleared by connect / reset
        self._script_pub: Any = None
        self._unlock: Any = None
        self._tf: TransformListener | None = None
        self._lock = threading.Lock()   # the driver's state, written by the executor thread
        self._clear_driver_state()
        self._fault: str | None = None
        self._move: _Move | None = None
        self._halted_fraction = 1.0
        self.sent: deque[str] = deque(maxlen=100)   # the programs published last (newest last)

    def _clear_driver_state(self) -> None:
        with self._lock:
            self._pose: np.ndarray | None = None
            self._pose_stamp: int | None = None
            self._pose_time = -math.inf      # monotonic time of the newest fresh pose
            self._still_pose: np.ndarray | None = None
            self._still_since = -math.inf    # monotonic time the tool last moved by more than still_tolerance
            self._safety_mode: int | None = None
            self._robot_mode: int | None = None
            self._program_running: bool | None = None
            self._program_starts = 0         # External Control program false -> true transitions seen

    # -- connection ----------------------------------------------------------------------------
    def connect(self) -> None:
        """Create the node, wait (up to `connect_timeout`) for the driver's TF, safety and robot modes and
        script subscriber; ArmError (one line) naming what is missing."""
        self.disconnect()
        self._aborted.clear()
        self._fault, self._move, self._halted_fraction = None, None, 1.0
        self._clear_driver_state()   # nothing from an earlier connection counts (a restarted driver's clock)
        try:
            self._open()
        except Exception as exc:  # noqa: BLE001 - rclpy refusing a name or the context: one line, no traceback
            self.disconnect()
            self._fault = f"cannot subscribe to the UR driver: {' '.join(str(exc).split())}"
            raise ArmError(self._fault) from exc
        missing = self._wait_for_driver(self.config.connect_timeout)
        if missing:
            message = f"no UR driver: {missing} within {self.config.connect_timeout:g} s (is ur_robot_driver running?)"
            self._fault = message
            raise ArmError(message)

    def disconnect(self) -> None:
        if self._node is None:
            return
        if self._move is not None:
            self.stop()
        self._spinning.clear()
        if self._spinner is not None:
            self._spinner.join(timeout=2.0)
        try:
            if self._executor is not None:
                self._executor.shutdown()
            self._node.destroy_node()
        except Exception:  # noqa: BLE001 - the context is already gone: nothing left to release
            pass
        self._node = self._executor = self._spinner = self._script_pub = self._unlock = self._tf = None

    def keepalive(self) -> None:
        """Nothing to kick: the driver has no watchdog for script programs; each movel is one bounded
        segment, so a hang here lets at most the current one finish."""

    # -- state ---------------------------------------------------------------------------------
    @property
    def program_running(self) -> bool | None:
        """The driver's External Control program runs (ros2_control/MoveIt hold the robot). None: nothing
        received, which means false (the driver publishes it on change from false, latched)."""
        with self._lock:
            return self._program_running

    def tcp_pose(self) -> np.ndarray:
        with self._lock:
            pose = self._pose
        if pose is None:
            raise ArmError(self._fault or "arm not connected")
        return pose.copy()

    def fault(self) -> str | None:
        """The first of: a latched fault, an unhealthy safety or robot mode, a lost driver, a move that does
        not start or stalls, the External Control program taking the robot back. One line; None if healthy."""
        if self._fault is not None or self._node is None:
            return self._fault
        now = time.monotonic()
        with self._lock:
            safety, robot, pose_time = self._safety_mode, self._robot_mode, self._pose_time
            still_since, starts, pose = self._still_since, self._program_starts, self._pose
        fault: str | None = None
        if safety is not None and safety not in HEALTHY_SAFETY_MODES:
            kind = ("protective stop" if safety == PROTECTIVE_STOP else
                    "emergency stop" if safety in EMERGENCY_STOPS else "safety stop")
            fault = f"{kind} (safety mode {SAFETY_MODES.get(safety, safety)})"
        elif robot is not None and robot != ROBOT_RUNNING:
            fault = (f"the robot is not running (robot mode {ROBOT_MODES.get(robot, robot)}): power it on and "
                     "release the brakes")
        elif now - pose_time > self.config.driver_timeout:
            fault = (f"lost the UR driver: no {self.config.base_frame} -> {self.config.tool_frame} on TF for "
                     f"{min(now - pose_time, 1e6):.2g} s")
        elif self._move is not None and pose is not None:
            move = self._move
            if starts > move.programs_started:
                fault = "the driver's External Control program started during the move and ended it"
            elif _distance(pose, move.target) > self.config.arrive_tolerance:
                moved = still_since > move.sent
                idle = now - max(still_since, move.sent)
                if not moved and idle > self.config.start_timeout:
                    fault = (f"the robot did not start the movel within {self.config.start_timeout:g} s (remote "
                             "control off, or the program refused?)")
                elif moved and idle > self.config.stall_timeout:
                    fault = (f"the tool stopped {1000 * _distance(pose, move.target):.3g} mm short of the movel's "
                             f"target for {self.config.stall_timeout:g} s (another program took the robot?)")
        if fault is not None:
            self._fault = fault
        return self._fault

    def is_moving(self) -> bool:
        """A movel of ours is under way: sent, and the tool not yet standing still (for `settle_time`) within
        `arrive_tolerance` of its target. (A program sent earlier would replace this one on the robot.)"""
        move = self._move
        if move is None:
            return False
        with self._lock:
            still_since = self._still_since
        if (_distance(self.tcp_pose(), move.target) <= self.config.arrive_tolerance
                and time.monotonic() - still_since >= self.config.settle_time):
            self._move, self._halted_fraction = None, 1.0
            return False
        return True

    def progress(self) -> float:
        """Fraction (0..1) of the current or last move, from the tool pose on TF."""
        move = self._move
        if move is None:
            return self._halted_fraction
        return _move_fraction(move, self.tcp_pose())

    # -- motion --------------------------------------------------------------------------------
    def _check_ready(self) -> None:
        """ArmError unless a program may be published now: not aborted, connected, no fault, and the
        driver's urscript_interface subscribed."""
        self._check_aborted()
        if self._node is None:
            raise ArmError(self._fault or "arm not connected")
        fault = self.fault()
        if fault is not None:
            raise ArmError(f"arm faulted: {fault}")
        if self._node.count_subscribers(self._script_pub.topic_name) == 0:
            raise ArmError(f"nobody subscribes to {self._script_pub.topic_name}: is the driver's urscript_interface "
                           "running?")

    def move_linear(self, target_pose: ArrayLike, speed: float, accel: float, asynchronous: bool = True) -> None:
        """Publish one movel program; everything is checked first (limits, a finite target, a healthy
        driver with a script subscriber), so a refused move publishes nothing."""
        target = self.limits.check(target_pose, speed, accel)
        program = movel_program(target, speed, accel)
        self._check_ready()
        start = self.tcp_pose()
        with self._lock:
            self._move = _Move(start, target, time.monotonic(), self._program_starts)
        self._publish(program)
        if not asynchronous:
            self._wait_for_move()

    def move_path(self, waypoints: ArrayLike, speed: float, accel: float, blend: float,
                  asynchronous: bool = True) -> None:
        """Publish one program of movels through the waypoints with blend radii (`path_program`): touchdown
        and lift-off at speed. Everything is checked first (every waypoint and corner, `ArmLimits.check_path`;
        the tool at the first waypoint; a healthy driver with a script subscriber), so a refused path
        publishes nothing. If this process hangs, the robot finishes at most this path (one pass)."""
        points = self.limits.check_path(waypoints, speed, accel, blend)
        program = path_program(points, speed, accel, blend)
        self._check_ready()
        start = self.tcp_pose()
        check_path_start(start, points)
        with self._lock:
            self._move = _Move(start, points[-1], time.monotonic(), self._program_starts, points)
        self._publish(program)
        if not asynchronous:
            self._wait_for_move()

    def _wait_for_move(self) -> None:
        while self.is_moving():
            if self._aborted.is_set():
                self.stop()
                self._check_aborted()
            fault = self.fault()
            if fault is not None:
                self.stop()
                raise ArmError(f"arm faulted: {fault}")
            time.sleep(0.01)

    def stop(self) -> None:
        """stopl, when a movel of ours may still move the robot; nothing otherwise (a program we did not start
        is not ours to stop). Safe to call at any time, connected or not."""
        move = self._move
        if move is None or self._node is None:
            return
        with self._lock:
            pose = self._pose
        self._halted_fraction = _move_fraction(move, pose) if pose is not None else 0.0
        self._move = None
        try:
            self._publish(stopl_program(self.config.stop_deceleration))
        except Exception as exc:  # noqa: BLE001 - the context went down: nothing can be sent any more
            self._fault = self._fault or f"stopl could not be sent: {' '.join(str(exc).split())}"

    def abort(self) -> None:
        """From any thread: a wait under way (connecting, a reset, a synchronous move) gives up with ArmError
        at once, and moves are refused until `connect()` or `reset_fault()`. Nothing here blocks in a call
        that cannot be given up: every wait polls."""
        self._aborted.set()

    def _check_aborted(self) -> None:
        if self._aborted.is_set():
            raise ArmError("given up (the arm was aborted): reset the fault to use it again")

    def reset_fault(self) -> None:
        """Clear what can be cleared: unlock a protective stop through `unlock_service` (the dashboard client;
        the controller allows it 5 s after the stop), wait for the driver to report the robot healthy and
        its pose fresh; ArmError (one line) saying why not otherwise (an emergency stop: released on the
        pendant first)."""
        self._aborted.clear()
        if self._node is None:
            self.connect()
            return
        self.stop()   # a program of ours that may still run is stopped first
        deadline = time.monotonic() + self.config.reset_timeout
        with self._lock:
            safety = self._safety_mode
        if safety in EMERGENCY_STOPS:
            raise ArmError(f"emergency stop ({SAFETY_MODES[safety]}): release it on the teach pendant, then reset")
        if safety == PROTECTIVE_STOP:
            self._unlock_protective_stop(deadline)
        missing = self._wait_for_driver(max(deadline - time.monotonic(), 0.0), healthy=True)
        self._fault = None
        fault = self.fault()
        if fault is not None:
            raise ArmError(f"the fault remains after the reset: {fault}")
        if missing:
            raise ArmError(f"the fault remains after the reset: no {missing}")

    # -- internals -----------------------------------------------------------------------------
    def _open(self) -> None:
        import rclpy
        from rclpy.executors import SingleThreadedExecutor
        from ur_dashboard_msgs.msg import RobotMode, SafetyMode

        context = self._context
        node = self._node = rclpy.create_node(self._node_name, context=context, start_parameter_services=False)
        cfg = self.config
        self._script_pub = node.create_publisher(String, cfg.script_topic, SCRIPT_QOS)
        node.create_subscription(Bool, cfg.program_running_topic, self._on_program_running, LATCHED_QOS)
        node.create_subscription(SafetyMode, cfg.safety_mode_topic, self._on_safety_mode, LATCHED_QOS)
        node.create_subscription(RobotMode, cfg.robot_mode_topic, self._on_robot_mode, LATCHED_QOS)
        self._unlock = node.create_client(Trigger, cfg.unlock_service) if cfg.unlock_service else None
        self._tf = TransformListener(node, TransformBuffer(cache_ns=2_000_000_000), on_update=self._on_tf)
        executor = SingleThreadedExecutor(context=node.context)
        executor.add_node(node)
        self._executor = executor
        self._spinning.set()
        self._spinner = threading.Thread(target=self._spin, name="ur-driver-arm", daemon=True)
        self._spinner.start()

    def _spin(self) -> None:
        executor, node = self._executor, self._node
        while self._spinning.is_set() and node is not None and node.context.ok():
            try:
                executor.spin_once(timeout_sec=0.05)
            except Exception:  # noqa: BLE001 - the context shut down under us: stop spinning
                if node.context.ok() and self._spinning.is_set():
                    raise
                return

    def _publish(self, program: str) -> None:
        self._script_pub.publish(String(data=program))
        self.sent.append(program)

    def _wait_for_driver(self, timeout: float, healthy: bool = False) -> str:
        """Wait until the driver's state is all here (and, with `healthy`, fresh and healthy); '' when it is,
        else what is still missing."""
        deadline = time.monotonic() + timeout
        while True:
            self._check_aborted()
            missing = self._missing(healthy)
            if not missing or time.monotonic() > deadline:
                return missing
            time.sleep(0.02)

    def _missing(self, healthy: bool) -> str:
        assert self._node is not None
        cfg = self.config
        with self._lock:
            pose_age = time.monotonic() - self._pose_time
            # not robot_program_running: upstream publishes it on change from false, so a driver whose
            # External Control program never ran has published nothing on it
            state = {"safety mode": self._safety_mode, "robot mode": self._robot_mode}
            safety, robot = self._safety_mode, self._robot_mode
        if pose_age > cfg.driver_timeout:
            return f"{cfg.base_frame} -> {cfg.tool_frame} on TF"
        topics = {"safety mode": cfg.safety_mode_topic, "robot mode": cfg.robot_mode_topic}
        for what, value in state.items():
            if value is None:
                return f"{what} on {topics[what]}"
        if self._node.count_subscribers(self._script_pub.topic_name) == 0:
            return f"subscriber on {self._script_pub.topic_name}"
        if healthy and (safety not in HEALTHY_SAFETY_MODES or robot != ROBOT_RUNNING):
            return (f"healthy robot (safety mode {SAFETY_MODES.get(safety or 0, safety)}, robot mode "
                    f"{ROBOT_MODES.get(robot if robot is not None else -2, robot)})")
        return ""

    def _unlock_protective_stop(self, deadline: float) -> None:
        service = self.config.unlock_service
        if self._unlock is None:
            raise ArmError("protective stop: unlock it on the teach pendant once its cause is clear (ur_driver."
                           "unlock_service is empty), then reset")
        if not self._unlock.wait_for_service(timeout_sec=max(deadline - time.monotonic(), 0.01)):
            raise ArmError(f"protective stop: {service} is not offered (start the driver's dashboard client, or "
                           "unlock on the teach pendant), then reset")
        done = threading.Event()
        future = self._unlock.call_async(Trigger.Request())
        future.add_done_callback(lambda _: done.set())
        while not done.wait(0.02) and time.monotonic() < deadline:
            self._check_aborted()
        if not done.is_set():
            raise ArmError(f"protective stop: {service} did not answer within ur_driver.reset_timeout "
                           f"({self.config.reset_timeout:g} s)")
        answer = future.result()
        if answer is None or not answer.success:
            why = " ".join(str(getattr(answer, "message", "")).split()) or "no reason given"
            raise ArmError(f"the protective stop persists: {service} refused to unlock it ({why}); clear its "
                           "cause (the controller allows an unlock 5 s after the stop), then reset")

    # subscription callbacks (executor thread)
    def _on_program_running(self, message: Any, info: Any) -> None:
        with self._lock:
            if message.data and not self._program_running:   # None: nothing published yet, i.e. false
                # The first message may be the latched state, published before our move and delivered
                # late by discovery: that is not a start during the move. A false -> true change is.
                move = self._move
                latched_before_move = (self._program_running is None and move is not None
                                       and int(info["source_timestamp"]) < move.sent_ns)
                if not latched_before_move:
                    self._program_starts += 1
            self._program_running = bool(message.data)

    def _on_safety_mode(self, message: Any) -> None:
        with self._lock:
            self._safety_mode = int(message.mode)

    def _on_robot_mode(self, message: Any) -> None:
        with self._lock:
            self._robot_mode = int(message.mode)

    def _on_tf(self, static: bool) -> None:
        tf = self._tf
        if tf is None:
            return
        cfg = self.config
        with tf.lock:
            try:
                stamp = tf.buffer.latest_common_stamp(cfg.base_frame, cfg.tool_frame)
                transform = tf.buffer.lookup(cfg.base_frame, cfg.tool_frame, stamp)
            except TransformError:
                return
        if stamp is None:
            return   # a chain of static transforms only: says nothing about the driver being alive
        with self._lock:
            if self._pose_stamp is not None and stamp <= self._pose_stamp:
                return   # nothing newer (a static update, or a transform of some other frame)
            now = time.monotonic()
            pose = np.concatenate([np.asarray(transform.translation, np.float64), _rotation_vector(transform)])
            self._pose, self._pose_stamp, self._pose_time = pose, stamp, now
            if self._still_pose is None or _distance(pose, self._still_pose) > cfg.still_tolerance:
                self._still_pose, self._still_since = pose, now


def _rotation_vector(transform: Any) -> np.ndarray:
    """UR rotation vector (axis * angle) of a Transform's quaternion (x, y, z, w)."""
    x, y, z, w = (float(v) for v in transform.rotation)
    if w < 0:
        x, y, z, w = -x, -y, -z, -w
    s = math.sqrt(x * x + y * y + z * z)
    if s < 1e-12:
        return np.zeros(3)
    angle = 2.0 * math.atan2(s, w)
    return np.array([x, y, z]) / s * angle


def _distance(a: Sequence[float] | np.ndarray, b: Sequence[float] | np.ndarray) -> float:
    return float(np.linalg.norm(np.asarray(a, np.float64)[:3] - np.asarray(b, np.float64)[:3]))


def _move_fraction(move: _Move, pose: np.ndarray) -> float:
    if move.path is not None:
        return fraction_along_path(move.path, pose)
    return _fraction_along(move.start, move.target, pose)


def _fraction_along(start: np.ndarray, target: np.ndarray, pose: np.ndarray) -> float:
    delta = target[:3] - start[:3]
    length_sq = float(delta @ delta)
    if length_sq == 0.0:
        return 1.0
    fraction = float((pose[:3] - start[:3]) @ delta) / length_sq
    return min(max(fraction, 0.0), 1.0) if math.isfinite(fraction) else float("nan")


__all__ = ["UR_DRIVER_PARAMETERS", "URDriverArm", "URDriverConfig", "make_ur_driver_arm", "movel_program",
           "path_program", "stopl_program"]
