"""The scenes' own motions and their ground truth, frame by frame.

- `roll`: one linear roll of `motion.length` in `motion.duration` seconds (trapezoid velocity profile
  with `motion.accel`), at penetration `motion.depth`; frames at `fps` over [0, duration].
- `taps`: the paper's 3-stick solid (contact localisation). Three vertical sticks with spherical
  tips whose heights make them touch the roller at central angles 0, pi/12, pi/6 (placed from the
  front) or 0, -pi/12, -pi/6 (from the back), tapped at 1/4, 1/2, 3/4 of the roller's length.
- `hemispheres`: the 2x5 frame of 1 mm hemispheres pressed into the roller (extrinsic calibration).
- `chessboard`: a printed chessboard held in front of the bare camera (intrinsic calibration).
Reference frames with no contact come first where a detector needs them.
"""
from __future__ import annotations

import math
from collections.abc import Iterator
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any

import numpy as np

from touchroller_driver.motion import TrapezoidProfile

if TYPE_CHECKING:
    from touchroller_driver.sim.render import RollerState, SimulatedSensor
    from touchroller_driver.sim.scene import Scene

NO_CONTACT_DEPTH = -1.0e-2   # the roller held 10 mm above the surface


@dataclass
class Step:
    t: float
    state: RollerState | None
    truth: dict[str, Any] = field(default_factory=dict)
    board_pose: tuple[np.ndarray, np.ndarray] | None = None


def roll_profile(motion: dict[str, Any]) -> TrapezoidProfile:
    """The trapezoid move that covers `length` in exactly `duration` with acceleration `accel`."""
    length = float(motion.get("length", 0.11))
    duration = float(motion.get("duration", 10.0))
    accel = float(motion.get("accel", 0.05))
    if not (length > 0 and duration > 0 and accel > 0):
        raise ValueError("motion: length, duration and accel must be > 0")
    disc = (accel * duration) ** 2 - 4.0 * accel * length
    if disc < 0:
        raise ValueError(f"motion: {length} m cannot be covered in {duration} s with accel {accel} m/s^2 "
                         f"(needs at least {2 * math.sqrt(length / accel):.2f} s)")
    v_max = 0.5 * (accel * duration - math.sqrt(disc))
    return TrapezoidProfile(length, v_max, accel)


def roll_extent(scene: Scene) -> tuple[float, float, float]:
    """(travel at start, travel at end, x_along) of a roll scene (surface extent otherwise)."""
    m = scene.motion
    if m.get("kind") == "roll":
        direction = 1.0 if float(m.get("direction", 1)) >= 0 else -1.0
        length = float(m.get("length", 0.11))
        # rolling backwards starts at the far end of the surface unless told otherwise
        start = float(m["start"]) if m.get("start") is not None else (0.0 if direction > 0 else length)
        end = start + direction * length
        return start, end, float(m.get("x_along", 0.0))
    s = scene.surface
    return 0.0, float(s.get("length", 0.11)), 0.0


def scene_duration(scene: Scene) -> float:
    kind = scene.motion.get("kind")
    if kind == "roll":
        return float(scene.motion.get("duration", 10.0))
    return frame_count(scene) / scene.fps


def frame_count(scene: Scene) -> int:
    m = scene.motion
    kind = m.get("kind")
    if kind == "roll":
        return int(math.floor(float(m.get("duration", 10.0)) * scene.fps + 1e-9)) + 1
    ref = int(m.get("reference_frames", 5))
    if kind == "taps":
        taps = 2 * len(m.get("positions", [0.25, 0.5, 0.75])) * int(m.get("repeats", 3))
        return ref + taps * (int(m.get("hold_frames", 3)) + int(m.get("gap_frames", 2)))
    if kind == "hemispheres":
        return ref + int(m.get("presses", 10)) * (int(m.get("hold_frames", 1)) + int(m.get("gap_frames", 1)))
    if kind == "chessboard":
        return int(m.get("views", 20))
    if kind == "ball_presses":
        return ref + int(m.get("presses", 20)) * (int(m.get("hold_frames", 1)) + int(m.get("gap_frames", 1)))
    raise ValueError(f"unknown motion kind {kind!r}")


