"""A simulated scan without ROS: the simulated arm runs a sweep plan on the simulated clock and the
simulated sensor on it films every frame, as fast as the machine renders (the same images as
`touchroller scan` of the same plan: the same clock, poses and frame grid).

`simulate_sweep(sensor, plan, ...)` yields, in time order, `("tf", t_ns, T_base_tool0)` at every tick
of the clock and `("image", stamp_ns, image, k)` for every frame (stamped `latency_s` late), so a caller
can write a recording with /tf and /tf_static or feed a mapper directly. Used by the benchmarks and tests.

A plan with a path (`sweep.profile` blend or constant, `touchroller_driver.path`) is run as that path:
the arm moves from the rest pose to its first point (a trapezoid move), then follows it; `jitter` (a
fraction of the speed, 0.01-0.05 as real arms vary) and `pauses` ((arc length m, seconds) along the
path) vary how it is followed. `tf_hz` publishes /tf at its own rate (the clock's ticks by default)
with `tf_jitter_s` of random timing error per stamp, as a robot driver's TF arrives.
"""
from __future__ import annotations

import dataclasses
from collections.abc import Iterator
from typing import Any

import numpy as np

from touchroller_driver.arm import SimulatedArm, SweepPlan, SweepSequencer, as_pose
from touchroller_driver.sim.camera import ArmCamera
from touchroller_driver.sim.clock import NS, SimClock
from touchroller_driver.sim.render import SimulatedSensor
from touchroller_perception.transforms import Transform, TransformBuffer

START_NS = 1_700_000_000 * NS


def simulate_sweep(sensor: SimulatedSensor, plan: SweepPlan, rest_pose: Any, mount: Transform, *,
                   tick_hz: float = 60.0, fps: float = 30.0, latency_s: float = 0.0, lead_in_s: float = 0.5,
                   tail_s: float = 0.5, world: str = "base", tool: str = "tool0",
                   cylinder: str = "touchroller_cylinder", jitter: float = 0.0, pauses: tuple = (),
                   seed: int = 0, tf_hz: float | None = None, tf_jitter_s: float = 0.0) -> Iterator[tuple[Any, ...]]:
    """Run `plan` from `rest_pose` (the arm's pose before it starts) and film it; see the module docstring.
    The plan starts `lead_in_s` after the clock (on a whole second) and the clock runs `tail_s` past its end."""
    clock = SimClock(tick_hz, start_ns=START_NS, rate=1.0)
    arm = SimulatedArm(as_pose(rest_pose), clock=clock.now)
    arm.connect()
    buffer = TransformBuffer(cache_ns=5 * NS)
    buffer.set_transform(tool, cylinder, 0, mount, static=True)

    def pose(t_ns: int) -> Transform | None:
        return buffer.lookup(world, cylinder, t_ns) if buffer.can_transform(world, cylinder, t_ns) else None

    camera = ArmCamera(sensor, now_ns=clock.now_ns, cylinder_pose=pose, fps=fps, latency_s=latency_s)
    camera.open()
    sequencer = SweepSequencer(arm)
    path = plan.path
    if path is not None and (jitter or pauses):
        path = dataclasses.replace(path, jitter=jitter, pauses=tuple(pauses), seed=seed)
    path_t0: float | None = None   # when the arm started along the path
    rng = np.random.default_rng(seed)
    tf_period = None if tf_hz is None else round(NS / tf_hz)
    next_tf = START_NS
    started = finished_at = None

    def pose_at(t_ns: int) -> Transform:
        if path_t0 is not None and t_ns >= path_t0 * NS:
            tool_pose = path.pose(t_ns / NS - path_t0)   # type: ignore[union-attr]
        else:
            tool_pose = arm.pose_at(t_ns / NS)
        return Transform.from_rotation_vector(tool_pose[:3], tool_pose[3:])

    while True:
        t = clock.now_ns()
        if tf_period is None:
            transform = pose_at(t)
            buffer.set_transform(world, tool, t, transform)
            yield ("tf", t, transform)
        while tf_period is not None and next_tf <= t:
            # the driver's stamp is off by its jitter; the pose is the arm's at the stamp it carries
            stamp = next_tf + round(float(rng.normal(0.0, tf_jitter_s)) * NS) if tf_jitter_s else next_tf
            transform = pose_at(stamp)
            buffer.set_transform(world, tool, stamp, transform)
            yield ("tf", stamp, transform)
            next_tf += tf_period
        while (frame := camera.read(0.0)) is not None:
            yield ("image", frame.stamp_ns, frame.image, frame.seq)
        if path is not None:
            if started is None and t - START_NS >= lead_in_s * NS:
                arm.move_linear(path.waypoints[0], path.speed, path.accel)
                started = t
            elif started is not None and path_t0 is None and not arm.is_moving():
                path_t0 = t / NS
            elif path_t0 is not None and finished_at is None and t / NS - path_t0 >= path.duration:
                finished_at = t
        elif started is None and t - START_NS >= lead_in_s * NS:
            sequencer.start(plan)
            started = t
        elif started is not None:
            status = sequencer.poll()
            if not sequencer.active and finished_at is None:
                finished_at = t
                if status.phase.value != "done":
                    raise RuntimeError(f"the simulated sweep ended in {status.phase.value}: {status.message}")
        if finished_at is not None and t - finished_at >= tail_s * NS:
            return
        clock.step()   # no pacing: as fast as the machine renders
