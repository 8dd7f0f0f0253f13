"""A fake ur_robot_driver for tests: the topics and habits `URDriverArm` relies on, on a SimulatedArm.

What it mimics (the upstream driver's, as documented and as its io_and_status_controller publishes):
- `/urscript_interface/script_command` (std_msgs/String, depth 1): a program replaces whatever runs on
  the robot (the arm halts, the External Control program stops: `robot_program_running` goes false);
  only `movel(p[x, y, z, rx, ry, rz], a=A, v=V)`, a path of such movels with `, r=R` (one a line, run as
  `SimulatedArm.move_path`) and `stopl(A)` programs, bare or in a `def name(): ... end`, are understood;
  anything else is silently not run (as a real robot does with invalid script);
  programs are refused during a protective stop.
- `/tf`: `base -> tool0` at 125 Hz, stamped with the node's clock; with `chain=True` as the real tree
  is shaped: `base_link -> base` on /tf_static (a half turn about z, as ur_description has it) and
  `base_link -> tool0` on /tf, so the arm has to chain the lookup.
- `/io_and_status_controller/{safety_mode,robot_mode,robot_program_running}`: latched, on change (the
  program state from a default false: nothing is published while the External Control program never ran).
- `/dashboard_client/unlock_protective_stop` (std_srvs/Trigger): unlocks only when `unlockable`.
Not mimicked: timing of a real controller, stopl's deceleration (the simulated arm halts at once),
joint limits, singularities, speed scaling.
"""
from __future__ import annotations

import math
import re
import threading
from typing import Any

import numpy as np
import rclpy
from rclpy.executors import SingleThreadedExecutor
from std_msgs.msg import Bool, String
from std_srvs.srv import Trigger
from ur_dashboard_msgs.msg import RobotMode, SafetyMode

from touchroller_bringup.tf import TransformPublisher
from touchroller_bringup.ur_driver_arm import LATCHED_QOS
from touchroller_driver.arm import ArmError, ArmLimits, SimulatedArm
from touchroller_perception.transforms import Transform

_NUM = r"-?\d+(?:\.\d*)?"
MOVEL = re.compile(rf"movel\(p\[\s*({_NUM}(?:\s*,\s*{_NUM}){{5}})\s*\]"
                   rf"\s*,\s*a\s*=\s*({_NUM})\s*,\s*v\s*=\s*({_NUM})\s*(?:,\s*r\s*=\s*({_NUM})\s*)?\)")
STOPL = re.compile(rf"stopl\(\s*({_NUM})\s*\)")
PROGRAM = re.compile(r"def\s+\w+\(\)\s*:\s*\n(.*)\n\s*end\s*", re.S)

BASE_LINK_TO_BASE = Transform.from_rpy((0.0, 0.0, 0.0), (0.0, 0.0, math.pi))


def parse_program(text: str) -> tuple[str, tuple[float, ...]] | None:
    """("movel", (x, y, z, rx, ry, rz, a, v)), ("path", (x, y, z, rx, ry, rz, a, v, r) * N: movels with blend
    radii, one a line) or ("stopl", (a,)); None for anything else."""
    match = PROGRAM.fullmatch(text)
    body = (match.group(1) if match else text).strip()
    lines = [line.strip() for line in body.split("\n")]
    if lines and all(m is not None and m.group(4) is not None for m in map(MOVEL.fullmatch, lines)):
        values: list[float] = []
        for line in lines:
            m = MOVEL.fullmatch(line)
            assert m is not None
            values += [*(float(v) for v in m.group(1).split(",")), float(m.group(2)), float(m.group(3)),
                       float(m.group(4))]
        return "path", tuple(values)
    if (m := MOVEL.fullmatch(body)) is not None and m.group(4) is None:
        pose = tuple(float(v) for v in m.group(1).split(","))
        return "movel", (*pose, float(m.group(2)), float(m.group(3)))
    if (m := STOPL.fullmatch(body)) is not None:
        return "stopl", (float(m.group(1)),)
    return None


