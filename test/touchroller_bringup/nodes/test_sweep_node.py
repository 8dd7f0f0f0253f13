"""The sweep node in a real rclpy context: explicit start, limits, progress, faults, diagnostics."""
from __future__ import annotations

import importlib.util
import math
import threading
import time
from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("rclpy")

from diagnostic_msgs.msg import DiagnosticArray  # noqa: E402
from geometry_msgs.msg import PoseStamped  # noqa: E402
from rclpy.executors import SingleThreadedExecutor  # noqa: E402
from rclpy.node import Node  # noqa: E402
from rclpy.parameter import Parameter  # noqa: E402
from std_msgs.msg import Float32  # noqa: E402
from std_srvs.srv import Trigger  # noqa: E402

from touchroller_bringup import names  # noqa: E402
from touchroller_bringup.nodes.sweep_node import SweepNode, rotation_vector_to_quaternion  # noqa: E402
from touchroller_driver.arm import ArmLimits, SimulatedArm, SweepPhase  # noqa: E402

pytestmark = [pytest.mark.ros, pytest.mark.timeout(60)]

_spec = importlib.util.spec_from_file_location("sweep_arms", Path(__file__).parents[1] / "sweep_arms.py")
assert _spec is not None and _spec.loader is not None
sweep_arms = importlib.util.module_from_spec(_spec)
_spec.loader.exec_module(sweep_arms)
START, SWEEP_SPEED, SPEEDUP = sweep_arms.START, sweep_arms.SWEEP_SPEED, sweep_arms.SPEEDUP
SLOW_ROLL = sweep_arms.SLOW_ROLL
ScaledClock, SlowRollArm, fast_clock = sweep_arms.ScaledClock, sweep_arms.SlowRollArm, sweep_arms.fast_clock
OVERRIDES = [
    Parameter("sweep.length", value=0.02),
    Parameter("sweep.speed", value=SWEEP_SPEED),
    Parameter("sweep.approach_speed", value=0.01),
    Parameter("sweep.start_pose", value=START),
]


class Harness:
    """The node under test plus a probe node that calls its services and records its topics."""

    def __init__(self, context, arm=None, overrides=OVERRIDES) -> None:
        self.node = SweepNode(arm=arm, context=context, parameter_overrides=list(overrides))
        self.probe = Node("probe", context=context)
        self.executor = SingleThreadedExecutor(context=context)
        self.executor.add_node(self.node)
        self.executor.add_node(self.probe)
        self.poses: list[PoseStamped] = []
        self.progress: list[float] = []
        self.diagnostics: list[DiagnosticArray] = []
        self.probe.create_subscription(PoseStamped, names.topic(names.TCP_POSE), self.poses.append, 50)
        self.probe.create_subscription(Float32, names.topic(names.SWEEP_PROGRESS),
                                       lambda m: self.progress.append(m.data), 50)
        self.probe.create_subscription(DiagnosticArray, "/diagnostics", self.diagnostics.append, 10)
        self.clients = {name: self.probe.create_client(Trigger, names.service(names.SWEEP_NODE, name))
                        for name in (names.START, names.STOP, names.RESET_FAULT)}

    def call(self, spin_until, name: str):
        client = self.clients[name]
        assert spin_until(self.executor, client.service_is_ready, timeout=10.0)
        future = client.call_async(Trigger.Request())
        assert spin_until(self.executor, future.done, timeout=10.0)
        return future.result()

    def close(self) -> None:
        self.executor.shutdown()
        self.node.destroy_node()
        self.probe.destroy_node()


@pytest.fixture
def harness_factory(ros_context):
    made = []

    def make(**kwargs) -> Harness:
        harness = Harness(ros_context, **kwargs)
        made.append(harness)
        return harness

    yield make
    for harness in made:
        harness.close()


def sim_arm(**kwargs) -> SimulatedArm:
    return SimulatedArm(START, clock=fast_clock, **kwargs)


def test_no_motion_without_start(harness_factory, spin_until):
    arm = sim_arm()
    h = harness_factory(arm=arm)
    assert spin_until(h.executor, lambda: len(h.poses) >= 5, timeout=10.0)
    assert not arm.is_moving()
    assert h.node.status.phase is SweepPhase.IDLE
    last = h.poses[-1].pose.position
    assert (last.x, last.y, last.z) == pytest.approx(START[:3])
    assert all(p == 0.0 for p in h.progress)


