"""The arm that rolls the sensor: one interface, a simulated implementation (the UR5 one is in `ur5.py`).

Poses are UR TCP poses in the robot base frame: (x, y, z, rx, ry, rz), metres and a rotation vector
(radians), z up. Every motion command is checked against `ArmLimits` before it is sent, and an arm that
has faulted refuses further motion until `reset_fault()` clears the fault (what a UR's dashboard
"unlock protective stop" and a reconnect do). No rclpy here: the sweep node drives an
`Arm` from its one worker thread.
"""
from __future__ import annotations

import functools
import math
import threading
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from enum import Enum
from typing import Protocol, runtime_checkable

import numpy as np
from numpy.typing import ArrayLike

from touchroller_driver.motion import TrapezoidProfile
from touchroller_driver.path import BlendedPath, blend_radii, corner_accelerations, least_blend, raster_waypoints
from touchroller_perception.transforms import Transform


class ArmError(RuntimeError):
    """An arm command could not be carried out (not connected, faulted, refused by the controller)."""


class ArmLimitError(ArmError, ValueError):
    """A command asked for more speed, acceleration or reach than the limits allow; nothing was sent."""


@dataclass(frozen=True)
class ArmLimits:
    """Hard limits checked before any motion command.

    The defaults are conservative for rolling a tactile sensor (the paper rolls at about 1 cm/s);
    a UR5's own tool limits are higher. `workspace_min`/`workspace_max` optionally bound the target
    position (base frame, metres).
    """

    max_speed: float = 0.1  # m/s
    max_accel: float = 0.5  # m/s^2
    workspace_min: tuple[float, float, float] | None = None
    workspace_max: tuple[float, float, float] | None = None
    reach: float | None = None  # m: the farthest a target position may be from the base frame's origin

    def __post_init__(self) -> None:
        for name in ("max_speed", "max_accel", *(("reach",) if self.reach is not None else ())):
            value = getattr(self, name)
            if not (math.isfinite(value) and value > 0):
                raise ValueError(f"ArmLimits.{name} must be a finite number > 0, got {value}")

    def check_reach(self, position: ArrayLike) -> None:
        """ArmLimitError unless the position (x, y, z in the base frame) is within `reach` of the origin."""
        xyz = np.asarray(position, dtype=np.float64).reshape(-1)[:3]
        if self.reach is not None and not float(np.linalg.norm(xyz)) <= self.reach:
            raise ArmLimitError(f"target {np.round(xyz, 4).tolist()} is {float(np.linalg.norm(xyz)):.4g} m from the "
                                f"arm's base, beyond its reach of {self.reach:g} m (arm.reach)")

    def check(self, target_pose: ArrayLike, speed: float, accel: float) -> np.ndarray:
        """Validate a linear move; return the target as a float64 (6,) array or raise ArmLimitError."""
        pose = as_pose(target_pose)
        if not (math.isfinite(speed) and 0 < speed <= self.max_speed):
            raise ArmLimitError(f"speed {speed} m/s outside (0, {self.max_speed}]")
        if not (math.isfinite(accel) and 0 < accel <= self.max_accel):
            raise ArmLimitError(f"acceleration {accel} m/s^2 outside (0, {self.max_accel}]")
        if self.workspace_min is not None and np.any(pose[:3] < np.asarray(self.workspace_min)):
            raise ArmLimitError(f"target {pose[:3].tolist()} below workspace minimum {list(self.workspace_min)}")
        if self.workspace_max is not None and np.any(pose[:3] > np.asarray(self.workspace_max)):
            raise ArmLimitError(f"target {pose[:3].tolist()} above workspace maximum {list(self.workspace_max)}")
        self.check_reach(pose[:3])
        return pose

    def check_path(self, waypoints: ArrayLike, speed: float, accel: float, blend: float) -> np.ndarray:
        """Validate a blended path (`Arm.move_path`): every waypoint as a linear move's target (the blended
        corners lie in the waypoints' convex hull, and the workspace box and the reach ball are convex, so
        they are inside too), and every corner taken at `speed` with its blend radius within `accel`
        (`corner_accelerations`: a sharp turn at speed is refused); return the waypoints as a float64
        (N, 6) array or raise ArmLimitError (one line)."""
        array = np.asarray(waypoints, dtype=np.float64)
        if array.ndim != 2 or array.shape[1] != 6 or len(array) < 1:
            raise ArmLimitError(f"a path is waypoints (N, 6) poses, got an array of shape {array.shape}")
        if not (math.isfinite(blend) and blend >= 0):
            raise ArmLimitError(f"blend radius {blend} m must be a finite number >= 0")
        for k, pose in enumerate(array):
            try:
                self.check(pose, speed, accel)
            except ArmLimitError as exc:
                raise ArmLimitError(f"path waypoint {k + 1} of {len(array)}: {exc}") from None
        needed = corner_accelerations(array, speed, blend)
        if np.any(needed > accel):
            k = int(np.argmax(needed))
            raise ArmLimitError(f"path waypoint {k + 1} of {len(array)}: its corner at {speed:g} m/s with a blend "
                                f"radius of {blend_radii(array, blend)[k]:.3g} m needs {needed[k]:.3g} m/s^2, more "
                                f"than the acceleration {accel:g} (a larger blend, or a lower speed)")
        return array


