"""The simulated sensor on the arm: one simulated clock, exact poses, deterministic frames."""
from __future__ import annotations

import math

import numpy as np
import pytest

from touchroller_driver.arm import (
    DEFAULT_MOUNT_RPY,
    DEFAULT_MOUNT_XYZ,
    DEFAULT_START_POSE,
    SimulatedArm,
    mount_transform,
)
from touchroller_driver.sim import RollerState, SimulatedSensor, load_scene
from touchroller_driver.sim.camera import ArmCamera, roller_state, surface_frame
from touchroller_driver.sim.clock import SimClock, first_frame_at_or_after, frame_time_ns
from touchroller_perception.transforms import Transform, TransformBuffer

MOUNT = mount_transform(DEFAULT_MOUNT_XYZ, DEFAULT_MOUNT_RPY)


def tool_pose(pose) -> Transform:
    return Transform.from_rotation_vector(pose[:3], pose[3:])


def clock_on_second(t_ns: int) -> bool:
    return t_ns % 1_000_000_000 == 0


def test_frame_grid_and_clock_ticks_meet_on_whole_seconds():
    assert frame_time_ns(30, 30.0) == 1_000_000_000
    assert frame_time_ns(1, 30.0) == 33_333_333
    assert [frame_time_ns(2 * k, 60.0) for k in range(5)] == [frame_time_ns(k, 30.0) for k in range(5)]
    assert first_frame_at_or_after(1_000_000_000, 30.0) == 30
    assert first_frame_at_or_after(1_000_000_001, 30.0) == 31
    clock = SimClock(60.0, start_ns=1_700_000_000_400_000_000, rate=1000.0)
    assert clock.now_ns() == 1_700_000_000_000_000_000 and clock.on_whole_second()   # rounded down
    ticks = [clock.advance() for _ in range(60)]
    assert ticks[0] == 1_700_000_000_016_666_666 and not clock_on_second(ticks[0])
    assert ticks[-1] == 1_700_000_001_000_000_000 and clock.on_whole_second()   # on the grid: no drift
    with pytest.raises(ValueError):
        SimClock(0.0)


def test_the_default_scene_lies_under_the_default_start_pose():
    """The default sweep's start pose touches the default scene's surface at its grid origin, the roller's
    axis along the surface's x, rolling along its y."""
    scene = load_scene("surface_mapping")
    cylinder = tool_pose(DEFAULT_START_POSE) @ MOUNT
    state = roller_state(surface_frame(scene).inverse() @ cylinder, radius=0.05)
    assert (state.x_along, state.travel, state.depth) == pytest.approx((0.0, 0.0, 0.0), abs=1e-12)
    moved = tool_pose(np.array(DEFAULT_START_POSE) + [0.01, 0.002, -0.0005, 0, 0, 0]) @ MOUNT
    state = roller_state(surface_frame(scene).inverse() @ moved, radius=0.05)
    assert (state.x_along, state.travel, state.depth) == pytest.approx((0.002, 0.01, 0.0005), abs=1e-12)


def test_a_turned_roller_is_refused():
    turned = Transform.from_rpy((0.0, 0.0, 0.0), (0.0, 0.0, math.radians(5.0)))
    with pytest.raises(ValueError, match="turned 5.0 deg"):
        roller_state(turned, radius=0.05)


def arm_camera(latency_s: float = 0.0, effects=("noise",)):
    """An arm on a simulated clock, its poses in a TF buffer at every tick, and the camera reading both."""
    sensor = SimulatedSensor(load_scene("surface_mapping", effects=list(effects)), seed=3)
    clock = SimClock(60.0, start_ns=1_700_000_000_000_000_000, rate=1000.0)
    arm = SimulatedArm(np.array(DEFAULT_START_POSE), clock=clock.now)
    arm.connect()
    buffer = TransformBuffer(cache_ns=None)
    buffer.set_transform("tool0", "touchroller_cylinder", 0, MOUNT, static=True)

    def tick():
        t = clock.advance()
        buffer.set_transform("base", "tool0", t, tool_pose(arm.tcp_pose()))

    def pose(t_ns):
        return buffer.lookup("base", "touchroller_cylinder", t_ns) if buffer.can_transform(
            "base", "touchroller_cylinder", t_ns) else None

    camera = ArmCamera(sensor, now_ns=clock.now_ns, cylinder_pose=pose, fps=30.0, latency_s=latency_s)
    return sensor, clock, arm, tick, camera


def test_frames_render_the_arms_exact_pose_at_their_time_stamped_late():
    sensor, clock, arm, tick, camera = arm_camera(latency_s=0.04)
    camera.open()
    tick()
    start = np.array(DEFAULT_START_POSE) + [0, 0, -0.0005, 0, 0, 0]
    arm.move_linear(start, 0.1, 0.5)   # press, then roll 5 mm at 11 mm/s
    frames = []
    for _ in range(120):
        tick()
        if not arm.is_moving() and arm.tcp_pose()[0] < start[0] + 0.001:
            arm.move_linear(start + [0.005, 0, 0, 0, 0, 0], 0.011, 0.1)
        frame = camera.read(0.0)
        if frame is not None:
            frames.append(frame)
    assert len(frames) >= 55
    seqs = [f.seq for f in frames]
    assert seqs == list(range(seqs[0], seqs[0] + len(seqs)))   # every frame of the grid, none skipped
    for frame in frames[::10]:
        t_k = frame_time_ns(frame.seq, 30.0)
        assert frame.stamp_ns == t_k + 40_000_000
        expected = camera.state_at(t_k)
        truth = roller_state(surface_frame(sensor.scene).inverse() @ tool_pose(arm.pose_at(t_k * 1e-9)) @ MOUNT, 0.05)
        # ticks fall on the frame grid: exact up to seconds-as-doubles at an epoch of 1.7e9 s (nanometres)
        assert expected.travel == pytest.approx(truth.travel, abs=1e-8)
        assert np.array_equal(frame.image, sensor.render(expected, frame=frame.seq))


def test_the_same_frame_is_the_same_image_however_many_came_before():
    sensor = SimulatedSensor(load_scene("surface_mapping", effects=["noise", "dropped_frames"],
                                        effect_params={"dropped_frames": {"probability": 0.3}}), seed=1)
    state = RollerState(travel=0.01, depth=5e-4)
    first = sensor.render(state, frame=7)
    sensor.render(state)   # other frames in between
    assert np.array_equal(sensor.render(state, frame=7), first)
    assert not np.array_equal(sensor.render(state, frame=8), first)
    drops = [sensor.capture(state, frame=k) is None for k in range(200)]
    assert drops == [sensor.capture(state, frame=k) is None for k in range(200)]
    assert 30 <= sum(drops) <= 90


def test_no_frame_before_the_clock_and_the_pose_are_known():
    sensor = SimulatedSensor(load_scene("surface_mapping", effects=[]), seed=0)
    now = {"t": 0}
    known = {"pose": None}
    camera = ArmCamera(sensor, now_ns=lambda: now["t"], cylinder_pose=lambda t: known["pose"], fps=30.0,
                       max_lag_s=1.0)
    camera.open()
    assert camera.read(0.0) is None                       # no clock yet
    now["t"] = 10 ** 18
    assert camera.read(0.01) is None                      # no pose yet
    now["t"] += 3 * 10 ** 9                               # the pose of those frames never came: catch up
    assert camera.read(0.0) is None and camera.stats.dropped > 0
    known["pose"] = tool_pose(DEFAULT_START_POSE) @ MOUNT
    assert camera.read(0.0) is not None
