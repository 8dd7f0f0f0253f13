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
from touchroller_driver.sim.scene import load_scene
from touchroller_perception.height import (
    MAP_PHOTOMETRIC,
    BallPress,
    PhotometricCalibration,
    PressCalibrationConfig,
    calibrate_photometric,
    pixel_size_at,
)
from touchroller_perception.world_height import WorldHeightConfig

#: the calibration a world height map gets: the product's map model (`MAP_PHOTOMETRIC`: the image smoothed by
#: 1 px before the colour features, not the default 2; a map cell averages some twenty frames)
MAP_CALIBRATION = PressCalibrationConfig(model=MAP_PHOTOMETRIC)


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


def sim_photometric(sensor: SimulatedSensor, seed: int = 0, presses: int = 24,
                    config: PressCalibrationConfig | None = None, ball_radius: float | None = None,
                    press_depth: float | None = None, band_depth: float | None = None) -> SimPhotometric:
    """Calibrate the photometric model of a simulated sensor from `presses` ball presses (the
    `ball_presses` scene with its scene's camera and sensor), and render its reference.

    The presses land at random over the rows a press of `band_depth` reaches (default: the rows a world
    height map integrates, `WorldHeightConfig.band_depth`) and along the axis: the model learns how a slope
    looks where it was pressed, and its position terms do not extrapolate (pressed only near the contact
    line, the slopes of a scan's contact band away from that line read too gentle)."""
    scene = sensor.scene
    if presses < 4:
        raise ValueError(f"a photometric calibration needs at least 4 presses, got {presses}")
    depth = WorldHeightConfig().band_depth if band_depth is None else float(band_depth)
    radius = float(sensor.camera.radius)
    if not (math.isfinite(depth) and 0 < depth < radius):
        raise ValueError(f"band_depth must be in (0, the roller's radius {radius} m), got {depth}")
    overrides: dict[str, Any] = {"camera": dict(scene.data["camera"]), "sensor": dict(scene.data["sensor"]),
                                 "motion.presses": presses, "motion.alpha_span": math.acos(1.0 - depth / radius)}
    if ball_radius is not None:
        overrides["motion.ball_radius"] = ball_radius
    if press_depth is not None:
        overrides["motion.press_depth"] = press_depth
    balls = load_scene("ball_presses", **overrides)
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