def timeline(scene: Scene, sensor: SimulatedSensor) -> Iterator[Step]:
    kind = scene.motion.get("kind")
    if kind == "roll":
        yield from _roll(scene)
    elif kind == "taps":
        yield from _taps(scene, sensor)
    elif kind == "hemispheres":
        yield from _hemispheres(scene, sensor)
    elif kind == "chessboard":
        yield from _chessboard(scene, sensor)
    elif kind == "ball_presses":
        yield from _ball_presses(scene, sensor)
    else:
        raise ValueError(f"unknown motion kind {kind!r}")


# --------------------------------------------------------------------------- roll
def _roll(scene: Scene) -> Iterator[Step]:
    from touchroller_driver.sim.render import RollerState

    m = scene.motion
    profile = roll_profile(m)
    start, _, x_along = roll_extent(scene)
    direction = 1.0 if float(m.get("direction", 1)) >= 0 else -1.0
    depth = float(m.get("depth", 5e-4))
    for k in range(frame_count(scene)):
        t = k / scene.fps
        travel = start + direction * float(profile.position(t))
        speed = direction * float(profile.velocity(t))
        yield Step(t, RollerState(x_along=x_along, travel=travel, depth=depth, speed=speed, t=t))


# --------------------------------------------------------------------------- taps (3-stick solid)
def stick_angles(side: int) -> list[float]:
    return [0.0, side * math.pi / 12.0, side * math.pi / 6.0]


def _idle(t: float) -> RollerState:
    from touchroller_driver.sim.render import RollerState

    return RollerState(depth=NO_CONTACT_DEPTH, t=t)


def _taps(scene: Scene, sensor: SimulatedSensor) -> Iterator[Step]:
    from touchroller_driver.sim.render import Indenter, RollerState

    m = scene.motion
    rng = sensor._rng_motion
    cam = sensor.camera
    tip = float(m.get("tip_radius", 1.0e-3))
    press = float(m.get("press_depth", 4.0e-4))
    press_jitter = float(m.get("press_jitter", 5.0e-5))
    positions = [float(p) for p in m.get("positions", [0.25, 0.5, 0.75])]
    hold, gap = int(m.get("hold_frames", 3)), int(m.get("gap_frames", 2))
    k = 0
    for _ in range(int(m.get("reference_frames", 5))):
        yield Step(k / scene.fps, _idle(k / scene.fps), {"contacts": [], "phase": "reference"})
        k += 1
    for repeat in range(int(m.get("repeats", 3))):
        for side in (1, -1):
            for fraction in positions:
                x = (fraction - 0.5) * cam.length
                indenters, contacts = [], []
                depth = press + float(rng.normal(0.0, press_jitter))
                for angle in stick_angles(side):
                    membrane = sensor.membrane_point(x, angle)
                    radius_here = float(np.hypot(membrane[1], membrane[2]))
                    centre_dist = radius_here + tip - depth
                    centre = (x, centre_dist * math.sin(angle), centre_dist * math.cos(angle))
                    indenters.append(Indenter(centre, tip))
                    uv, ok = cam.project(membrane)
                    contacts.append({
                        "point": [float(c) for c in membrane],
                        "pixel": [float(c) for c in uv] if bool(ok) else [math.nan, math.nan],
                        "x": x, "alpha": angle, "position_fraction": fraction, "side": side,
                        "penetration": depth,
                    })
                tap_truth = {"contacts": contacts, "phase": "tap", "repeat": repeat}
                for _ in range(hold):
                    t = k / scene.fps
                    yield Step(t, RollerState(depth=NO_CONTACT_DEPTH, t=t, indenters=tuple(indenters)), tap_truth)
                    k += 1
                for _ in range(gap):
                    yield Step(k / scene.fps, _idle(k / scene.fps), {"contacts": [], "phase": "gap"})
                    k += 1


