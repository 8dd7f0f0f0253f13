"""The second generator's camera: what the camera on the roller's axis sees of the contact strip.

Band model. The camera (the project's contract, docs/design.md: a pinhole at the cylinder frame's origin
turned by `theta` about x and moved `d` along z; here with the parameters of config/touchroller.yaml)
looks at the membrane, a cylinder of radius r. Each pixel's ray meets the undeformed membrane at
(X, Y, Z); the ground under that point lies at z_g = r - depth + h - s(X, Y) in the cylinder frame
(z down; h the roller's height above its pressed height, s the surface's height at the base point the
point lies over). The membrane is the smooth minimum of the circle and the ground (a soft contact of
scale `contact_softness`): pressed flat against the surface and its relief in the strip where the ground
reaches it (|Y| < sqrt(2 r depth) at rest), the undeformed tube elsewhere. The elastomer low-passes it
(`gel_blur`).

Shading: three coloured point-like LEDs inside the tube (directions fixed in the cylinder frame)
light the membrane's inner face; each contributes Lambert + a Blinn-Phong highlight seen from the
camera. A pixel is the mean irradiance over its footprint: the membrane is shaded at `pixel_samples` x
`pixel_samples` points inside each pixel, its slopes from differences between points 1 / `pixel_samples`
px apart, and the irradiance averaged over the pixel (slopes taken by central differences between the
pixel centres would span two pixels and low-pass the relief's slopes well beyond what the pixel and the
gel do: at a 4-pixel wavelength they keep 0.64 of its slope, a pixel's footprint 0.90). Then a static
flat field (cos^4 vignetting, an LED falloff along the axis, dust specks on the
gel), and a sensor: Poisson-Gaussian noise (photo-electrons of `electrons_per_level`, read noise), a
row-wise offset noise, 8-bit quantisation. Motion blur: the frame is the mean of `exposure_samples`
renders across the exposure.

Nothing here uses the simulator or `CameraModel`: rays, intersections and shading are written out here.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numpy as np

from bench.raster_generator.surfaces import Surface


@dataclass(frozen=True)
class Camera:
    """The camera contract's parameters (docs/design.md), read from a params file by `load_camera`."""

    fx: float = 500.0
    fy: float = 500.0
    cx: float = 319.5
    cy: float = 239.5
    width: int = 640
    height: int = 480
    theta: float = 0.0
    d: float = 0.0
    radius: float = 0.05
    mount_xyz: tuple[float, float, float] = (0.0, 0.0, 0.1)
    mount_rpy: tuple[float, float, float] = (0.0, 0.0, -math.pi / 2)


def load_camera(path: str) -> Camera:
    """The camera and mount of a ROS 2 params file (`/**: ros__parameters:` as config/touchroller.yaml)."""
    import yaml

    with open(path, encoding="utf-8") as handle:
        data = yaml.safe_load(handle)
    params = next(iter(data.values()))["ros__parameters"]
    distortion = params.get("camera.distortion", [0.0] * 5)
    if any(abs(float(v)) > 0 for v in distortion):
        raise ValueError("the second generator renders an undistorted pinhole only")
    return Camera(fx=float(params["camera.fx"]), fy=float(params["camera.fy"]), cx=float(params["camera.cx"]),
                  cy=float(params["camera.cy"]), width=int(params.get("camera.width", 640)),
                  height=int(params.get("camera.height", 480)), theta=float(params["extrinsics.theta"]),
                  d=float(params["extrinsics.d"]), radius=float(params["cylinder.radius"]),
                  mount_xyz=tuple(float(v) for v in params["mount.xyz"]),           # type: ignore[arg-type]
                  mount_rpy=tuple(float(v) for v in params["mount.rpy"]))           # type: ignore[arg-type]


