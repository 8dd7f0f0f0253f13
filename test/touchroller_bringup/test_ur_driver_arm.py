"""URDriverArm against a fake ur_robot_driver (fake_ur_driver.py beside this file): raster, faults, stop, reset.

A real ur_robot_driver is not installable here; the fake mimics its topics, QoS and habits (see its
docstring), so these tests show the back end's logic over the real ROS transport, not a real robot.
"""
from __future__ import annotations

import importlib.util
import math
import time
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

pytest.importorskip("rclpy")
pytest.importorskip("ur_dashboard_msgs.msg")
from std_msgs.msg import Bool  # noqa: E402

from touchroller_bringup.errors import UserError  # noqa: E402
from touchroller_bringup.ur_driver_arm import (  # noqa: E402
    UR_DRIVER_PARAMETERS,
    URDriverArm,
    URDriverConfig,
    make_ur_driver_arm,
    movel_program,
    path_program,
    stopl_program,
)
from touchroller_driver.arm import (  # noqa: E402
    DEFAULT_MOUNT_RPY,
    DEFAULT_MOUNT_XYZ,
    DEFAULT_START_POSE,
    Arm,
    ArmError,
    ArmLimitError,
    SweepPhase,
    SweepSequencer,
    mount_transform,
    plan_raster,
)

_spec = importlib.util.spec_from_file_location("fake_ur_driver", Path(__file__).with_name("fake_ur_driver.py"))
assert _spec is not None and _spec.loader is not None
fake_ur_driver = importlib.util.module_from_spec(_spec)
_spec.loader.exec_module(fake_ur_driver)
FakeURDriver = fake_ur_driver.FakeURDriver
parse_program = fake_ur_driver.parse_program

REST = np.array(DEFAULT_START_POSE) + np.array([0.0, 0.0, 0.005, 0.0, 0.0, 0.0])
# generous for a loaded machine: the behaviour is tested, not the timing
CONFIG = URDriverConfig(driver_timeout=1.0, connect_timeout=10.0, start_timeout=3.0, stall_timeout=3.0)


def wait_for(predicate, timeout: float = 15.0) -> bool:
    deadline = time.monotonic() + timeout
    while not predicate():
        if time.monotonic() > deadline:
            return bool(predicate())
        time.sleep(0.01)
    return True


@pytest.fixture
def driver(ros_context):
    fake = FakeURDriver(ros_context, REST)
    yield fake
    fake.close()


@pytest.fixture
def arm(ros_context, driver):
    arm = URDriverArm(CONFIG, context=ros_context)
    arm.connect()
    yield arm
    arm.disconnect()


def run(sequencer: SweepSequencer, timeout: float = 60.0) -> None:
    deadline = time.monotonic() + timeout
    while sequencer.active and time.monotonic() < deadline:
        sequencer.poll()
        time.sleep(0.02)


def small_raster(profile: str = "ramp"):
    return plan_raster(DEFAULT_START_POSE, area=[0.4, 0.0, 0.02, 0.1], mount=mount_transform(DEFAULT_MOUNT_XYZ,
                       DEFAULT_MOUNT_RPY), speed=0.05, accel=0.5, depth=0.0005, approach_speed=0.05,
                       clearance=0.002, profile=profile)


# -- the programs ------------------------------------------------------------------------------

finite = st.floats(min_value=-10.0, max_value=10.0, allow_nan=False, allow_infinity=False)


@given(st.lists(finite, min_size=6, max_size=6), st.floats(1e-6, 1.0), st.floats(1e-6, 5.0))
def test_movel_program_carries_the_exact_pose_speed_and_acceleration(pose, speed, accel):
    kind, values = parse_program(movel_program(pose, speed, accel))
    assert kind == "movel"
    assert values == (*[float(v) for v in pose], accel, speed)   # URScript's order: a=, then v=


def test_stopl_program_and_bad_values_never_become_script():
    assert parse_program(stopl_program(0.5)) == ("stopl", (0.5,))
    with pytest.raises(ArmLimitError):
        movel_program([0.4, 0.0, math.nan, math.pi, 0.0, 0.0], 0.01, 0.1)
    with pytest.raises(ArmError):
        movel_program([0.4, 0.0, 0.2, math.pi, 0.0, 0.0], math.inf, 0.1)
    with pytest.raises(ArmError):
        stopl_program(0.0)


