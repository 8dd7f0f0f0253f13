"""A second renderer of calibration images, independent of the simulator (`touchroller_driver.sim`).

Calibration tuned on one renderer can learn that renderer's habits. This module renders the same
two calibration scenes from the same paper geometry with its own models and its own code, so the
calibration can be checked on data it was not tuned on:

* **Hemisphere presses** (theta, d): the 2x5 frame placed by hand within +-1 mm around the contact
  line. Each imprint is the Hertzian displacement of an elastic half-space under a rigid sphere
  (contact radius a = sqrt(R delta) for an approach delta, half the approach at the rim, a tail
  falling off as 1/rho outside it), so an imprint's size and strength grow with how deep its
  hemisphere presses, and the row nearer the contact line presses deeper. Shading is GelSight-like:
  one light at a low elevation on one side (Lambert on the membrane normal), its irradiance falling
  off away from the lit side, over a static background of uneven gel and specks.
* **Chessboard views** (intrinsics) through a strongly distorting lens (k1, k2, k3 and small
  tangential terms), every board kept within the central half of the image in each direction, so
  the image corners are never seen.

Nothing here uses `CameraModel.project`, `back_project` or `undistort_normalised`, nor the
simulator: pixel rays come from `cv2.undistortPoints` (with criteria), projections from `cv2.projectPoints`,
and the cylinder intersection is written out here. `CameraModel` only carries the true parameters.

Only evaluation code (bench scripts and the tests of their goals) uses this module; the product
never does, which is why it lives in `bench/` and not in the simulator.
"""
from __future__ import annotations

import dataclasses
import math

import cv2
import numpy as np

from touchroller_perception.geometry import CameraModel

#: the paper's sensor seen through a cheap, strongly distorting wide-angle lens
TRUE_CAMERA = CameraModel(fx=380.0, fy=381.5, cx=323.0, cy=236.5,
                          distortion=(-0.16, 0.045, 4.0e-4, -3.0e-4, -0.006),
                          theta=math.radians(2.0), d=1.5e-3)


# =========================================================================== shared geometry
def _rotation(camera: CameraModel) -> np.ndarray:
    """Cylinder -> camera rotation of DESIGN.md's Eq. bigeq (rotation by theta about x)."""
    c, s = math.cos(camera.theta), math.sin(camera.theta)
    return np.array([[1.0, 0.0, 0.0], [0.0, c, s], [0.0, -s, c]])


def _opencv_intrinsics(camera: CameraModel) -> tuple[np.ndarray, np.ndarray]:
    k_matrix = np.array([[camera.fx, 0.0, camera.cx], [0.0, camera.fy, camera.cy], [0.0, 0.0, 1.0]])
    return k_matrix, np.asarray(camera.distortion, dtype=np.float64)


def pixel_rays(camera: CameraModel, supersample: int = 1) -> np.ndarray:
    """Undistorted normalised rays (H*s, W*s, 2) of sub-pixel sample points, by OpenCV's own
    iterative undistortion (tight criteria; the lens is monotone over the whole image)."""
    s = supersample
    offsets = (np.arange(s) + 0.5) / s - 0.5
    us = (np.arange(camera.width)[:, None] + offsets[None, :]).ravel()
    vs = (np.arange(camera.height)[:, None] + offsets[None, :]).ravel()
    uu, vv = np.meshgrid(us, vs)
    k_matrix, dist = _opencv_intrinsics(camera)
    points = np.stack([uu, vv], axis=-1).reshape(-1, 1, 2)
    criteria = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 200, 1e-12)
    rays = cv2.undistortPoints(points, k_matrix, dist, criteria=criteria)
    return rays.reshape(uu.shape + (2,))


def project_points(camera: CameraModel, points: np.ndarray) -> np.ndarray:
    """Cylinder-frame points (N, 3) -> pixels (N, 2) through OpenCV's projection."""
    k_matrix, dist = _opencv_intrinsics(camera)
    rvec, _ = cv2.Rodrigues(_rotation(camera))
    tvec = np.array([0.0, 0.0, camera.d])
    uv, _ = cv2.projectPoints(np.asarray(points, dtype=np.float64).reshape(-1, 1, 3), rvec, tvec, k_matrix, dist)
    return uv.reshape(-1, 2)