@dataclass(frozen=True)
class Look:
    """Lights (azimuth in the membrane's tangent plane from +X towards +Y, elevation, BGR colour and
    strength), the highlight, the flat field and the sensor."""

    lights: tuple[tuple[float, float, tuple[float, float, float]], ...] = (
        (90.0, 18.0, (0.15, 0.40, 1.00)),      # a red-ish LED low on the +Y side (ahead of the roll)
        (270.0, 40.0, (0.50, 0.20, 0.05)),     # a weaker blue LED higher on the -Y side
        (20.0, 25.0, (0.25, 0.80, 0.25)),      # a green LED low along the axis
    )
    gain: float = 140.0
    ambient: float = 18.0
    shininess: float = 30.0
    specular: float = 0.25
    contact_softness: float = 2e-6   # m
    gel_blur_px: float = 0.6
    vignetting: float = 1.0          # strength of the cos^4 fall-off
    axial_falloff: float = 0.25      # relative irradiance change over the seen axis
    specks: int = 40
    electrons_per_level: float = 4.0
    read_noise: float = 1.2          # grey levels
    row_noise: float = 0.6           # grey levels, per row and frame
    exposure_samples: int = 2
    exposure_s: float = 0.008
    pixel_samples: int = 3           # shading points per pixel along each image axis (1: at the pixel centres)


def _light_vectors(look: Look) -> np.ndarray:
    out = []
    for azimuth, elevation, _ in look.lights:
        a, e = math.radians(azimuth), math.radians(elevation)
        out.append((math.cos(e) * math.cos(a), math.cos(e) * math.sin(a), -math.sin(e)))
    return np.array(out)


class Lighting:
    """The LEDs' light on the membrane's inner face: Lambert + a Blinn-Phong highlight seen from the axis."""

    def __init__(self, look: Look) -> None:
        self.look = look
        self.lights = _light_vectors(look)
        self.colours = np.array([colour for _, _, colour in look.lights])     # (lights, 3) BGR

    def lit(self, fx: np.ndarray, fy: np.ndarray) -> np.ndarray:
        """BGR irradiance of a membrane whose depth z (down) has slopes fx = dz/dX, fy = dz/dY."""
        look = self.look
        norm = np.sqrt(1.0 + fx * fx + fy * fy)
        nx, ny, nz = fx / norm, fy / norm, -1.0 / norm      # the membrane's inner normal (towards the axis)
        out = np.full(fx.shape + (3,), look.ambient, fx.dtype)
        view = np.array([0.0, 0.0, -1.0])
        for light, colour in zip(self.lights, self.colours, strict=True):
            lambert = np.maximum(nx * light[0] + ny * light[1] + nz * light[2], 0.0)
            half = light + view
            half /= np.linalg.norm(half)
            highlight = np.maximum(nx * half[0] + ny * half[1] + nz * half[2], 0.0)
            shine = look.gain * (lambert + look.specular * highlight ** look.shininess)
            out += shine[..., None] * colour.astype(fx.dtype)
        return out


def appearance(surface: Surface, camera: Camera, look: Look, origin: tuple[float, float], shape: tuple[int, int],
               resolution: float, roll: np.ndarray) -> np.ndarray:
    """Grey (rows growing with y, float32) of the surface pressed flat under the roller, on a base grid
    (cell (r, c) centred at origin + ((c + 0.5), (r + 0.5)) * resolution), lit as the frames are with the
    roller's y axis along `roll` (unit, base); no flat field, no noise: what an ideal map shows."""
    rows, cols = shape
    xs = origin[0] + (np.arange(cols) + 0.5) * resolution
    ys = origin[1] + (np.arange(rows) + 0.5) * resolution
    xx, yy = np.meshgrid(xs, ys)
    s = surface.sample(np.stack([xx, yy], axis=-1)).astype(np.float64)
    # the gel's low pass, in metres as in the frames (pixels there are ~ r / fx)
    sigma = look.gel_blur_px * camera.radius / camera.fx / resolution
    s = cv2.GaussianBlur(s, (0, 0), sigma)
    gy, gx = np.gradient(s, resolution)
    axis = np.array([-roll[1], roll[0]])
    # the membrane's depth (down) is -s: its slopes along the cylinder's X (the axis) and Y
    fx = -(gx * axis[0] + gy * axis[1])
    fy = -(gx * roll[0] + gy * roll[1])
    bgr = Lighting(look).lit(fx, fy)
    return (0.114 * bgr[..., 0] + 0.587 * bgr[..., 1] + 0.299 * bgr[..., 2]).astype(np.float32)


