"""The arm interface, its limits, and the simulated arm's kinematics (with an injected clock)."""
from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from touchroller_driver.arm import (
    Arm,
    ArmError,
    ArmLimitError,
    ArmLimits,
    SimulatedArm,
    SweepPhase,
    SweepSequencer,
    as_pose,
    plan_sweep,
)
from touchroller_driver.motion import TrapezoidProfile

START = (0.4, 0.0, 0.2, math.pi, 0.0, 0.0)


class FakeClock:
    def __init__(self, t: float = 100.0) -> None:
        self.t = t

    def __call__(self) -> float:
        return self.t


def make_arm(**kwargs) -> tuple[SimulatedArm, FakeClock]:
    clock = FakeClock()
    arm = SimulatedArm(START, clock=clock, **kwargs)
    arm.connect()
    return arm, clock


def test_simulated_arm_satisfies_the_protocol():
    arm, _ = make_arm()
    assert isinstance(arm, Arm)


@pytest.mark.parametrize(("speed", "accel"), [
    (0.2, 0.1),            # too fast
    (0.01, 5.0),           # accelerates too hard
    (0.0, 0.1),            # not moving at all
    (-0.01, 0.1),
    (float("nan"), 0.1),
    (0.01, float("inf")),
])
def test_limits_are_checked_before_any_motion(speed, accel):
    arm, clock = make_arm(limits=ArmLimits(max_speed=0.1, max_accel=0.5))
    target = np.array(START) + [0.05, 0, 0, 0, 0, 0]
    with pytest.raises(ArmLimitError):
        arm.move_linear(target, speed, accel)
    clock.t += 10.0
    assert not arm.is_moving()
    np.testing.assert_allclose(arm.tcp_pose(), START)


def test_non_finite_or_malformed_targets_are_refused():
    arm, _ = make_arm()
    with pytest.raises(ArmLimitError, match="non-finite"):
        arm.move_linear([0.4, float("nan"), 0.2, 0, 0, 0], 0.01, 0.1)
    with pytest.raises(ArmLimitError, match="6 values"):
        arm.move_linear([0.4, 0.0, 0.2], 0.01, 0.1)


def test_workspace_bounds_refuse_targets_outside():
    limits = ArmLimits(workspace_min=(0.2, -0.3, 0.1), workspace_max=(0.6, 0.3, 0.5))
    arm, _ = make_arm(limits=limits)
    with pytest.raises(ArmLimitError, match="below workspace"):
        arm.move_linear([0.4, 0.0, 0.05, math.pi, 0, 0], 0.01, 0.1)
    arm.move_linear([0.45, 0.0, 0.15, math.pi, 0, 0], 0.01, 0.1)  # inside: accepted


def test_invalid_limits_are_rejected():
    with pytest.raises(ValueError):
        ArmLimits(max_speed=0.0)
    with pytest.raises(ValueError):
        ArmLimits(max_accel=float("nan"))


def test_motion_requires_connection():
    arm = SimulatedArm(START, clock=FakeClock())
    with pytest.raises(ArmError, match="not connected"):
        arm.move_linear(np.array(START) + [0.01, 0, 0, 0, 0, 0], 0.01, 0.1)


def test_linear_move_follows_the_trapezoid_profile():
    arm, clock = make_arm()
    target = np.array(START) + [0.11, 0.0, 0.0, 0, 0, 0]
    arm.move_linear(target, 0.011, 0.1)
    profile = TrapezoidProfile(0.11, 0.011, 0.1)
    t0 = clock.t
    for dt in (0.05, 1.0, 5.0, profile.duration - 0.05):
        clock.t = t0 + dt
        assert arm.is_moving()
        pose = arm.tcp_pose()
        assert pose[0] == pytest.approx(START[0] + profile.position(dt), abs=1e-12)
        assert pose[1:] == pytest.approx(START[1:])
        assert arm.progress() == pytest.approx(profile.position(dt) / 0.11)
    clock.t = t0 + profile.duration + 1e-6
    assert not arm.is_moving()
    np.testing.assert_allclose(arm.tcp_pose(), target)
    assert arm.progress() == pytest.approx(1.0)