class FakeURDriver:
    """See the module docstring. `programs` holds every program received, `executed` the parsed ones run."""

    def __init__(self, context: Any, start_pose: Any, *, chain: bool = False, rate_hz: float = 125.0,
                 program_running: bool = True, execute: bool = True) -> None:
        self.arm = SimulatedArm(start_pose, limits=ArmLimits(max_speed=1.0, max_accel=5.0))   # the robot's own
        self.arm.connect()
        self.chain = chain
        self.execute = execute           # False: a robot not in remote control (programs are not run)
        self.unlockable = False
        self.silent = False
        self.programs: list[str] = []
        self.executed: list[tuple[str, tuple[float, ...]]] = []
        self.lock = threading.Lock()
        node = self.node = rclpy.create_node("fake_ur_driver", context=context)
        node.create_subscription(String, "/urscript_interface/script_command", self._on_script, 1)
        self._running_pub = node.create_publisher(Bool, "/io_and_status_controller/robot_program_running",
                                                  LATCHED_QOS)
        self._safety_pub = node.create_publisher(SafetyMode, "/io_and_status_controller/safety_mode", LATCHED_QOS)
        self._mode_pub = node.create_publisher(RobotMode, "/io_and_status_controller/robot_mode", LATCHED_QOS)
        node.create_service(Trigger, "/dashboard_client/unlock_protective_stop", self._on_unlock)
        self.tf = TransformPublisher(node)
        if chain:
            self.tf.set_static("base_link", "base", BASE_LINK_TO_BASE)
        self.safety_mode = SafetyMode.NORMAL
        self.set_safety_mode(SafetyMode.NORMAL)
        self._mode_pub.publish(RobotMode(mode=RobotMode.RUNNING))
        self.program_running = program_running
        if program_running:   # upstream publishes on change from a default false: nothing while never running
            self._running_pub.publish(Bool(data=True))
        node.create_timer(1.0 / rate_hz, self._publish_tf)
        self._executor = SingleThreadedExecutor(context=context)
        self._executor.add_node(node)
        self._spinning = True
        self._thread = threading.Thread(target=self._spin, name="fake-ur-driver", daemon=True)
        self._thread.start()

    # -- what a test does to the robot ---------------------------------------------------------
    def inject_protective_stop(self) -> None:
        with self.lock:
            self.arm.inject_fault("protective stop")
            self.set_safety_mode(SafetyMode.PROTECTIVE_STOP)

    def inject_emergency_stop(self) -> None:
        with self.lock:
            self.arm.inject_fault("emergency stop", resettable=False)
            self.set_safety_mode(SafetyMode.ROBOT_EMERGENCY_STOP)

    def clear_on_pendant(self) -> None:
        """The operator clears the stop on the teach pendant (no unlock through the dashboard)."""
        with self.lock:
            # the pendant clears any stop: the same robot, where it halted, without the fault
            self.arm = SimulatedArm(self.arm.tcp_pose(), limits=self.arm.limits)
            self.arm.connect()
            self.set_safety_mode(SafetyMode.NORMAL)

    def start_external_control(self) -> None:
        """resend_robot_program / the play button: the driver's program replaces ours."""
        with self.lock:
            self.arm.stop()
            self.program_running = True
            self._running_pub.publish(Bool(data=True))

    def go_silent(self) -> None:
        self.silent = True

    def set_safety_mode(self, mode: int) -> None:
        self.safety_mode = mode
        self._safety_pub.publish(SafetyMode(mode=mode))

    def pose(self) -> np.ndarray:
        return self.arm.tcp_pose()

    def moves(self) -> list[tuple[float, ...]]:
        with self.lock:
            return [values for kind, values in self.executed if kind == "movel"]

    def close(self) -> None:
        self._spinning = False
        self._thread.join(timeout=2.0)
        self._executor.shutdown()
        self.node.destroy_node()

    # -- the driver's side ---------------------------------------------------------------------
    def _spin(self) -> None:
        while self._spinning and self.node.context.ok():
            try:
                self._executor.spin_once(timeout_sec=0.05)
            except Exception:  # noqa: BLE001 - the context shut down under us
                return

    def _on_script(self, message: Any) -> None:
        with self.lock:
            self.programs.append(message.data)
            parsed = parse_program(message.data)
            if parsed is None or not self.execute or self.safety_mode != SafetyMode.NORMAL:
                return   # invalid script, local mode or a stop: silently not run
            if self.program_running:
                self.program_running = False
                self._running_pub.publish(Bool(data=False))
            self.arm.stop()   # the new program replaces the running one
            kind, values = parsed
            try:
                if kind == "movel":
                    self.arm.move_linear(values[:6], speed=values[7], accel=values[6])
                elif kind == "path":   # the robot's own blending, as the simulated arm follows a path
                    rows = np.array(values).reshape(-1, 9)
                    self.arm.move_path(rows[:, :6], speed=float(rows[0, 7]), accel=float(rows[0, 6]),
                                       blend=float(rows[:, 8].max()))
            except ArmError:
                return
            self.executed.append(parsed)

    def _on_unlock(self, request: Any, response: Any) -> Any:
        with self.lock:
            if self.safety_mode != SafetyMode.PROTECTIVE_STOP:
                response.success, response.message = True, "no protective stop"
            elif not self.unlockable:
                response.success, response.message = False, "cannot unlock: the cause persists"
            else:
                self.arm.reset_fault()
                self.set_safety_mode(SafetyMode.NORMAL)
                response.success, response.message = True, "protective stop released"
        return response

    def _publish_tf(self) -> None:
        if self.silent:
            return
        pose = self.arm.tcp_pose()
        tool = Transform.from_rotation_vector(pose[:3], pose[3:])
        stamp = self.node.get_clock().now().nanoseconds
        if self.chain:
            self.tf.send([("base_link", "tool0", stamp, BASE_LINK_TO_BASE @ tool)])
        else:
            self.tf.send([("base", "tool0", stamp, tool)])