def as_pose(pose: ArrayLike) -> np.ndarray:
    """A finite (6,) float64 pose, or ArmLimitError (a NaN target must never reach a robot)."""
    array = np.asarray(pose, dtype=np.float64).reshape(-1)
    if array.shape != (6,):
        raise ArmLimitError(f"a pose has 6 values (x, y, z, rx, ry, rz), got {array.size}")
    if not np.all(np.isfinite(array)):
        raise ArmLimitError(f"pose has non-finite values: {array.tolist()}")
    return array


DEFAULT_START_POSE = (0.4, 0.0, 0.2, math.pi, 0.0, 0.0)  # the sweep's touching pose (UR base frame)
DEFAULT_CLEARANCE = 0.002  # m the arm rests above the touching pose
DEFAULT_DIRECTION = (1.0, 0.0, 0.0)  # rolling direction in the base frame
# touchroller_cylinder in the tool frame: the roller's axis 10 cm below the flange (along tool z), its
# x axis (the roller axis) along -tool y. With the flange pointing down (rx = pi) that puts the axis
# along base +y and cylinder z down, so the default sweep.direction (base +x) rolls it.
DEFAULT_MOUNT_XYZ = (0.0, 0.0, 0.1)
DEFAULT_MOUNT_RPY = (0.0, 0.0, -math.pi / 2)


def mount_transform(xyz: Sequence[float], rpy: Sequence[float]) -> Transform:
    """T_tool_cylinder from `mount.xyz` (m) and `mount.rpy` (fixed-axis roll, pitch, yaw, rad)."""
    xyz, rpy = list(xyz), list(rpy)
    if len(xyz) != 3 or len(rpy) != 3:
        raise ValueError(f"mount.xyz and mount.rpy take 3 numbers each, got {xyz} and {rpy}")
    if not all(math.isfinite(float(v)) for v in xyz + rpy):
        raise ValueError(f"mount.xyz and mount.rpy must be finite, got {xyz} and {rpy}")
    return Transform.from_rpy(xyz, rpy)


def simulated_arm_origin(start_pose: ArrayLike, clearance: float) -> tuple[np.ndarray, float]:
    """(rest pose, surface z) of the sweep node's simulated arm: it rests `clearance` above the start
    pose, where the roller just touches the surface. One definition for the sweep node and for a
    simulated camera that follows the arm's published poses."""
    touching = as_pose(start_pose)
    if not (math.isfinite(clearance) and clearance >= 0):
        raise ArmLimitError(f"sweep clearance must be a finite number >= 0, got {clearance}")
    return touching + np.array([0.0, 0.0, float(clearance), 0.0, 0.0, 0.0]), float(touching[2])


@runtime_checkable
class Arm(Protocol):
    """What the sweep node needs from an arm. All calls come from one thread."""

    limits: ArmLimits

    def connect(self) -> None: ...
    def tcp_pose(self) -> np.ndarray: ...
    def move_linear(self, target_pose: ArrayLike, speed: float, accel: float,
                    asynchronous: bool = True) -> None: ...
    # through the waypoints (N, 6) as one motion, inner corners blended by `blend` m (`blend_radii`), at
    # `speed`: touchdown and lift-off without stopping (sweep.profile blend/constant). Every waypoint and
    # corner is checked (`ArmLimits.check_path`) and the tool must be within PATH_START_TOLERANCE of the
    # first waypoint, else ArmLimitError/ArmError and nothing moves
    def move_path(self, waypoints: ArrayLike, speed: float, accel: float, blend: float,
                  asynchronous: bool = True) -> None: ...
    def progress(self) -> float: ...
    def is_moving(self) -> bool: ...
    def stop(self) -> None: ...
    def fault(self) -> str | None: ...
    def reset_fault(self) -> None: ...  # clear a fault (unlock a protective stop, reconnect) or raise ArmError
    def keepalive(self) -> None: ...  # at >= 10 Hz while connected: a real arm stops when calls cease
    def disconnect(self) -> None: ...
    def abort(self) -> None: ...  # from ANY thread: give up a blocking call under way (it raises ArmError)


@dataclass(frozen=True)
class _Move:
    t0: float
    start: np.ndarray
    target: np.ndarray
    profile: TrapezoidProfile

    @property
    def direction(self) -> np.ndarray:
        delta = self.target - self.start
        length = float(np.linalg.norm(delta[:3]))
        return delta / length if length > 0 else np.zeros(6)

    def pose(self, t: float) -> np.ndarray:
        distance = abs(self.profile.distance)
        fraction = float(self.profile.position(t - self.t0)) / distance if distance > 0 else 1.0
        return self.start + fraction * (self.target - self.start)

    def velocity(self, t: float) -> np.ndarray:
        return float(self.profile.velocity(t - self.t0)) * self.direction[:3]

    def fraction(self, t: float) -> float:
        distance = abs(self.profile.distance)
        return float(self.profile.position(t - self.t0)) / distance if distance > 0 else 1.0

    def end_time(self) -> float:
        return self.t0 + self.profile.duration