def membrane_coordinates(camera: CameraModel) -> tuple[np.ndarray, np.ndarray]:
    """For every pixel, where its ray meets the membrane: axial x and arc length s = r * alpha (m)."""
    rays = pixel_rays(camera)
    rotation = _rotation(camera)
    direction = np.concatenate([rays, np.ones(rays.shape[:2] + (1,))], axis=-1) @ rotation   # R^T (xn, yn, 1)
    origin = -rotation.T @ np.array([0.0, 0.0, camera.d])
    dy, dz = direction[..., 1], direction[..., 2]
    a = dy * dy + dz * dz
    b = 2.0 * (origin[1] * dy + origin[2] * dz)
    c = origin[1] ** 2 + origin[2] ** 2 - camera.radius ** 2
    step = (-b + np.sqrt(b * b - 4.0 * a * c)) / (2.0 * a)
    point = origin + step[..., None] * direction
    return point[..., 0], camera.radius * np.arctan2(point[..., 1], point[..., 2])


# =========================================================================== hemisphere presses
@dataclasses.dataclass(frozen=True)
class FrameLayout:
    """The 2x5 hemisphere frame (the paper's layout; pitches as in the calibration defaults)."""

    rows: int = 2
    columns: int = 5
    pitch_x: float = 0.010
    pitch_y: float = 0.008
    hemisphere_radius: float = 0.001

    def plate_points(self) -> np.ndarray:
        """(rows*columns, 2) hemisphere centres on the plate, row-major, rows by increasing y."""
        xs = (np.arange(self.columns) - 0.5 * (self.columns - 1)) * self.pitch_x
        ys = (np.arange(self.rows) - 0.5 * (self.rows - 1)) * self.pitch_y
        return np.array([(x, y) for y in ys for x in xs])


@dataclasses.dataclass(frozen=True)
class Placement:
    """How a hand places the frame for each press: uniform within +-`shift` (m) in x and y,
    +-`yaw_deg` about z, the plate pressed `depth` (m, at the frame's centre line) +- `depth_jitter`."""

    shift: float = 1.0e-3
    yaw_deg: float = 1.0
    depth: float = 5.0e-4
    depth_jitter: float = 8.0e-5


@dataclasses.dataclass(frozen=True)
class Look:
    """The imprint model's appearance.

    `light_azimuth_deg`: where the light comes from in the membrane's tangent plane (0: from +x, the
    image's +u; 90: from +s, the image's +v). `light_elevation_deg` above the membrane. `falloff`:
    relative change of irradiance per 10 mm towards the light (0 for a uniform light). `gain`: grey
    levels of the light at normal incidence. `ambient`: grey levels without the light. `noise`:
    read noise sigma (grey levels). `gel_blur_px`: the elastomer's and optics' low pass."""

    light_azimuth_deg: float = 90.0
    light_elevation_deg: float = 35.0
    falloff: float = 0.15
    gain: float = 190.0
    ambient: float = 25.0
    colour: tuple[float, float, float] = (0.80, 1.00, 0.90)     # b, g, r of the light
    noise: float = 2.0
    gel_blur_px: float = 0.8


@dataclasses.dataclass(frozen=True)
class PressTruth:
    shift: tuple[float, float]        # m, the frame's placement (x, y)
    yaw: float                        # rad
    plate_z: float                    # m, distance from the axis to the plate's hemisphere centres
    approach: np.ndarray              # (10,) m, how deep each hemisphere presses
    centres_px: np.ndarray            # (10, 2) true imprint centres (projections of the contact points)


@dataclasses.dataclass(frozen=True)
class PressSet:
    reference: np.ndarray             # bgr8, no contact (median of 5 frames)
    images: list[np.ndarray]          # bgr8, one per press
    truth: list[PressTruth]
    camera: CameraModel
    dark: np.ndarray | None = None    # bgr8, no contact with the light off (median of 5 frames)


def hertz_displacement(rho: np.ndarray, approach: float, sphere_radius: float) -> tuple[np.ndarray, np.ndarray]:
    """Surface displacement w (m, towards the camera) of an elastic half-space under a rigid sphere
    pressed `approach` deep, and dw/drho, at distances `rho` (m) from the contact centre."""
    a = math.sqrt(sphere_radius * approach)          # Hertz: approach = a^2 / R
    rho = np.maximum(rho, 1e-12)
    inside = rho <= a
    q = np.clip(a / rho, 0.0, 1.0)
    with np.errstate(invalid="ignore"):
        root = np.sqrt(np.maximum(rho * rho - a * a, 0.0))
        outside_w = approach / math.pi * ((2.0 - rho * rho / (a * a)) * np.arcsin(q) + root / a)
        outside_dw = approach / math.pi * (-2.0 * rho / (a * a) * np.arcsin(q) + 2.0 * root / (a * rho))
    w = np.where(inside, approach * (1.0 - rho * rho / (2.0 * a * a)), outside_w)
    dw = np.where(inside, -approach * rho / (a * a), outside_dw)
    return w, dw