# --------------------------------------------------------------------------- hemispheres (2x5 frame)
def hemisphere_layout(m: dict[str, Any]) -> np.ndarray:
    """Frame coordinates (10, 2) of the hemisphere centres: 5 along the axis x, 2 across (y)."""
    pitch_x = float(m.get("pitch_x", 1.0e-2))
    pitch_y = float(m.get("pitch_y", 8.0e-3))
    cols, rows = int(m.get("columns", 5)), int(m.get("rows", 2))
    xs = (np.arange(cols) - (cols - 1) / 2.0) * pitch_x
    ys = (np.arange(rows) - (rows - 1) / 2.0) * pitch_y
    return np.array([(x, y) for y in ys for x in xs])


def _hemispheres(scene: Scene, sensor: SimulatedSensor) -> Iterator[Step]:
    from touchroller_driver.sim.render import Indenter, RollerState

    m = scene.motion
    rng = sensor._rng_motion
    cam = sensor.camera
    radius = float(m.get("hemisphere_radius", 1.0e-3))
    press = float(m.get("press_depth", 5.0e-4))
    shift = float(m.get("pose_jitter", 1.5e-3))
    yaw_jitter = math.radians(float(m.get("yaw_jitter_deg", 2.0)))
    layout = hemisphere_layout(m)
    hold, gap = int(m.get("hold_frames", 1)), int(m.get("gap_frames", 1))
    k = 0
    for _ in range(int(m.get("reference_frames", 5))):
        yield Step(k / scene.fps, _idle(k / scene.fps), {"contacts": [], "phase": "reference"})
        k += 1
    for press_index in range(int(m.get("presses", 10))):
        ox, oy = (rng.uniform(-shift, shift, size=2) if press_index else (0.0, 0.0))
        yaw = float(rng.uniform(-yaw_jitter, yaw_jitter)) if press_index else 0.0
        depth = press + (float(rng.uniform(-1e-4, 1e-4)) if press_index else 0.0)
        c, s = math.cos(yaw), math.sin(yaw)
        plate_z = cam.radius + radius - depth    # the hemispheres' centres lie on the plate
        indenters, contacts = [], []
        for fx_, fy_ in layout:
            x = ox + c * fx_ - s * fy_
            y = oy + s * fx_ + c * fy_
            alpha = math.atan2(y, plate_z)
            membrane = sensor.membrane_point(x, alpha)
            indenters.append(Indenter((x, y, plate_z), radius))
            uv, ok = cam.project(membrane)
            contacts.append({
                "point": [float(v) for v in membrane],
                "pixel": [float(v) for v in uv] if bool(ok) else [math.nan, math.nan],
                "x": x, "alpha": alpha, "frame_xy": [float(fx_), float(fy_)],
                "penetration": float(np.hypot(membrane[1], membrane[2]) + radius - math.hypot(y, plate_z)),
            })
        truth = {"contacts": contacts, "phase": "press",
                 "frame_pose": {"x": float(ox), "y": float(oy), "yaw": yaw, "plate_z": plate_z}}
        for _ in range(hold):
            t = k / scene.fps
            yield Step(t, RollerState(depth=NO_CONTACT_DEPTH, t=t, indenters=tuple(indenters)), truth)
            k += 1
        for _ in range(gap):
            yield Step(k / scene.fps, _idle(k / scene.fps), {"contacts": [], "phase": "gap"})
            k += 1