@dataclass(frozen=True)
class _PathMove:
    t0: float
    path: BlendedPath

    def pose(self, t: float) -> np.ndarray:
        return self.path.pose(t - self.t0)

    def fraction(self, t: float) -> float:
        length = self.path.length
        return self.path.travelled(t - self.t0) / length if length > 0 else 1.0

    def end_time(self) -> float:
        return self.t0 + self.path.duration


class SimulatedArm:
    """A kinematic arm: linear moves follow a trapezoid velocity profile in the time of `clock` (seconds:
    real time by default; the sweep node's simulated clock in simulation, which the simulated camera
    shares). It knows nothing of the sensor: the camera reads its pose (over TF). `stop()` halts
    instantly (an idealisation); `inject_fault` stands in for a protective stop (or, not resettable, an
    emergency stop still pressed) and `inject_disconnect` for a lost connection.
    """

    def __init__(self, start_pose: ArrayLike = DEFAULT_START_POSE, *, limits: ArmLimits | None = None,
                 clock: Callable[[], float] = time.monotonic) -> None:
        self.limits = limits or ArmLimits()
        self.origin = as_pose(start_pose)
        self.clock = clock
        self._lock = threading.Lock()
        self._connected = False
        self._fault: str | None = None
        self._fault_resettable = True
        self._move: _Move | _PathMove | None = None
        self._rest_pose = self.origin.copy()
        self._halted_fraction = 1.0  # progress of a move that was stopped part-way

    # -- Arm interface -------------------------------------------------------------------------
    def connect(self) -> None:
        with self._lock:
            self._connected = True
            self._fault = None

    def disconnect(self) -> None:
        self.stop()
        with self._lock:
            self._connected = False

    def tcp_pose(self) -> np.ndarray:
        return self.pose_at(self.clock())

    def move_linear(self, target_pose: ArrayLike, speed: float, accel: float,
                    asynchronous: bool = True) -> None:
        target = self.limits.check(target_pose, speed, accel)
        with self._lock:
            self._require_ready()
            now = self.clock()
            start = self._pose_locked(now)
            distance = float(np.linalg.norm(target[:3] - start[:3]))
            self._move = move = _Move(now, start, target, TrapezoidProfile(distance, speed, accel))
        if not asynchronous:
            self._wait_until(move.end_time())

    def move_path(self, waypoints: ArrayLike, speed: float, accel: float, blend: float,
                  asynchronous: bool = True) -> None:
        """From the first waypoint (where the tool is) through the rest as one `BlendedPath` (one trapezoid
        over its length: it stops only at its end), every waypoint and corner checked first."""
        points = self.limits.check_path(waypoints, speed, accel, blend).copy()
        with self._lock:
            self._require_ready()
            now = self.clock()
            start = self._pose_locked(now)
            _check_path_start(start, points)
            points[0] = start
            move: _Move | _PathMove
            if float(np.linalg.norm(np.diff(points[:, :3], axis=0), axis=1).sum()) < 1e-9:   # nowhere to go
                move = _Move(now, start, points[-1], TrapezoidProfile(0.0, speed, accel))
            else:
                move = _PathMove(now, BlendedPath(points, speed, accel, blend))
            self._move = move
        if not asynchronous:
            self._wait_until(move.end_time())

    def progress(self) -> float:
        """Fraction (0..1) of the current or last move; 1.0 if there was none."""
        with self._lock:
            move = self._move
        return self._halted_fraction if move is None else move.fraction(self.clock())

    def is_moving(self) -> bool:
        with self._lock:
            move = self._move
        return move is not None and self.clock() < move.end_time()

    def stop(self) -> None:
        with self._lock:
            self._halt_locked(self.clock())

    def fault(self) -> str | None:
        with self._lock:
            return self._fault

    def reset_fault(self) -> None:
        """Clear the fault and reconnect, as unlocking a protective stop does; ArmError while the cause
        persists (an injected fault that is not resettable)."""
        with self._lock:
            if self._fault is not None and not self._fault_resettable:
                raise ArmError(f"cannot reset: {self._fault}")
            self._fault, self._fault_resettable = None, True
            self._connected = True

    def keepalive(self) -> None:
        """Nothing to keep alive: the simulation stops with the process."""

    def abort(self) -> None:
        """Nothing blocks here: every call returns at once."""

    # -- simulation ----------------------------------------------------------------------------
    def inject_fault(self, message: str = "protective stop", *, resettable: bool = True) -> None:
        """Behave like a protective stop: the arm halts where it is and refuses motion until `reset_fault()`
        (which fails while `resettable` is False, as with an emergency stop still pressed)."""
        with self._lock:
            self._halt_locked(self.clock())
            self._fault, self._fault_resettable = message, resettable

    def inject_disconnect(self) -> None:
        """Behave like a lost connection: the arm halts and every command fails until `reset_fault()`."""
        with self._lock:
            self._halt_locked(self.clock())
            self._connected = False
            self._fault, self._fault_resettable = "lost the connection to the arm", True

    def pose_at(self, t: float) -> np.ndarray:
        with self._lock:
            return self._pose_locked(t)

    # -- internals -----------------------------------------------------------------------------
    def _require_ready(self) -> None:
        if not self._connected:
            raise ArmError("arm not connected")
        if self._fault is not None:
            raise ArmError(f"arm faulted: {self._fault}")

    def _pose_locked(self, t: float) -> np.ndarray:
        if self._move is None:
            return self._rest_pose.copy()
        return self._move.pose(t)

    def _halt_locked(self, t: float) -> None:
        if self._move is not None:
            self._halted_fraction = self._move.fraction(t)
        self._rest_pose = self._pose_locked(t)
        self._move = None

    def _wait_until(self, t_end: float) -> None:
        while self.clock() < t_end:
            if self.fault() is not None:
                raise ArmError(f"arm faulted: {self.fault()}")
            time.sleep(min(0.01, max(t_end - self.clock(), 0.0)))


