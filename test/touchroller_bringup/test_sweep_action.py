"""The sweep node's Sweep action against the simulated arm, with rclpy's ActionClient: accept, feedback,
result; cancel stops the arm as ~/stop does; invalid goals are rejected without motion; one sweep at a
time; a client that disappears mid-goal stops the arm; a fault aborts the goal; no action where
touchroller_interfaces is missing."""
from __future__ import annotations

import importlib.util
import math
import os
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from touchroller_bringup.sweep_action import Outcome, SweepFeedback, goal_settings, passes_done, sweep_feedback
from touchroller_driver.arm import SweepPhase, SweepStatus, plan_sweep

_spec = importlib.util.spec_from_file_location("sweep_arms", Path(__file__).with_name("sweep_arms.py"))
assert _spec is not None and _spec.loader is not None
sweep_arms = importlib.util.module_from_spec(_spec)
_spec.loader.exec_module(sweep_arms)
START, SWEEP_SPEED, SPEEDUP = sweep_arms.START, sweep_arms.SWEEP_SPEED, sweep_arms.SPEEDUP
SLOW_ROLL = sweep_arms.SLOW_ROLL
ScaledClock, SlowRollArm = sweep_arms.ScaledClock, sweep_arms.SlowRollArm
SETTINGS = {"sweep.length": 0.11, "sweep.speed": 0.011, "sweep.depth": 0.0005, "sweep.accel": 0.1,
            "sweep.approach_speed": 0.005, "sweep.overlap": 0.25, "sweep.area": [0.0, 0.0, 0.0, 0.0],
            "sweep.start_pose": START, "sweep.direction": [1.0, 0.0, 0.0], "sweep.retract": True}


class _Goal:
    """A goal message's fields at their .action defaults, without the generated type."""

    def __init__(self, **fields) -> None:
        self.area, self.start_pose, self.direction = [], [], []
        self.length = self.speed = self.depth = self.accel = self.approach_speed = self.overlap = -1.0
        for name, value in fields.items():
            setattr(self, name, value)


# -- pure: goal -> parameters, feedback -----------------------------------------------------------

def test_a_goal_at_its_defaults_takes_the_nodes_parameters():
    assert goal_settings(_Goal(), SETTINGS) == SETTINGS


def test_goal_fields_override_their_parameters():
    merged = goal_settings(_Goal(speed=0.02, depth=0.0, area=[0.3, 0.0, 0.05, 0.1]), SETTINGS)
    assert merged["sweep.speed"] == 0.02 and merged["sweep.depth"] == 0.0   # depth 0 is a depth, not "unset"
    assert merged["sweep.area"] == [0.3, 0.0, 0.05, 0.1]
    assert merged["sweep.length"] == SETTINGS["sweep.length"]


@pytest.mark.parametrize("fields", [{"area": [0.3, 0.0, 0.05]}, {"area": [0.3, 0.0, 0.05, -0.1]},
                                    {"start_pose": [0.4, 0.0, 0.2]},
                                    {"speed": math.nan}, {"depth": math.inf}])
def test_malformed_goal_fields_are_one_line_errors(fields):
    with pytest.raises(ValueError, match="goal"):
        goal_settings(_Goal(**fields), SETTINGS)


def test_feedback_of_a_single_roll():
    plan = plan_sweep(START, length=0.02, speed=0.02, accel=0.1, depth=0.0005)
    before = sweep_feedback(plan, SweepStatus(SweepPhase.MOVING, "to_start", 0.0), 0.0)
    assert before == SweepFeedback(0, 1, 0.0, 0.0, "moving")
    half = sweep_feedback(plan, SweepStatus(SweepPhase.SWEEPING, "sweep", 0.5, "", 0, 0.5), 0.0)
    assert (half.pass_index, half.pass_count) == (1, 1)
    assert half.distance == pytest.approx(0.01) and half.coverage == pytest.approx(0.5)
    assert passes_done(half, SweepStatus(SweepPhase.STOPPED, "sweep", 0.5, "", 0, 0.5)) == 0
    done = SweepStatus(SweepPhase.DONE, None, 1.0, "sweep complete", 0, 1.0)
    assert passes_done(sweep_feedback(plan, done, 0.0), done) == 1


@settings(max_examples=60)
@given(width=st.floats(0.0, 0.5), length=st.floats(0.001, 0.2), roll=st.integers(0, 20),
       fraction=st.floats(0.0, 1.0))