def test_config_refuses_bad_values_in_one_line():
    for bad in ({"driver_timeout": math.nan}, {"reset_timeout": 0.0}, {"connect_timeout": -1.0}, {"script_topic": ""},
                {"tool_frame": "base"}, {"still_tolerance": 1.0}, {"base_frame": "my base"},
                {"stall_timeout": True}, {"safety_mode_topic": "/io//safety"}, {"script_topic": "1abc"},
                {"unlock_service": "no spaces"}):
        with pytest.raises(ValueError) as excinfo:
            URDriverConfig(**bad)
        assert "\n" not in str(excinfo.value) and "ur_driver." in str(excinfo.value)


def test_parameter_table_declares_every_field_and_the_factory_reads_it(ros_context):
    import rclpy
    from rclpy.parameter import Parameter

    from touchroller_driver.arm import ArmLimits

    node = rclpy.create_node("factory", context=ros_context, parameter_overrides=[
        Parameter("ur_driver.tool_frame", value="flange"), Parameter("ur_driver.driver_timeout", value=0.25)])
    try:
        arm = make_ur_driver_arm(node, ArmLimits(max_speed=0.05))
        assert isinstance(arm, Arm)
        assert arm.config.tool_frame == "flange" and arm.config.driver_timeout == 0.25
        assert arm.limits.max_speed == 0.05
        for name in UR_DRIVER_PARAMETERS:
            descriptor = node.describe_parameter(name)
            assert descriptor.description and descriptor.read_only
    finally:
        node.destroy_node()
    node = rclpy.create_node("factory_bad", context=ros_context, parameter_overrides=[
        Parameter("ur_driver.base_frame", value="tool0")])
    try:
        # refused as the node's other bindings refuse: one line naming the node and the parameters
        with pytest.raises(UserError, match="^factory_bad: ur_driver.base_frame and ur_driver.tool_frame are both "
                                            "'tool0'$"):
            make_ur_driver_arm(node, ArmLimits())
    finally:
        node.destroy_node()


# -- against the fake driver -------------------------------------------------------------------

def test_a_raster_through_the_driver_ends_where_planned(ros_context):
    fake = FakeURDriver(ros_context, REST, chain=True)   # base -> tool0 through base_link, as the real tree
    arm = URDriverArm(CONFIG, context=ros_context)
    try:
        arm.connect()
        assert np.allclose(arm.tcp_pose(), REST, atol=1e-9)
        assert arm.program_running is True   # the driver's External Control program held the robot
        plan = small_raster()
        assert len(plan.passes) == 2
        sequencer = SweepSequencer(arm)
        sequencer.start(plan)
        run(sequencer)
        assert sequencer.status.phase is SweepPhase.DONE, sequencer.status
        assert sequencer.status.roll_progress == 1.0
        final = plan.segments[-1].target
        assert np.allclose(fake.pose(), final, atol=1e-9)
        assert np.allclose(arm.tcp_pose()[:3], final[:3], atol=CONFIG.arrive_tolerance)
        moves = fake.moves()
        assert len(moves) == len(plan.segments)   # one movel per segment, each the planned one
        for (x, y, z, rx, ry, rz, a, v), segment in zip(moves, plan.segments, strict=True):
            assert (x, y, z, rx, ry, rz) == tuple(segment.target) and (a, v) == (segment.accel, segment.speed)
        assert arm.program_running is False   # our programs replaced it, as they do on a real robot
        assert arm.fault() is None
    finally:
        arm.disconnect()
        fake.close()


def test_a_protective_stop_mid_pass_is_a_fault_and_the_sequence_stops(driver, arm):
    sequencer = SweepSequencer(arm)
    plan = small_raster()
    sequencer.start(plan)
    assert wait_for(lambda: sequencer.poll().phase is SweepPhase.SWEEPING and arm.progress() > 0.1)
    driver.inject_protective_stop()
    run(sequencer)
    assert sequencer.status.phase is SweepPhase.FAULT
    assert "protective stop" in sequencer.status.message
    sent = len(driver.programs)
    halted = driver.pose()
    time.sleep(0.3)
    assert len(driver.programs) == sent   # nothing more is sent
    assert np.array_equal(driver.pose(), halted)
    assert len(driver.moves()) < len(plan.segments)
    with pytest.raises(ArmError, match="protective stop"):
        arm.move_linear(plan.segments[-1].target, 0.01, 0.1)
    assert len(driver.programs) == sent