def test_start_service_runs_the_whole_sweep(harness_factory, spin_until):
    arm = sim_arm()
    h = harness_factory(arm=arm)
    response = h.call(spin_until, "start")
    assert response.success
    assert spin_until(h.executor, h.node.finished.is_set, timeout=20.0)
    assert h.node.status.phase is SweepPhase.DONE
    assert spin_until(h.executor, lambda: h.progress and h.progress[-1] == 1.0, timeout=20.0)
    rolling = [p for p in h.progress if 0.0 < p < 1.0]
    assert rolling and rolling == sorted(rolling)
    # The arm ends lifted to sweep.clearance above the roll's end ...
    final = arm.tcp_pose()
    assert final[0] == pytest.approx(START[0] + 0.02, abs=1e-9)
    assert final[2] == pytest.approx(START[2] + 0.002, abs=1e-9)
    # ... and the node publishes that pose. Progress reaches 1.0 when the roll ends, before the lift,
    # and the two topics are delivered independently, so wait for the pose itself.
    def published_final() -> bool:
        return bool(h.poses) and np.allclose(
            [h.poses[-1].pose.position.x, h.poses[-1].pose.position.z], final[[0, 2]], atol=1e-9)
    assert spin_until(h.executor, published_final, timeout=20.0)
    assert h.poses[-1].header.frame_id == "base"
    # Once done, a second start runs again (from where the arm is, via the start pose).
    assert h.call(spin_until, "start").success


def test_start_is_refused_while_a_sweep_runs_and_stop_halts(harness_factory, spin_until):
    arm = SlowRollArm()   # at 10x the whole sweep took 0.15 s: a late second call found it done (and passed)
    h = harness_factory(arm=arm)
    assert h.call(spin_until, "start").success
    assert not h.call(spin_until, "start").success
    assert arm.is_moving() and h.node.sequencer.active   # the refusal above was for a running sweep
    assert h.call(spin_until, "stop").success
    assert h.node.finished.wait(10.0)
    assert h.node.status.phase is SweepPhase.STOPPED
    assert not arm.is_moving()


def test_parameters_beyond_the_arm_limits_are_rejected(harness_factory):
    h = harness_factory(arm=sim_arm(limits=ArmLimits(max_speed=0.05, max_accel=0.5)))
    result = h.node.set_parameters([Parameter("sweep.speed", value=0.08)])[0]
    assert not result.successful and "speed" in result.reason
    assert h.node.get_parameter("sweep.speed").value == pytest.approx(0.02)
    result = h.node.set_parameters([Parameter("sweep.start_pose", value=[0.4, 0.0, 0.2])])[0]
    assert not result.successful
    assert h.node.set_parameters([Parameter("sweep.speed", value=0.04)])[0].successful
    assert h.node.settings["sweep.speed"] == pytest.approx(0.04)
    assert not h.node.set_parameters([Parameter("arm.max_speed", value=1.0)])[0].successful  # read-only


def test_fault_stops_the_sweep_and_shows_in_diagnostics(harness_factory, spin_until):
    arm = SlowRollArm()   # the roll lasted 0.1 s at 10x: a test thread descheduled that long missed it
    h = harness_factory(arm=arm)
    assert h.call(spin_until, "start").success
    assert spin_until(h.executor, lambda: h.node.status.phase is SweepPhase.SWEEPING, timeout=20.0)
    assert arm.is_moving()
    arm.inject_fault("protective stop")
    assert spin_until(h.executor, h.node.finished.is_set, timeout=20.0)
    assert h.node.status.phase is SweepPhase.FAULT

    def error_reported() -> bool:
        return any(s.level == b"\x02" and "protective stop" in s.message
                   for array in h.diagnostics for s in array.status)

    assert spin_until(h.executor, error_reported, timeout=20.0)
    response = h.call(spin_until, "start")
    assert not response.success


def test_unreachable_robot_is_a_fault_not_a_crash(harness_factory, spin_until):
    overrides = [*OVERRIDES, Parameter("use_sim", value=False), Parameter("robot_ip", value="127.0.0.213")]
    h = harness_factory(overrides=overrides)
    assert spin_until(h.executor, lambda: h.node.status.phase is SweepPhase.FAULT, timeout=10.0)
    assert "cannot connect" in h.node.status.message
    response = h.call(spin_until, "start")
    assert not response.success
    assert "127.0.0.213" in response.message