# -- the sweep: a plan of linear moves and a sequencer that drives any Arm through it ---------------

class SweepPhase(str, Enum):
    CONNECTING = "connecting"   # the sweep node is opening the connection to the arm
    IDLE = "idle"
    MOVING = "moving"      # on the way to the start pose, pressing in, or lifting off
    SWEEPING = "sweeping"  # rolling along the surface at the sweep speed and depth
    DONE = "done"
    STOPPED = "stopped"
    FAULT = "fault"


@dataclass(frozen=True)
class Segment:
    name: str
    target: np.ndarray
    speed: float
    accel: float


@dataclass(frozen=True)
class PathSegment:
    """A pass rolled as one blended path (`Arm.move_path`): from above and `lead` before the pass down to
    the surface, along it and up again, at `speed` all the way (waypoints: before, touchdown, lift-off,
    after), so the roller touches down and lifts off while moving."""

    name: str
    waypoints: np.ndarray
    speed: float
    accel: float
    blend: float

    @property
    def target(self) -> np.ndarray:
        return np.asarray(self.waypoints[-1])

    def roll_fraction(self, progress: float) -> float:
        """How much of the pass's roll (touchdown to lift-off) is done at `progress` (0..1) of the path."""
        legs = np.linalg.norm(np.diff(self.waypoints[:, :3], axis=0), axis=1)
        total = float(legs.sum())
        if total <= 0 or len(legs) < 2 or legs[1] <= 0:
            return min(max(progress, 0.0), 1.0)
        return min(max((progress * total - float(legs[0])) / float(legs[1]), 0.0), 1.0)


Move = Segment | PathSegment


@dataclass(frozen=True)
class SweepPlan:
    """Linear moves: above the start pose, press in by `depth`, roll, lift off; a raster repeats that
    for every pass. `rolls` are the indices of the rolling segments, `lengths` their lengths."""

    segments: tuple[Segment, ...]
    rolls: tuple[int, ...]
    lengths: tuple[float, ...]
    passes: tuple[RasterPass, ...] = ()
    profile: str = "ramp"              # SWEEP_PROFILES
    #: profile blend/constant: (waypoints, speed, accel, blend) of the whole raster as one path (`path`)
    raster_path: tuple[np.ndarray, float, float, float] | None = None
    #: profile blend/constant: what an arm runs (a linear move above each pass's start, then the pass as
    #: one PathSegment), and the indices of the passes among them
    path_moves: tuple[Move, ...] = ()
    path_rolls: tuple[int, ...] = ()

    @functools.cached_property
    def path(self) -> BlendedPath | None:
        """profile blend/constant: the whole raster as one path at speed (what `simulate_sweep` films),
        made on first use: planning and checking a start never samples it (a long raster's is large)."""
        if self.raster_path is None:
            return None
        waypoints, speed, accel, blend = self.raster_path
        return BlendedPath(waypoints, speed, accel, blend)

    def motion(self) -> tuple[tuple[Move, ...], tuple[int, ...]]:
        """(moves, indices of the rolls among them) an arm runs: the segments (ramp) or the path moves."""
        if self.path_moves:
            return self.path_moves, self.path_rolls
        return self.segments, self.rolls

    @property
    def length(self) -> float:
        """Total rolled length, m."""
        return float(sum(self.lengths))

    def roll_number(self, index: int) -> int | None:
        """Which roll (0-based) move `index` (of `motion()`) is, None if it is not one."""
        rolls = self.motion()[1]
        return rolls.index(index) if index in rolls else None


def _check_path_start(pose: np.ndarray, waypoints: np.ndarray) -> None:
    """ArmError unless the tool (`pose`) is within PATH_START_TOLERANCE of the path's first waypoint."""
    gap = float(np.linalg.norm(np.asarray(pose, np.float64)[:3] - waypoints[0, :3]))
    if not gap <= PATH_START_TOLERANCE:
        raise ArmError(f"a path starts where the tool is: it is {1000 * gap:.3g} mm from the first waypoint "
                       f"(at most {1000 * PATH_START_TOLERANCE:g} mm)")


def check_path_start(pose: ArrayLike, waypoints: ArrayLike) -> None:
    """`Arm.move_path`'s start rule for every back end: ArmError unless the tool is at the first waypoint."""
    _check_path_start(np.asarray(pose, np.float64), np.asarray(waypoints, np.float64).reshape(-1, 6))