def test_a_silent_driver_is_a_fault_within_the_timeout(ros_context, driver):
    arm = URDriverArm(URDriverConfig(driver_timeout=0.3, connect_timeout=10.0), context=ros_context)
    try:
        arm.connect()
        assert arm.fault() is None
        driver.go_silent()
        assert wait_for(lambda: arm.fault() is not None)
        assert "lost the UR driver" in arm.fault()
        with pytest.raises(ArmError, match="lost the UR driver"):
            arm.move_linear(REST, 0.01, 0.1)
        assert driver.programs == []
        driver.silent = False   # the driver is back: the fault stays until reset, which then clears it
        time.sleep(0.1)
        assert "lost the UR driver" in arm.fault()
        arm.reset_fault()
        assert arm.fault() is None
    finally:
        arm.disconnect()


def test_no_driver_fails_connect_in_one_line(ros_context):
    arm = URDriverArm(URDriverConfig(connect_timeout=0.3), context=ros_context)
    try:
        with pytest.raises(ArmError) as excinfo:
            arm.connect()
        assert "no UR driver" in str(excinfo.value) and "\n" not in str(excinfo.value)
        assert arm.fault() == str(excinfo.value)
    finally:
        arm.disconnect()


def test_abort_gives_up_a_connect_at_once_and_refuses_moves_until_reset(ros_context, driver):
    """The sweep node's shutdown calls abort() from another thread: a wait under way gives up at once."""
    import threading

    from touchroller_driver.arm import Arm

    arm = URDriverArm(URDriverConfig(connect_timeout=30.0), context=ros_context)
    assert isinstance(arm, Arm)
    driver.go_silent()
    errors: list[str] = []

    def connect() -> None:
        try:
            arm.connect()
        except ArmError as exc:
            errors.append(str(exc))

    try:
        worker = threading.Thread(target=connect)
        started = time.monotonic()
        worker.start()
        time.sleep(0.3)
        arm.abort()
        worker.join(5.0)
        assert not worker.is_alive() and time.monotonic() - started < 5.0
        assert errors and "given up" in errors[0]
        with pytest.raises(ArmError, match="given up"):
            arm.move_linear(REST, 0.01, 0.1)
        assert driver.programs == []
        driver.silent = False
        arm.reset_fault()
        assert arm.fault() is None
    finally:
        arm.disconnect()


def test_stop_mid_move_halts_and_stop_when_idle_sends_nothing(driver, arm):
    arm.stop()   # idle: the driver's External Control program is not ours to stop
    assert driver.programs == [] and not arm.sent
    target = REST + np.array([0.05, 0.0, 0.0, 0.0, 0.0, 0.0])
    arm.move_linear(target, 0.01, 0.1)
    assert wait_for(lambda: arm.progress() > 0.05)
    assert arm.is_moving()
    arm.stop()
    assert not arm.is_moving()
    assert wait_for(lambda: driver.executed and driver.executed[-1][0] == "stopl")
    halted = driver.pose()
    time.sleep(0.3)
    assert np.array_equal(driver.pose(), halted)
    assert np.linalg.norm(halted[:3] - target[:3]) > 0.01
    assert 0.0 < arm.progress() < 1.0
    assert arm.fault() is None   # a stop on request is no fault
    arm.stop()   # again: nothing of ours moves any more
    assert sum(p.count("stopl") for p in arm.sent) == 1


def test_reset_refuses_while_the_protective_stop_persists_then_clears_it(driver, arm):
    driver.inject_protective_stop()
    assert wait_for(lambda: arm.fault() is not None)
    with pytest.raises(ArmError, match="persists") as excinfo:
        arm.reset_fault()
    assert "\n" not in str(excinfo.value)
    assert arm.fault() is not None
    driver.unlockable = True   # the cause is gone; the controller allows the unlock now
    arm.reset_fault()
    assert arm.fault() is None
    target = REST + np.array([0.0, 0.0, 0.002, 0.0, 0.0, 0.0])
    arm.move_linear(target, 0.01, 0.1)
    assert wait_for(lambda: not arm.is_moving() or arm.fault() is not None)
    assert arm.fault() is None
    assert np.allclose(driver.pose(), target, atol=1e-9)


