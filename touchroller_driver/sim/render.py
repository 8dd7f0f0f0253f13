"""The simulated TouchRoller: what the webcam on the roller's axis sees.

Pipeline of one frame (float32, only the image rows the contact can reach):
1. indentation D (m, membrane pushed towards the camera) per pixel: the flat surface plane at depth
   `depth` into the roller plus the relief h(X, Y) (low-passed by the elastomer, remapped through
   per-pixel lookup maps precomputed from `CameraModel.back_project`), and any spherical indenters;
   D = max(0, z(pixel) - (r - depth) + h). A flat surface gives the band |y| < sqrt(2 r depth).
   Motion blur (if listed) is a box filter of the remapped relief along v, of length speed * exposure.
2. photometric shading of the membrane: normals from the gradient of D (Sobel, scaled to metres per
   pixel), three coloured lights from different azimuths (Lambert + ambient): contacts are lit on
   one side and shaded on the other. Or (`sensor.directional_light_deg`) one white LED from one
   azimuth whose irradiance falls off across the membrane away from it, as a GelSight-type sensor
   with directional LEDs: every imprint bright on the slope facing it, dark on the other.
3. static background: uneven LED illumination and specks (gain, offset) and vignetting, all
   precomputed; the rows the contact cannot reach are a precomputed static frame.
4. read noise (a pre-drawn bank sliced per frame), JPEG compression, dropped frames.
"""
from __future__ import annotations

import math
from collections.abc import Iterator
from dataclasses import asdict, dataclass, field
from typing import Any

import cv2
import numpy as np

from touchroller_driver.sim import effects
from touchroller_driver.sim.scene import Scene
from touchroller_driver.sim.surfaces import Surface, make_surface
from touchroller_perception.geometry import CameraModel


@dataclass(frozen=True)
class Indenter:
    """A sphere pressed into the membrane: centre (x, y, z) in `touchroller_cylinder` (m), radius (m)."""

    centre: tuple[float, float, float]
    radius: float


def sphere_indentation(points: np.ndarray, indenter: Indenter) -> np.ndarray:
    """How far (m, float32, 0 outside the contact) each membrane point (..., 3: on the tube, cylinder frame)
    is pushed in along its normal (radial, towards the axis) by the sphere: the membrane point P moved
    in by D along the outward normal n lies on the sphere, |P - D n - C| = R, so with w = P - C,
    D = w.n + sqrt((w.n)^2 - |w|^2 + R^2) (the root on the sphere's side facing the axis). Pressed
    into a flat membrane by d this is the cap sqrt(R^2 - rho^2) - (R - d); the distance inside the
    sphere along the line to its centre, R - |P - C|, is not (near the centre it is d - rho^2 / (2 (R - d)):
    curved as a ball of radius R - d, its slopes steeper by about R / (R - d))."""
    P = np.asarray(points, np.float32)
    w = P - np.asarray(indenter.centre, np.float32)
    radial = np.sqrt(P[..., 1] ** 2 + P[..., 2] ** 2)
    safe = np.where(radial > 0, radial, np.float32(1.0))
    wn = (w[..., 1] * P[..., 1] + w[..., 2] * P[..., 2]) / safe
    disc = wn * wn - (w * w).sum(axis=-1) + np.float32(indenter.radius) ** 2
    depth = wn + np.sqrt(np.maximum(disc, 0.0))
    out: np.ndarray = np.where((disc > 0) & (radial > 0), np.maximum(depth, 0.0), 0.0).astype(np.float32)
    return out


