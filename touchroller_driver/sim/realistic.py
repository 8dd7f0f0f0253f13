"""A realistic appearance for simulated presses, calibrated from a real sensor's frames.

The simulator's own shading (`render.py`) is ideal: a Lambertian membrane under three coloured
lights, a synthetic background and white noise. A real GelSight-style sensor differs in all three:
its colour response to a slope is neither linear nor symmetric and saturates, its background is an
uneven LED field with texture, and its noise is correlated between neighbouring pixels (demosaicing,
compression). `fit_appearance` measures the three on real frames of ball presses with known centres
and radii (e.g. the `taxim` wheel's calibration data):

* **press shape**: the slope of a ball pressed into the membrane, in units of the contact radius R:
  a spherical cap of radius `ball_ratio` x R inside the contact, and outside it a Gaussian fall-off of
  width `halo` x R (the membrane's halo); both chosen by least squares on the frames;
* **colour response**: per channel, a cubic polynomial in the two slope components, fitted by least
  squares on every pixel within 2.5 R of the presses (`response`, grey levels);
* **illumination field**: the real no-contact frame itself is the background;
* **noise**: per-channel standard deviation and correlation length of the frame-to-frame difference
  far from the presses (white noise blurred by a Gaussian of `noise_correlation_px`).

`RealisticPressRenderer` renders presses with that appearance and `IdealPressRenderer` with the
simulator's default Lambert shading, on the same press shape, so the two can be compared with the
real frames at the same place and radius.
"""
from __future__ import annotations

import dataclasses
import math
from collections.abc import Sequence

import cv2
import numpy as np

REACH = 2.5                        # fit and compare within this many contact radii of the centre
BALL_RATIOS = (1.1, 1.3, 1.6, 2.0, 3.0)
HALOS = (0.2, 0.35, 0.5, 0.8)


@dataclasses.dataclass(frozen=True)
class PressShape:
    """Slope profile of a ball press in units of the contact radius (1 at the contact's edge)."""

    ball_ratio: float = 3.0        # ball radius / contact radius (> 1)
    halo: float = 0.35             # width of the fall-off outside the contact / contact radius

    def slopes(self, shape: tuple[int, int], centre: Sequence[float], radius: float,
               origin: tuple[int, int] = (0, 0)) -> tuple[np.ndarray, ...]:
        """(slope along u, slope along v, distance / radius) on a `shape` (h, w) window whose top-left
        pixel is `origin` (u, v) in the image; outward positive."""
        h, w = shape
        yy, xx = np.mgrid[origin[1]:origin[1] + h, origin[0]:origin[0] + w].astype(np.float32)
        dx, dy = (xx - float(centre[0])) / radius, (yy - float(centre[1])) / radius
        r = np.sqrt(dx * dx + dy * dy) + np.float32(1e-6)
        rho2 = self.ball_ratio ** 2
        edge = 1.0 / math.sqrt(rho2 - 1.0)
        inside = r / np.sqrt(np.maximum(rho2 - r * r, 1e-6))
        outside = edge * np.exp(-((r - 1.0) ** 2) / (2.0 * self.halo ** 2))
        magnitude = np.where(r < 1.0, inside, outside) / edge
        return magnitude * dx / r, magnitude * dy / r, r

    @property
    def edge_slope(self) -> float:
        """The physical slope at the contact's edge (the unit of `slopes`)."""
        return 1.0 / math.sqrt(self.ball_ratio ** 2 - 1.0)


def _features(gx: np.ndarray, gy: np.ndarray) -> np.ndarray:
    """Cubic terms of the slope (no constant: no slope, no change)."""
    return np.stack([gx, gy, gx * gx, gx * gy, gy * gy, gx ** 3, gy ** 3, gx * gx * gy, gx * gy * gy], axis=-1)