def test_reset_after_the_stop_was_cleared_on_the_pendant_and_refusal_for_an_emergency_stop(driver, arm):
    driver.inject_emergency_stop()
    assert wait_for(lambda: arm.fault() is not None)
    assert "emergency stop" in arm.fault()
    with pytest.raises(ArmError, match="teach pendant"):
        arm.reset_fault()
    driver.clear_on_pendant()
    assert wait_for(lambda: arm._safety_mode == 1)   # noqa: SLF001 - the driver's news has arrived
    arm.reset_fault()
    assert arm.fault() is None


def test_a_driver_whose_external_control_program_never_ran_is_usable(ros_context):
    fake = FakeURDriver(ros_context, REST, program_running=False)   # publishes nothing on robot_program_running
    arm = URDriverArm(CONFIG, context=ros_context)
    try:
        arm.connect()
        assert arm.program_running is None
        target = REST + np.array([0.0, 0.002, 0.0, 0.0, 0.0, 0.0])
        arm.move_linear(target, 0.01, 0.1, asynchronous=False)
        assert np.allclose(fake.pose(), target, atol=1e-9) and arm.fault() is None
        fake.start_external_control()   # between moves: not ours to judge
        assert wait_for(lambda: arm.program_running is True)
        assert arm.fault() is None
    finally:
        arm.disconnect()
        fake.close()


def test_a_movel_the_robot_does_not_run_is_a_fault(ros_context):
    fake = FakeURDriver(ros_context, REST, execute=False)   # not in remote control: programs are not run
    arm = URDriverArm(URDriverConfig(start_timeout=0.3, connect_timeout=10.0, driver_timeout=1.0),
                      context=ros_context)
    try:
        arm.connect()
        arm.move_linear(REST + np.array([0.01, 0, 0, 0, 0, 0]), 0.01, 0.1)
        assert wait_for(lambda: arm.fault() is not None)
        assert "did not start the movel" in arm.fault()
    finally:
        arm.disconnect()
        fake.close()


def test_the_latched_program_state_delivered_after_a_move_was_sent_is_not_a_start(ros_context):
    """Discovery can deliver the driver's latched robot_program_running after our first movel is sent: a
    state published before the move is not the program starting during it (the stamp tells them apart)."""
    fake = FakeURDriver(ros_context, REST, program_running=False, execute=False)   # nothing latched yet
    arm = URDriverArm(URDriverConfig(start_timeout=30.0, connect_timeout=10.0, driver_timeout=1.0),
                      context=ros_context)
    try:
        arm.connect()
        arm.move_linear(REST + np.array([0.01, 0, 0, 0, 0, 0]), 0.01, 0.1)
        sent_ns = arm._move.sent_ns   # noqa: SLF001 - the stamp the callback compares with
        arm._on_program_running(Bool(data=True), {"source_timestamp": sent_ns - 10**8})   # noqa: SLF001
        assert arm.fault() is None and arm.program_running is True
        arm._on_program_running(Bool(data=False), {"source_timestamp": sent_ns + 10**6})   # noqa: SLF001
        arm._on_program_running(Bool(data=True), {"source_timestamp": sent_ns + 2 * 10**6})   # noqa: SLF001
        assert "started during the move" in (arm.fault() or "")
    finally:
        arm.disconnect()
        fake.close()


def test_a_first_program_start_published_after_the_move_was_sent_is_a_fault(ros_context):
    fake = FakeURDriver(ros_context, REST, program_running=False, execute=False)
    arm = URDriverArm(URDriverConfig(start_timeout=30.0, connect_timeout=10.0, driver_timeout=1.0),
                      context=ros_context)
    try:
        arm.connect()
        arm.move_linear(REST + np.array([0.01, 0, 0, 0, 0, 0]), 0.01, 0.1)
        arm._on_program_running(Bool(data=True), {"source_timestamp": time.time_ns()})   # noqa: SLF001
        assert "started during the move" in (arm.fault() or "")
    finally:
        arm.disconnect()
        fake.close()


def test_external_control_taking_the_robot_back_mid_move_is_a_fault(driver, arm):
    arm.move_linear(REST + np.array([0.05, 0.0, 0.0, 0.0, 0.0, 0.0]), 0.01, 0.1)
    assert wait_for(lambda: arm.progress() > 0.02)
    driver.start_external_control()
    assert wait_for(lambda: arm.fault() is not None)
    assert "External Control program started" in arm.fault()


