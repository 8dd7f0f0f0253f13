"""A small tap renderer: GelSight-style dents on the membrane, seen through a `CameraModel`.

Independent of the full simulator (`touchroller_driver.sim.render`): each dent is a Gaussian on the
membrane's (x, arc length) coordinates, shaded by three coloured lights, over a static background
with dust. Tests and benchmarks use it where they need taps at chosen pixels quickly.
"""
from __future__ import annotations

import dataclasses
import math
from collections.abc import Sequence

import numpy as np

from touchroller_perception.geometry import CameraModel


@dataclasses.dataclass(frozen=True)
class TapRendering:
    """Settings of the fallback tap renderer (a GelSight-style dent seen through the camera model)."""

    tip_radius: float = 1.5e-3    # m, Gaussian radius of the dent on the membrane
    amplitude: float = 45.0       # grey levels per unit of normalised slope
    lit_gain: float = 1.4         # the lit side changes more than the shaded side darkens
    shade_gain: float = 0.6
    noise_std: float = 2.0        # grey levels, sensor noise
    azimuths_deg: tuple[float, float, float] = (90.0, 210.0, 330.0)   # B, G, R lights on the membrane


class TapRenderer:
    """Renders taps for a truth camera: per-pixel membrane coordinates are computed once."""

    def __init__(self, camera: CameraModel, settings: TapRendering | None = None, seed: int = 0):
        self.camera = camera
        self.settings = settings or TapRendering()
        h, w = camera.height, camera.width
        vv, uu = np.mgrid[0:h, 0:w].astype(np.float64)
        points, valid = camera.back_project(np.stack([uu, vv], axis=-1))
        x, alpha = camera.surface_coords(points)
        self.x = np.where(valid, x, np.nan)
        self.s = np.where(valid, camera.radius * alpha, np.nan)      # arc length around the tube
        rng = np.random.default_rng(seed)
        shading = [110 + 35 * np.exp(-((uu - w / 2) ** 2 + (vv - h / 2) ** 2) / (2 * (0.45 * w) ** 2))
                   + 8 * np.sin(uu / 37.0 + c) for c in range(3)]
        background = np.stack(shading, axis=-1)
        specks = rng.random((h, w)) < 0.002                              # static dust on the membrane
        background[specks] -= 40.0
        self.background = np.where(valid[..., None], background, 20.0)

    def render(self, pixels: Sequence[Sequence[float]], rng: np.random.Generator) -> np.ndarray:
        """bgr8 frame with a dent centred on each of the given true pixel positions."""
        cfg = self.settings
        frame = self.background.copy()
        for u, v in pixels:
            centre, ok = self.camera.back_project(np.array([u, v], dtype=np.float64))
            if not ok:
                continue
            x0, a0 = self.camera.surface_coords(centre)
            dx = (self.x - x0) / cfg.tip_radius
            ds = (self.s - self.camera.radius * a0) / cfg.tip_radius
            with np.errstate(invalid="ignore"):
                dent = np.exp(-0.5 * (dx * dx + ds * ds))
            dent = np.nan_to_num(dent)
            gx, gs = -dx * dent, -ds * dent
            gx, gs = np.nan_to_num(gx), np.nan_to_num(gs)
            for c, azimuth in enumerate(np.deg2rad(cfg.azimuths_deg)):
                slope = cfg.amplitude * (math.cos(azimuth) * gx + math.sin(azimuth) * gs)
                frame[..., c] += np.where(slope > 0, cfg.lit_gain * slope, cfg.shade_gain * slope)
        frame += rng.normal(0.0, cfg.noise_std, frame.shape)
        return np.clip(np.rint(frame), 0, 255).astype(np.uint8)