def test_stop_halts_where_the_arm_is_and_keeps_progress():
    arm, clock = make_arm()
    target = np.array(START) + [0.1, 0.0, 0.0, 0, 0, 0]
    arm.move_linear(target, 0.01, 0.1)
    clock.t += 5.0
    halted = arm.tcp_pose()
    arm.stop()
    clock.t += 20.0
    assert not arm.is_moving()
    np.testing.assert_allclose(arm.tcp_pose(), halted)
    assert 0.3 < arm.progress() < 0.6


def test_fault_stops_motion_and_refuses_commands_until_reconnect():
    arm, clock = make_arm()
    arm.move_linear(np.array(START) + [0.1, 0, 0, 0, 0, 0], 0.01, 0.1)
    clock.t += 2.0
    arm.inject_fault("protective stop")
    assert arm.fault() == "protective stop"
    assert not arm.is_moving()
    with pytest.raises(ArmError, match="protective stop"):
        arm.move_linear(START, 0.01, 0.1)
    arm.connect()
    assert arm.fault() is None
    arm.move_linear(START, 0.01, 0.1)


@settings(max_examples=60, deadline=None)
@given(
    distance=st.floats(-0.3, 0.3).filter(lambda d: abs(d) > 1e-6),
    speed=st.floats(1e-3, 0.1),
    accel=st.floats(1e-2, 0.5),
    fraction=st.floats(0.0, 1.2),
)
def test_pose_stays_on_the_segment_and_progress_is_monotonic(distance, speed, accel, fraction):
    arm, clock = make_arm()
    target = np.array(START) + [0.0, distance, 0.0, 0, 0, 0]
    arm.move_linear(target, speed, accel)
    duration = TrapezoidProfile(abs(distance), speed, accel).duration
    t0 = clock.t
    clock.t = t0 + fraction * duration
    first = arm.progress()
    pose = arm.tcp_pose()
    assert 0.0 <= first <= 1.0
    assert min(START[1], target[1]) - 1e-12 <= pose[1] <= max(START[1], target[1]) + 1e-12
    clock.t += 0.01 * duration
    assert arm.progress() >= first


def test_as_pose_returns_a_float_copy():
    pose = as_pose([1, 2, 3, 4, 5, 6])
    assert pose.dtype == np.float64 and pose.shape == (6,)


# -- the sweep plan and sequencer -------------------------------------------------------------------

def run_sweep(arm: SimulatedArm, clock: FakeClock, plan, *, step: float = 0.05, until: float = 60.0):
    sequencer = SweepSequencer(arm)
    sequencer.start(plan)
    seen = []
    while sequencer.active and until > 0:
        clock.t += step
        until -= step
        status = sequencer.poll()
        seen.append(status)
    return sequencer, seen


def test_plan_approaches_from_and_lifts_to_the_clearance():
    plan = plan_sweep(START, length=0.1, speed=0.01, accel=0.1, depth=0.001, clearance=0.003)
    hover, press, _, lift = (s.target for s in plan.segments)
    assert hover[2] == pytest.approx(START[2] + 0.003)
    assert press[2] == pytest.approx(START[2] - 0.001)
    assert lift[2] == pytest.approx(START[2] + 0.003)
    with pytest.raises(ArmLimitError):
        plan_sweep(START, length=0.1, speed=0.01, accel=0.1, depth=0.001, clearance=-0.001)