def test_a_nan_pose_is_refused_before_anything_is_published(driver, arm):
    for bad in ([0.4, 0.0, math.nan, math.pi, 0.0, 0.0], [0.4, 0.0, 0.2, math.pi, math.inf, 0.0], [0.4, 0.0]):
        with pytest.raises(ArmLimitError):
            arm.move_linear(bad, 0.01, 0.1)
    with pytest.raises(ArmLimitError):
        arm.move_linear(REST, 5.0, 0.1)   # over arm.max_speed
    with pytest.raises(ArmLimitError):
        arm.move_linear(REST, math.nan, 0.1)
    assert not arm.sent
    time.sleep(0.2)
    assert driver.programs == []
    assert arm.fault() is None


def test_the_sweep_node_as_it_is_runs_a_sweep_and_latches_a_fault_through_the_driver_arm(ros_context, driver):
    """The sweep node takes any Arm (`arm=`): its services drive URDriverArm as they drive the others."""
    from rclpy.parameter import Parameter

    from touchroller_bringup.nodes.sweep_node import SweepNode

    arm = URDriverArm(CONFIG, context=ros_context)
    node = SweepNode(arm=arm, context=ros_context, parameter_overrides=[
        Parameter("publish_tf", value=False), Parameter("sweep.length", value=0.01),
        Parameter("sweep.speed", value=0.05), Parameter("sweep.approach_speed", value=0.05),
        Parameter("sweep.start_pose", value=list(DEFAULT_START_POSE))])
    try:
        assert wait_for(lambda: node.status.phase is SweepPhase.IDLE), node.status
        assert node.request_start()[0]
        assert node.finished.wait(30.0)
        assert node.status.phase is SweepPhase.DONE, node.status
        end = np.array(DEFAULT_START_POSE) + np.array([0.01, 0.0, 0.002, 0.0, 0.0, 0.0])   # rolled, lifted
        assert np.allclose(driver.pose(), end, atol=1e-9)
        assert node.request_stop()[0]
        assert not any("stopl" in p for p in driver.programs)   # idle: nothing of ours to stop
        driver.inject_protective_stop()
        assert wait_for(lambda: node.status.phase is SweepPhase.FAULT)
        ok, message = node.request_start()
        assert not ok and "reset_fault" in message
        ok, message = node.request_reset_fault()
        assert not ok and "persists" in message
        driver.unlockable = True
        ok, message = node.request_reset_fault()
        assert ok, message
        assert node.status.phase is SweepPhase.IDLE
    finally:
        node.destroy_node()


def test_the_sweep_node_builds_the_driver_arm_from_arm_backend(ros_context, driver):
    """`arm.backend: ur_driver` (the sweep node's wiring): the node makes a URDriverArm with the ur_driver.*
    parameters, leaves base -> tool0 to the driver and runs a sweep through it."""
    from rclpy.parameter import Parameter

    from touchroller_bringup.nodes.sweep_node import SweepNode

    node = SweepNode(context=ros_context, parameter_overrides=[
        Parameter("use_sim", value=False), Parameter("arm.backend", value="ur_driver"),
        Parameter("ur_driver.driver_timeout", value=CONFIG.driver_timeout),
        Parameter("sweep.length", value=0.01), Parameter("sweep.speed", value=0.05),
        Parameter("sweep.approach_speed", value=0.05), Parameter("sweep.start_pose", value=list(DEFAULT_START_POSE))])
    try:
        assert isinstance(node.arm, URDriverArm)
        assert node.arm.config.driver_timeout == CONFIG.driver_timeout
        assert not node._publish_tf   # noqa: SLF001 - the driver publishes base -> tool0
        assert wait_for(lambda: node.status.phase is SweepPhase.IDLE), node.status
        assert node.request_start()[0]
        assert node.finished.wait(30.0)
        assert node.status.phase is SweepPhase.DONE, node.status
    finally:
        node.destroy_node()


@given(st.lists(finite, min_size=3, max_size=3), st.lists(st.floats(-1.0, 1.0), min_size=3, max_size=3),
       st.floats(0.0, math.pi - 1e-6))
def test_the_pose_read_from_tf_is_the_ur_rotation_vector(translation, axis, angle):
    from touchroller_bringup.ur_driver_arm import _rotation_vector
    from touchroller_perception.transforms import Transform

    axis_array = np.asarray(axis)
    if np.linalg.norm(axis_array) < 1e-3:
        axis_array = np.array([1.0, 0.0, 0.0])
    rotation = axis_array / np.linalg.norm(axis_array) * angle
    read = _rotation_vector(Transform.from_rotation_vector(translation, rotation))
    assert np.allclose(read, rotation, atol=1e-6)


