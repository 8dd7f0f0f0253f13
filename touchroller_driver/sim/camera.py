"""The simulated sensor as a camera on the arm: frames of the arm's pose at their exposure time.

`ArmCamera` is a `FrameSource` (touchroller_driver.sources). It renders frame k at exactly
`frame_time_ns(k, fps)` on the shared simulated clock (`now_ns`), with the roller where the arm has it
then (`cylinder_pose(t_ns)`: T_world_cylinder, e.g. looked up in a TF buffer fed by the sweep node),
relative to the scene's surface, which lies in the world frame at `surface_frame(scene)`. It never
skips a frame it can render (a slow machine delays frames, it does not change them), and stamps each
one `latency_s` late, as a webcam does (the delay from exposure to the host's stamp), so a mapper that
is not told the latency must find it.

The surface frame S: x along the surface grid's columns (the roller's axis), y along its rows (the
rolling direction), z down into the surface, origin on the surface plane at grid point (0, 0). The
roller's state follows from the cylinder frame's origin in S: x_along = x, travel = y, penetration
depth = z + r (the cylinder's lowest point below the surface plane). The renderer draws the surface
under an axis-aligned roller, so the cylinder frame must be parallel to S (any yaw is refused).
"""
from __future__ import annotations

import math
import time
from collections.abc import Callable

import numpy as np

from touchroller_driver.sim.clock import first_frame_at_or_after, frame_time_ns
from touchroller_driver.sim.render import RollerState, SimulatedSensor
from touchroller_driver.sim.scene import Scene
from touchroller_driver.sources import Frame, SourceStats, as_bgr8
from touchroller_perception.transforms import Transform

# S axes in the world frame at yaw 0: x (roller axis) along world +y, y (rolling) along world +x, z down.
_SURFACE_AXES = np.array([[0.0, 1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, -1.0]])
MAX_TILT_RAD = math.radians(1.0)
SPEED_DT_NS = 5_000_000   # speed (for motion blur) from the pose 5 ms before the frame


def surface_frame(scene: Scene) -> Transform:
    """T_world_S: where the scene's surface lies in the world frame (scene `world.surface_origin`,
    `world.surface_yaw`: the rolling axis's angle from world x, rad)."""
    world = scene.world
    yaw = float(world["surface_yaw"])
    c, s = math.cos(yaw), math.sin(yaw)
    rotation = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]]) @ _SURFACE_AXES
    matrix = np.eye(4)
    matrix[:3, :3] = rotation
    matrix[:3, 3] = [float(v) for v in world["surface_origin"]]
    return Transform.from_matrix(matrix)


def roller_state(surface_from_cylinder: Transform, radius: float, speed: float = 0.0, t: float = 0.0) -> RollerState:
    """The renderer's RollerState for the cylinder frame at T_S_cylinder."""
    rotation = surface_from_cylinder.matrix()[:3, :3]
    tilt = math.acos(max(-1.0, min(1.0, (float(np.trace(rotation)) - 1.0) / 2.0)))
    if tilt > MAX_TILT_RAD:
        raise ValueError(f"the roller is turned {math.degrees(tilt):.1f} deg from the simulated surface's axes; "
                         "the simulator rolls it with its axis along the surface's x (check mount.rpy, "
                         "sweep.start_pose and the scene's world.surface_yaw)")
    x, y, z = surface_from_cylinder.translation
    return RollerState(x_along=x, travel=y, depth=z + radius, speed=speed, t=t)


class ArmCamera:
    """A FrameSource: the simulated sensor on the arm; see the module docstring.

    now_ns: the simulated clock (ns; <= 0 while unknown, e.g. before the first /clock message).
    cylinder_pose: T_world_cylinder at a time, or None while unknown (the pose has not arrived yet).
    max_lag_s: a frame this far behind the clock that still has no pose is given up (counted dropped),
      so a source that fell behind a TF buffer's memory catches up instead of waiting forever.
    """

    def __init__(self, sensor: SimulatedSensor, *, now_ns: Callable[[], int],
                 cylinder_pose: Callable[[int], Transform | None], fps: float | None = None,
                 latency_s: float = 0.0, surface: Transform | None = None, max_lag_s: float = 2.0) -> None:
        if not (math.isfinite(latency_s) and latency_s >= 0):
            raise ValueError(f"latency must be a finite number of seconds >= 0, got {latency_s}")
        self.sensor = sensor
        self.now_ns = now_ns
        self.cylinder_pose = cylinder_pose
        self.fps = float(fps or sensor.scene.fps)
        if not (math.isfinite(self.fps) and self.fps > 0):
            raise ValueError(f"fps must be > 0, got {fps}")
        self.latency_ns = round(latency_s * 1e9)
        self.surface_inverse = (surface or surface_frame(sensor.scene)).inverse()
        self.max_lag_ns = round(max_lag_s * 1e9)
        self.stats = SourceStats()
        self._next: int | None = None   # index of the next frame on the grid

    @property
    def info(self) -> str:
        return f"sim {self.sensor.scene.name} (on the arm, {self.fps:g} fps, latency {self.latency_ns / 1e6:g} ms)"

    def open(self) -> None:
        self.stats.connected = True
        self._next = None

    def close(self) -> None:
        self.stats.connected = False

    def read(self, timeout: float) -> Frame | None:
        deadline = time.monotonic() + max(timeout, 0.0)
        while True:
            frame = self._try_frame()
            if frame is not None or time.monotonic() >= deadline:
                return frame
            time.sleep(min(0.002, max(deadline - time.monotonic(), 0.0)))

    def state_at(self, t_ns: int) -> RollerState | None:
        pose = self.cylinder_pose(t_ns)
        if pose is None:
            return None
        before = self.cylinder_pose(t_ns - SPEED_DT_NS)
        here = self.surface_inverse @ pose
        speed = 0.0
        if before is not None:
            speed = (here.translation[1] - (self.surface_inverse @ before).translation[1]) / (SPEED_DT_NS * 1e-9)
        return roller_state(here, self.sensor.camera.radius, speed, t_ns * 1e-9)

    def _try_frame(self) -> Frame | None:
        now = self.now_ns()
        if now <= 0:
            return None
        if self._next is None:
            self._next = first_frame_at_or_after(now, self.fps)
        t_k = frame_time_ns(self._next, self.fps)
        if now < t_k:
            return None
        state = self.state_at(t_k)
        if state is None:
            if now - t_k > self.max_lag_ns:   # the pose of that time will not come any more: catch up
                skipped = first_frame_at_or_after(now - self.max_lag_ns // 2, self.fps)
                self.stats.dropped += skipped - self._next
                self._next = skipped
            return None
        k = self._next
        self._next += 1
        self.stats.captured += 1
        image = self.sensor.capture(state, frame=k)   # None: the scene's dropped_frames effect ate it
        if image is None:
            self.stats.dropped += 1
            return None
        self.stats.delivered += 1
        return Frame(t_k + self.latency_ns, as_bgr8(image), k)

    def __repr__(self) -> str:  # pragma: no cover - debugging aid
        return f"ArmCamera({self.info})"