def test_feedback_stays_within_the_plan(width, length, roll, fraction):
    from touchroller_driver.arm import DEFAULT_MOUNT_RPY, DEFAULT_MOUNT_XYZ, mount_transform, plan_raster

    plan = plan_raster(START, area=[0.3, -0.1, length, width], mount=mount_transform(DEFAULT_MOUNT_XYZ,
                       DEFAULT_MOUNT_RPY), speed=0.02, accel=0.1, depth=0.0005)
    status = SweepStatus(SweepPhase.SWEEPING, "sweep", 0.0, "", min(roll, len(plan.rolls) - 1), fraction)
    feedback = sweep_feedback(plan, status, width)
    assert 1 <= feedback.pass_index <= feedback.pass_count == len(plan.rolls)
    assert 0.0 <= feedback.coverage <= 1.0
    assert 0.0 <= feedback.distance <= plan.length + 1e-12
    assert 0 <= passes_done(feedback, status) <= feedback.pass_count
    further = sweep_feedback(plan, SweepStatus(SweepPhase.SWEEPING, "sweep", 0.0, "", status.roll, 1.0), width)
    assert further.distance >= feedback.distance and further.coverage >= feedback.coverage - 1e-12


# -- the node with rclpy ----------------------------------------------------------------------------

rclpy = pytest.importorskip("rclpy")
Sweep = pytest.importorskip("touchroller_interfaces.action", reason="touchroller_interfaces is not built").Sweep

from action_msgs.msg import GoalStatus  # noqa: E402
from rclpy.action import ActionClient  # noqa: E402
from rclpy.executors import MultiThreadedExecutor, SingleThreadedExecutor  # noqa: E402
from rclpy.node import Node  # noqa: E402
from rclpy.parameter import Parameter  # noqa: E402
from std_srvs.srv import Trigger  # noqa: E402

from touchroller_bringup import names  # noqa: E402
from touchroller_bringup.nodes.sweep_node import SweepNode  # noqa: E402
from touchroller_driver.arm import SimulatedArm  # noqa: E402

pytestmark = [pytest.mark.ros, pytest.mark.timeout(120)]

OVERRIDES = [Parameter("sweep.length", value=0.02), Parameter("sweep.speed", value=SWEEP_SPEED),
             Parameter("sweep.approach_speed", value=0.01), Parameter("sweep.start_pose", value=START)]
ACTION = names.topic(names.SWEEP_ACTION)


class CountingArm(SimulatedArm):
    def __init__(self) -> None:
        super().__init__(START, clock=lambda: time.monotonic() * SPEEDUP)
        self.moves = 0

    def move_linear(self, target_pose, speed: float, accel: float, asynchronous: bool = True) -> None:
        self.moves += 1
        super().move_linear(target_pose, speed, accel, asynchronous)


class Harness:
    """The sweep node and a probe node with an ActionClient and the Trigger clients, one executor."""

    def __init__(self, context, arm, overrides=OVERRIDES, client: bool = True, threads: int = 1) -> None:
        self.arm = arm
        self.node = SweepNode(arm=arm, context=context, parameter_overrides=list(overrides))
        self.probe = Node("action_probe", context=context)
        # one thread for everything is the strictest (the console script's); touchroller scan runs several
        self.executor = SingleThreadedExecutor(context=context) if threads == 1 else \
            MultiThreadedExecutor(num_threads=threads, context=context)
        self.executor.add_node(self.node)
        self.executor.add_node(self.probe)
        self.client = ActionClient(self.probe, Sweep, ACTION) if client else None
        self.feedback: list = []
        self.start = self.probe.create_client(Trigger, names.service(names.SWEEP_NODE, names.START))

    def send(self, spin_until, **fields):
        assert spin_until(self.executor, lambda: self.client.server_is_ready(), timeout=20.0)
        goal = Sweep.Goal(**fields)
        future = self.client.send_goal_async(goal, feedback_callback=lambda m: self.feedback.append(m.feedback))
        assert spin_until(self.executor, future.done, timeout=20.0)
        return future.result()

    def result(self, spin_until, handle, timeout: float = 30.0):
        future = handle.get_result_async()
        assert spin_until(self.executor, future.done, timeout=timeout)
        return future.result()

    def call_start(self, spin_until):
        assert spin_until(self.executor, self.start.service_is_ready, timeout=10.0)
        future = self.start.call_async(Trigger.Request())
        assert spin_until(self.executor, future.done, timeout=10.0)
        return future.result()

    def close(self) -> None:
        self.executor.shutdown()
        if self.client is not None:
            self.client.destroy()
        self.node.destroy_node()
        self.probe.destroy_node()


