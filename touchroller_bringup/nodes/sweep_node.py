"""The sweep node: rolls the sensor over a surface with an arm (UR5 via ur_rtde, or simulated).

Safety (docs/ur5.md, "Safety rules"): the arm moves only after `~/start` answered success. A start is
planned and checked whole on a planner thread (every segment against `arm.max_speed`/`arm.max_accel`/
`arm.reach`, read-only at run time; at most MAX_PASSES passes; at most `sweep.max_duration` from where the
arm is), then the arm thread commits to it just before the first motion command; a start its caller
stopped waiting for (COMMAND_TIMEOUT_S, or shutdown) is abandoned instead, and never moves the arm.
`sweep.profile` (ramp, blend, constant) says how each pass moves: stop-and-go linear moves, or the pass as
one blended path through the arm (`Arm.move_path`), every waypoint and corner checked first (docs/ur5.md).
Start-up parameter values get the on-set callback's checks (one line, exit 2). All arm calls happen on
one worker thread; a fault (protective/emergency stop, lost connection, refused command, a robot that
stopped answering), during a sweep or while idle, stops the sweep, shows as ERROR on `/diagnostics` and
stays until `~/reset_fault` clears it (the UR dashboard's "unlock protective stop", then a reconnect):
meanwhile `~/start` answers failure. The worker thread connects to the arm (CONNECTING, WARN, on
`/diagnostics`; a UR is probed with a timeout first, and ur_rtde runs in a child process with deadlines),
so the node answers services, publishes diagnostics and ends on SIGINT while a robot is slow or silent; a
stop or a shutdown the arm thread cannot answer gives its arm call up (`Arm.abort`). Publishes the TCP pose
(`tcp_pose`, geometry_msgs/PoseStamped in the robot base frame) and the roll progress
(`sweep_progress`, std_msgs/Float32, 0..1) at `sweep.publish_rate`; topics are relative to the node's
namespace (`touchroller` by default, names in `touchroller_bringup.names`). TF: base -> tool0 on /tf
(unless `publish_tf` is false) and tool0 -> touchroller_cylinder (`mount.*`) on /tf_static.

With `use_sim` the arm is simulated on a simulated clock (`touchroller_driver.sim.clock.SimClock`) that
this node's arm loop advances one tick (1 / `sweep.publish_rate`) per pass, paced to `sim.rate` x real
time, and publishes on /clock; the graph runs every node with use_sim_time, so the simulated camera
renders on the same clock as the arm (exact poses), and a sweep starts on a whole second of it, so the
same sweep gives the same images. With `sim.lockstep` the clock also waits for the frames: it moves on
only while the camera's frames (`camera_info`) are no more than `sim.max_lead` s behind it and the
perception node has finished them (`image_done`), and a recorder of the images has written them
(`image_raw/recorded`, `touchroller_bringup.recorder`) when one runs, so on a loaded machine simulated
time runs slower and every frame is rendered, delivered, processed and recorded as on an idle one
(`touchroller_driver.sim.clock.FrameGate`). `~/start` answers at once; the simulated sweep begins on the
clock's next whole second.

Services `~/start`, `~/stop` and `~/reset_fault` are std_srvs/Trigger (`ros2 service call
/touchroller/sweep/start std_srvs/srv/Trigger`). Beside them, where touchroller_interfaces is installed,
the `sweep` action (touchroller_interfaces/action/Sweep, `/touchroller/sweep`): the same start with
the goal's area, speed and depth, feedback, cancel and a result (`touchroller_bringup.sweep_action`).
"""
from __future__ import annotations

import math
import queue
import threading
import time
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from geometry_msgs.msg import PoseStamped
from rclpy.callback_groups import MutuallyExclusiveCallbackGroup
from rclpy.node import Node
from rclpy.qos import QoSProfile, ReliabilityPolicy
from rosgraph_msgs.msg import Clock
from sensor_msgs.msg import CameraInfo
from std_msgs.msg import Float32, Header, UInt32MultiArray
from std_srvs.srv import Trigger

from touchroller_bringup import names
from touchroller_bringup.answer_delivery import AnswerDelivery
from touchroller_bringup.ros_diagnostics import ERROR, OK, WARN, DiagnosticsPublisher, Status
from touchroller_bringup.ros_params import ConfigParameters, declare_frame_prefix, parameter_values
from touchroller_bringup.sweep_action import SweepActionServer, make_sweep_action
from touchroller_bringup.sweep_settings import (
    ARM_BACKENDS,
    ARM_FIELDS,
    MOUNT_FIELDS,
    SWEEP_FIELDS,
    ArmSettings,
    MountConfig,
    SweepSettings,
)
from touchroller_bringup.tf import TransformPublisher
from touchroller_driver.arm import (
    Arm,
    ArmError,
    ArmLimits,
    SimulatedArm,
    SweepPhase,
    SweepPlan,
    SweepSequencer,
    SweepStatus,
    check_plan,
    plan_duration,
    plan_raster,
    plan_sweep,
    raster_coverage,
    simulated_arm_origin,
)
from touchroller_driver.sim.clock import FrameGate, SimClock
from touchroller_perception.transforms import Transform

