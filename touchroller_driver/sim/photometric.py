"""A photometric model of a simulated sensor, made on the fly as a user would make one of theirs.

The simulator knows its own shading, but a height map made from it must go the way a real one goes:
the scene's sensor (same camera, same lights, same gel) presses a ball of known radius in the
`ball_presses` scene, and those presses are calibrated (`touchroller_perception.height`), each labelled
from the scene's truth; the no-contact reference is the scene's own sensor held off the surface (the
median of a few frames: its noise averaged). Made on the fly rather than shipped as a file: a file would
hold for one camera and one light set only, and a scene may change either.
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np

from touchroller_driver.sim.render import RollerState, SimulatedSensor
from touchroller_driver.sim.scenarios import NO_CONTACT_DEPTH
from touchroller_driver.sim.scene import Scene, load_scene
from touchroller_perception.height import (
    MAP_CALIBRATION,
    BallPress,
    PhotometricCalibration,
    PressCalibrationConfig,
    calibrate_photometric,
    pixel_size_at,
)
from touchroller_perception.world_height import WorldHeightConfig


@dataclass(frozen=True)
class SimPhotometric:
    """The calibration (its model and per-press fit) and the no-contact reference of the scene's sensor."""

    calibration: PhotometricCalibration
    reference: np.ndarray


def no_contact_reference(sensor: SimulatedSensor, frames: int = 5) -> np.ndarray:
    """The sensor's no-contact frame: the median of `frames` renders held off the surface (bgr8)."""
    state = RollerState(depth=NO_CONTACT_DEPTH)
    stack = np.stack([sensor.render(state, frame=k) for k in range(max(frames, 1))])
    return np.median(stack, axis=0).astype(np.uint8)


def in_view_span(sensor: SimulatedSensor, alpha_span: float = 0.0, samples: int = 401) -> float:
    """The part of the roller's length the camera sees over the rows within `alpha_span` (rad) of the contact
    line, as the `ball_presses` scene's `x_span` (a fraction of the length, centred): presses beyond it are
    out of view and lost."""
    cam = sensor.camera
    half = 0.5 * float(cam.length)
    xs = np.linspace(-half, half, samples)
    seen = np.ones(samples, bool)
    for alpha in np.linspace(-alpha_span, alpha_span, 5):
        for k, x in enumerate(xs):
            uv, ok = cam.project(sensor.membrane_point(float(x), float(alpha)))
            seen[k] &= (bool(ok) and bool(np.isfinite(uv).all()) and 0.0 <= float(uv[0]) < cam.width
                        and 0.0 <= float(uv[1]) < cam.height)
    inside = xs[seen]
    if inside.size == 0:
        raise ValueError("the camera does not see the roller's contact band")
    return float(min(-inside.min(), inside.max(), half) / half)


def ball_press_scene(sensor: SimulatedSensor, presses: int = 24, ball_radius: float | None = None,
                     press_depth: float | None = None, band_depth: float | None = None,
                     placement: str = "stratified") -> Scene:
    """The `ball_presses` scene with `sensor`'s camera and sensor: `presses` presses over the rows a press of
    `band_depth` reaches (default: the rows a world height map integrates, `WorldHeightConfig.band_depth`)
    and along the part of the axis the camera sees (`in_view_span`), placed `placement` (`stratified`:
    evenly over that band whatever the draw; `random`: independent uniform places)."""
    if presses < 4:
        raise ValueError(f"a photometric calibration needs at least 4 presses, got {presses}")
    depth = WorldHeightConfig().band_depth if band_depth is None else float(band_depth)
    radius = float(sensor.camera.radius)
    if not (math.isfinite(depth) and 0 < depth < radius):
        raise ValueError(f"band_depth must be in (0, the roller's radius {radius} m), got {depth}")
    alpha_span = math.acos(1.0 - depth / radius)
    scene = sensor.scene
    overrides: dict[str, Any] = {"camera": dict(scene.data["camera"]), "sensor": dict(scene.data["sensor"]),
                                 "motion.presses": presses, "motion.alpha_span": alpha_span,
                                 "motion.placement": placement, "motion.x_span": in_view_span(sensor, alpha_span)}
    if ball_radius is not None:
        overrides["motion.ball_radius"] = ball_radius
    if press_depth is not None:
        overrides["motion.press_depth"] = press_depth
    return load_scene("ball_presses", **overrides)


def sim_photometric(sensor: SimulatedSensor, seed: int = 0, presses: int = 24,
                    config: PressCalibrationConfig | None = None, ball_radius: float | None = None,
                    press_depth: float | None = None, band_depth: float | None = None,
                    placement: str = "stratified") -> SimPhotometric:
    """Calibrate the photometric model of a simulated sensor from `presses` ball presses (`ball_press_scene`:
    the `ball_presses` scene with its scene's camera and sensor), and render its reference.

    The presses land evenly over the rows a press of `band_depth` reaches and along the axis: the model
    learns how a slope looks where it was pressed, and its position terms do not extrapolate (pressed only
    near the contact line, the slopes of a scan's contact band away from that line read too gentle). The
    default calibration (`MAP_CALIBRATION`) chooses the model's position degree on held-out presses."""
    balls = ball_press_scene(sensor, presses, ball_radius, press_depth, band_depth, placement)
    press_sensor = SimulatedSensor(balls, seed=seed + 1)
    camera = press_sensor.camera
    refs: list[np.ndarray] = []
    items: list[BallPress] = []
    ball = 0.0
    for frame in press_sensor.frames():
        phase = frame.truth.get("phase")
        if phase == "reference":
            refs.append(frame.image)
        elif phase == "press":
            contact = frame.truth["contacts"][0]
            u, v = contact["pixel"]
            if not (np.isfinite(u) and np.isfinite(v) and 0 <= u < camera.width and 0 <= v < camera.height):
                continue   # pressed out of view
            ball = float(contact["ball_radius"])
            items.append(BallPress(frame.image, float(u), float(v), float(contact["radius_px"]),
                                   pixel_size_at(camera, u, v), str(len(items)), float(camera.radius)))
    if len(items) < 4:
        raise ValueError("too few ball presses in view to calibrate the simulated sensor")
    reference = np.median(np.stack(refs), axis=0).astype(np.uint8)
    calibration = calibrate_photometric(items, reference, ball, config or MAP_CALIBRATION)
    return SimPhotometric(calibration, no_contact_reference(sensor))