def check_plan(limits: ArmLimits, plan: SweepPlan) -> None:
    """Every move an arm would run for `plan` (each waypoint and blended corner of a path) against
    `limits`; ArmLimitError (one line) before anything moves."""
    for move in plan.motion()[0]:
        if isinstance(move, PathSegment):
            limits.check_path(move.waypoints, move.speed, move.accel, move.blend)
        else:
            limits.check(move.target, move.speed, move.accel)


def _path_moves(rolled: Sequence[tuple[np.ndarray, np.ndarray]], *, above: float, lead: float, speed: float,
                accel: float, slow: float, blend: float) -> tuple[tuple[Move, ...], tuple[int, ...]]:
    """Each pass (pressed start, pressed end) as a linear move to above and `lead` before its start, then
    one PathSegment through its touchdown and lift-off to above and `lead` beyond its end. Its blend
    radius is `blend` (0: constant, as sharp as allowed), and at least what takes its corners at `speed`
    within `accel` (`least_blend`, with a margin): a real arm cannot turn a sharp corner without stopping."""
    waypoints = raster_waypoints(rolled, above, lead)
    moves: list[Move] = []
    rolls: list[int] = []
    for k in range(len(rolled)):
        points = waypoints[4 * k:4 * k + 4]
        moves.append(Segment("to_start" if k == 0 else "across", points[0], slow if k == 0 else max(slow, speed),
                             accel))
        rolls.append(len(moves))
        radius = max(blend, CORNER_MARGIN * least_blend(points, speed, accel))
        moves.append(PathSegment("pass", points, speed, accel, radius))
    return tuple(moves), tuple(rolls)


@dataclass(frozen=True)
class RasterPass:
    """One pass of a raster in the world frame's horizontal plane: the contact line's centre rolls from
    `start` to `end` (x, y, m); it covers `across` = (low, high) m of the rectangle's width."""

    start: tuple[float, float]
    end: tuple[float, float]
    across: tuple[float, float]


#: `sweep.profile`: ramp (press, accelerate from rest, roll, stop, lift: today's moves), blend (touchdown
#: and lift-off at speed, corners rounded by `blend` as a UR program with blend radii), constant (the same
#: path at speed with sharp corners)
SWEEP_PROFILES = ("ramp", "blend", "constant")

#: path profiles: a pass's blend radius is at least this times the least that keeps its corners within accel
CORNER_MARGIN = 1.5

#: how far (m) the tool may be from a path's first waypoint when the path is sent (`Arm.move_path`)
PATH_START_TOLERANCE = 1e-3

#: the most passes a raster may have: its plan (4 moves a pass) is built and checked at once, and a
#: raster of more passes is a typo (a width in mm given in m) far more often than a wish
MAX_PASSES = 1000


def raster_pass_count(width: float, usable_width: float, overlap: float) -> int:
    """How many passes `raster_offsets` makes, computed without making them (any finite width)."""
    if not (math.isfinite(usable_width) and usable_width > 0):
        raise ArmLimitError(f"the roller's usable width must be > 0 m, got {usable_width}")
    if not (0.0 <= overlap < 1.0):
        raise ArmLimitError(f"pass overlap must be in [0, 1), got {overlap}")
    if not math.isfinite(width):
        raise ArmLimitError(f"the raster's width must be finite, got {width}")
    if width <= usable_width:
        return 1
    step = usable_width * (1.0 - overlap)
    return math.ceil((width - usable_width) / step - 1e-9) + 1


def raster_offsets(width: float, usable_width: float, overlap: float) -> list[float]:
    """Centre lines of the passes across a rectangle `width` wide (0 = the edge): as few passes of
    `usable_width` as cover it with neighbours sharing at least `overlap` of the usable width, spread
    evenly, the first and last flush with the edges; one centred pass when the rectangle is narrower.
    ArmLimitError beyond MAX_PASSES passes."""
    count = raster_pass_count(width, usable_width, overlap)
    if count > MAX_PASSES:
        raise ArmLimitError(f"sweep.area {width:g} m wide takes {count} passes of {usable_width:g} m "
                            f"(overlap {overlap:g}); at most {MAX_PASSES}")
    if count == 1:
        return [width / 2.0]
    pitch = (width - usable_width) / (count - 1)
    return [usable_width / 2.0 + k * pitch for k in range(count)]