def test_plan_presses_rolls_and_lifts():
    plan = plan_sweep(START, length=0.11, speed=0.011, accel=0.1, depth=0.001, direction=(0, 2, 0))
    names = [s.name for s in plan.segments]
    assert names == ["to_start", "press", "sweep", "lift"]
    press, sweep, lift = (s.target for s in plan.segments[1:])
    assert press[2] == pytest.approx(START[2] - 0.001)
    np.testing.assert_allclose(sweep - press, [0, 0.11, 0, 0, 0, 0], atol=1e-12)
    assert lift[2] == pytest.approx(START[2])
    assert plan.rolls == (2,) and plan.segments[plan.rolls[0]].speed == 0.011


@pytest.mark.parametrize("kwargs", [
    {"length": -0.1}, {"depth": float("nan")}, {"direction": (0, 0, 1)}, {"direction": (1, float("inf"), 0)},
])
def test_plan_rejects_nonsense(kwargs):
    args = {"length": 0.1, "speed": 0.01, "accel": 0.1, "depth": 0.001} | kwargs
    with pytest.raises(ArmLimitError):
        plan_sweep(START, **args)


def test_sequencer_runs_the_whole_sweep_and_reports_roll_progress():
    arm, clock = make_arm()
    plan = plan_sweep(START, length=0.11, speed=0.011, accel=0.1, depth=0.001)
    sequencer, seen = run_sweep(arm, clock, plan)
    assert sequencer.status.phase is SweepPhase.DONE
    rolling = [s.roll_progress for s in seen if s.phase is SweepPhase.SWEEPING]
    assert len(rolling) > 100  # ~10 s of rolling at 20 Hz polling
    assert rolling == sorted(rolling) and rolling[-1] > 0.95
    assert all(s.roll_progress == 0.0 for s in seen if s.segment in ("to_start", "press"))
    np.testing.assert_allclose(arm.tcp_pose(), plan.segments[-1].target, atol=1e-12)


def test_sequencer_checks_every_segment_before_the_first_command():
    arm, clock = make_arm(limits=ArmLimits(max_speed=0.02, max_accel=0.5))
    plan = plan_sweep(START, length=0.11, speed=0.05, accel=0.1, depth=0.001, approach_speed=0.01)
    with pytest.raises(ArmLimitError):
        SweepSequencer(arm).start(plan)
    clock.t += 5
    assert not arm.is_moving()
    np.testing.assert_allclose(arm.tcp_pose(), START)


def test_fault_during_the_roll_stops_the_sweep():
    arm, clock = make_arm()
    plan = plan_sweep(START, length=0.11, speed=0.011, accel=0.1, depth=0.001)
    sequencer = SweepSequencer(arm)
    sequencer.start(plan)
    while sequencer.status.phase is not SweepPhase.SWEEPING:
        clock.t += 0.05
        sequencer.poll()
    clock.t += 3.0
    sequencer.poll()
    arm.inject_fault("protective stop")
    halted = arm.tcp_pose()
    status = sequencer.poll()
    assert status.phase is SweepPhase.FAULT and status.message == "protective stop"
    assert 0.1 < status.roll_progress < 0.5
    clock.t += 10
    assert sequencer.poll().phase is SweepPhase.FAULT
    np.testing.assert_allclose(arm.tcp_pose(), halted)


def test_stop_request_ends_the_sweep_in_stopped():
    arm, clock = make_arm()
    sequencer = SweepSequencer(arm)
    sequencer.start(plan_sweep(START, length=0.11, speed=0.011, accel=0.1, depth=0.001))
    clock.t += 0.5
    sequencer.poll()
    sequencer.stop()
    assert sequencer.status.phase is SweepPhase.STOPPED and not sequencer.active
    with pytest.raises(ArmError):  # a faulted arm cannot start a new sweep
        arm.inject_fault("estop")
        sequencer.start(plan_sweep(START, length=0.1, speed=0.01, accel=0.1, depth=0.0))


def test_simulated_arm_origin_rests_above_the_touching_pose():
    from touchroller_driver.arm import ArmLimitError, simulated_arm_origin

    rest, surface_z = simulated_arm_origin(START, 0.003)
    assert surface_z == START[2] and rest[2] == pytest.approx(START[2] + 0.003)
    np.testing.assert_allclose(rest[[0, 1, 3, 4, 5]], np.array(START)[[0, 1, 3, 4, 5]])
    with pytest.raises(ArmLimitError):
        simulated_arm_origin(START, -0.001)