# -- sweep.profile blend/constant: a pass as one program of blended movels ------------------------------

def test_a_path_program_is_one_movel_a_waypoint_with_its_blend_radius():
    plan = small_raster("blend")
    move = plan.motion()[0][1]
    kind, values = parse_program(path_program(move.waypoints, move.speed, move.accel, move.blend))
    rows = np.array(values).reshape(-1, 9)
    assert kind == "path" and rows.shape == (4, 9)
    np.testing.assert_array_equal(rows[:, :6], move.waypoints)
    assert (rows[:, 6:8] == [move.accel, move.speed]).all()
    assert rows[0, 8] == rows[-1, 8] == 0.0 and rows[1, 8] == rows[2, 8] == move.blend > 0
    with pytest.raises(ArmError):
        path_program(move.waypoints, move.speed, move.accel, math.nan)


def trace_sweep(arm, fake, plan, until=lambda status: False, timeout: float = 60.0):
    """Run the plan through the driver arm, sampling the robot's pose (its clock is the monotonic one)."""
    sequencer = SweepSequencer(arm)
    sequencer.start(plan)
    rows = []
    deadline = time.monotonic() + timeout
    while sequencer.active and time.monotonic() < deadline:
        status = sequencer.poll()
        t = time.monotonic()
        rows.append((t, *fake.pose()[:3]))
        if until(status):
            break
        time.sleep(0.005)
    return sequencer, np.array(rows)


@pytest.mark.parametrize("profile", ["ramp", "blend"])
def test_a_blended_raster_through_the_driver_touches_down_at_speed(ros_context, driver, arm, profile):
    plan = small_raster(profile)
    sequencer, trace = trace_sweep(arm, driver, plan)
    assert sequencer.status.phase is SweepPhase.DONE, sequencer.status
    pressed_z = plan.segments[plan.rolls[0]].target[2]
    speed = np.hypot(*np.diff(trace[:, 1:3], axis=0).T) / np.diff(trace[:, 0])
    pressed = np.abs(trace[:-1, 3] - pressed_z) < 1e-5
    edges = np.flatnonzero(np.diff(pressed.astype(int)))
    assert len(edges) == 4   # both passes touch down and lift off once
    kinds = [kind for kind, _ in driver.executed]
    if profile == "ramp":
        assert speed[edges].max() < 0.2 * 0.05 and set(kinds) == {"movel"}   # stop-and-go, as before
    else:
        assert speed[edges].min() > 0.8 * 0.05   # at the roll speed when touching down and lifting off
        assert kinds == ["movel", "path"] * 2
    assert np.allclose(driver.pose(), plan.motion()[0][-1].target, atol=1e-9)
    assert arm.fault() is None


def test_stop_mid_path_halts_the_robot_and_a_path_out_of_limits_publishes_nothing(driver, arm):
    plan = small_raster("blend")
    sequencer, _ = trace_sweep(arm, driver, plan, until=lambda status: status.segment == "pass"
                               and arm.progress() > 0.3)
    assert sequencer.status.segment == "pass" and arm.is_moving()
    sequencer.stop()
    assert not arm.is_moving()
    assert wait_for(lambda: driver.executed and driver.executed[-1][0] == "stopl")
    halted = driver.pose()
    time.sleep(0.3)
    assert np.array_equal(driver.pose(), halted)
    assert 0.0 < arm.progress() < 1.0 and arm.fault() is None
    sent = len(driver.programs)
    here = arm.tcp_pose()
    ahead = np.array([here, here + [0.01, 0, 0, 0, 0, 0], here + [0.02, 0, 0, 0, 0, 0]])
    from touchroller_driver.arm import ArmLimits

    arm.limits = ArmLimits(workspace_max=(float(here[0]) + 0.015, 1.0, 1.0))
    with pytest.raises(ArmLimitError, match="path waypoint 3 of 3"):
        arm.move_path(ahead, 0.01, 0.1, 0.002)
    arm.limits = ArmLimits()
    with pytest.raises(ArmError, match="first waypoint"):
        arm.move_path(ahead[1:], 0.01, 0.1, 0.002)
    time.sleep(0.2)
    assert len(driver.programs) == sent and np.array_equal(driver.pose(), halted)