@dataclasses.dataclass(frozen=True)
class RealAppearance:
    """What a real sensor's frames look like, fitted by `fit_appearance`."""

    background: np.ndarray         # HxWx3 float32, the no-contact frame
    shape: PressShape
    response: np.ndarray           # (9, 3): grey-level change per channel = _features(slope) @ response
    noise_std: np.ndarray          # (3,) per-frame noise std, grey levels
    noise_correlation_px: float    # Gaussian correlation length of the noise
    fit_rms: float                 # residual of the response fit, grey levels
    centres: np.ndarray | None = None   # (n, 2) the fitted presses' centres after refinement (None: as given)

    def change(self, centre: Sequence[float], radius: float) -> np.ndarray:
        """The colour change (HxWx3 float32) a press at `centre` with contact `radius` makes (zero
        beyond 2.5 contact radii)."""
        out = np.zeros(self.background.shape, np.float32)
        (u0, v0, u1, v1) = press_box(self.background.shape[:2], centre, radius)
        gx, gy, r = self.shape.slopes((v1 - v0, u1 - u0), centre, radius, (u0, v0))
        out[v0:v1, u0:u1] = (_features(gx, gy) @ self.response.astype(np.float32)) * (r < REACH)[..., None]
        return out


def press_box(shape: tuple[int, int], centre: Sequence[float], radius: float) -> tuple[int, int, int, int]:
    """The image box (u0, v0, u1, v1) within REACH contact radii of the centre."""
    h, w = shape
    reach = REACH * radius + 1
    return (max(0, int(centre[0] - reach)), max(0, int(centre[1] - reach)),
            min(w, int(centre[0] + reach) + 1), min(h, int(centre[1] + reach) + 1))


def fit_appearance(background: np.ndarray, presses: np.ndarray, centres: np.ndarray, radii: np.ndarray,
                   indices: Sequence[int] | None = None, refine_rounds: int = 0) -> RealAppearance:
    """Fits press shape, colour response and noise to real frames of presses with known centres and radii.

    With `refine_rounds` > 0 the centres are only a start: each round fits the appearance, then moves
    each press's centre to where that appearance explains its frame best (`refine_centres`), and the
    last fit uses the moved centres (`RealAppearance.centres`). Hand-placed centres are off by a few
    pixels; a response fitted around them learns their offset as part of the sensor's colour
    response (a press rendered with it is then not centred on its own centre).
    """
    order = list(range(len(presses))) if indices is None else list(indices)
    if not order:
        raise ValueError("fit_appearance needs at least one press")
    base = np.asarray(background, np.float32)
    current = np.array(centres, np.float64, copy=True)
    for round_ in range(refine_rounds + 1):
        rms, shape, response = _fit_shape_and_response(base, presses, current, radii, order)
        if round_ == refine_rounds:
            break
        moved = refine_centres(base, presses, current, radii, order, shape, response)
        if np.max(np.abs(moved[order] - current[order])) < 0.05:
            current = moved
            rms, shape, response = _fit_shape_and_response(base, presses, current, radii, order)
            break
        current = moved
    std, correlation = _fit_noise(base, presses, current, radii, order)
    return RealAppearance(base, shape, response.astype(np.float32), std, correlation, rms,
                          current[order] if refine_rounds > 0 else None)


def _fit_shape_and_response(background: np.ndarray, presses: np.ndarray, centres: np.ndarray, radii: np.ndarray,
                            order: Sequence[int]) -> tuple[float, PressShape, np.ndarray]:
    best: tuple[float, PressShape, np.ndarray] | None = None
    for ball_ratio in BALL_RATIOS:
        for halo in HALOS:
            shape = PressShape(ball_ratio, halo)
            response, rms = _fit_response(background, presses, centres, radii, order, shape)
            if best is None or rms < best[0]:
                best = (rms, shape, response)
    assert best is not None
    return best


def press_residual(background: np.ndarray, frame: np.ndarray, centre: Sequence[float], radius: float,
                   shape: PressShape, response: np.ndarray) -> float:
    """RMS difference (grey levels) between a frame's change and the model's press at `centre`, within
    REACH contact radii (every other row and column)."""
    u0, v0, u1, v1 = press_box(background.shape[:2], centre, radius)
    gx, gy, r = shape.slopes((v1 - v0, u1 - u0), centre, radius, (u0, v0))
    near = r < REACH
    near[1::2] = False
    near[:, 1::2] = False
    real = np.asarray(frame[v0:v1, u0:u1], np.float32)[near] - background[v0:v1, u0:u1][near]
    model = _features(gx[near], gy[near]) @ np.asarray(response, np.float32)
    return float(np.sqrt(np.mean((model - real) ** 2)))