class PressRenderer:
    """Renders hemisphere-frame presses for one camera and look; the membrane map is computed once."""

    def __init__(self, camera: CameraModel = TRUE_CAMERA, look: Look = Look(), layout: FrameLayout = FrameLayout(),
                 seed: int = 0) -> None:
        self.camera, self.look, self.layout = camera, look, layout
        self.x, self.s = membrane_coordinates(camera)
        rng = np.random.default_rng(np.random.SeedSequence([seed, 71]))
        self._rng = rng
        h, w = camera.height, camera.width
        azimuth = math.radians(look.light_azimuth_deg)
        elevation = math.radians(look.light_elevation_deg)
        self.light = np.array([math.cos(elevation) * math.cos(azimuth), math.cos(elevation) * math.sin(azimuth),
                               math.sin(elevation)])
        towards_light = (self.x * math.cos(azimuth) + self.s * math.sin(azimuth)) / 0.010
        self.irradiance = look.gain * np.clip(1.0 + look.falloff * towards_light, 0.2, None)
        # the static gel: slow unevenness and a few specks (the same in the reference and the presses)
        slow = cv2.resize(rng.standard_normal((5, 6)).astype(np.float32), (w, h), interpolation=cv2.INTER_CUBIC)
        specks = np.zeros((h, w), np.float32)
        for u, v in zip(rng.integers(0, w, 25), rng.integers(0, h, 25), strict=True):
            cv2.circle(specks, (int(u), int(v)), int(rng.integers(1, 3)), -25.0, -1)
        self.background = look.ambient + 6.0 * slow + cv2.GaussianBlur(specks, (0, 0), 0.7)

    def _shade(self, gx: np.ndarray, gs: np.ndarray) -> np.ndarray:
        """Grey level of the membrane with slopes (gx, gs), before colour and noise."""
        normal_dot_light = (-gx * self.light[0] - gs * self.light[1] + self.light[2]) / np.sqrt(1 + gx * gx + gs * gs)
        return self.background + self.irradiance * np.maximum(normal_dot_light, 0.0)

    def _finish(self, grey: np.ndarray) -> np.ndarray:
        grey = cv2.GaussianBlur(grey.astype(np.float32), (0, 0), self.look.gel_blur_px)
        colour = np.stack([grey * c for c in self.look.colour], axis=-1)
        colour += self._rng.normal(0.0, self.look.noise, colour.shape)
        return np.clip(np.rint(colour), 0, 255).astype(np.uint8)

    def reference(self, frames: int = 5) -> np.ndarray:
        flat = np.zeros_like(self.x)
        stack = np.stack([self._finish(self._shade(flat, flat)) for _ in range(frames)])
        return np.median(stack, axis=0).astype(np.uint8)

    def dark(self, frames: int = 5) -> np.ndarray:
        """No contact with the light off: the gel's background alone (ambient, unevenness, specks)."""
        stack = np.stack([self._finish(self.background.copy()) for _ in range(frames)])
        return np.median(stack, axis=0).astype(np.uint8)

    def press(self, shift: tuple[float, float], yaw: float, depth: float) -> tuple[np.ndarray, PressTruth]:
        """One press: the plate `depth` into the membrane at its centre line, placed at `shift`, `yaw`."""
        r, radius = self.camera.radius, self.layout.hemisphere_radius
        plate_z = r + radius - depth
        c, s = math.cos(yaw), math.sin(yaw)
        plate = self.layout.plate_points()
        px = shift[0] + c * plate[:, 0] - s * plate[:, 1]
        py = shift[1] + s * plate[:, 0] + c * plate[:, 1]
        approach = r + radius - np.hypot(py, plate_z)            # deeper nearer the contact line
        alpha = np.arctan2(py, plate_z)
        gx = np.zeros_like(self.x)
        gs = np.zeros_like(self.x)
        for x0, s0, delta in zip(px, r * alpha, approach, strict=True):
            if delta <= 0:
                continue
            dx, ds = self.x - x0, self.s - s0
            rho = np.hypot(dx, ds)
            _, slope = hertz_displacement(rho, float(delta), radius)
            with np.errstate(invalid="ignore", divide="ignore"):
                gx += np.where(rho > 0, slope * dx / rho, 0.0)
                gs += np.where(rho > 0, slope * ds / rho, 0.0)
        # the membrane moves towards the camera: its height is +w, slopes as computed
        image = self._finish(self._shade(gx, gs))
        points = np.stack([px, r * np.sin(alpha), r * np.cos(alpha)], axis=-1)
        truth = PressTruth(shift=(float(shift[0]), float(shift[1])), yaw=float(yaw), plate_z=float(plate_z),
                           approach=approach, centres_px=project_points(self.camera, points))
        return image, truth