@pytest.fixture
def harness(ros_context):
    made: list[Harness] = []

    def make(arm, **kwargs) -> Harness:
        made.append(Harness(ros_context, arm, **kwargs))
        return made[-1]

    yield make
    for h in made:
        h.close()


@pytest.mark.parametrize("threads", [1, 4], ids=["single_threaded", "multi_threaded"])
def test_a_goal_runs_the_raster_with_feedback_and_a_result(harness, spin_until, threads):
    h = harness(CountingArm(), threads=threads)
    area = [0.4, -0.05, 0.02, 0.1]   # 2 passes of the 0.06 m usable width with 25 % overlap
    handle = h.send(spin_until, area=area, speed=0.02)
    assert handle.accepted
    response = h.result(spin_until, handle)
    assert response.status == GoalStatus.STATUS_SUCCEEDED
    result = response.result
    assert result.outcome == Outcome.SUCCEEDED and result.message == "sweep complete"
    assert (result.passes_done, result.pass_count) == (2, 2)
    assert result.distance == pytest.approx(0.04)
    assert spin_until(h.executor, lambda: bool(h.feedback) and h.feedback[-1].phase == "done", timeout=10.0)
    assert {f.pass_index for f in h.feedback} >= {1, 2} and all(f.pass_count == 2 for f in h.feedback)
    distances = [f.distance for f in h.feedback]
    assert distances == sorted(distances) and distances[-1] == pytest.approx(0.04)
    assert h.feedback[-1].coverage == pytest.approx(1.0)
    assert h.node.plan is not None and len(h.node.plan.rolls) == 2   # the goal's area, not sweep.area
    assert h.node.settings["sweep.area"] == [0.0, 0.0, 0.0, 0.0]    # the parameters are left as they were


@pytest.mark.parametrize("threads", [1, 4], ids=["single_threaded", "multi_threaded"])
def test_cancel_mid_sweep_stops_the_arm_as_stop_does(harness, spin_until, threads):
    h = harness(SlowRollArm(), threads=threads)
    handle = h.send(spin_until)
    assert handle.accepted
    assert spin_until(h.executor, lambda: h.node.status.phase is SweepPhase.SWEEPING, timeout=20.0)
    assert h.arm.is_moving()
    cancel = handle.cancel_goal_async()
    assert spin_until(h.executor, cancel.done, timeout=20.0)
    assert len(cancel.result().goals_canceling) == 1
    response = h.result(spin_until, handle)
    assert response.status == GoalStatus.STATUS_CANCELED
    assert response.result.outcome == Outcome.CANCELLED and response.result.passes_done == 0
    assert 0.0 < response.result.distance < 0.02
    # the checks of the Trigger stop test: the sweep ended STOPPED and the arm stands still
    assert h.node.finished.is_set() and h.node.status.phase is SweepPhase.STOPPED
    assert not h.arm.is_moving()
    halted = h.arm.tcp_pose()
    time.sleep(0.2)
    np.testing.assert_allclose(h.arm.tcp_pose(), halted, rtol=0, atol=1e-9)


@pytest.mark.parametrize("fields, reason", [
    ({"speed": 0.5}, "speed"),                                       # beyond arm.max_speed (0.1 m/s)
    ({"area": [0.4, 0.0, -0.02, 0.05]}, "length and width >= 0"),    # a negative area
    ({"area": [0.4, 0.0, 0.02]}, "takes 4 numbers"),                 # not an area
    ({"area": [900.0, 0.0, 0.02, 0.05]}, "reach"),                   # out of the arm's reach
])
def test_an_invalid_goal_is_rejected_and_the_arm_never_moves(harness, spin_until, fields, reason):
    h = harness(CountingArm())
    before = h.arm.tcp_pose()
    handle = h.send(spin_until, **fields)
    assert not handle.accepted
    assert reason in (h.node._action.last_rejection or "")
    spin_until(h.executor, lambda: False, timeout=0.3)
    assert h.arm.moves == 0 and not h.arm.is_moving() and not h.node.active
    np.testing.assert_allclose(h.arm.tcp_pose(), before, rtol=0, atol=0)
    assert h.call_start(spin_until).success   # the node is unharmed: a start runs