def plan_raster(start_pose: ArrayLike, *, area: Sequence[float], mount: Transform, speed: float, accel: float,
                depth: float, direction: Sequence[float] = (1.0, 0.0, 0.0), usable_width: float = 0.06,
                overlap: float = 0.25, approach_speed: float | None = None, clearance: float = 0.0,
                limits: ArmLimits | None = None, profile: str = "ramp", lead: float = 0.01,
                blend: float = 0.004) -> SweepPlan:
    """A boustrophedon raster over the rectangle `area` = (x, y, length, width) of the world's horizontal
    plane: corner (x, y), `length` along `direction`, `width` along the roller's axis (+axis side).
    Every pass rolls the whole length, pressed `depth` into the surface, alternately forwards and back;
    between passes the roller lifts by `clearance`, moves across and presses again. `start_pose` gives
    the tool's orientation and the height at which the roller just touches the surface; `mount` is
    T_tool_cylinder (the roller's axis centre in the tool frame). With `limits`, the raster's corners are
    checked against its reach before any pass is planned (the tool's path lies within their hull), so an
    area kilometres wide is refused at once; and no raster has more than MAX_PASSES passes. `profile`
    (SWEEP_PROFILES): with blend or constant the plan's `path` rolls the raster at speed, descending over
    `lead` m before each pass and rising over `lead` after it (`touchroller_driver.path`: what
    `simulate_sweep` films); its segments stay those of ramp, and its `path_moves` are what an arm runs
    through `SweepSequencer` (each pass one blended path, the moves between them linear)."""
    if profile not in SWEEP_PROFILES:
        raise ArmLimitError(f"sweep.profile must be one of {', '.join(SWEEP_PROFILES)}, got {profile!r}")
    start = as_pose(start_pose)
    values = [float(v) for v in area]
    if len(values) != 4 or not all(math.isfinite(v) for v in values):
        raise ArmLimitError(f"sweep.area is [x, y, length, width] (4 finite numbers, m), got {list(area)}")
    x0, y0, length, width = values
    for name, value in (("area length", length), ("area width", width), ("depth", depth), ("clearance", clearance)):
        if value < 0:
            raise ArmLimitError(f"sweep {name} must be >= 0, got {value}")
    heading = _horizontal(direction, "sweep direction")
    tool = Transform.from_rotation_vector(start[:3], start[3:])
    cylinder = tool @ mount
    axis = _horizontal(cylinder.matrix()[:3, 0], "the roller's axis (mount.rpy and the start pose's rotation)")
    if abs(float(axis @ heading)) > math.sin(math.radians(2.0)):
        raise ArmLimitError("sweep.direction must be perpendicular to the roller's axis (from mount.rpy and "
                            "sweep.start_pose); it rolls along its circumference only")
    across = axis if float(np.cross(heading, axis)[2]) > 0 else -axis   # the rectangle spans +across (left)
    # tool xy that puts the cylinder's centre over a world xy (the orientation stays the start pose's)
    offset = np.asarray(cylinder.translation)[:2] - start[:2]
    corner = np.array([x0, y0])
    slow = min(speed, approach_speed) if approach_speed is not None else speed
    segments: list[Segment] = []
    rolls: list[int] = []
    passes: list[RasterPass] = []

    def tool_at(xy: np.ndarray, dz: float) -> np.ndarray:
        pose = start.copy()
        pose[:2] = xy - offset
        pose[2] += dz
        return pose

    count = raster_pass_count(width, usable_width, overlap)
    if limits is not None:   # the reach is a ball (convex): the rectangle's corners bound every target
        first, last = (width / 2.0, width / 2.0) if count == 1 else (usable_width / 2.0, width - usable_width / 2.0)
        for centre in (first, last):
            for along in (0.0, length):
                for dz in (clearance, -depth):
                    limits.check_reach(tool_at(corner + centre * across[:2] + along * heading[:2], dz)[:3])
    for k, centre in enumerate(raster_offsets(width, usable_width, overlap)):
        a = corner + centre * across[:2]
        b = a + length * heading[:2]
        begin, finish = (a, b) if k % 2 == 0 else (b, a)
        above, pressed = tool_at(begin, clearance), tool_at(begin, -depth)
        move = "to_start" if k == 0 else "across"
        segments.append(Segment(move, above, slow if k == 0 else max(slow, speed), accel))
        segments.append(Segment("press", pressed, slow, accel))
        rolls.append(len(segments))
        segments.append(Segment("sweep", tool_at(finish, -depth), speed, accel))
        segments.append(Segment("lift", tool_at(finish, clearance), slow, accel))
        passes.append(RasterPass((float(begin[0]), float(begin[1])), (float(finish[0]), float(finish[1])),
                                 (centre - usable_width / 2.0, centre + usable_width / 2.0)))
    whole: tuple[np.ndarray, float, float, float] | None = None
    moves: tuple[Move, ...] = ()
    path_rolls: tuple[int, ...] = ()
    if profile != "ramp":
        rolled = [(segments[k - 1].target, segments[k].target) for k in rolls]
        radius = blend if profile == "blend" else 0.0
        whole = (raster_waypoints(rolled, depth + clearance, lead), speed, accel, radius)
        moves, path_rolls = _path_moves(rolled, above=depth + clearance, lead=lead, speed=speed, accel=accel,
                                        slow=slow, blend=radius)
    return SweepPlan(tuple(segments), tuple(rolls), tuple([length] * len(passes)), tuple(passes), profile, whole,
                     moves, path_rolls)