def render_presses(seed: int, presses: int = 10, *, look: Look = Look(), placement: Placement = Placement(),
                   camera: CameraModel = TRUE_CAMERA, layout: FrameLayout = FrameLayout()) -> PressSet:
    """`presses` presses of the frame placed by hand (uniform placement, see `Placement`)."""
    renderer = PressRenderer(camera, look, layout, seed)
    rng = np.random.default_rng(np.random.SeedSequence([seed, 72]))
    images, truths = [], []
    for _ in range(presses):
        shift = tuple(rng.uniform(-placement.shift, placement.shift, 2))
        yaw = math.radians(float(rng.uniform(-placement.yaw_deg, placement.yaw_deg)))
        depth = placement.depth + float(rng.uniform(-placement.depth_jitter, placement.depth_jitter))
        image, truth = renderer.press((float(shift[0]), float(shift[1])), yaw, depth)
        images.append(image)
        truths.append(truth)
    reference = renderer.reference()
    return PressSet(reference=reference, images=images, truth=truths, camera=camera, dark=renderer.dark())


# =========================================================================== chessboard views
@dataclasses.dataclass(frozen=True)
class BoardSet:
    images: list[np.ndarray]          # bgr8
    corners_px: list[np.ndarray]      # (N, 2) true inner corners per view, OpenCV's order
    camera: CameraModel
    columns: int
    rows: int
    square: float


def render_chessboards(seed: int, views: int = 20, *, camera: CameraModel = TRUE_CAMERA, columns: int = 7,
                       rows: int = 7, square: float = 0.012, region: float = 0.5, max_tilt_deg: float = 40.0,
                       noise: float = 2.0, supersample: int = 4) -> BoardSet:
    """`views` chessboard views (7x7 inner corners, 12 mm squares by default), the whole board (with
    one square of white margin) inside the central `region` of the image in each direction."""
    rng = np.random.default_rng(np.random.SeedSequence([seed, 73]))
    rays = pixel_rays(camera, supersample)
    rays3 = np.concatenate([rays, np.ones(rays.shape[:2] + (1,))], axis=-1)
    k_matrix, dist = _opencv_intrinsics(camera)
    lo = np.array([camera.width, camera.height]) * (0.5 - region / 2)
    hi = np.array([camera.width, camera.height]) * (0.5 + region / 2)
    corners = np.array([(i * square, j * square, 0.0) for j in range(rows) for i in range(columns)])
    outline = np.array([[-2, -2, 0], [columns + 1, -2, 0], [columns + 1, rows + 1, 0], [-2, rows + 1, 0]],
                       dtype=np.float64) * square
    centre = np.array([(columns - 1) / 2, (rows - 1) / 2, 0.0]) * square
    images, truths = [], []
    attempts = 0
    while len(images) < views:
        attempts += 1
        if attempts > 5000 * views:
            raise ValueError("cannot place the board inside the central region; use a smaller board")
        tilt = np.radians(rng.uniform(-max_tilt_deg, max_tilt_deg, 2))
        spin = math.radians(float(rng.uniform(-25.0, 25.0)))
        rotation = cv2.Rodrigues(np.array([0.0, 0.0, spin]))[0] @ cv2.Rodrigues(np.array([0.0, tilt[1], 0.0]))[0] \
            @ cv2.Rodrigues(np.array([tilt[0], 0.0, 0.0]))[0]
        distance = float(rng.uniform(0.17, 0.32))
        aim = np.array([*rng.uniform(-0.16, 0.16, 2) * distance, distance])
        tvec = aim - rotation @ centre
        rvec = cv2.Rodrigues(rotation)[0]
        if np.any((outline @ rotation.T + tvec)[:, 2] <= 0.03):
            continue
        hull, _ = cv2.projectPoints(outline, rvec, tvec, k_matrix, dist)
        hull = hull.reshape(-1, 2)
        if np.any(hull < lo) or np.any(hull > hi):
            continue
        truth, _ = cv2.projectPoints(corners, rvec, tvec, k_matrix, dist)
        box = (max(int(hull[:, 0].min()) - 3, 0), max(int(hull[:, 1].min()) - 3, 0),
               min(int(hull[:, 0].max()) + 4, camera.width), min(int(hull[:, 1].max()) + 4, camera.height))
        images.append(_board_image(rays3, rotation, tvec, columns, rows, square, camera, supersample, noise, rng, box))
        truths.append(truth.reshape(-1, 2))
    return BoardSet(images=images, corners_px=truths, camera=camera, columns=columns, rows=rows, square=square)