def test_rotation_vector_to_quaternion():
    assert rotation_vector_to_quaternion([0, 0, 0]) == (0.0, 0.0, 0.0, 1.0)
    q = rotation_vector_to_quaternion([math.pi, 0, 0])
    np.testing.assert_allclose(q, [1.0, 0.0, 0.0, 0.0], atol=1e-12)
    q = rotation_vector_to_quaternion([0, 0, math.pi / 2])
    np.testing.assert_allclose(q, [0, 0, math.sin(math.pi / 4), math.cos(math.pi / 4)])


def test_the_arm_thread_keeps_the_arm_alive(harness_factory, spin_until):
    class CountingArm(SimulatedArm):
        kicks = 0

        def keepalive(self) -> None:
            CountingArm.kicks += 1

    h = harness_factory(arm=CountingArm(START, clock=fast_clock))
    assert spin_until(h.executor, lambda: CountingArm.kicks >= 10, timeout=5.0)  # 50 Hz loop, >= 10 Hz needed


def test_shutting_the_context_down_mid_sweep_stops_the_arm(ros_context):
    """Ctrl-C under `ros2 run`: rclpy shuts the context down; the arm thread stops the arm and exits."""
    arm = SlowRollArm()   # at 10x the roll lasted 0.1 s: a late poll found the sweep over and the arm still
    node = SweepNode(arm=arm, context=ros_context, parameter_overrides=list(OVERRIDES))
    try:
        assert node.request_start()[0]
        deadline = time.monotonic() + 20.0
        while node.status.phase is not SweepPhase.SWEEPING and time.monotonic() < deadline:
            time.sleep(0.01)
        assert arm.is_moving()
        ros_context.try_shutdown()
        node._worker.join(timeout=20.0)
        assert not node._worker.is_alive()
        assert not arm.is_moving()
        halted = arm.tcp_pose()
        time.sleep(0.2)   # still rolling, the arm would move 0.2 s x SLOW_ROLL x 0.02 m/s = 80 um by now
        np.testing.assert_allclose(arm.tcp_pose(), halted, rtol=0, atol=1e-9)
    finally:
        node.destroy_node()


def sweep_errors(h: Harness) -> list[str]:
    return [s.message for array in h.diagnostics for s in array.status
            if s.name.endswith(names.SWEEP_NODE) and s.level == b"\x02"]


def test_a_protective_stop_while_idle_shows_and_needs_a_reset(harness_factory, spin_until):
    arm = sim_arm()
    h = harness_factory(arm=arm)
    assert spin_until(h.executor, lambda: h.node.status.phase is SweepPhase.IDLE, timeout=20.0)
    arm.inject_fault("protective stop")
    assert spin_until(h.executor, lambda: any("protective stop" in m for m in sweep_errors(h)), timeout=20.0)
    assert h.node.status.phase is SweepPhase.FAULT
    response = h.call(spin_until, "start")
    assert not response.success and "protective stop" in response.message and names.RESET_FAULT in response.message
    assert not arm.is_moving()
    response = h.call(spin_until, names.RESET_FAULT)
    assert response.success and "protective stop" in response.message
    assert h.node.status.phase is SweepPhase.IDLE and arm.fault() is None
    assert h.call(spin_until, "start").success
    assert spin_until(h.executor, h.node.finished.is_set, timeout=20.0)
    assert h.node.status.phase is SweepPhase.DONE


def test_after_a_disconnect_mid_roll_start_fails_until_reset(harness_factory, spin_until):
    arm = SlowRollArm()
    h = harness_factory(arm=arm)
    assert h.call(spin_until, "start").success
    assert spin_until(h.executor, lambda: h.node.status.phase is SweepPhase.SWEEPING, timeout=20.0)
    arm.inject_disconnect()
    assert spin_until(h.executor, h.node.finished.is_set, timeout=20.0)
    assert h.node.status.phase is SweepPhase.FAULT
    assert not h.call(spin_until, "start").success   # the sweep has faulted: no success for a dead arm
    assert spin_until(h.executor, lambda: any("lost the connection" in m for m in sweep_errors(h)), timeout=20.0)
    assert h.call(spin_until, names.RESET_FAULT).success
    arm.clock.set_rate(SPEEDUP)
    assert h.call(spin_until, "start").success