def raster_coverage(plan: SweepPlan, width: float, roll: int, fraction: float) -> float:
    """Percent of the raster's rectangle (`width` across) rolled over once roll `roll` (0-based) is
    `fraction` done; the passes are parallel strips, each rolled whole before the next."""
    if not plan.passes or width <= 0:
        return 100.0 * (roll + fraction) / max(len(plan.rolls), 1)
    covered, union = 0.0, []
    for k, raster_pass in enumerate(plan.passes[:roll + 1]):
        low, high = max(raster_pass.across[0], 0.0), min(raster_pass.across[1], width)
        new = max(high - low, 0.0) - sum(max(min(high, h) - max(low, lo), 0.0) for lo, h in union)
        covered += new * (fraction if k == roll else 1.0)
        union.append((low, high))
    return 100.0 * min(covered / width, 1.0)


def _horizontal(vector: ArrayLike, what: str) -> np.ndarray:
    v = np.asarray(vector, dtype=np.float64).reshape(-1)
    if v.shape != (3,) or not np.all(np.isfinite(v)):
        raise ArmLimitError(f"{what} must be 3 finite numbers, got {list(v)}")
    v = v - np.array([0.0, 0.0, v[2]])
    if np.linalg.norm(v) < 1e-9:
        raise ArmLimitError(f"{what} must have a horizontal component")
    return v / np.linalg.norm(v)


def plan_sweep(start_pose: ArrayLike, *, length: float, speed: float, accel: float, depth: float,
               direction: Sequence[float] = (1.0, 0.0, 0.0), approach_speed: float | None = None,
               retract: bool = True, clearance: float = 0.0, profile: str = "ramp", lead: float = 0.01,
               blend: float = 0.004) -> SweepPlan:
    """The moves of one sweep. `start_pose` is where the roller just touches the surface (z up); the
    roller approaches it from `clearance` above and lifts back to that height at the end. `profile`
    blend or constant: the roll as one path touching down and lifting off at speed (as `plan_raster`;
    it always lifts off)."""
    if profile not in SWEEP_PROFILES:
        raise ArmLimitError(f"sweep.profile must be one of {', '.join(SWEEP_PROFILES)}, got {profile!r}")
    if profile != "ramp" and not retract:
        raise ArmLimitError(f"sweep.profile {profile} lifts off while moving: it needs sweep.retract true")
    start = as_pose(start_pose)
    for name, value in (("length", length), ("depth", depth), ("clearance", clearance)):
        if not (math.isfinite(value) and value >= 0):
            raise ArmLimitError(f"sweep {name} must be a finite number >= 0, got {value}")
    heading = np.asarray(direction, dtype=np.float64).reshape(-1)
    if heading.shape != (3,) or not np.all(np.isfinite(heading)):
        raise ArmLimitError(f"sweep direction must be 3 finite numbers, got {list(direction)}")
    heading = heading - np.array([0.0, 0.0, heading[2]])  # roll along the surface, never into it
    if np.linalg.norm(heading) == 0:
        raise ArmLimitError("sweep direction must have a horizontal component")
    heading /= np.linalg.norm(heading)
    slow = min(speed, approach_speed) if approach_speed is not None else speed
    up = np.array([0.0, 0.0, 1.0, 0.0, 0.0, 0.0])
    pressed = start - depth * up
    end = pressed + np.concatenate([length * heading, np.zeros(3)])
    segments = [Segment("to_start", start + clearance * up, slow, accel), Segment("press", pressed, slow, accel),
                Segment("sweep", end, speed, accel)]
    if retract:
        segments.append(Segment("lift", end + (depth + clearance) * up, slow, accel))
    if profile == "ramp":
        return SweepPlan(tuple(segments), rolls=(2,), lengths=(float(length),))
    moves, rolls = _path_moves([(pressed, end)], above=depth + clearance, lead=lead, speed=speed, accel=accel,
                               slow=slow, blend=blend if profile == "blend" else 0.0)
    return SweepPlan(tuple(segments), rolls=(2,), lengths=(float(length),), profile=profile, path_moves=moves,
                     path_rolls=rolls)


def plan_duration(plan: SweepPlan, from_pose: ArrayLike | None = None) -> float:
    """Seconds the plan's moves take at their speeds and accelerations (trapezoid profiles, rest to rest,
    as the simulated arm moves; a UR blends nothing between our moves either; a path of `sweep.profile`
    blend/constant is one trapezoid over its waypoints' polyline), from `from_pose` (the arm's pose now),
    or from the first target when it is not known."""
    moves = plan.motion()[0]
    if not moves:
        return 0.0
    targets = np.array([move.target[:3] for move in moves])
    start = targets[0] if from_pose is None else as_pose(from_pose)[:3]
    distances = np.linalg.norm(np.diff(np.vstack([start, targets]), axis=0), axis=1)
    for k, move in enumerate(moves):   # a path's length is its polyline's (a blend only shortens it)
        if isinstance(move, PathSegment):
            distances[k] = float(np.linalg.norm(np.diff(move.waypoints[:, :3], axis=0), axis=1).sum())
    speeds = np.array([move.speed for move in moves])
    accels = np.array([move.accel for move in moves])
    # TrapezoidProfile's duration, vectorised: 2 v/a + (d - v^2/a)/v with v = min(v_max, sqrt(a d))
    peaks = np.minimum(speeds, np.sqrt(accels * distances))
    with np.errstate(divide="ignore", invalid="ignore"):
        cruise = np.where(peaks > 0, (distances - peaks**2 / accels) / peaks, 0.0)
    return float(np.sum(2.0 * peaks / accels + np.maximum(cruise, 0.0)))