def _board_image(rays: np.ndarray, rotation: np.ndarray, tvec: np.ndarray, columns: int, rows: int, square: float,
                 camera: CameraModel, supersample: int, noise: float, rng: np.random.Generator,
                 box: tuple[int, int, int, int]) -> np.ndarray:
    """The board plane intersected with each sample ray; squares of (columns+1) x (rows+1), a white
    margin of one square, a grey wall behind; area-averaged over the samples (a pixel integrates
    the light that falls on it), a light blur, noise. Only the pixels in `box` (u0, v0, u1, v1)
    can see the board."""
    wall = 110.0
    u0, v0, u1, v1 = box
    s = supersample
    local_rays = rays[v0 * s:v1 * s, u0 * s:u1 * s]
    normal = rotation[:, 2]
    with np.errstate(invalid="ignore", divide="ignore"):
        step = (normal @ tvec) / (local_rays @ normal)
        local = (step[..., None] * local_rays - tvec) @ rotation
    bx, by = local[..., 0] / square, local[..., 1] / square
    on_board = (bx >= -2) & (bx < columns + 1) & (by >= -2) & (by < rows + 1) & (step > 0)
    squares = (bx >= -1) & (bx < columns) & (by >= -1) & (by < rows)
    dark = squares & ((np.floor(bx) + np.floor(by)) % 2 == 0)
    value = np.where(on_board, np.where(dark, 35.0, 205.0), wall)
    grey = np.full((camera.height, camera.width), wall, np.float32)
    grey[v0:v1, u0:u1] = value.reshape(v1 - v0, s, u1 - u0, s).mean(axis=(1, 3))
    grey = cv2.GaussianBlur(grey, (0, 0), 0.6)
    grey = grey + rng.normal(0.0, noise, grey.shape).astype(np.float32)
    grey = np.clip(np.rint(grey), 0, 255).astype(np.uint8)
    return cv2.merge([grey, grey, grey])


def seen_mask(board_set: BoardSet) -> np.ndarray:
    """Pixels inside the convex hull of some view's detected-corner grid ("where the board was seen")."""
    mask = np.zeros((board_set.camera.height, board_set.camera.width), np.uint8)
    for corners in board_set.corners_px:
        hull = cv2.convexHull(corners.astype(np.float32)).astype(np.int32)
        cv2.fillConvexPoly(mask, hull, 1)
    return mask.astype(bool)


def ray_errors(fitted: CameraModel, truth: CameraModel, step: int = 4) -> tuple[np.ndarray, np.ndarray]:
    """Per pixel (on a grid of `step`): how far (px) the fitted model puts the true ray of that
    pixel, and the grid's pixel coordinates (..., 2). The true ray comes from OpenCV's undistortion
    of the true lens, the fitted projection from OpenCV's projection of the fitted lens."""
    us, vs = np.meshgrid(np.arange(0, truth.width, step, dtype=np.float64),
                         np.arange(0, truth.height, step, dtype=np.float64))
    uv = np.stack([us, vs], axis=-1)
    k_true, dist_true = _opencv_intrinsics(truth)
    criteria = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 200, 1e-12)
    rays = cv2.undistortPoints(uv.reshape(-1, 1, 2), k_true, dist_true, criteria=criteria).reshape(-1, 2)
    k_fit, dist_fit = _opencv_intrinsics(fitted)
    points = np.concatenate([rays, np.ones((rays.shape[0], 1))], axis=1)
    projected, _ = cv2.projectPoints(points.reshape(-1, 1, 3), np.zeros(3), np.zeros(3), k_fit, dist_fit)
    error = np.linalg.norm(projected.reshape(-1, 2) - uv.reshape(-1, 2), axis=1).reshape(us.shape)
    return error, uv