# --------------------------------------------------------------------------- ball presses (photometric calibration)
def _ball_presses(scene: Scene, sensor: SimulatedSensor) -> Iterator[Step]:
    """One ball of known radius pressed at random places of the contact band (docs/height.md). Truth per
    press: the contact centre's pixel and a label radius in pixels (the flat-contact radius
    sqrt(d (2 R - d)) over the pixel size there), as a hand label would give them."""
    from touchroller_driver.sim.render import Indenter, RollerState

    m = scene.motion
    rng = sensor._rng_motion
    cam = sensor.camera
    radius = float(m.get("ball_radius", 2.0e-3))
    press = float(m.get("press_depth", 3.0e-4))
    jitter = float(m.get("press_jitter", 5.0e-5))
    x_span = float(m.get("x_span", 0.8)) * 0.5 * cam.length
    alpha_span = float(m.get("alpha_span", 0.04))
    hold, gap = int(m.get("hold_frames", 1)), int(m.get("gap_frames", 1))
    k = 0
    for _ in range(int(m.get("reference_frames", 5))):
        yield Step(k / scene.fps, _idle(k / scene.fps), {"contacts": [], "phase": "reference"})
        k += 1
    count = int(m.get("presses", 20))
    placement = str(m.get("placement", "random"))
    if placement == "random":
        places = [(float(rng.uniform(-x_span, x_span)), float(rng.uniform(-alpha_span, alpha_span)))
                  for _ in range(count)]
    elif placement == "stratified":
        places = stratified_places(count, x_span, alpha_span, alpha_span * float(cam.radius), rng)
    else:
        raise ValueError(f"ball_presses: placement must be random or stratified, got {placement!r}")
    for x, alpha in places:
        depth = press + float(rng.uniform(-jitter, jitter))
        membrane = sensor.membrane_point(x, alpha)
        dist = float(np.hypot(membrane[1], membrane[2])) + radius - depth
        centre = (x, dist * math.sin(alpha), dist * math.cos(alpha))
        uv, ok = cam.project(membrane)
        step_uv, _ = cam.project(sensor.membrane_point(x + 1e-4, alpha))
        px_per_m = float(np.hypot(*(step_uv - uv))) / 1e-4
        contact = math.sqrt(max(depth * (2 * radius - depth), 0.0))
        truth = {"contacts": [{"point": [float(c) for c in membrane],
                               "pixel": [float(c) for c in uv] if bool(ok) else [math.nan, math.nan],
                               "radius_px": contact * px_per_m, "x": x, "alpha": alpha, "penetration": depth,
                               "ball_radius": radius}], "phase": "press"}
        for _ in range(hold):
            t = k / scene.fps
            yield Step(t, RollerState(depth=NO_CONTACT_DEPTH, t=t, indenters=(Indenter(centre, radius),)), truth)
            k += 1
        for _ in range(gap):
            yield Step(k / scene.fps, _idle(k / scene.fps), {"contacts": [], "phase": "gap"})
            k += 1


def stratified_places(count: int, x_span: float, alpha_span: float, across: float,
                      rng: np.random.Generator) -> list[tuple[float, float]]:
    """`count` (x, alpha) press places spread evenly over x in [-x_span, x_span] and alpha in
    [-alpha_span, alpha_span] (`across`: that half span in metres on the membrane): rows across the band,
    as many as keep the cells about square, each row's presses in equal strata along x, each place uniform
    within its cell. Every part of the band gets its share of
    presses whatever the draw, where independent uniform places leave holes and clumps."""
    if count < 1:
        return []
    rows = int(np.clip(round(math.sqrt(count * across / max(x_span, 1e-12))), 1, count))
    per_row = [count // rows + (1 if j < count % rows else 0) for j in range(rows)]
    places = []
    for j, n in enumerate(per_row):
        for i in range(n):
            fx = (i + float(rng.uniform(0.0, 1.0))) / n
            fa = (j + float(rng.uniform(0.0, 1.0))) / rows
            places.append(((2.0 * fx - 1.0) * x_span, (2.0 * fa - 1.0) * alpha_span))
    return places


# --------------------------------------------------------------------------- chessboard
def _chessboard(scene: Scene, sensor: SimulatedSensor) -> Iterator[Step]:
    board = sensor._board
    for k, (rvec, tvec) in enumerate(board.poses(frame_count(scene), sensor._rng_motion)):
        corners = board.corner_pixels(rvec, tvec)
        truth = {"board": {"rvec": [float(v) for v in rvec], "tvec": [float(v) for v in tvec],
                           "corners_px": corners.tolist()}}
        yield Step(k / scene.fps, None, truth, board_pose=(rvec, tvec))