@dataclass(frozen=True)
class SweepStatus:
    phase: SweepPhase
    segment: str | None
    roll_progress: float  # 0..1 of all the rolling (the passes of a raster, in order)
    message: str = ""
    roll: int | None = None   # the roll under way or last done (0-based), None before the first
    roll_fraction: float = 0.0   # how much of it is done


class SweepSequencer:
    """Drives an `Arm` through a `SweepPlan`, one `poll()` at a time, from the caller's (single) thread.

    Every segment is checked against the arm's limits before the first command is sent, so a sweep
    either starts whole or not at all. A fault stops the arm and ends the sweep in FAULT.
    """

    def __init__(self, arm: Arm) -> None:
        self.arm = arm
        self.plan: SweepPlan | None = None
        self._index = -1
        self._status = SweepStatus(SweepPhase.IDLE, None, 0.0)

    @property
    def status(self) -> SweepStatus:
        return self._status

    @property
    def active(self) -> bool:
        return self._status.phase in (SweepPhase.MOVING, SweepPhase.SWEEPING)

    def start(self, plan: SweepPlan) -> None:
        if self.active:
            raise ArmError("a sweep is already running")
        check_plan(self.arm.limits, plan)
        fault = self.arm.fault()
        if fault is not None:
            raise ArmError(f"arm faulted: {fault}")
        self.plan, self._index = plan, -1
        self._status = SweepStatus(SweepPhase.MOVING, None, 0.0)
        self._next_segment()
        if self._status.phase is SweepPhase.FAULT:   # the first command was refused: the sweep never started
            raise ArmError(self._status.message)

    def stop(self, message: str = "stopped on request") -> None:
        was_active = self.active
        self.arm.stop()
        if was_active:
            self._status = self._make_status(SweepPhase.STOPPED, self._status.segment, message)

    def clear(self) -> None:
        """Back to IDLE after a sweep that ended (done, stopped or faulted), e.g. once a fault is reset."""
        if not self.active:
            self._status = SweepStatus(SweepPhase.IDLE, None, 0.0)

    def poll(self) -> SweepStatus:
        """Advance through the plan; call regularly (e.g. at 50 Hz) while a sweep runs."""
        if not self.active:
            return self._status
        fault = self.arm.fault()
        if fault is not None:
            self.arm.stop()
            self._status = self._make_status(SweepPhase.FAULT, self._status.segment, fault)
            return self._status
        if not self.arm.is_moving():
            self._next_segment()
        else:
            self._status = self._make_status(self._status.phase, self._status.segment)
        return self._status

    def _next_segment(self) -> None:
        assert self.plan is not None
        self._index += 1
        moves, rolls = self.plan.motion()
        if self._index >= len(moves):
            self._status = SweepStatus(SweepPhase.DONE, None, 1.0, "sweep complete", len(rolls) - 1, 1.0)
            return
        segment = moves[self._index]
        phase = SweepPhase.SWEEPING if self.plan.roll_number(self._index) is not None else SweepPhase.MOVING
        try:
            if isinstance(segment, PathSegment):
                self.arm.move_path(segment.waypoints, segment.speed, segment.accel, segment.blend,
                                   asynchronous=True)
            else:
                self.arm.move_linear(segment.target, segment.speed, segment.accel, asynchronous=True)
        except Exception as exc:  # noqa: BLE001 - whatever failed (a refusal, a bug), the arm stops: FAULT
            try:
                self.arm.stop()
            finally:
                message = str(exc) if isinstance(exc, ArmError) else f"{type(exc).__name__}: {exc}"
                self._status = self._make_status(SweepPhase.FAULT, segment.name, " ".join(message.split()))
            return
        self._status = self._make_status(phase, segment.name)

    def _make_status(self, phase: SweepPhase, segment: str | None, message: str = "") -> SweepStatus:
        roll, fraction = self._roll_state()
        return SweepStatus(phase, segment, self._roll_progress(), message, roll, fraction)

    def _roll_state(self) -> tuple[int | None, float]:
        """(the roll under way or last done, its fraction done)."""
        if self.plan is None:
            return None, 0.0
        moves, rolls = self.plan.motion()
        done = [k for k, index in enumerate(rolls) if index <= self._index]
        if not done:
            return None, 0.0
        roll = done[-1]
        if rolls[roll] < self._index:
            return roll, 1.0
        progress = self.arm.progress()
        if not math.isfinite(progress):
            return roll, 0.0
        move = moves[rolls[roll]]
        if isinstance(move, PathSegment):
            return roll, move.roll_fraction(progress)
        return roll, min(max(progress, 0.0), 1.0)

    def _roll_progress(self) -> float:
        roll, fraction = self._roll_state()
        if self.plan is None or roll is None:
            return 0.0
        lengths = self.plan.lengths
        total = sum(lengths)
        if total <= 0:
            return (roll + fraction) / len(lengths)
        return min((sum(lengths[:roll]) + fraction * lengths[roll]) / total, 1.0)
