"""A simulated scan without ROS: the simulated arm runs a sweep plan on the simulated clock and the
simulated sensor on it films every frame, as fast as the machine renders (the same images as
`touchroller scan` of the same plan: the same clock, poses and frame grid).

`simulate_sweep(sensor, plan, ...)` yields, in time order, `("tf", t_ns, T_base_tool0)` at every tick
of the clock and `("image", stamp_ns, image, k)` for every frame (stamped `latency_s` late), so a caller
can write a recording with /tf and /tf_static or feed a mapper directly. Used by the benchmarks and tests.
"""
from __future__ import annotations

from collections.abc import Iterator
from typing import Any

from touchroller_driver.arm import SimulatedArm, SweepPlan, SweepSequencer, as_pose
from touchroller_driver.sim.camera import ArmCamera
from touchroller_driver.sim.clock import NS, SimClock
from touchroller_driver.sim.render import SimulatedSensor
from touchroller_perception.transforms import Transform, TransformBuffer

START_NS = 1_700_000_000 * NS


def simulate_sweep(sensor: SimulatedSensor, plan: SweepPlan, rest_pose: Any, mount: Transform, *,
                   tick_hz: float = 60.0, fps: float = 30.0, latency_s: float = 0.0, lead_in_s: float = 0.5,
                   tail_s: float = 0.5, world: str = "base", tool: str = "tool0",
                   cylinder: str = "touchroller_cylinder") -> Iterator[tuple[Any, ...]]:
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
    started = finished_at = None
    while True:
        t = clock.now_ns()
        tool_pose = arm.pose_at(t / NS)
        transform = Transform.from_rotation_vector(tool_pose[:3], tool_pose[3:])
        buffer.set_transform(world, tool, t, transform)
        yield ("tf", t, transform)
        while (frame := camera.read(0.0)) is not None:
            yield ("image", frame.stamp_ns, frame.image, frame.seq)
        if started is None and t - START_NS >= lead_in_s * NS:
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