def test_a_fault_that_remains_is_not_reset(harness_factory, spin_until):
    arm = sim_arm()
    h = harness_factory(arm=arm)
    assert spin_until(h.executor, lambda: h.node.status.phase is SweepPhase.IDLE, timeout=20.0)
    arm.inject_fault("emergency stop", resettable=False)
    assert spin_until(h.executor, lambda: h.node.status.phase is SweepPhase.FAULT, timeout=20.0)
    response = h.call(spin_until, names.RESET_FAULT)
    assert not response.success and "emergency stop" in response.message
    assert h.node.status.phase is SweepPhase.FAULT
    assert not h.call(spin_until, "start").success
    assert h.call(spin_until, names.RESET_FAULT).success is False
    arm.inject_fault("protective stop")   # released on the pendant; the protective stop that is left resets
    assert h.call(spin_until, names.RESET_FAULT).success
    assert h.call(spin_until, "start").success


@pytest.mark.timeout(180)
def test_a_silent_robot_leaves_the_node_responsive_and_sigint_ends_it(ros_context, spin_until, silent_ur_host):
    """A host that accepts TCP on the UR ports and never answers: the sweep node (a process, as `ros2 run`
    starts it) still publishes diagnostics (ERROR), answers ~/start (failure), and exits on SIGINT."""
    import signal
    import subprocess
    import sys

    process = subprocess.Popen([sys.executable, "-m", "touchroller_bringup.nodes.sweep_node", "--ros-args",
                                "-p", "use_sim:=false", "-p", f"robot_ip:={silent_ur_host}"],
                               stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    probe = Node("silent_robot_probe", context=ros_context)
    executor = SingleThreadedExecutor(context=ros_context)
    executor.add_node(probe)
    diagnostics: list[DiagnosticArray] = []
    probe.create_subscription(DiagnosticArray, "/diagnostics", diagnostics.append, 10)
    start = probe.create_client(Trigger, names.service(names.SWEEP_NODE, names.START))
    try:
        def error_shown() -> bool:
            return any(s.name.endswith(names.SWEEP_NODE) and s.level == b"\x02" and silent_ur_host in s.message
                       for array in diagnostics for s in array.status)

        assert spin_until(executor, error_shown, timeout=60.0), "no ERROR on /diagnostics"
        message = next(s.message for array in diagnostics for s in array.status
                       if s.name.endswith(names.SWEEP_NODE) and s.level == b"\x02")
        assert "no RTDE answer" in message
        assert spin_until(executor, start.service_is_ready, timeout=30.0)
        future = start.call_async(Trigger.Request())
        assert spin_until(executor, future.done, timeout=60.0), "~/start did not answer"
        assert not future.result().success and silent_ur_host in future.result().message
        process.send_signal(signal.SIGINT)
        try:
            process.wait(timeout=60)
        except subprocess.TimeoutExpired:
            pytest.fail("the sweep node ignored SIGINT")
        assert "Traceback" not in process.stdout.read()
    finally:
        if process.poll() is None:
            process.kill()
            process.wait(timeout=10)
        executor.shutdown()
        probe.destroy_node()


# -- issue #29: a refused start never moves the arm; bounded rasters; start-up values checked ---------

def test_a_start_answered_failure_never_moves_the_arm(harness_factory, spin_until, monkeypatch):
    """Planning outlasts the service's wait: ~/start answers failure, and the start is cancelled, so the
    arm stays where it is once planning ends (it used to sweep a few seconds after the failure)."""
    from touchroller_bringup.nodes import sweep_node

    slow = threading.Event()
    planned = threading.Event()
    original = sweep_node.plan_sweep

    def slow_plan(*args, **kwargs):
        if slow.is_set():
            time.sleep(1.5)
            planned.set()
        return original(*args, **kwargs)

    monkeypatch.setattr(sweep_node, "plan_sweep", slow_plan)
    monkeypatch.setattr(sweep_node, "COMMAND_TIMEOUT_S", 0.3)
    arm = sim_arm()
    h = harness_factory(arm=arm)
    assert spin_until(h.executor, lambda: h.node.status.phase is SweepPhase.IDLE, timeout=20.0)
    rest = arm.tcp_pose()
    slow.set()
    response = h.call(spin_until, "start")
    assert not response.success and "cancelled" in response.message
    assert planned.wait(20.0)
    slow.clear()
    # the arm thread has had every chance to run the abandoned start: many loops of it
    assert spin_until(h.executor, lambda: len(h.poses) >= 20, timeout=20.0)
    h.poses.clear()
    assert spin_until(h.executor, lambda: len(h.poses) >= 20, timeout=20.0)
    assert not arm.is_moving() and not h.node.active
    np.testing.assert_allclose(arm.tcp_pose(), rest, rtol=0, atol=0)
    assert h.node.status.phase is SweepPhase.IDLE
    assert h.call(spin_until, "start").success   # the next start, answered in time, runs


@pytest.mark.parametrize(("name", "value", "why"), [
    ("sweep.area", [0.40, -0.03, 0.04, 3000.0], "reach"),             # 66 667 passes, 2.67 km of rolling
    ("sweep.area", [1000.0, 1000.0, 0.05, 0.05], "reach"),            # an approach of about 78 h
    ("sweep.area", [0.4, -0.03, 5000.0, 5000.0], "reach"),            # 5 km: blocked the parameter service
    ("sweep.area", [0.3, -0.02, 0.3, 0.04], "max_duration"),          # within reach, but 30 x 27 s of rolling
    ("sweep.area", [0.40, -0.03, 0.04], "4 finite"),
    ("sweep.area", [0.40, float("nan"), 0.04, 0.04], "finite"),
    ("sweep.direction", [0.0, 0.0, 0.0], "horizontal"),
    ("sweep.direction", [0.0, 0.0, 1.0], "horizontal"),
    ("sweep.direction", [float("nan"), 0.0, 0.0], "finite"),
    ("sweep.speed", 0.5, "speed"),
    ("sweep.profile", "zigzag", "sweep.profile must be one of ramp, blend, constant"),
])
def test_out_of_bounds_sweeps_are_refused_at_set_time_and_at_start_up(harness_factory, ros_context, name, value,
                                                                      why):
    arm = sim_arm()
    overrides = [*OVERRIDES, Parameter("sweep.usable_width", value=0.001), Parameter("sweep.overlap", value=0.0),
                 Parameter("sweep.max_duration", value=300.0)] if why == "max_duration" else OVERRIDES
    h = harness_factory(arm=arm, overrides=overrides)
    result = h.node.set_parameters([Parameter(name, value=value)])[0]
    assert not result.successful and why in result.reason and "\n" not in result.reason, result.reason
    assert not arm.is_moving()
    from touchroller_bringup.errors import UserError

    with pytest.raises((ValueError, UserError), match=why) as refused:
        SweepNode(arm=sim_arm(), context=ros_context, node_name="refused",
                  parameter_overrides=[*overrides, Parameter(name, value=value)])
    # one line, from the sweep's own checks or, for a non-finite number, from the declaration's
    assert "\n" not in str(refused.value) and str(refused.value).startswith(("sweep parameters refused", name))


def test_a_huge_raster_is_refused_before_any_pass_is_planned(harness_factory, monkeypatch):
    """The raster's size and corners are bounded analytically: a 5 km area never reaches the pass loop."""
    from touchroller_driver import arm as arm_module

    h = harness_factory(arm=sim_arm())
    built = []
    original = arm_module.raster_offsets
    monkeypatch.setattr(arm_module, "raster_offsets", lambda *a: built.append(a) or original(*a))
    for area in ([0.4, -0.03, 5000.0, 5000.0], [0.40, -0.03, 0.04, 3000.0]):
        assert not h.node.set_parameters([Parameter("sweep.area", value=area)])[0].successful
    assert built == []
    h.node.set_parameters([Parameter("sweep.area", value=[0.38, -0.05, 0.05, 0.1])])
    assert len(built) == 1   # a sane raster is planned (the check above is not vacuous)


@pytest.mark.timeout(120)
@pytest.mark.parametrize("argument", ["sweep.speed:=0.5", "sweep.direction:=[.nan,0.0,0.0]",
                                      "sweep.area:=[1000.0,1000.0,0.05,0.05]"])
def test_the_node_process_refuses_bad_start_up_values_in_one_line(argument):
    import subprocess
    import sys

    done = subprocess.run([sys.executable, "-m", "touchroller_bringup.nodes.sweep_node", "--ros-args", "-p",
                           argument], capture_output=True, text=True, timeout=100)
    assert done.returncode == 2, done.stderr
    lines = done.stderr.strip().splitlines()
    name = argument.split(":=")[0]
    assert len(lines) == 1 and "Traceback" not in done.stderr
    assert "sweep parameters refused" in lines[0] or f"{name} must be a finite number" in lines[0], lines[0]


@pytest.mark.timeout(180)
def test_a_robot_that_greets_then_stalls_leaves_the_node_responsive_and_sigint_ends_it(ros_context, spin_until,
                                                                                       half_alive_ur_host):
    """The host passes the start-up probes, then ur_rtde's constructor waits for ever (it froze the whole
    node, SIGINT included): now ERROR on /diagnostics, ~/start and ~/reset_fault answer failure, and SIGINT
    (sent while a ~/start retries the connection) ends the process."""
    import signal
    import subprocess
    import sys

    process = subprocess.Popen([sys.executable, "-m", "touchroller_bringup.nodes.sweep_node", "--ros-args",
                                "-p", "use_sim:=false", "-p", f"robot_ip:={half_alive_ur_host}",
                                "-p", "robot_timeout:=1.0"],
                               stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    probe = Node("half_alive_probe", context=ros_context)
    executor = SingleThreadedExecutor(context=ros_context)
    executor.add_node(probe)
    diagnostics: list[DiagnosticArray] = []
    probe.create_subscription(DiagnosticArray, "/diagnostics", diagnostics.append, 10)
    clients = {name: probe.create_client(Trigger, names.service(names.SWEEP_NODE, name))
               for name in (names.START, names.RESET_FAULT)}
    try:
        def errors() -> list[str]:
            return [s.message for array in diagnostics for s in array.status
                    if s.name.endswith(names.SWEEP_NODE) and s.level == b"\x02"]

        assert spin_until(executor, lambda: bool(errors()), timeout=60.0), "no ERROR on /diagnostics"
        assert half_alive_ur_host in errors()[0] and "RTDEReceiveInterface" in errors()[0], errors()[0]
        for name in (names.RESET_FAULT, names.START):
            assert spin_until(executor, clients[name].service_is_ready, timeout=30.0)
            future = clients[name].call_async(Trigger.Request())
            assert spin_until(executor, future.done, timeout=60.0), f"~/{name} did not answer"
            assert not future.result().success and half_alive_ur_host in future.result().message
        clients[names.START].call_async(Trigger.Request())   # a start retrying the connection ...
        time.sleep(0.5)
        process.send_signal(signal.SIGINT)   # ... and Ctrl-C meanwhile
        try:
            process.wait(timeout=30)
        except subprocess.TimeoutExpired:
            pytest.fail("the sweep node ignored SIGINT")
        assert "Traceback" not in process.stdout.read()
    finally:
        if process.poll() is None:
            process.kill()
            process.wait(timeout=10)
        executor.shutdown()
        probe.destroy_node()


@pytest.mark.ros
def test_two_rollers_in_two_namespaces_share_the_robots_base(ros_context, spin_until):
    """#27.2: with namespace:=left, `base` and `tool0` became left/base and left/tool0, so with a real driver
    publishing `base` the map never linked. Only our own frames take the prefix; the robot's are the
    driver's names (here two arms with their own flanges, as a user configures them)."""
    from touchroller_bringup.nodes.perception_node import PerceptionNode
    from touchroller_bringup.tf import TransformListener

    rollers = [SweepNode(arm=SimulatedArm(START), context=ros_context, namespace=side,
                         parameter_overrides=[*OVERRIDES, Parameter("arm.tool_frame", value=f"{side}_tool0")])
               for side in ("left", "right")]
    perception = PerceptionNode(context=ros_context, namespace="left")
    probe = Node("frames_probe", context=ros_context)
    listener = TransformListener(probe)
    executor = SingleThreadedExecutor(context=ros_context)
    for node in (*rollers, perception, probe):
        executor.add_node(node)
    try:
        assert perception.world_frame == "base"
        for side in ("left", "right"):
            assert spin_until(executor, lambda side=side: listener.lookup(
                "base", f"{side}/touchroller_cylinder") is not None, timeout=20.0), side
            assert listener.lookup(f"{side}_tool0", f"{side}/touchroller_cylinder") is not None
            assert listener.lookup(f"{side}/base", f"{side}/touchroller_cylinder") is None
    finally:
        executor.shutdown()
        for node in (*rollers, perception, probe):
            node.destroy_node()


# -- sweep.profile ---------------------------------------------------------------------------------------

class PathRecordingArm(SimulatedArm):
    """A SimulatedArm that records its path moves; `slow_paths` makes a path roll at SLOW_ROLL x real time."""

    def __init__(self, slow_paths: bool = False) -> None:
        super().__init__(START, clock=ScaledClock())
        self.paths: list[tuple] = []
        self.slow_paths = slow_paths
        self.rolling = threading.Event()

    def move_path(self, waypoints, speed, accel, blend, asynchronous=True) -> None:
        super().move_path(waypoints, speed, accel, blend, asynchronous)
        self.paths.append((np.array(waypoints), speed, accel, blend))
        if self.slow_paths and not self.rolling.is_set():
            self.clock.set_rate(SLOW_ROLL)
            self.rolling.set()


def test_sweep_profile_is_declared_validated_and_blend_runs_each_pass_as_one_path(harness_factory, spin_until):
    arm = PathRecordingArm()
    h = harness_factory(arm=arm)
    descriptor = h.node.describe_parameter("sweep.profile")
    assert "blend" in descriptor.description and "ramp, blend, constant" in descriptor.additional_constraints
    assert h.node.get_parameter("sweep.profile").value == "ramp"   # the default: nothing changes
    assert h.node.set_parameters([Parameter("sweep.profile", value="blend")])[0].successful
    assert h.call(spin_until, "start").success
    assert spin_until(h.executor, h.node.finished.is_set, timeout=20.0)
    assert h.node.status.phase is SweepPhase.DONE
    plan = h.node.plan
    assert plan is not None and plan.profile == "blend" and len(arm.paths) == 1
    waypoints, speed, _, blend = arm.paths[0]
    np.testing.assert_allclose(waypoints[1:3], [plan.segments[1].target, plan.segments[2].target])
    assert speed == pytest.approx(SWEEP_SPEED) and blend > 0
    np.testing.assert_allclose(arm.tcp_pose(), waypoints[-1], atol=1e-9)
    h.node.set_parameters([Parameter("sweep.profile", value="ramp")])
    assert h.call(spin_until, "start").success
    assert spin_until(h.executor, h.node.finished.is_set, timeout=20.0)
    assert len(arm.paths) == 1   # ramp: linear moves only, as before


def test_stop_mid_path_halts_the_arm(harness_factory, spin_until):
    arm = PathRecordingArm(slow_paths=True)
    h = harness_factory(arm=arm, overrides=[*OVERRIDES, Parameter("sweep.profile", value="constant")])
    assert h.call(spin_until, "start").success
    assert arm.rolling.wait(20.0)
    assert arm.is_moving()
    assert h.call(spin_until, "stop").success
    assert h.node.finished.wait(10.0)
    assert h.node.status.phase is SweepPhase.STOPPED
    here = arm.tcp_pose()
    time.sleep(0.2)
    assert not arm.is_moving() and np.array_equal(arm.tcp_pose(), here)


def test_a_start_whose_answer_never_reaches_its_caller_stops_the_arm(harness_factory, other_participant,
                                                                     never_answered_qos, spin_until):
    """rmw dropped the answer of a start that succeeded (a caller in another participant whose reply reader
    never matches): once the answer is given up, the sweep it started is stopped, as the arm moves only
    after a start that was answered success."""
    arm = SlowRollArm()   # the roll lasts 50 s of wall time: the stop comes while it rolls
    h = harness_factory(arm=arm)
    caller = Node("deaf_caller", context=other_participant)
    deaf = caller.create_client(Trigger, names.service(names.SWEEP_NODE, names.START), qos_profile=never_answered_qos)
    try:
        deadline = time.monotonic() + 30.0
        while not arm.moves and time.monotonic() < deadline:   # until its request writer is matched
            deaf.call_async(Trigger.Request())
            spin_until(h.executor, lambda: arm.moves > 0, timeout=0.5)
        assert arm.moves, "the start was never taken"
        assert spin_until(h.executor, h.node.finished.is_set, timeout=30.0)
        assert h.node.status.phase is SweepPhase.STOPPED and not arm.is_moving()
        assert not h.progress or h.progress[-1] < 1.0   # stopped, not finished
        assert h.node.answers.counts.lost >= 1
        assert h.call(spin_until, "start").success   # a caller who hears the answer starts it again
        assert arm.is_moving() or h.node.sequencer.active
        assert h.call(spin_until, "stop").success
    finally:
        caller.destroy_node()