def test_an_accepted_goal_whose_start_outlasts_the_wait_is_aborted_and_never_moves_the_arm(harness, spin_until,
                                                                                           monkeypatch):
    """#29.1 for goals: the goal passed its checks; its start's planning then outlasts the wait, the start is
    abandoned, the goal aborted, and the arm never moves for it, then or later."""
    from touchroller_bringup.nodes import sweep_node

    original, calls = sweep_node.plan_sweep, []

    def slow_on_the_second_call(*args, **kwargs):
        calls.append(1)
        if len(calls) == 2:   # the first plans the acceptance's dry run, the second the start
            time.sleep(1.5)
        return original(*args, **kwargs)

    monkeypatch.setattr(sweep_node, "plan_sweep", slow_on_the_second_call)
    monkeypatch.setattr(sweep_node, "COMMAND_TIMEOUT_S", 0.3)
    h = harness(CountingArm())
    assert spin_until(h.executor, lambda: h.node.status.phase is SweepPhase.IDLE, timeout=20.0)
    calls.clear()   # the node's start-up check planned once
    rest = h.arm.tcp_pose()
    handle = h.send(spin_until)
    assert handle.accepted
    response = h.result(spin_until, handle)
    assert len(calls) == 2
    assert response.status == GoalStatus.STATUS_ABORTED
    assert response.result.outcome == Outcome.FAULT and "the arm does not move for it" in response.result.message
    spin_until(h.executor, lambda: False, timeout=2.5)   # the planning is long done; the arm thread looped on
    assert h.arm.moves == 0 and not h.arm.is_moving() and not h.node.active
    np.testing.assert_allclose(h.arm.tcp_pose(), rest, rtol=0, atol=0)


def test_one_sweep_at_a_time(harness, spin_until):
    h = harness(SlowRollArm())
    first = h.send(spin_until)
    assert first.accepted
    assert spin_until(h.executor, lambda: h.node.status.phase is SweepPhase.SWEEPING, timeout=20.0)
    second = h.send(spin_until, speed=0.01)
    assert not second.accepted and "goal is running" in h.node._action.last_rejection
    response = h.call_start(spin_until)
    assert not response.success and "goal is running" in response.message
    assert h.arm.is_moving() and h.node.plan is not None   # the first goal's sweep goes on
    cancel = first.cancel_goal_async()
    assert spin_until(h.executor, cancel.done, timeout=20.0)
    assert h.result(spin_until, first).status == GoalStatus.STATUS_CANCELED


def test_a_start_sweep_rejects_goals(harness, spin_until):
    h = harness(SlowRollArm())
    assert h.call_start(spin_until).success
    handle = h.send(spin_until)
    assert not handle.accepted and "already running" in h.node._action.last_rejection


def test_a_fault_aborts_the_goal_with_its_message(harness, spin_until):
    h = harness(SlowRollArm())
    handle = h.send(spin_until)
    assert handle.accepted
    assert spin_until(h.executor, lambda: h.node.status.phase is SweepPhase.SWEEPING, timeout=20.0)
    h.arm.inject_fault("protective stop")
    response = h.result(spin_until, handle)
    assert response.status == GoalStatus.STATUS_ABORTED
    assert response.result.outcome == Outcome.FAULT and "protective stop" in response.result.message
    assert not h.arm.is_moving()
    assert not h.send(spin_until).accepted and "protective stop" in h.node._action.last_rejection


def test_a_failure_of_the_action_on_the_arm_thread_stops_the_arm_and_aborts_the_goal(harness, spin_until,
                                                                                     monkeypatch):
    from touchroller_bringup import sweep_action

    h = harness(SlowRollArm())
    handle = h.send(spin_until)
    assert handle.accepted
    assert spin_until(h.executor, lambda: h.node.status.phase is SweepPhase.SWEEPING, timeout=20.0)

    def broken(self, goal, feedback):
        raise RuntimeError("feedback publisher gone")

    monkeypatch.setattr(sweep_action.SweepActionServer, "_publish_feedback", broken)
    response = h.result(spin_until, handle)
    assert response.status == GoalStatus.STATUS_ABORTED
    assert response.result.outcome == Outcome.STOPPED and "feedback publisher gone" in response.result.message
    assert spin_until(h.executor, h.node.finished.is_set, timeout=20.0)
    assert h.node.status.phase is SweepPhase.STOPPED and not h.arm.is_moving()
    assert h.node._worker.is_alive()   # the arm thread goes on watching the arm