def _camera_rays(camera: Camera, rows: slice, samples: int = 1) -> tuple[np.ndarray, np.ndarray]:
    """Origin (3,) and unit directions (h, w, 3) of the pixels' rays in the cylinder frame; with `samples`
    > 1, of `samples` x `samples` points evenly inside each pixel ((h samples, w samples, 3), pixel
    (v, u)'s points at rows v samples .. (v + 1) samples - 1)."""
    offsets = (np.arange(samples) + 0.5) / samples - 0.5
    vs = (np.arange(rows.start, rows.stop)[:, None] + offsets[None, :]).reshape(-1)
    us = (np.arange(camera.width)[:, None] + offsets[None, :]).reshape(-1)
    v, u = np.meshgrid(vs, us, indexing="ij")
    xn, yn = (u - camera.cx) / camera.fx, (v - camera.cy) / camera.fy
    c, s = math.cos(camera.theta), math.sin(camera.theta)
    # camera coordinates p_c = R p + (0, 0, d), R = [[1,0,0],[0,c,s],[0,-s,c]]: p = R^T (p_c - (0, 0, d))
    direction = np.stack([xn, c * yn - s * np.ones_like(yn), s * yn + c * np.ones_like(yn)], axis=-1)
    direction /= np.linalg.norm(direction, axis=-1, keepdims=True)
    origin = np.array([0.0, s * camera.d, -c * camera.d])     # R^T (0, 0, -d)
    return origin, direction


def membrane_points(camera: Camera, rows: slice, samples: int = 1) -> np.ndarray:
    """(h, w, 3) where each pixel's ray meets the undeformed membrane y^2 + z^2 = r^2 (the far root); with
    `samples` > 1 the rays of `samples` x `samples` points inside each pixel (`_camera_rays`)."""
    origin, direction = _camera_rays(camera, rows, samples)
    dy, dz = direction[..., 1], direction[..., 2]
    a = dy * dy + dz * dz
    b = 2.0 * (origin[1] * dy + origin[2] * dz)
    c = origin[1] ** 2 + origin[2] ** 2 - camera.radius ** 2
    t = (-b + np.sqrt(b * b - 4 * a * c)) / (2 * a)
    return origin + t[..., None] * direction