@dataclass(frozen=True)
class RollerState:
    """Where the roller is, as the arm reports it.

    x_along: world X of the roller's centre over the surface, along its axis (m).
    travel: world Y of the roller's centre along the rolling direction (m).
    roll: roll angle of the tube (rad); None means rolling without slip, travel / radius. The camera
        does not turn with the tube, so the image depends on travel, not on roll (kept for the truth).
    depth: how far the surface's base plane is pressed into the roller (m); <= 0 means no contact.
    speed: d(travel)/dt (m/s), sets the motion blur.
    t: time (s).
    indenters: spheres pressed into the membrane (contact and calibration scenes).
    """

    x_along: float = 0.0
    travel: float = 0.0
    roll: float | None = None
    depth: float = 5e-4
    speed: float = 0.0
    t: float = 0.0
    indenters: tuple[Indenter, ...] = ()

    def as_dict(self, radius: float) -> dict[str, Any]:
        out = asdict(self)
        out["roll"] = self.travel / radius if self.roll is None else self.roll
        out["indenters"] = [{"centre": list(i.centre), "radius": i.radius} for i in self.indenters]
        return out


@dataclass
class Frame:
    stamp_ns: int               # capture time
    image: np.ndarray           # HxWx3 bgr8
    truth: dict[str, Any] = field(default_factory=dict)


@dataclass(frozen=True)
class TruthMap:
    """The true surface at camera pixel scale: rows along the rolling direction (world Y increasing)."""

    image: np.ndarray           # uint8 grey, 0..255 = 0..max relief
    height: np.ndarray          # float32 metres
    tactile: np.ndarray         # uint8 grey: the relief as the sensor shades it (ideal, flat press,
                                # no blur/noise/background), like for like with a stitched grey map
    mm_per_px_rows: float       # along the rolling direction
    mm_per_px_cols: float       # along the roller axis (at the contact line)
    y_start: float              # world Y of row 0's centre (m)
    x_of_column: np.ndarray     # world X of each column (m)


def lowpass_sigma(sensor: dict[str, Any]) -> float:
    """Gaussian sigma (m) by which the membrane smooths the relief; grows with the gel's thickness."""
    value = sensor.get("lowpass_sigma", "auto")
    if value == "auto" or value is None:
        value = float(sensor["lowpass_per_thickness"]) * float(sensor["elastomer_thickness"])
    value = float(value)
    if not math.isfinite(value) or value < 0:
        raise ValueError(f"sensor.lowpass_sigma must be a finite number >= 0, got {value}")
    return value