def refine_centres(background: np.ndarray, presses: np.ndarray, centres: np.ndarray, radii: np.ndarray,
                   indices: Sequence[int], shape: PressShape, response: np.ndarray,
                   step: float = 4.0, finest: float = 0.25) -> np.ndarray:
    """Each press's centre (of `indices`) moved to where the model's press best explains its frame.

    Compass search from the given centre: try a step along +-u and +-v, move while the residual
    (`press_residual`) drops, halve the step when it does not, down to `finest` px. The radius stays.
    Returns a copy of `centres` with the moved ones.
    """
    base = np.asarray(background, np.float32)
    out = np.array(centres, np.float64, copy=True)
    for i in indices:
        radius = float(radii[i])
        centre = out[i].copy()
        best = press_residual(base, presses[i], centre, radius, shape, response)
        size = step
        while size >= finest:
            moved = False
            for du, dv in ((size, 0.0), (-size, 0.0), (0.0, size), (0.0, -size)):
                trial = centre + (du, dv)
                error = press_residual(base, presses[i], trial, radius, shape, response)
                if error < best:
                    best, centre, moved = error, trial, True
                    break
            if not moved:
                size /= 2.0
        out[i] = centre
    return out


def _fit_response(background: np.ndarray, presses: np.ndarray, centres: np.ndarray, radii: np.ndarray,
                  order: Sequence[int], shape: PressShape) -> tuple[np.ndarray, float]:
    rows, targets = [], []
    for i in order:
        u0, v0, u1, v1 = press_box(background.shape[:2], centres[i], float(radii[i]))
        gx, gy, r = shape.slopes((v1 - v0, u1 - u0), centres[i], float(radii[i]), (u0, v0))
        near = r < REACH
        near[1::2] = False        # every other row: a quarter of the pixels fits as well, 4x sooner
        near[:, 1::2] = False
        rows.append(_features(gx[near], gy[near]))
        targets.append(np.asarray(presses[i][v0:v1, u0:u1], np.float32)[near] - background[v0:v1, u0:u1][near])
    x = np.concatenate(rows).astype(np.float64)
    y = np.concatenate(targets).astype(np.float64)
    response, *_ = np.linalg.lstsq(x, y, rcond=None)
    return response, float(np.sqrt(np.mean((x @ response - y) ** 2)))


def _fit_noise(background: np.ndarray, presses: np.ndarray, centres: np.ndarray, radii: np.ndarray,
               order: Sequence[int]) -> tuple[np.ndarray, float]:
    """Per-frame noise std and correlation length, from the difference to the background far from the press."""
    h, w = background.shape[:2]
    yy, xx = np.mgrid[0:h, 0:w]
    residuals, lag_products, powers = [], [], []
    for i in order:
        diff = np.asarray(presses[i], np.float32) - background
        fine = diff - cv2.GaussianBlur(diff, (0, 0), 8.0)          # shading and the halo's slow parts out
        far = np.hypot(xx - centres[i][0], yy - centres[i][1]) > 4.0 * radii[i]
        far[:16], far[-16:], far[:, :16], far[:, -16:] = False, False, False, False
        residuals.append(fine[far])
        lag = far[:, :-1] & far[:, 1:]
        lag_products.append((fine[:, :-1] * fine[:, 1:])[lag])
        powers.append((fine[:, :-1] ** 2)[lag])
    residual = np.concatenate(residuals)
    # robust std of the difference of two frames -> of one frame
    spread = 1.4826 * np.median(np.abs(residual - np.median(residual, axis=0)), axis=0) / math.sqrt(2.0)
    correlation = float(np.sum(np.concatenate(lag_products)) / max(np.sum(np.concatenate(powers)), 1e-12))
    # white noise blurred by a Gaussian of sigma s has lag-1 correlation exp(-1 / (4 s^2))
    length = math.sqrt(-1.0 / (4.0 * math.log(min(max(correlation, 1e-3), 0.999)))) if correlation > 0.02 else 0.0
    return spread.astype(np.float32), length