#: how long a service waits for its answer; a start not accepted by then is cancelled (it never moves the arm)
COMMAND_TIMEOUT_S = 5.0
#: shutting down (a stop signal, the node destroyed): how long the arm thread gets to stop the arm before a
#: call it is stuck in is given up (`Arm.abort`: the ur_rtde process ends, the robot's watchdog stops it)
SHUTDOWN_STOP_S = 0.5
#: sim.lockstep: wall seconds without any frame published or finished before the clock goes on regardless
#: (a camera or perception that stopped must not freeze the simulation; said on the log)
LOCKSTEP_STALL_S = 10.0
#: sim.lockstep: the topics (relative) on which the frames' consumers say up to which frame they are done
FRAME_CONSUMERS = {names.IMAGE_DONE: "perception", names.IMAGE_RECORDED: "recorder"}


def rotation_vector_to_quaternion(rotation: Sequence[float]) -> tuple[float, float, float, float]:
    """UR rotation vector (axis * angle) -> quaternion (x, y, z, w)."""
    vector = np.asarray(rotation, dtype=np.float64)
    angle = float(np.linalg.norm(vector))
    if angle < 1e-12:
        return 0.0, 0.0, 0.0, 1.0
    axis = vector / angle * math.sin(angle / 2.0)
    return float(axis[0]), float(axis[1]), float(axis[2]), math.cos(angle / 2.0)


@dataclass
class _Command:
    """A service request handed to the planner and the arm thread. A start is PENDING until the arm
    thread commits to it (just before the first motion command) or its caller gives up waiting
    (abandons it): exactly one of the two happens, so a start whose caller was answered failure never
    moves the arm."""

    name: str
    done: threading.Event
    success: bool = False
    message: str = ""
    plan: SweepPlan | None = None
    settings: dict[str, Any] | None = None   # a start's sweep parameters (None: the node's)
    dry_run: bool = False    # a start checked whole (planner and arm thread) that never moves the arm
    owner: Any = None        # the SweepActionServer whose goal this start is
    state: str = "pending"   # pending, committed, abandoned
    _lock: threading.Lock = field(default_factory=threading.Lock)

    def commit(self) -> bool:
        """The arm thread is about to move the arm for this command; False if its caller gave up."""
        with self._lock:
            if self.state == "pending":
                self.state = "committed"
            return self.state == "committed"

    def abandon(self) -> bool:
        """The caller gives up waiting; False if the arm thread has already committed to it."""
        with self._lock:
            if self.state == "pending":
                self.state = "abandoned"
            return self.state == "abandoned"