def test_raster_covers_the_rectangle_in_alternating_passes():
    from touchroller_driver.arm import (
        DEFAULT_MOUNT_RPY,
        DEFAULT_MOUNT_XYZ,
        mount_transform,
        plan_raster,
        raster_coverage,
        raster_offsets,
    )

    assert raster_offsets(0.04, 0.06, 0.25) == [0.02]                 # narrower than the roller: one pass
    offsets = raster_offsets(0.18, 0.06, 0.25)
    assert offsets[0] == pytest.approx(0.03) and offsets[-1] == pytest.approx(0.15)
    assert all(0.06 - (b - a) >= 0.25 * 0.06 - 1e-12 for a, b in zip(offsets, offsets[1:], strict=False))
    mount = mount_transform(DEFAULT_MOUNT_XYZ, DEFAULT_MOUNT_RPY)
    plan = plan_raster(START, area=[0.38, -0.09, 0.24, 0.18], mount=mount, speed=0.02, accel=0.1, depth=5e-4,
                       clearance=0.002, approach_speed=0.005)
    assert len(plan.rolls) == len(offsets) == 4 and plan.length == pytest.approx(0.96)
    rolls = [plan.segments[i] for i in plan.rolls]
    for k, (roll, raster_pass) in enumerate(zip(rolls, plan.passes, strict=True)):
        press = plan.segments[plan.rolls[k] - 1]
        assert press.name == "press" and press.target[2] == pytest.approx(START[2] - 5e-4)
        # default mount: the cylinder centre is under the flange, so tool xy = contact line xy
        assert roll.target[:2] == pytest.approx(raster_pass.end)
        assert press.target[:2] == pytest.approx(raster_pass.start)
        assert raster_pass.start[0] == pytest.approx(0.38 if k % 2 == 0 else 0.62)   # boustrophedon
        assert raster_pass.start[1] == pytest.approx(-0.09 + offsets[k])
    assert [s.name for s in plan.segments[4:8]] == ["across", "press", "sweep", "lift"]
    assert raster_coverage(plan, 0.18, 0, 0.5) == pytest.approx(100 * 0.03 / 0.18)
    assert raster_coverage(plan, 0.18, 3, 1.0) == pytest.approx(100.0)
    with pytest.raises(ArmLimitError, match="perpendicular"):
        plan_raster(START, area=[0.38, -0.09, 0.24, 0.18], mount=mount, speed=0.02, accel=0.1, depth=5e-4,
                    direction=(1.0, 1.0, 0.0))


def test_sequencer_reports_progress_over_all_passes():
    from touchroller_driver.arm import DEFAULT_MOUNT_RPY, DEFAULT_MOUNT_XYZ, mount_transform, plan_raster

    arm, clock = make_arm()
    plan = plan_raster(START, area=[0.4, -0.05, 0.02, 0.1], mount=mount_transform(DEFAULT_MOUNT_XYZ, DEFAULT_MOUNT_RPY),
                       speed=0.02, accel=0.1, depth=5e-4, clearance=0.002)
    sequencer = SweepSequencer(arm)
    sequencer.start(plan)
    seen = []
    for _ in range(4000):
        clock.t += 0.01
        status = sequencer.poll()
        seen.append((status.roll, round(status.roll_progress, 3)))
        if not sequencer.active:
            break
    assert status.phase.value == "done" and status.roll_progress == 1.0
    progress = [p for _, p in seen]
    assert progress == sorted(progress)                          # never goes back
    assert any(roll == 1 and 0.5 < p < 1.0 for roll, p in seen)   # the second pass is the second half