class SimulatedSensor:
    """Renders the scene's camera images. `camera` is the true camera model of the simulated unit."""

    def __init__(self, scene: Scene, seed: int = 0) -> None:
        self.scene = scene
        self.seed = int(seed)
        self.camera: CameraModel = scene.camera
        seeds = np.random.SeedSequence(self.seed).spawn(6)
        self._rng_surface, self._rng_background, self._rng_noise, self._rng_frames, self._rng_motion, \
            self._rng_thickness = (np.random.default_rng(s) for s in seeds)
        self.effects = tuple(e for e in scene.effects)
        self.counts: dict[str, int] = {}
        s = scene.sensor
        self._lowpass = lowpass_sigma(s)
        self.surface: Surface = make_surface(scene.surface, self._rng_surface)
        self._relief = self.surface.lowpassed(self._lowpass)
        self._relief_max = self._relief.max_height
        self._thickness_variation = float(s.get("thickness_variation", 0.0))
        self._thickness_phase = self._rng_thickness.uniform(0.0, 2 * math.pi, size=2)
        self._mpp_contact: tuple[float, float] | None = None
        self._band_cache: dict[float, dict[str, float]] = {}
        self._build_maps()
        self._build_lights(s)
        self._build_static()
        self._noise: effects.NoiseBank | None = None
        if "noise" in self.effects and (float(scene.effect_params("noise")["sigma"]) > 0
                                        or float(scene.effect_params("noise")["shot"]) > 0):
            params = scene.effect_params("noise")
            self._noise = effects.NoiseBank((self.camera.height, self.camera.width, 3), float(params["sigma"]),
                                            self._rng_noise, shot_dn_per_electron=float(params.get("shot", 0.0)))
        self._board = None
        if scene.motion.get("kind") == "chessboard":
            from touchroller_driver.sim.chessboard import ChessboardRenderer

            self._board = ChessboardRenderer(self.camera, scene, self._rng_background)

    # ------------------------------------------------------------------ public API
    @property
    def pipeline(self) -> tuple[str, ...]:
        """The stages a frame goes through, in order (the effects the scene listed, nothing else)."""
        stages = ["indentation"]
        if "blur" in self.effects:
            stages.append("blur")
        stages.append("shading")
        if self._gain is not None:
            stages.append("static_gain")
        for name in ("noise", "compression"):
            if name in self.effects:
                stages.append(name)
        return tuple(stages)

    def thickness_offset(self, x: np.ndarray | float, alpha: np.ndarray | float) -> np.ndarray:
        """Membrane radius error (m) at axial x and angle alpha: the elastomer's uneven thickness."""
        if self._thickness_variation == 0.0:
            return np.zeros(np.broadcast(np.asarray(x), np.asarray(alpha)).shape)
        p1, p2 = self._thickness_phase
        L = self.camera.length
        return self._thickness_variation * (0.6 * np.cos(2 * math.pi * np.asarray(x) / L + p1)
                                             + 0.4 * np.cos(3.0 * np.asarray(alpha) + p2))

    def membrane_point(self, x: float, alpha: float) -> np.ndarray:
        """The true membrane point (with thickness variation) at (x, alpha), cylinder frame."""
        radius = self.camera.radius + float(self.thickness_offset(x, alpha))
        return np.array([x, radius * math.sin(alpha), radius * math.cos(alpha)])

    def render(self, state: RollerState, frame: int | None = None) -> np.ndarray:
        """The bgr8 image for a roller state; `frame` (an index) fixes the random effects to that frame."""
        return self._render(state, frame=frame)[0]

    def capture(self, state: RollerState, frame: int | None = None) -> np.ndarray | None:
        """Like a camera read: the image, or None when the scene's `dropped_frames` effect drops it.
        With `frame` (an index, e.g. on the simulated clock's frame grid) noise and drops are functions
        of the frame, not of how many frames came before."""
        if "dropped_frames" in self.effects and effects.frame_dropped(
                self._rng_frames, float(self.scene.effect_params("dropped_frames")["probability"]), frame, self.seed):
            self.counts["dropped_frames"] = self.counts.get("dropped_frames", 0) + 1
            return None
        return self.render(state, frame)

    def render_layers(self, state: RollerState) -> dict[str, Any]:
        """The image plus its intermediate layers (full-size indentation and relief, m) for validation."""
        image, layers = self._render(state, keep_layers=True)
        layers["image"] = image
        return layers

    def frames(self) -> Iterator[Frame]:
        """The scene's own motion, frame by frame (dropped frames are skipped, like a real camera)."""
        from touchroller_driver.sim.scenarios import timeline

        drop_p = float(self.scene.effect_params("dropped_frames")["probability"])
        start = int(self.scene.data["start_stamp_ns"])
        for step in timeline(self.scene, self):
            stamp_ns = start + round(step.t * 1e9)
            if "dropped_frames" in self.effects and effects.frame_dropped(self._rng_frames, drop_p):
                self.counts["dropped_frames"] = self.counts.get("dropped_frames", 0) + 1
                continue
            if step.board_pose is not None:
                image = self._render_board(step.board_pose)
            else:
                image = self.render(step.state)
            truth = dict(step.truth)
            truth["t"] = step.t
            truth["stamp_ns"] = stamp_ns
            if step.state is not None:
                truth["state"] = step.state.as_dict(self.camera.radius)
                truth["pose"] = self.roller_pose(step.state)
                if step.state.depth > 0:
                    truth["band"] = self.band_truth(step.state.depth)
            yield Frame(stamp_ns, image, truth)

    def roller_pose(self, state: RollerState) -> list[float]:
        """World pose of the roller's axis centre: X (along axis), Y (travel), Z (height above the base
        plane, metres), roll angle (rad)."""
        roll = state.travel / self.camera.radius if state.roll is None else state.roll
        return [state.x_along, state.travel, self.camera.radius - state.depth, roll]

    def band_truth(self, depth: float) -> dict[str, float]:
        """The flat-contact band at penetration `depth`: half-width (m, 2D geometry sqrt(2 r d - d^2)),
        edge angles, and the image rows of its edges and centre line at x = 0 (nominal radius)."""
        cached = self._band_cache.get(depth)
        if cached is not None:
            return dict(cached)
        r = self.camera.radius
        half = math.sqrt(max(2 * r * depth - depth * depth, 0.0))
        edge = math.asin(min(half / r, 1.0))
        pts = self.camera.surface_point(np.zeros(3), np.array([-edge, 0.0, edge]))
        uv, _ = self.camera.project(pts)
        band = {"half_width_m": half, "alpha_edge": edge, "v_top": float(uv[0, 1]),
                "v_centre": float(uv[1, 1]), "v_bottom": float(uv[2, 1])}
        if len(self._band_cache) < 4096:
            self._band_cache[depth] = band
        return dict(band)

    def contact_row(self) -> float:
        """Image row v of the contact line (x=0 on the membrane's lowest point)."""
        uv, _ = self.camera.project(self.membrane_point(0.0, 0.0))
        return float(uv[1])

    def metres_per_px_at_contact(self) -> tuple[float, float]:
        """(along u = axis, along v = rolling direction) metres per pixel at the contact line."""
        if self._mpp_contact is None:
            row = int(np.clip(round(self.contact_row()), 0, self.camera.height - 1))
            col = int(np.clip(round(self.camera.cx), 0, self.camera.width - 1))
            self._mpp_contact = (float(self._mpp_u[row, col]), float(self._mpp_v[row, col]))
        return self._mpp_contact

    def surface_map_truth(self, travel_start: float | None = None, travel_end: float | None = None,
                          x_along: float | None = None, lowpassed: bool = True) -> TruthMap:
        """The true surface resampled to camera pixels: columns = image columns at the contact line,
        rows = world Y at the camera's metres-per-pixel along v (rows increase with Y)."""
        from touchroller_driver.sim.scenarios import roll_extent

        lo, hi, default_x = roll_extent(self.scene)
        travel_start = lo if travel_start is None else travel_start
        travel_end = hi if travel_end is None else travel_end
        x_along = default_x if x_along is None else x_along
        mpp_u, mpp_v = self.metres_per_px_at_contact()
        row = int(np.clip(round(self.contact_row()), 0, self.camera.height - 1))
        x_cols = self._points[row, :, 0].astype(np.float64) + x_along
        y_lo, y_hi = min(travel_start, travel_end), max(travel_start, travel_end)
        rows = max(1, int(math.floor((y_hi - y_lo) / mpp_v)) + 1)
        ys = y_lo + np.arange(rows) * mpp_v
        surf = self._relief if lowpassed else self.surface
        X, Y = np.meshgrid(x_cols, ys)
        height = surf.sample(X, Y).astype(np.float32)
        top = max(self.surface.max_height, 1e-12)
        image = np.clip(np.rint(height / top * 255.0), 0, 255).astype(np.uint8)
        gy, gx = np.gradient(height.astype(np.float64), mpp_v, x_cols, axis=(0, 1)) if min(height.shape) > 1 \
            else (np.zeros_like(height), np.zeros_like(height))
        shaded = self._shade_slopes(gx.astype(np.float32), gy.astype(np.float32))
        tactile = cv2.cvtColor(cv2.convertScaleAbs(shaded), cv2.COLOR_BGR2GRAY)
        return TruthMap(image, height, tactile, mpp_v * 1e3, mpp_u * 1e3, y_lo, x_cols)

    def world_truth(self, surface_frame: Any, origin: tuple[float, float], shape: tuple[int, int],
                    resolution: float) -> tuple[np.ndarray, np.ndarray]:
        """The true surface on a grid of the world plane (rows growing with world y, cell (r, c) centred
        at origin + ((c + 0.5), (r + 0.5)) * resolution), given T_world_S (`sim.camera.surface_frame`):
        (height, m, as the membrane follows it; tactile grey: the relief as the sensor shades it).
        The like-for-like reference for a world map, in place (no alignment)."""
        rows, cols = shape
        xs = origin[0] + (np.arange(cols) + 0.5) * resolution
        ys = origin[1] + (np.arange(rows) + 0.5) * resolution
        X, Y = np.meshgrid(xs, ys)
        world = np.stack([X, Y, np.zeros_like(X)], axis=-1).reshape(-1, 3)
        in_surface = surface_frame.inverse().apply(world)
        height = self._relief.sample(in_surface[:, 0], in_surface[:, 1]).reshape(rows, cols).astype(np.float32)
        if min(rows, cols) > 1:
            gy, gx = np.gradient(height.astype(np.float64), resolution)
        else:
            gy = gx = np.zeros_like(height, np.float64)
        # slopes in the cylinder frame's axes (x along the roller, y along the roll) as the shading wants them
        axes = surface_frame.matrix()[:2, :2]   # world xy of S's x and y
        sx = gx * axes[0, 0] + gy * axes[1, 0]
        sy = gx * axes[0, 1] + gy * axes[1, 1]
        shaded = self._shade_slopes(sx.astype(np.float32), sy.astype(np.float32))
        tactile = cv2.cvtColor(cv2.convertScaleAbs(shaded), cv2.COLOR_BGR2GRAY)
        return height, tactile

    # ------------------------------------------------------------------ precomputation
    def _build_maps(self) -> None:
        cam = self.camera
        H, W = cam.height, cam.width
        uu, vv = np.meshgrid(np.arange(W, dtype=np.float64), np.arange(H, dtype=np.float64))
        uv = np.stack([uu, vv], axis=-1)
        points, valid = cam.back_project(uv)
        if self._thickness_variation != 0.0:
            points, valid = self._reintersect(uv, points, valid)
        self._valid = valid
        pts = np.where(valid[..., None], points, 0.0)
        self._points = pts.astype(np.float32)
        res = self.surface.resolution
        far = -1e6   # remap reads the base plane (0) there
        self._map_x0 = np.where(valid, (pts[..., 0] - self.surface.x0) / res - 0.5, far).astype(np.float32)
        self._map_y0 = np.where(valid, (pts[..., 1] - self.surface.y0) / res - 0.5, far).astype(np.float32)
        self._gap = np.where(valid, pts[..., 2] - cam.radius, -1.0).astype(np.float32)
        # metres per pixel along u and v (3D distance between neighbouring membrane points)
        du = np.linalg.norm(np.gradient(pts, axis=1), axis=-1)
        dv = np.linalg.norm(np.gradient(pts, axis=0), axis=-1)
        du = np.where(valid & (du > 0), du, np.nan)
        dv = np.where(valid & (dv > 0), dv, np.nan)
        self._mpp_u = np.nan_to_num(du, nan=np.nanmedian(du)).astype(np.float32)
        self._mpp_v = np.nan_to_num(dv, nan=np.nanmedian(dv)).astype(np.float32)
        self._sobel_ku = (1.0 / (8.0 * self._mpp_u)).astype(np.float32)
        self._sobel_kv = (1.0 / (8.0 * self._mpp_v)).astype(np.float32)
        self._row_max_gap = np.where(valid.any(axis=1), self._gap.max(axis=1), -1.0)
        self._row_all_valid = valid.all(axis=1)

    def _reintersect(self, uv: np.ndarray, nominal: np.ndarray, valid: np.ndarray):
        """Rays meet the real membrane (radius r + thickness error) instead of the nominal cylinder."""
        origin, direction, ok = self.camera.pixel_rays(uv)
        x_n, a_n = CameraModel.surface_coords(nominal)
        radius = self.camera.radius + self.thickness_offset(np.nan_to_num(x_n), np.nan_to_num(a_n))
        dy, dz = direction[..., 1], direction[..., 2]
        a = dy * dy + dz * dz
        b = 2.0 * (origin[1] * dy + origin[2] * dz)
        c = origin[1] ** 2 + origin[2] ** 2 - radius * radius
        with np.errstate(invalid="ignore", divide="ignore"):
            t = (-b + np.sqrt(b * b - 4.0 * a * c)) / (2.0 * a)
        points = origin + t[..., None] * direction
        valid = valid & ok & np.isfinite(t) & (np.abs(points[..., 0]) <= 0.5 * self.camera.length)
        points[~valid] = np.nan
        return points, valid

    def _build_lights(self, s: dict[str, Any]) -> None:
        elevation = math.radians(float(s["light_elevation_deg"]))
        azimuths = [math.radians(float(a)) for a in s["light_azimuths_deg"]]
        if len(azimuths) != 3:
            raise ValueError("sensor.light_azimuths_deg needs 3 angles (blue, green, red)")
        self._irradiance: np.ndarray | None = None
        directional = s.get("directional_light_deg")
        if directional is not None:
            azimuth = math.radians(float(directional))
            falloff = float(s.get("directional_falloff", 0.0))
            if not (math.isfinite(azimuth) and math.isfinite(falloff)):
                raise ValueError("sensor.directional_light_deg and directional_falloff must be finite")
            azimuths = [azimuth] * 3
            # irradiance across the membrane: grows towards the light (x along the axis, s = r alpha around it)
            x, alpha = CameraModel.surface_coords(self._points.astype(np.float64))
            towards = (x * math.cos(azimuth) + self.camera.radius * alpha * math.sin(azimuth)) / 0.010
            self._irradiance = np.clip(1.0 + falloff * np.nan_to_num(towards), 0.2, None).astype(np.float32)
        self._lights = [(math.cos(elevation) * math.cos(a), math.cos(elevation) * math.sin(a), math.sin(elevation))
                        for a in azimuths]
        self._ambient = float(s["ambient"])
        self._light_gain = float(s["light_gain"])
        self._dn = 255.0 * float(s["exposure_scale"])

    def _build_static(self) -> None:
        cam = self.camera
        H, W = cam.height, cam.width
        gain = None
        offset = None
        if "background" in self.effects:
            p = self.scene.effect_params("background")
            gain, offset = effects.gel_background(
                H, W, self._rng_background, illumination=float(p["illumination"]),
                led_falloff=float(p["led_falloff"]), specks=int(p["specks"]),
                speck_radius_px=tuple(p["speck_radius_px"]))
        if "vignetting" in self.effects:
            vig = effects.vignetting(H, W, cam.fx, cam.fy, cam.cx, cam.cy,
                                     float(self.scene.effect_params("vignetting")["strength"]))
            gain = np.repeat(vig[:, :, None], 3, axis=2) if gain is None else gain * vig[:, :, None]
        if not self._valid.all():
            mask = self._valid.astype(np.float32)[:, :, None]
            gain = np.repeat(mask, 3, axis=2) if gain is None else gain * mask
            if offset is not None:
                offset = offset * mask
        self._gain = gain
        self._offset = offset
        if self._irradiance is None:
            flat = np.array([self._flat_level(c) for c in range(3)], np.float32)
            static = np.broadcast_to(flat, (H, W, 3)).astype(np.float32)
        else:
            zeros = np.zeros((H, W), np.float32)
            static = self._shade_slopes(zeros, zeros.copy(), self._irradiance)
        self._static = self._apply_static(static, 0, H)

    def _flat_level(self, channel: int) -> float:
        return self._dn * (self._ambient + self._light_gain * max(0.0, self._lights[channel][2]))

    def _apply_static(self, shade: np.ndarray, v0: int, v1: int) -> np.ndarray:
        if self._gain is not None:
            shade = cv2.multiply(shade, self._gain[v0:v1])
        if self._offset is not None:
            shade = cv2.add(shade, self._offset[v0:v1])
        return cv2.convertScaleAbs(shade)   # saturating round to uint8 (values are >= 0)

    # ------------------------------------------------------------------ per frame
    def _count(self, name: str) -> None:
        self.counts[name] = self.counts.get(name, 0) + 1

    def _render(self, state: RollerState, keep_layers: bool = False,
                frame: int | None = None) -> tuple[np.ndarray, dict[str, Any]]:
        if self._board is not None:
            raise ValueError("the chessboard scene shows a board to the bare camera; use frames()")
        values = (state.x_along, state.travel, state.depth, state.speed)
        if not all(math.isfinite(v) for v in values) or not all(
                math.isfinite(c) for i in state.indenters for c in (*i.centre, i.radius)):
            raise ValueError(f"RollerState has non-finite values: {state}")
        image = self._static.copy()
        layers: dict[str, Any] = {}
        region = self._indentation(state, layers if keep_layers else None)
        if region is not None:
            D, v0, v1 = region
            shade = self._shade(D, v0, v1)
            image[v0:v1] = self._apply_static(shade, v0, v1)
            self._count("shading")
        if self._noise is not None:
            effects.add_noise(image, self._noise, frame)
            self._count("noise")
        if "compression" in self.effects:
            image = effects.compress(image, int(self.scene.effect_params("compression")["quality"]))
            self._count("compression")
        return image, layers

    def _rows_for_surface(self, depth: float, pad: int) -> tuple[int, int] | None:
        reach = self._row_max_gap + depth + self._relief_max
        rows = np.flatnonzero(reach > 0)
        if rows.size == 0:
            return None
        return max(0, int(rows[0]) - pad), min(self.camera.height, int(rows[-1]) + 1 + pad)

    def _indenter_box(self, ind: Indenter) -> tuple[int, int, int, int] | None:
        """Pixel box (v0, v1, u0, u1) that the sphere's contact patch can cover, or None if none."""
        cx, cy, cz = ind.centre
        dist = math.hypot(cy, cz)
        alpha = math.atan2(cy, cz)
        r_outer = self.camera.radius + abs(self._thickness_variation)
        overlap = r_outer + ind.radius - dist
        if overlap <= 0:
            return None
        patch = math.sqrt(max(ind.radius**2 - (ind.radius - overlap) ** 2, 0.0)) + 2e-4
        xs = np.array([cx - patch, cx + patch, cx, cx])
        al = np.array([alpha, alpha, alpha - patch / self.camera.radius, alpha + patch / self.camera.radius])
        pts = np.stack([xs, self.camera.radius * np.sin(al), self.camera.radius * np.cos(al)], axis=-1)
        uv, ok = self.camera.project(pts)
        if not ok.any():
            return None
        uv = uv[ok]
        u0, v0 = np.floor(uv.min(axis=0)).astype(int) - 3
        u1, v1 = np.ceil(uv.max(axis=0)).astype(int) + 4
        H, W = self.camera.height, self.camera.width
        u0, u1, v0, v1 = max(0, u0), min(W, u1), max(0, v0), min(H, v1)
        if u0 >= u1 or v0 >= v1:
            return None
        return v0, v1, u0, u1

    def _blur_px(self, state: RollerState) -> float:
        if "blur" not in self.effects:
            return 0.0
        _, mpp_v = self.metres_per_px_at_contact()
        return abs(state.speed) * self.scene.exposure / mpp_v

    def _indentation(self, state: RollerState, layers: dict[str, Any] | None):
        touching = state.depth + self._relief_max > 0 and state.depth > -1.0
        blur_px = self._blur_px(state) if touching else 0.0
        pad = 3 + int(math.ceil(blur_px / 2.0))
        spans = []
        if touching:
            rows = self._rows_for_surface(state.depth, pad)
            if rows is not None:
                spans.append(rows)
            else:
                touching = False
        boxes = [b for b in (self._indenter_box(i) for i in state.indenters) if b is not None]
        spans += [(max(0, b[0] - 3), min(self.camera.height, b[1] + 3)) for b in boxes]
        if not spans:
            if layers is not None:
                layers["indentation"] = np.zeros(self._gap.shape, np.float32)
                layers["relief"] = np.zeros(self._gap.shape, np.float32)
            return None
        v0 = min(s[0] for s in spans)
        v1 = max(s[1] for s in spans)
        D = np.zeros((v1 - v0, self.camera.width), np.float32)
        relief = None
        if touching:
            res = self.surface.resolution
            mx = self._map_x0[v0:v1] + np.float32(state.x_along / res)
            my = self._map_y0[v0:v1] + np.float32(state.travel / res)
            relief = self._relief.remap(mx, my)   # a tiled surface reads only the tiles under the band
            if blur_px > 1.0:
                relief = effects.motion_blur(relief, blur_px)
                self._count("blur")
            D = cv2.add(self._gap[v0:v1], relief)
            D += np.float32(state.depth)
            np.maximum(D, 0.0, out=D)
        for ind, box in zip((i for i in state.indenters if self._indenter_box(i) is not None), boxes, strict=True):
            b0, b1, u0, u1 = box
            sub = D[b0 - v0:b1 - v0, u0:u1]
            np.maximum(sub, sphere_indentation(self._points[b0:b1, u0:u1], ind), out=sub)
            sub *= self._valid[b0:b1, u0:u1]
        self._count("indentation")
        if layers is not None:
            full = np.zeros(self._gap.shape, np.float32)
            full[v0:v1] = D
            layers["indentation"] = full
            rel = np.zeros(self._gap.shape, np.float32)
            if relief is not None:
                rel[v0:v1] = relief
            layers["relief"] = rel
            layers["rows"] = (v0, v1)
        return D, v0, v1

    def _shade(self, D: np.ndarray, v0: int, v1: int) -> np.ndarray:
        """Photometric forward model: Lambertian membrane under three coloured lights, DN float32."""
        gx = cv2.Sobel(D, cv2.CV_32F, 1, 0, ksize=3)
        gx *= self._sobel_ku[v0:v1]
        gy = cv2.Sobel(D, cv2.CV_32F, 0, 1, ksize=3)
        gy *= self._sobel_kv[v0:v1]
        return self._shade_slopes(gx, gy, None if self._irradiance is None else self._irradiance[v0:v1])

    def _shade_slopes(self, gx: np.ndarray, gy: np.ndarray, irradiance: np.ndarray | None = None) -> np.ndarray:
        """Slopes of the membrane towards the camera (dD/dx, dD/ds, float32, consumed) -> bgr DN;
        `irradiance`: the light's relative strength per pixel (same shape; None = uniform)."""
        # unit normal facing the camera: (-gx, -gy, 1) / sqrt(1 + gx^2 + gy^2)
        inv = cv2.magnitude(gx, gy)
        cv2.multiply(inv, inv, dst=inv)
        inv += 1.0
        cv2.sqrt(inv, dst=inv)
        cv2.divide(1.0, inv, dst=inv)
        gx *= inv
        gy *= inv
        channels = []
        for lx, ly, lz in self._lights:
            dot = cv2.addWeighted(gx, -lx, gy, -ly, 0.0)
            dot = cv2.scaleAdd(inv, lz, dot)
            np.maximum(dot, 0.0, out=dot)
            level = cv2.addWeighted(dot, self._dn * self._light_gain, dot, 0.0, self._dn * self._ambient)
            if irradiance is not None:      # the LED makes the gel's diffuse glow too: both scale with it
                level = cv2.multiply(level, irradiance)
            channels.append(level)
        return cv2.merge(channels)

    def _render_board(self, pose: Any) -> np.ndarray:
        image = self._board.render(*pose)
        if self._noise is not None:
            effects.add_noise(image, self._noise)
            self._count("noise")
        if "compression" in self.effects:
            image = effects.compress(image, int(self.scene.effect_params("compression")["quality"]))
        return image