def correlated_noise(shape: tuple[int, int, int], std: np.ndarray, length: float,
                     rng: np.random.Generator) -> np.ndarray:
    """Gaussian noise of per-channel `std` whose neighbours correlate as white noise blurred by `length` px."""
    noise = rng.standard_normal(shape).astype(np.float32)
    if length > 0.3:
        noise = np.atleast_3d(cv2.GaussianBlur(noise, (0, 0), length))
        noise /= max(float(noise.std()), 1e-6)
    return noise * np.asarray(std, np.float32)


class RealisticPressRenderer:
    """Ball presses rendered with a real sensor's fitted appearance (background, colour response, noise)."""

    def __init__(self, appearance: RealAppearance):
        self.appearance = appearance

    @property
    def background(self) -> np.ndarray:
        return np.clip(np.rint(self.appearance.background), 0, 255).astype(np.uint8)

    def change(self, centre: Sequence[float], radius: float) -> np.ndarray:
        return self.appearance.change(centre, radius)

    def render(self, presses: Sequence[tuple[float, float, float]], rng: np.random.Generator | None) -> np.ndarray:
        """bgr8 frame with a press per (u, v, contact radius); rng None renders without noise."""
        a = self.appearance
        frame = a.background.copy()
        for u, v, radius in presses:
            frame += self.change((u, v), radius)
        if rng is not None:
            frame += correlated_noise(frame.shape, a.noise_std, a.noise_correlation_px, rng)
        return np.clip(np.rint(frame), 0, 255).astype(np.uint8)


class IdealPressRenderer:
    """The same ball presses with the simulator's default ideal appearance: a Lambertian membrane under
    three coloured lights (the scene's `sensor` settings), a flat background and white noise."""

    def __init__(self, shape: tuple[int, int], press_shape: PressShape, noise_std: float = 2.0):
        from touchroller_driver.sim.scene import load_scene

        sensor = load_scene("contact_localisation").sensor
        elevation = math.radians(float(sensor["light_elevation_deg"]))
        self.lights = [(math.cos(elevation) * math.cos(math.radians(a)),
                        math.cos(elevation) * math.sin(math.radians(a)),
                        math.sin(elevation)) for a in sensor["light_azimuths_deg"]]
        self.scale = 255.0 * float(sensor["exposure_scale"])
        self.ambient, self.gain = float(sensor["ambient"]), float(sensor["light_gain"])
        self.size = shape
        self.press_shape = press_shape
        self.noise_std = noise_std
        flat = [self._shade(np.zeros(shape, np.float32), np.zeros(shape, np.float32), light) for light in self.lights]
        self.flat = np.stack(flat, axis=-1)

    @property
    def background(self) -> np.ndarray:
        return np.clip(np.rint(self.flat), 0, 255).astype(np.uint8)

    def _shade(self, gx: np.ndarray, gy: np.ndarray, light: tuple[float, float, float]) -> np.ndarray:
        # the membrane's height falls outward from the press: its surface slopes are minus the profile's
        inv = 1.0 / np.sqrt(1.0 + gx * gx + gy * gy)
        dot = np.maximum((gx * light[0] + gy * light[1] + light[2]) * inv, 0.0)
        return (self.scale * (self.ambient + self.gain * dot)).astype(np.float32)

    def change(self, centre: Sequence[float], radius: float) -> np.ndarray:
        out = np.zeros(self.flat.shape, np.float32)
        (u0, v0, u1, v1) = press_box(self.size, centre, radius)
        gx, gy, r = self.press_shape.slopes((v1 - v0, u1 - u0), centre, radius, (u0, v0))
        edge = self.press_shape.edge_slope
        shaded = np.stack([self._shade(gx * edge, gy * edge, light) for light in self.lights], axis=-1)
        out[v0:v1, u0:u1] = (shaded - self.flat[v0:v1, u0:u1]) * (r < REACH)[..., None]
        return out

    def render(self, presses: Sequence[tuple[float, float, float]], rng: np.random.Generator | None) -> np.ndarray:
        frame = self.flat.copy()
        for u, v, radius in presses:
            frame += self.change((u, v), radius)
        if rng is not None:
            frame += rng.normal(0.0, self.noise_std, frame.shape).astype(np.float32)
        return np.clip(np.rint(frame), 0, 255).astype(np.uint8)