def test_reset_fault_clears_a_protective_stop_but_not_an_emergency_stop():
    arm, clock = make_arm()
    arm.inject_fault("protective stop")
    with pytest.raises(ArmError, match="protective stop"):
        arm.move_linear(START, 0.01, 0.1)
    arm.reset_fault()
    assert arm.fault() is None
    arm.move_linear(np.array(START) + [0.01, 0, 0, 0, 0, 0], 0.01, 0.1)
    arm.inject_fault("emergency stop", resettable=False)
    with pytest.raises(ArmError, match="emergency stop"):
        arm.reset_fault()
    assert arm.fault() == "emergency stop"
    arm.inject_fault("protective stop")   # the e-stop released, a protective stop left: that one resets
    arm.reset_fault()
    assert arm.fault() is None


def test_a_lost_connection_is_a_fault_until_reset():
    arm, clock = make_arm()
    arm.move_linear(np.array(START) + [0.1, 0, 0, 0, 0, 0], 0.01, 0.1)
    clock.t += 1.0
    arm.inject_disconnect()
    assert not arm.is_moving() and "lost the connection" in arm.fault()
    with pytest.raises(ArmError):
        arm.move_linear(START, 0.01, 0.1)
    arm.reset_fault()
    assert arm.fault() is None
    arm.move_linear(START, 0.01, 0.1)


def test_a_sweep_whose_first_command_is_refused_does_not_start():
    """A refused first move (the arm gone, with no fault to say so beforehand) must fail `start`, not
    answer success with the sweep already in FAULT."""
    arm, clock = make_arm()
    arm.disconnect()
    assert arm.fault() is None
    sequencer = SweepSequencer(arm)
    with pytest.raises(ArmError, match="not connected"):
        sequencer.start(plan_sweep(START, length=0.05, speed=0.01, accel=0.1, depth=0.0))
    assert sequencer.status.phase is SweepPhase.FAULT and not sequencer.active
    sequencer.clear()
    assert sequencer.status.phase is SweepPhase.IDLE


def test_reach_refuses_a_target_beyond_it_and_the_pass_count_is_analytic():
    from touchroller_driver.arm import MAX_PASSES, plan_duration, raster_pass_count

    limits = ArmLimits(reach=0.85)
    limits.check([0.8, 0.0, 0.2, math.pi, 0.0, 0.0], 0.01, 0.1)
    with pytest.raises(ArmLimitError, match="beyond its reach of 0.85 m"):
        limits.check([0.85, 0.0, 0.2, math.pi, 0.0, 0.0], 0.01, 0.1)
    with pytest.raises(ValueError):
        ArmLimits(reach=float("nan"))
    assert raster_pass_count(0.05, 0.06, 0.25) == 1
    assert raster_pass_count(3000.0, 0.06, 0.25) > MAX_PASSES   # 66 667, counted without making them
    assert raster_pass_count(0.18, 0.06, 0.25) == 4
    plan = plan_sweep(START, length=0.11, speed=0.011, accel=0.1, depth=0.001, clearance=0.002)
    # each move: distance / speed + speed / accel (the two ramps); roll, press and lift (3 mm each way)
    assert plan_duration(plan) == pytest.approx(0.11 / 0.011 + 3 * 0.011 / 0.1 + 2 * 0.003 / 0.011, rel=1e-9)


# -- sweep.profile blend/constant: each pass one blended path (Arm.move_path) ----------------------------

def _raster(profile: str):
    from touchroller_driver.arm import DEFAULT_MOUNT_RPY, DEFAULT_MOUNT_XYZ, mount_transform, plan_raster

    return plan_raster(START, area=(0.42, -0.045, 0.05, 0.09), mount=mount_transform(DEFAULT_MOUNT_XYZ,
                       DEFAULT_MOUNT_RPY), speed=0.02, accel=0.1, depth=5e-4, clearance=0.002, profile=profile)