CLIENT = r'''
import sys, time, rclpy
from rclpy.action import ActionClient
from rclpy.node import Node
from touchroller_interfaces.action import Sweep
rclpy.init()
node = Node("doomed_client")
client = ActionClient(node, Sweep, sys.argv[1])
assert client.wait_for_server(timeout_sec=30.0)
while True:   # a request sent before the server has discovered this client is lost (volatile): send again
    future = client.send_goal_async(Sweep.Goal())
    rclpy.spin_until_future_complete(node, future, timeout_sec=5.0)
    if future.done():
        break
print("accepted" if future.result().accepted else "rejected", flush=True)
while True:
    rclpy.spin_once(node, timeout_sec=0.1)
'''


SHORT_LEASE = """<?xml version="1.0" encoding="UTF-8" ?>
<dds xmlns="http://www.eprosima.com"><profiles>
  <participant profile_name="short_lease" is_default_profile="true"><rtps><builtin><discovery_config>
    <leaseDuration><sec>5</sec></leaseDuration>
    <leaseAnnouncement><sec>1</sec></leaseAnnouncement>
  </discovery_config></builtin></rtps></participant>
</profiles></dds>
"""


@pytest.mark.timeout(180)
def test_a_client_killed_mid_goal_stops_the_arm(harness, spin_until, tmp_path):
    """The goal's client is the only action client of the action (see sweep_action: a second one, still
    alive, would keep the goal going until it is cancelled or ~/stop). DDS forgets a killed process when its
    participant's lease runs out (Fast DDS: 20 s by default); the client here announces a 5 s lease, so the
    test takes seconds, not the default's 20 (a shorter one could run out on a loaded machine while the client
    lives: then too the arm stops, as it should when the client cannot be seen)."""
    h = harness(SlowRollArm(), client=False)
    profile = tmp_path / "short_lease.xml"
    profile.write_text(SHORT_LEASE)
    env = dict(os.environ, FASTDDS_DEFAULT_PROFILES_FILE=str(profile), FASTRTPS_DEFAULT_PROFILES_FILE=str(profile))
    client = subprocess.Popen([sys.executable, "-c", CLIENT, ACTION], stdout=subprocess.PIPE,
                              stderr=subprocess.STDOUT, text=True, env=env)
    try:
        lines: list[str] = []
        reader = threading.Thread(target=lambda: lines.extend(client.stdout), daemon=True)
        reader.start()
        # the goal as the server sees it (its answer may be lost on the way back, as its request may be)
        assert spin_until(h.executor, lambda: h.node.status.phase is SweepPhase.SWEEPING, timeout=90.0), \
            (h.node.status, lines)
        assert h.node._action.running
        client.kill()   # SIGKILL: no cancel, no goodbye; the graph forgets it when DDS's lease runs out
        client.wait(timeout=10)
        # the roll alone lasts 50 s here: ending within 60 s STOPPED, for the client, is the client check's doing
        assert spin_until(h.executor, h.node.finished.is_set, timeout=60.0), "the arm went on without its client"
        assert h.node.status.phase is SweepPhase.STOPPED and "client left" in h.node.status.message
        assert not h.arm.is_moving()
    finally:
        if client.poll() is None:
            client.kill()
            client.wait(timeout=10)


# namespaces no other test uses: a node of an earlier test on a reused ROS domain can linger in the ROS graph
def test_the_action_moves_with_the_namespace(ros_context):
    node = SweepNode(arm=CountingArm(), context=ros_context, namespace="action_left",
                     parameter_overrides=list(OVERRIDES))
    try:
        offered = dict(rclpy.action.get_action_server_names_and_types_by_node(node, node.get_name(), "/action_left"))
        assert offered.get("/action_left/sweep") == ["touchroller_interfaces/action/Sweep"]
        assert node._action is not None and node._action._feedback_topic == "/action_left/sweep/_action/feedback"
    finally:
        node.destroy_node()


def test_without_the_interface_the_node_runs_without_the_action(ros_context, spin_until, monkeypatch):
    monkeypatch.setitem(sys.modules, "touchroller_interfaces.action", None)   # its import fails
    arm = CountingArm()
    node = SweepNode(arm=arm, context=ros_context, namespace="action_missing", parameter_overrides=list(OVERRIDES))
    try:
        assert node._action is None
        assert rclpy.action.get_action_server_names_and_types_by_node(node, node.get_name(),
                                                                      node.get_namespace()) == []
        assert node.request_start()[0]
        assert spin_until(node, node.finished.is_set, timeout=20.0)
        assert node.status.phase is SweepPhase.DONE
    finally:
        node.destroy_node()