class SweepNode(Node):
    """Thin ROS shell around `SweepSequencer` and an `Arm`; pass `arm=` to supply one (e.g. a shared
    SimulatedArm that also drives the simulated camera in `touchroller scan`)."""

    def __init__(self, *, arm: Arm | None = None, node_name: str = names.SWEEP_NODE, **node_kwargs: Any) -> None:
        node_kwargs.setdefault("namespace", names.DEFAULT_NAMESPACE)
        super().__init__(node_name, **node_kwargs)
        self._declare_parameters()
        self.frame_prefix = declare_frame_prefix(self)
        self.limits = self._limits_from_parameters()
        if arm is not None:  # a supplied arm keeps its own limits; the stricter of the two apply here
            reaches = [r for r in (self.limits.reach, arm.limits.reach) if r is not None]
            self.limits = ArmLimits(max_speed=min(self.limits.max_speed, arm.limits.max_speed),
                                    max_accel=min(self.limits.max_accel, arm.limits.max_accel),
                                    reach=min(reaches) if reaches else None)
        # run-time parameters: the mount (re-published on /tf_static when it changes) and the sweep of the
        # next ~/start, checked whole (the plan) on set and at start-up
        self.mount_parameters = ConfigParameters(self, MountConfig(), MOUNT_FIELDS,
                                                 on_change=lambda _: self._publish_mount())
        self.sweep_parameters = ConfigParameters(
            self, SweepSettings(), SWEEP_FIELDS,
            check=lambda settings: self._plan_from(parameter_values(settings, SWEEP_FIELDS)),
            errors=(ArmError, TypeError, ValueError), refused="sweep parameters refused: ")
        self.sim_clock: SimClock | None = None   # use_sim: the one clock of the simulated arm and camera
        self._clock_pub: Any = None
        self.frame_gate: FrameGate | None = None   # use_sim and sim.lockstep: the clock waits for the frames
        self._deferred: SweepPlan | None = None    # simulated: a started sweep waiting for the whole second
        self._consumer_checked = -1.0
        self._consumers: tuple[str, ...] = ()
        self.arm: Arm = arm if arm is not None else self._make_arm()
        self.sequencer = SweepSequencer(self.arm)
        self.finished = threading.Event()  # set when a started sweep ends (done, stopped or fault)
        self._state_lock = threading.Lock()
        self._status = SweepStatus(SweepPhase.CONNECTING, None, 0.0, "connecting to the arm")
        self._connection_error: str | None = None
        self._fault: str | None = None   # latched until ~/reset_fault (the worker thread's)
        self._last_pose: np.ndarray | None = None
        self._commands: queue.Queue[_Command] = queue.Queue()
        self._planning: queue.Queue[_Command] = queue.Queue()   # starts, planned off the service thread
        self._shutdown = threading.Event()
        self.last_answer: tuple[str, bool, str] | None = None  # (service, success, message) of the last call

        # the robot's frames are the robot driver's names (parameters, no prefix); the prefix is on ours only
        self._frame_id = self.arm_settings.base_frame
        self._tool_frame = self.arm_settings.tool_frame
        self._cylinder_frame = names.frame(names.CYLINDER_FRAME, self.frame_prefix)
        # tool0 has one parent: the UR driver's robot_state_publisher publishes it when it drives the arm
        self._publish_tf = (self.arm_settings.publish_tf
                            and not getattr(self.arm, "publishes_tool_tf", False))
        self.tf = TransformPublisher(self)
        self._publish_mount()
        self._pose_pub = self.create_publisher(PoseStamped, names.TCP_POSE, 10)
        self._progress_pub = self.create_publisher(Float32, names.SWEEP_PROGRESS, 10)
        self._coverage_pub = self.create_publisher(Float32, names.COVERAGE, 10)
        self._pass_pub = self.create_publisher(UInt32MultiArray, names.SWEEP_PASS, 10)
        self._start_srv = self.create_service(Trigger, f"~/{names.START}", self._on_start)
        self._stop_srv = self.create_service(Trigger, f"~/{names.STOP}", self._on_stop)
        self._reset_srv = self.create_service(Trigger, f"~/{names.RESET_FAULT}", self._on_reset_fault)
        # an answer DDS dropped is sent again; a start answered success that never reaches its caller
        # stops the arm: the arm moves only after a start that was answered success (run_node hands
        # the node's other services to the same delivery)
        self.answers = AnswerDelivery(self)
        self.answers.handle(self._start_srv, on_lost=self._start_answer_lost)
        self._plan_settings: dict[str, Any] = dict(self.settings)   # the parameters of the sweep started last
        self._action: SweepActionServer | None = make_sweep_action(self)
        simulated = isinstance(self.arm, SimulatedArm)
        through_driver = getattr(self.arm, "publishes_tool_tf", False)
        hardware = ("simulated arm" if simulated else "UR through ur_robot_driver" if through_driver
                    else f"UR at {self.arm_settings.robot_ip}")
        self.diagnostics = DiagnosticsPublisher(self, self.get_fully_qualified_name(), hardware_id=hardware)
        self.diagnostics.add(self._diagnostic_status)

        self._worker = threading.Thread(target=self._run_worker, name="sweep-arm", daemon=True)
        self._worker.start()
        self._planner = threading.Thread(target=self._run_planner, name="sweep-plan", daemon=True)
        self._planner.start()

    # -- parameters ----------------------------------------------------------------------------
    def _declare_parameters(self) -> None:
        self.arm_parameters = ConfigParameters(self, ArmSettings(), ARM_FIELDS)   # read-only: read at start-up
        self.arm_settings = self.arm_parameters.config

    @property
    def settings(self) -> dict[str, Any]:
        """The sweep.* parameters of the next `~/start` (a new dict: name -> value as ROS holds it)."""
        return self.sweep_parameters.values()

    def mount(self) -> Transform:
        """T_tool_cylinder from the mount.* parameters."""
        return self.mount_parameters.config.transform()

    def _publish_mount(self) -> None:
        self.tf.set_static(self._tool_frame, self._cylinder_frame, self.mount())

    def _limits_from_parameters(self) -> ArmLimits:
        return ArmLimits(max_speed=self.arm_settings.max_speed, max_accel=self.arm_settings.max_accel,
                         reach=self.arm_settings.reach)

    def _plan_from(self, settings: dict[str, Any], from_pose: np.ndarray | None = None) -> SweepPlan:
        """The sweep of `settings`, checked whole: limits, reach, at most MAX_PASSES passes and at most
        sweep.max_duration (from `from_pose`, the arm's pose, when known). ArmError/ValueError in one line.
        A raster's size and corners are checked before any pass is planned, so this returns at once."""
        area = [float(v) for v in settings["sweep.area"]]
        if len(area) != 4 or not all(math.isfinite(v) for v in area):
            raise ValueError(f"sweep.area is [x, y, length, width] (4 finite numbers, m), got {area}")
        if area[2] > 0:   # a raster over the rectangle (one pass when it is narrower than the roller)
            plan = plan_raster(
                list(settings["sweep.start_pose"]), area=area, mount=self.mount(),
                speed=float(settings["sweep.speed"]), accel=float(settings["sweep.accel"]),
                depth=float(settings["sweep.depth"]), direction=list(settings["sweep.direction"]),
                usable_width=float(settings["sweep.usable_width"]), overlap=float(settings["sweep.overlap"]),
                approach_speed=float(settings["sweep.approach_speed"]), clearance=float(settings["sweep.clearance"]),
                limits=self.limits, profile=str(settings["sweep.profile"]))
        else:
            plan = plan_sweep(
                list(settings["sweep.start_pose"]), length=float(settings["sweep.length"]),
                speed=float(settings["sweep.speed"]), accel=float(settings["sweep.accel"]),
                depth=float(settings["sweep.depth"]), direction=list(settings["sweep.direction"]),
                approach_speed=float(settings["sweep.approach_speed"]), retract=bool(settings["sweep.retract"]),
                clearance=float(settings["sweep.clearance"]), profile=str(settings["sweep.profile"]))
        check_plan(self.limits, plan)   # every move, each path's waypoints and blended corners
        limit = self.arm_settings.max_duration
        duration = plan_duration(plan, from_pose)
        if not duration <= limit:
            where = "" if from_pose is None else " from where the arm is"
            raise ArmError(f"the sweep would take {duration:.0f} s{where}, more than sweep.max_duration ({limit:g} s)")
        return plan

    def _make_arm(self) -> Arm:
        settings = self.arm_settings
        backend = settings.backend
        if backend not in ARM_BACKENDS:
            raise ValueError(f"arm.backend must be one of {', '.join(ARM_BACKENDS)}, got {backend!r}")
        if settings.use_sim or backend == "sim":
            rest, _ = simulated_arm_origin(self.settings["sweep.start_pose"], float(self.settings["sweep.clearance"]))
            rate_hz = settings.publish_rate
            self.sim_clock = SimClock(rate_hz, rate=settings.sim_rate)
            self._clock_pub = self.create_publisher(Clock, names.CLOCK, 10)
            if settings.sim_lockstep:
                # at least one tick: the tick after a frame's stamp must be allowed (its pose on TF)
                self._follow_frames(max(settings.sim_max_lead, 1.0 / rate_hz))
            return SimulatedArm(rest, limits=self.limits, clock=self.sim_clock.now)
        if backend == "ur_driver":
            from touchroller_bringup.ur_driver_arm import make_ur_driver_arm

            return make_ur_driver_arm(self, self.limits)
        from touchroller_driver.ur5 import UR5Arm

        return UR5Arm(settings.robot_ip, limits=self.limits, open_timeout=settings.robot_timeout)

    def _follow_frames(self, lead_s: float) -> None:
        """sim.lockstep: the camera's frames (camera_info, one per image, same stamp) and the ones the
        perception node finished (image_done) and a recorder wrote (image_raw/recorded) feed the clock's
        FrameGate; in their own callback group, so
        they arrive while a service callback waits for the arm thread."""
        gate = self.frame_gate = FrameGate(round(lead_s * 1e9))
        group = MutuallyExclusiveCallbackGroup()
        qos = QoSProfile(depth=100, reliability=ReliabilityPolicy.RELIABLE)
        self.create_subscription(CameraInfo, names.CAMERA_INFO, lambda msg: gate.published(_stamp_ns(msg.header)),
                                 qos, callback_group=group)
        for topic, consumer in FRAME_CONSUMERS.items():
            self.create_subscription(Header, topic, lambda msg, c=consumer: gate.finished(_stamp_ns(msg), c), qos,
                                     callback_group=group)

    def _consumers_present(self) -> tuple[str, ...]:
        """The frames' consumers present: a perception node publishes image_done, a recorder of image_raw
        image_raw/recorded (asked of the ROS graph at most twice a second)."""
        now = time.monotonic()
        if now - self._consumer_checked >= 0.5:
            self._consumer_checked = now
            self._consumers = tuple(consumer for topic, consumer in FRAME_CONSUMERS.items()
                                    if self.count_publishers(topic) > 0)
        return self._consumers

    def _wait_for_frames(self) -> None:
        """sim.lockstep: hold the clock's next tick until the frame gate allows it; a command (a stop) or
        shutdown does not wait, and nothing moving for LOCKSTEP_STALL_S lets the clock go on (logged during a
        sweep)."""
        gate, clock = self.frame_gate, self.sim_clock
        assert gate is not None and clock is not None
        since, events = time.monotonic(), gate.events
        while not gate.allows(clock.next_ns(), self._consumers_present()):
            if not self._commands.empty() or self._shutdown.is_set() or not self.context.ok():
                return
            if gate.events != events:
                since, events = time.monotonic(), gate.events
            elif time.monotonic() - since > LOCKSTEP_STALL_S:
                if self.active:   # idle (a scan that stopped its camera and writes its files), it only goes on
                    self.get_logger().warning(f"sim.lockstep: no frame published or finished for "
                                              f"{LOCKSTEP_STALL_S:g} s; the simulated clock goes on",
                                              throttle_duration_sec=30.0)
                return
            gate.wait(0.05)

    # -- services (executor thread): hand the request to the worker and wait for its answer ----
    def _on_start(self, request: Any, response: Any) -> Any:
        return self._answer(response, self._submit("start"))

    def _on_stop(self, request: Any, response: Any) -> Any:
        return self._answer(response, self._stop())

    def _on_reset_fault(self, request: Any, response: Any) -> Any:
        return self._answer(response, self._submit("reset_fault"))

    def _start_answer_lost(self, response: Any) -> None:
        """A start's answer never reached its caller (AnswerDelivery gave up): a started sweep is stopped."""
        if not response.success:
            return
        stopped = self._stop()
        self.get_logger().error(f"start: its caller never heard the answer, so the sweep it started is stopped "
                                f"({stopped.message}); call ~/start again")

    def _stopping(self) -> bool:
        """Shutting down: the node is being destroyed, its context is down, or a stop signal arrived."""
        from touchroller_bringup.ros_main import StopSignals

        signals = StopSignals.installed()
        return self._shutdown.is_set() or not self.context.ok() or (signals is not None and signals.requested.is_set())

    def _submit(self, name: str, timeout: float | None = None, **fields: Any) -> _Command:
        """Hand a request over (a start to the planner, the rest to the arm thread) and wait for its
        answer. A request not answered within `timeout` (COMMAND_TIMEOUT_S), or while shutting down, is
        abandoned: a start is then dropped without moving the arm. One the arm thread has committed to is
        waited for (its first motion command is under way, itself bounded by the arm's call timeouts)."""
        command = _Command(name, threading.Event(), **fields)
        (self._planning if name == "start" else self._commands).put(command)
        deadline = time.monotonic() + (COMMAND_TIMEOUT_S if timeout is None else timeout)
        while not command.done.wait(0.05):
            stopping = name != "stop" and self._stopping()
            if not stopping and time.monotonic() < deadline:
                continue
            if command.abandon():
                command.success = False
                waited = COMMAND_TIMEOUT_S if timeout is None else timeout
                why = "the node is shutting down" if stopping else f"not answered within {waited:g} s"
                command.message = f"{name} {why} (planning or the arm thread was busy); cancelled" + \
                    (", the arm does not move for it" if name == "start" else "")
                status = self.status
                if status.phase in (SweepPhase.CONNECTING, SweepPhase.FAULT) and status.message:
                    command.message += f"; the arm: {status.message}"   # e.g. a robot that stays silent
                return command
            while not command.done.wait(0.05):   # committed: its first motion command is under way
                if self._shutdown.is_set():
                    break
            return command
        return command

    def _stop(self) -> _Command:
        """Stop the arm. A stop the arm thread does not answer in time (COMMAND_TIMEOUT_S; SHUTDOWN_STOP_S
        when shutting down) gives up the call it is stuck in (`Arm.abort`: a UR's ur_rtde process ends and
        the robot's communication watchdog stops the control script); the stop then runs."""
        command = self._submit("stop", SHUTDOWN_STOP_S if self._stopping() else COMMAND_TIMEOUT_S)
        if not command.done.is_set():
            self.arm.abort()
            if command.done.wait(1.0):
                command.message = f"arm stopped (the arm thread was stuck: {command.message})"
            else:
                command.message = "the arm thread did not answer stop; its connection to the arm was given up"
        return command

    def _answer(self, response: Any, command: _Command) -> Any:
        self.last_answer = (command.name, command.success, command.message)
        response.success = command.success
        response.message = command.message
        if command.success:  # two call sites: rclpy fixes a call site's severity on first use
            self.get_logger().info(f"{command.name}: {command.message}")
        else:
            self.get_logger().error(f"{command.name} refused: {command.message}")
        return response

    def request_start(self) -> tuple[bool, str]:
        """The same as calling `~/start` (for in-process callers)."""
        command = self._submit("start")
        return command.success, command.message

    def check_start(self, settings: dict[str, Any]) -> tuple[bool, str]:
        """Every check of a `~/start` with these sweep parameters (planner and arm thread), without moving
        the arm: (True, what would start) when a start would be answered success now."""
        command = self._submit("start", settings=settings, dry_run=True, owner=self._action)
        return command.success, command.message

    def start_goal(self, settings: dict[str, Any], owner: SweepActionServer) -> tuple[bool, str]:
        """A start with these sweep parameters for a Sweep goal of `owner` (told when the arm starts)."""
        command = self._submit("start", settings=settings, owner=owner)
        return command.success, command.message

    def request_stop(self) -> tuple[bool, str]:
        command = self._stop()
        return command.success, command.message

    def request_reset_fault(self) -> tuple[bool, str]:
        command = self._submit("reset_fault")
        return command.success, command.message

    # -- the planner thread: a start's plan and checks, before the arm thread sees it ------------
    def _run_planner(self) -> None:
        while not self._shutdown.is_set() and self.context.ok():
            try:
                command = self._planning.get(timeout=0.1)
            except queue.Empty:
                continue
            try:
                command.plan = self._plan_from(dict(command.settings or self.settings), self.last_pose)
            except (ArmError, ValueError) as exc:
                command.success, command.message = False, str(exc)
                command.done.set()
                continue
            if command.state == "abandoned":   # its caller has been answered already
                continue
            self._commands.put(command)

    # -- the worker thread: the only thread that talks to the arm ----------------------------
    def _connect(self) -> None:
        self._set_status(SweepStatus(SweepPhase.CONNECTING, None, 0.0, "connecting to the arm"))
        try:
            self.arm.connect()
        except ArmError as exc:
            self._connection_error = str(exc)
            self._set_status(SweepStatus(SweepPhase.FAULT, None, 0.0, str(exc)))
            self.get_logger().error(str(exc))
        else:
            self._connection_error = None
            self._set_status(SweepStatus(SweepPhase.IDLE, None, 0.0, "waiting for ~/start"))

    def _run_worker(self) -> None:
        self._connect()
        period = 1.0 / self.arm_settings.publish_rate
        while not self._shutdown.is_set() and self.context.ok():  # Ctrl-C shuts the context down first
            try:
                # Simulated, the loop is the clock: one tick per pass, paced by SimClock.advance.
                command = self._commands.get(timeout=period) if self.sim_clock is None else self._commands.get_nowait()
            except queue.Empty:
                command = None
            was_active = self.sequencer.active
            if self._action is not None:   # the goal's feedback and end; its client gone stops the arm here
                self._action_step()
            if command is not None:
                self._execute(command)
            if self._deferred is not None and self.sim_clock is not None and self.sim_clock.on_whole_second():
                self._begin(self._deferred)
            if self.sim_clock is not None:
                if self.frame_gate is not None:
                    self._wait_for_frames()
                self.sim_clock.advance(self._shutdown)
            self._step(was_active or self.sequencer.active)
            if self.sim_clock is not None:
                self._publish_clock(self.sim_clock.now_ns())
        self._release_arm()

    def _execute(self, command: _Command) -> None:
        try:
            if command.name == "reset_fault":
                self._reset_fault(command)
                return
            if command.name == "start":
                if self._connection_error is not None:
                    self._connect()  # try again: the robot may have come up since
                    if self._connection_error is not None:
                        raise ArmError(self._connection_error)
                if self._fault is not None:
                    raise ArmError(f"arm faulted: {self._fault}; call ~/{names.RESET_FAULT} once the cause is "
                                   "cleared")
                settings = dict(command.settings or self.settings)
                plan = command.plan if command.plan is not None else self._plan_from(settings)
                if command.owner is None and self._action is not None and self._action.running:
                    raise ArmError("a Sweep action goal is running (cancel it, or call ~/stop)")
                if self.sequencer.active or self._deferred is not None:
                    raise ArmError("a sweep is already running")
                fault = self.arm.fault()
                if fault is not None:
                    raise ArmError(f"arm faulted: {fault}")
                if command.dry_run:
                    command.success = True
                    command.message = f"the sweep can start: {plan.length:.4g} m in {len(plan.rolls)} pass(es)"
                    return
                if not command.commit():   # its caller was answered failure: it must not move the arm
                    command.success, command.message = False, "abandoned by its caller"
                    return
                if self.sim_clock is not None and not self.sim_clock.on_whole_second():
                    # Simulated, a sweep starts on a whole second of the clock: the frame grid of any
                    # whole-number frame rate lines up with it, so the same sweep gives the same images.
                    # Answered now (the service must not wait for the clock, which may wait for frames).
                    self._deferred = plan
                else:
                    self.sequencer.start(plan)
                self._plan_settings = settings
                if command.owner is not None:
                    command.owner.owns_start(plan)
                self.finished.clear()
                command.success = True
                command.message = (f"sweep started: {plan.length:.4g} m at {settings['sweep.speed']:.4g} m/s, "
                                   f"depth {settings['sweep.depth']:.4g} m")
            else:
                self._stop_on_arm_thread()
                command.success, command.message = True, "arm stopped"
        except (ArmError, ValueError) as exc:
            command.success, command.message = False, str(exc)
        finally:
            command.done.set()

    def _action_step(self) -> None:
        """The Sweep goal's part of the arm loop; a failure there stops the arm and ends the goal (it must
        never end the arm thread, which watches the arm)."""
        assert self._action is not None
        try:
            self._action.on_step(self.status, self.sequencer.plan, self.active, self._stop_on_arm_thread)
        except Exception as exc:  # noqa: BLE001 - whatever it is, the arm stops and the loop goes on
            if self.active:
                self.get_logger().error(f"Sweep action failed ({exc}); stopping the arm")
                self._stop_on_arm_thread(f"the Sweep action failed: {exc}")
            self._action.end(f"the Sweep action failed: {exc}")

    def _stop_on_arm_thread(self, message: str = "stopped on request") -> None:
        """What ~/stop does, on the arm thread."""
        if self._deferred is not None:   # stopped before it began
            self._deferred = None
            self.finished.set()
        self.sequencer.stop(message)

    def _begin(self, plan: SweepPlan) -> None:
        """Start a deferred sweep (simulated: on the clock's whole second)."""
        self._deferred = None
        try:
            self.sequencer.start(plan)
        except ArmError as exc:
            self._fault = str(exc)
            self._set_status(SweepStatus(SweepPhase.FAULT, None, 0.0, str(exc)))
            self.get_logger().error(f"sweep fault: {exc}")
            self.finished.set()

    def _reset_fault(self, command: _Command) -> None:
        """Clear a fault (the arm's own reset: unlock a protective stop, reconnect); the node's latched
        fault goes only when the arm says it is healthy again."""
        try:
            if self._connection_error is not None:
                self._connect()
                if self._connection_error is not None:
                    raise ArmError(self._connection_error)
            self.arm.reset_fault()
            fault = self.arm.fault()
            if fault is not None:
                raise ArmError(f"the fault remains: {fault}")
        except (ArmError, RuntimeError) as exc:
            command.success, command.message = False, str(exc)
            self._fault = self._fault or str(exc)
            self._set_status(SweepStatus(SweepPhase.FAULT, None, self.status.roll_progress, str(exc)))
            return
        was = self._fault
        self._fault = None
        self.sequencer.clear()
        self._set_status(SweepStatus(SweepPhase.IDLE, None, 0.0, "waiting for ~/start"))
        command.success = True
        command.message = f"fault cleared ({was})" if was else "no fault to clear"

    def _step(self, was_active: bool) -> None:
        if self._connection_error is not None:
            return
        try:
            self.arm.keepalive()
            status = self.sequencer.poll()
            if status.phase is not SweepPhase.FAULT and not self.sequencer.active:
                fault = self.arm.fault()   # a protective stop while idle, a connection lost between sweeps
                if fault is not None:
                    status = SweepStatus(SweepPhase.FAULT, None, status.roll_progress, fault)
            pose = self.arm.tcp_pose()
        except Exception as exc:  # noqa: BLE001 - e.g. the connection dropped mid-call; whatever it is, stop
            self.sequencer.stop(str(exc))
            status = SweepStatus(SweepPhase.FAULT, self.sequencer.status.segment,
                                 self.sequencer.status.roll_progress, str(exc))
            pose = None
        if status.phase is SweepPhase.FAULT:
            if self._fault is None:
                self._fault = status.message or "arm fault"
                if not was_active:
                    self.get_logger().error(f"arm fault: {self._fault}")
        elif self._fault is not None:
            # latched: after a fault the sequencer reads IDLE/STOPPED, the node still says FAULT until reset
            status = SweepStatus(SweepPhase.FAULT, status.segment, status.roll_progress, self._fault)
        self._set_status(status)
        if pose is not None:
            self._publish(pose, status)
        if was_active and not self.sequencer.active:
            self.finished.set()
            if status.phase is SweepPhase.FAULT:
                self.get_logger().error(f"sweep fault: {status.message}")
            else:
                self.get_logger().info(f"sweep {status.phase.value}: {status.message}")

    def _now_ns(self) -> int:
        """The arm's time: the simulated clock, else the node's ROS clock."""
        return self.sim_clock.now_ns() if self.sim_clock is not None else self.get_clock().now().nanoseconds

    def _publish_clock(self, stamp_ns: int) -> None:
        message = Clock()
        message.clock.sec, message.clock.nanosec = divmod(stamp_ns, 1_000_000_000)
        try:
            self._clock_pub.publish(message)
        except Exception:  # noqa: BLE001 - the context went down between the check and the publish
            if self.context.ok():
                raise

    def _publish(self, pose: np.ndarray, status: SweepStatus) -> None:
        with self._state_lock:
            self._last_pose = pose
        message = PoseStamped()
        stamp_ns = self._now_ns()
        message.header.stamp.sec, message.header.stamp.nanosec = divmod(stamp_ns, 1_000_000_000)
        message.header.frame_id = self._frame_id
        message.pose.position.x, message.pose.position.y, message.pose.position.z = (float(v) for v in pose[:3])
        q = rotation_vector_to_quaternion(pose[3:])
        o = message.pose.orientation
        o.x, o.y, o.z, o.w = q
        try:
            self._pose_pub.publish(message)
            if self._publish_tf:
                self.tf.send([(self._frame_id, self._tool_frame, stamp_ns,
                               Transform.from_rotation_vector(pose[:3], pose[3:]))])
            self._progress_pub.publish(Float32(data=float(status.roll_progress)))
            plan = self.sequencer.plan
            if plan is not None and status.roll is not None:
                width = float(self._plan_settings["sweep.area"][3]) if plan.passes else 0.0
                self._coverage_pub.publish(Float32(data=float(raster_coverage(plan, width, status.roll,
                                                                              status.roll_fraction))))
                self._pass_pub.publish(UInt32MultiArray(data=[status.roll + 1, len(plan.rolls)]))
        except Exception:  # noqa: BLE001 - the context went down between the check and the publish
            if self.context.ok():
                raise

    def _release_arm(self) -> None:
        try:
            self.arm.stop()
            self.arm.disconnect()
        except (ArmError, RuntimeError) as exc:
            self.get_logger().warning(f"releasing the arm: {exc}")

    # -- state for diagnostics and in-process callers -------------------------------------------
    def _set_status(self, status: SweepStatus) -> None:
        with self._state_lock:
            self._status = status

    @property
    def status(self) -> SweepStatus:
        with self._state_lock:
            return self._status

    @property
    def plan(self) -> SweepPlan | None:
        """The plan of the sweep started last (also while a simulated one waits for its whole second)."""
        deferred = self._deferred
        return deferred if deferred is not None else self.sequencer.plan

    @property
    def active(self) -> bool:
        """A started sweep has not ended (moving, or simulated and waiting for its whole second)."""
        return self._deferred is not None or self.sequencer.active

    @property
    def last_pose(self) -> np.ndarray | None:
        """The TCP pose last read by the arm thread (other threads must not call the arm)."""
        with self._state_lock:
            return None if self._last_pose is None else self._last_pose.copy()

    def _diagnostic_status(self) -> Status:
        status = self.status
        with self._state_lock:
            pose = self._last_pose
        level = {SweepPhase.FAULT: ERROR, SweepPhase.STOPPED: WARN, SweepPhase.CONNECTING: WARN}.get(status.phase, OK)
        plan = self.sequencer.plan
        values: dict[str, Any] = {"phase": status.phase.value, "segment": status.segment or "",
                                  "roll_progress": status.roll_progress,
                                  "pass": (status.roll or 0) + 1 if status.roll is not None else 0,
                                  "passes": len(plan.rolls) if plan is not None else 0,
                                  "sweep_speed_m_s": float(self.settings["sweep.speed"]),
                                  "sweep_length_m": float(self.settings["sweep.length"])}
        if pose is not None:
            values.update({f"tcp_{k}": float(v) for k, v in zip(("x", "y", "z", "rx", "ry", "rz"), pose, strict=True)})
        return Status(level, status.message or status.phase.value, values)

    def destroy_node(self) -> None:
        # Also called by the context's cleanup on a node whose __init__ failed half-way.
        if hasattr(self, "_shutdown"):
            self._shutdown.set()
        action = getattr(self, "_action", None)
        if action is not None:
            action.end("the sweep node is shutting down")
        planner, worker = getattr(self, "_planner", None), getattr(self, "_worker", None)
        if planner is not None and planner.is_alive():
            planner.join(timeout=1.0)
        if worker is not None and worker.is_alive():
            worker.join(timeout=1.0)   # it stops and releases the arm on its way out
            if worker.is_alive():   # stuck in an arm call: give the call up (the robot's watchdog stops it)
                self.arm.abort()
                worker.join(timeout=COMMAND_TIMEOUT_S)
        super().destroy_node()


def _stamp_ns(header: Any) -> int:
    return int(header.stamp.sec) * 1_000_000_000 + int(header.stamp.nanosec)


def main(args: list[str] | None = None) -> None:
    from touchroller_bringup.ros_main import run_node

    run_node(SweepNode, args)


if __name__ == "__main__":
    main()