def run_traced(arm: SimulatedArm, clock: FakeClock, sequencer: SweepSequencer, dt: float = 0.005,
               until=lambda t, status: False) -> np.ndarray:
    """Poll the sequencer every dt s of the fake clock; rows (t, x, y, z, roll progress)."""
    rows = []
    while sequencer.active:
        clock.t += dt
        status = sequencer.poll()
        rows.append((clock.t, *arm.tcp_pose()[:3], status.roll_progress))
        if until(clock.t, status):
            break
    return np.array(rows)


def touchdown_speeds(trace: np.ndarray, pressed_z: float) -> np.ndarray:
    """The tool's horizontal speed at every first and last instant of contact (pressed height)."""
    speed = np.hypot(*np.diff(trace[:, 1:3], axis=0).T) / np.diff(trace[:, 0])
    pressed = np.abs(trace[:-1, 3] - pressed_z) < 1e-5
    return speed[np.flatnonzero(np.diff(pressed.astype(int)))]


@pytest.mark.parametrize("profile", ["ramp", "blend", "constant"])
def test_a_path_profile_touches_down_at_speed_and_ramp_still_stops_and_goes(profile):
    plan = _raster(profile)
    arm = SimulatedArm(plan.segments[0].target, clock=(clock := FakeClock()))
    arm.connect()
    sequencer = SweepSequencer(arm)
    sequencer.start(plan)
    trace = run_traced(arm, clock, sequencer)
    assert sequencer.status.phase is SweepPhase.DONE and trace[-1, 4] == pytest.approx(1.0)
    assert np.all(np.diff(trace[:, 4]) >= -1e-12)   # the roll progress never goes back
    speeds = touchdown_speeds(trace, plan.segments[plan.rolls[0]].target[2])
    assert len(speeds) == 4   # 2 passes: each touches down and lifts off once
    if profile == "ramp":
        assert speeds.max() < 0.002    # pressed at rest, stopped before the lift: as before
    else:
        assert speeds.min() > 0.019    # at the roll speed (0.02) on both corners of both passes
    np.testing.assert_allclose(arm.tcp_pose(), plan.motion()[0][-1].target, atol=1e-9)


def test_stop_and_a_fault_mid_path_halt_the_arm_at_once():
    for interrupt in ("stop", "fault"):
        plan = _raster("blend")
        arm = SimulatedArm(plan.segments[0].target, clock=(clock := FakeClock()))
        arm.connect()
        sequencer = SweepSequencer(arm)
        sequencer.start(plan)
        run_traced(arm, clock, sequencer, until=lambda t, status: (status.roll_progress or 0) > 0.2)
        assert sequencer.status.segment == "pass" and arm.is_moving()
        if interrupt == "stop":
            sequencer.stop()
        else:
            arm.inject_fault()
            sequencer.poll()
        here = arm.tcp_pose()
        clock.t += 5.0
        np.testing.assert_array_equal(arm.tcp_pose(), here)
        assert not arm.is_moving()
        assert sequencer.status.phase is (SweepPhase.STOPPED if interrupt == "stop" else SweepPhase.FAULT)
        assert 0.2 < sequencer.status.roll_progress < 0.5


def test_a_path_out_of_limits_refuses_the_start_and_the_arm_never_moves():
    plan = _raster("blend")
    # the lead-out waypoint of the first pass lies beyond the rolled rectangle: a workspace that ends
    # at the rectangle's far edge refuses it, though every ramp segment fits
    pass_end = max(s.target[0] for s in plan.segments)
    limits = ArmLimits(workspace_max=(pass_end + 1e-4, 1.0, 1.0))
    for segment in plan.segments:
        limits.check(segment.target, segment.speed, segment.accel)
    arm = SimulatedArm(plan.segments[0].target, limits=limits, clock=(clock := FakeClock()))
    arm.connect()
    before = arm.tcp_pose()
    with pytest.raises(ArmLimitError, match="path waypoint"):
        SweepSequencer(arm).start(plan)
    clock.t += 1.0
    np.testing.assert_array_equal(arm.tcp_pose(), before)
    assert not arm.is_moving()