class BandRenderer:
    """Renders frames of the roller over a surface; the pixel geometry, the static flat field and a bank
    of unit noise are computed once. Rows outside `window` (around the contact line) are a fixed frame
    of the lifted roller. Depths are held relative to the pressed ground (r - depth), in float32."""

    NOISE_BANK = 6

    def __init__(self, camera: Camera, surface: Surface, look: Look = Look(), depth: float = 5e-4,
                 window: int = 80, seed: int = 0) -> None:
        self.camera, self.surface, self.look, self.depth = camera, surface, look, depth
        self.rng = np.random.default_rng(np.random.SeedSequence([seed, 2206]))
        centre = int(round(camera.cy - camera.fy * math.tan(camera.theta)))
        self.rows = slice(max(centre - window, 0), min(centre + window, camera.height))
        if look.pixel_samples < 1:
            raise ValueError(f"pixel_samples must be >= 1, got {look.pixel_samples}")
        points = membrane_points(camera, self.rows, look.pixel_samples)   # the shading points inside the pixels
        self.x_axial = points[..., 0].astype(np.float32)
        self.y_roll = points[..., 1].astype(np.float32)
        self.tube = (points[..., 2] - (camera.radius - depth)).astype(np.float32)   # below the pressed ground
        self.inverse_dx = (1.0 / np.gradient(points[..., 0], axis=1)).astype(np.float32)
        self.inverse_dy = (1.0 / np.gradient(points[..., 1], axis=0)).astype(np.float32)
        self.lighting = Lighting(look)
        whole = membrane_points(camera, slice(0, camera.height))
        self.flat = self._flat_field(whole)
        z = (whole[..., 2] - (camera.radius - depth)).astype(np.float32)    # the tube alone, nothing pressed
        lifted = self.lighting.lit(np.gradient(z, axis=1) / np.gradient(whole[..., 0], axis=1).astype(np.float32),
                                   np.gradient(z, axis=0) / np.gradient(whole[..., 1], axis=0).astype(np.float32))
        shape = (self.rows.stop - self.rows.start, camera.width, 3)
        self.bank = self.rng.standard_normal((self.NOISE_BANK,) + shape, dtype=np.float32)
        self.static = self._sensor(lifted * self.flat[..., None], whole=True)

    # ------------------------------------------------------------------ static parts
    def _flat_field(self, points: np.ndarray) -> np.ndarray:
        look, camera = self.look, self.camera
        h, w = points.shape[:2]
        off_axis = np.arctan(np.hypot(points[..., 0], points[..., 1]) / np.maximum(points[..., 2], 1e-9))
        vignette = np.cos(off_axis) ** (4 * look.vignetting)
        axial = 1.0 + look.axial_falloff * points[..., 0] / (camera.width / camera.fx * camera.radius)
        specks = np.ones((h, w), np.float32)
        for _ in range(look.specks):
            centre = (int(self.rng.integers(0, w)), int(self.rng.integers(0, h)))
            cv2.circle(specks, centre, int(self.rng.integers(1, 4)), float(self.rng.uniform(0.55, 0.85)), -1)
        specks = cv2.GaussianBlur(specks, (0, 0), 0.8)
        return (vignette * axial * specks).astype(np.float32)

    # ------------------------------------------------------------------ one frame
    def membrane(self, ground: np.ndarray) -> np.ndarray:
        """Depth of the deformed membrane (down, relative to the pressed ground): the soft minimum of the
        tube and the ground."""
        k = self.look.contact_softness
        return self.tube - k * np.logaddexp(np.float32(0.0), (self.tube - ground) / np.float32(k))

    def _shade(self, z: np.ndarray) -> np.ndarray:
        """BGR irradiance (h, w, 3) of the pixels seeing the membrane of depth `z` (at the shading points;
        the elastomer's low pass applied): the mean over each pixel's shading points."""
        n = self.look.pixel_samples
        if self.look.gel_blur_px:
            z = cv2.GaussianBlur(z, (0, 0), self.look.gel_blur_px * n)
        lit = self.lighting.lit(np.gradient(z, axis=1) * self.inverse_dx, np.gradient(z, axis=0) * self.inverse_dy)
        if n == 1:
            return lit
        h, w = lit.shape[0] // n, lit.shape[1] // n
        out: np.ndarray = lit.reshape(h, n, w, n, 3).mean(axis=(1, 3), dtype=np.float32)
        return out

    def _sensor(self, irradiance: np.ndarray, whole: bool = False) -> np.ndarray:
        """Shot noise (Gaussian of the Poisson variance), read noise and a per-row offset, quantised."""
        look = self.look
        signal = np.maximum(irradiance, 0.0).astype(np.float32)
        sigma = np.sqrt(signal / look.electrons_per_level + look.read_noise ** 2)
        if whole:
            unit = self.rng.standard_normal(signal.shape, dtype=np.float32)
        else:
            unit = np.roll(self.bank[int(self.rng.integers(self.NOISE_BANK))], int(self.rng.integers(signal.shape[1])),
                           axis=1)
        noisy = signal + sigma * unit + self.rng.normal(0.0, look.row_noise, (signal.shape[0], 1, 1)).astype(np.float32)
        return np.clip(np.rint(noisy), 0, 255).astype(np.uint8)

    def frame(self, poses: list[tuple[np.ndarray, np.ndarray, float]]) -> np.ndarray:
        """One bgr8 frame, the mean over the exposure of the roller at `poses`: each (position (2,) of the
        axis in base, the cylinder frame's y axis (2,) in base, h m above the pressed height)."""
        n = self.look.pixel_samples
        irradiance = np.zeros((self.tube.shape[0] // n, self.tube.shape[1] // n, 3), np.float32)
        for position, roll, h in poses:
            axis = np.array([-roll[1], roll[0]], np.float32)               # cylinder x (the axis) in base
            xy = (np.asarray(position, np.float32) + self.x_axial[..., None] * axis
                  + self.y_roll[..., None] * np.asarray(roll, np.float32))
            ground = np.float32(h) - self.surface.sample(xy)
            irradiance += self._shade(self.membrane(ground))
        irradiance *= self.flat[self.rows][..., None] / len(poses)
        image = self.static.copy()
        image[self.rows] = self._sensor(irradiance)
        return image