def test_move_path_refuses_a_sharp_corner_at_speed_and_a_path_that_starts_elsewhere():
    arm, clock = make_arm()
    here = np.array(START)
    corner = [here, here + [0.02, 0, 0, 0, 0, 0], here + [0.02, 0.02, 0, 0, 0, 0]]
    with pytest.raises(ArmLimitError, match="corner") as info:
        arm.move_path(corner, 0.02, 0.1, 0.0)   # a right angle at 2 cm/s needs an infinite acceleration
    assert "\n" not in str(info.value)
    with pytest.raises(ArmError, match="first waypoint"):
        arm.move_path([here + [0.01, 0, 0, 0, 0, 0], here + [0.03, 0, 0, 0, 0, 0]], 0.02, 0.1, 0.0)
    with pytest.raises(ArmLimitError, match="speed"):
        arm.move_path(corner, 0.5, 0.1, 0.01)
    clock.t += 1.0
    np.testing.assert_array_equal(arm.tcp_pose(), here)
    arm.move_path(corner, 0.02, 0.1, 0.01)   # rounded by 1 cm: 0.02^2 * sqrt(2) / 0.01 = 0.057 m/s^2
    clock.t += 10.0
    np.testing.assert_allclose(arm.tcp_pose(), corner[-1], atol=1e-9)


def test_any_exception_from_a_motion_command_stops_the_arm_and_ends_the_sweep_in_fault():
    class BrokenPathArm(SimulatedArm):
        stops = 0

        def move_path(self, *args, **kwargs):
            raise TypeError("a bug in the back end")

        def stop(self) -> None:
            BrokenPathArm.stops += 1
            super().stop()

    plan = _raster("blend")
    arm = BrokenPathArm(plan.segments[0].target, clock=(clock := FakeClock()))
    arm.connect()
    sequencer = SweepSequencer(arm)
    sequencer.start(plan)   # the first move is linear: it runs
    run_traced(arm, clock, sequencer)
    assert sequencer.status.phase is SweepPhase.FAULT and not sequencer.active
    assert "TypeError: a bug in the back end" in sequencer.status.message and BrokenPathArm.stops == 1
    assert not arm.is_moving()


@pytest.mark.parametrize("profile", ["blend", "constant"])
def test_plan_duration_of_a_path_plan_bounds_the_simulated_run(profile):
    from touchroller_driver.arm import plan_duration

    plan = _raster(profile)
    arm = SimulatedArm(plan.segments[0].target, clock=(clock := FakeClock()))
    arm.connect()
    sequencer = SweepSequencer(arm)
    start = clock.t
    sequencer.start(plan)
    run_traced(arm, clock, sequencer, dt=0.001)
    taken = clock.t - start
    # at least the run (a blend only shortens the path), and not much more than it
    assert taken - 0.01 <= plan_duration(plan, plan.segments[0].target) <= 1.05 * taken


def test_a_single_roll_with_a_path_profile_is_one_path_and_must_lift_off():
    plan = plan_sweep(START, length=0.05, speed=0.011, accel=0.1, depth=5e-4, clearance=0.002, profile="blend")
    moves, rolls = plan.motion()
    assert [m.name for m in moves] == ["to_start", "pass"] and rolls == (1,)
    np.testing.assert_allclose(moves[1].waypoints[1:3], [plan.segments[1].target, plan.segments[2].target])
    assert moves[1].waypoints[-1][2] == pytest.approx(START[2] + 0.002)   # lifted back to the clearance
    with pytest.raises(ArmLimitError, match="sweep.retract"):
        plan_sweep(START, length=0.05, speed=0.011, accel=0.1, depth=5e-4, retract=False, profile="constant")
    with pytest.raises(ArmLimitError, match="sweep.profile"):
        plan_sweep(START, length=0.05, speed=0.011, accel=0.1, depth=5e-4, profile="fast")
