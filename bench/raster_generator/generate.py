"""Film one raster: the trajectory, TF on /tf and /tf_static, the frames, and the truth beside the bag.

`generate(spec, folder)` writes `folder/bag/` (rosbag2: `/touchroller/image_raw` bgr8, `/tf` base ->
tool0 at `spec.tf_rate` with jitter, `/tf_static` tool0 -> touchroller_cylinder and touchroller_cylinder
-> touchroller_camera as the project's nodes publish them) and `folder/truth.json` + `surface.npy`.
Messages are logged in the order they would arrive: a transform 1 ms after its stamp, a frame at its
stamp (exposure + latency). Only the bag writing uses the project (`touchroller_bringup.bags.write_scan`).
"""
from __future__ import annotations

import math
from collections.abc import Iterator
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation

from bench.raster_generator.motion import Trajectory, pass_spacing, plan
from bench.raster_generator.render import BandRenderer, Camera, Look
from bench.raster_generator.surfaces import Surface, make_surface
from bench.raster_generator.truth import RasterSpec, RasterTruth, write_truth

EPOCH_NS = 1_750_000_000_000_000_000      # the recording's clock at the trajectory's t = 0
SURFACE_MARGIN = 0.03                     # m of surface around the raster rectangle


def raster_surface(spec: RasterSpec) -> Surface:
    """The spec's surface, big enough to hold the raster rectangle (and what the roller sees beyond it)."""
    polygon = spec.area_polygon()
    yaw = math.radians(spec.surface_yaw_deg)
    c, s = math.cos(yaw), math.sin(yaw)
    # the rectangle's extent in the surface's own axes
    local = np.stack([c * polygon[:, 0] + s * polygon[:, 1], -s * polygon[:, 0] + c * polygon[:, 1]], axis=-1)
    low, high = local.min(axis=0) - SURFACE_MARGIN, local.max(axis=0) + SURFACE_MARGIN
    origin = (c * low[0] - s * low[1], s * low[0] + c * low[1], spec.surface_z)
    return make_surface(spec.surface, (float(high[0] - low[0]), float(high[1] - low[1])), origin, yaw,
                        spec.surface_resolution, spec.seed, spec.weave_period, spec.features,
                        feature_margin=SURFACE_MARGIN + 0.006)   # planted inside the raster's extent


def cylinder_rotation(spec: RasterSpec) -> Rotation:
    """touchroller_cylinder in base: x (the axis) across the passes, y along them, z down."""
    axis, roll = spec.across, spec.roll
    matrix = np.array([[axis[0], roll[0], 0.0], [axis[1], roll[1], 0.0], [0.0, 0.0, -1.0]])
    return Rotation.from_matrix(matrix)


def mount(camera: Camera) -> tuple[np.ndarray, Rotation]:
    """tool0 -> touchroller_cylinder: `mount.xyz`, `mount.rpy` (fixed-axis roll, pitch, yaw)."""
    return np.asarray(camera.mount_xyz, dtype=np.float64), Rotation.from_euler("xyz", camera.mount_rpy)


def tool_poses(spec: RasterSpec, camera: Camera, trajectory: Trajectory, times: np.ndarray
               ) -> tuple[np.ndarray, np.ndarray]:
    """base -> tool0 at `times` (s): translations (N, 3) and quaternions (N, 4, x y z w)."""
    u, w, h = trajectory.at(times)
    xy = spec.to_base(u, w)
    z = spec.surface_z + camera.radius - spec.motion.depth + h
    axis_position = np.concatenate([xy, z[:, None]], axis=1)
    r_cyl = cylinder_rotation(spec)
    t_mount, r_mount = mount(camera)
    r_tool = r_cyl * r_mount.inv()
    tool = axis_position - r_tool.apply(t_mount)
    quat = np.tile(r_tool.as_quat(), (len(times), 1))
    return tool, quat


def camera_static(camera: Camera) -> tuple[tuple[float, float, float], tuple[float, float, float, float]]:
    """touchroller_cylinder -> touchroller_camera: the optical frame of the camera contract (theta, d)."""
    c, s = math.cos(camera.theta), math.sin(camera.theta)
    rotation = Rotation.from_matrix(np.array([[1.0, 0.0, 0.0], [0.0, c, s], [0.0, -s, c]]).T)
    q = rotation.as_quat()
    return (0.0, s * camera.d, -c * camera.d), (float(q[0]), float(q[1]), float(q[2]), float(q[3]))


def _xyz(v: np.ndarray) -> tuple[float, float, float]:
    return float(v[0]), float(v[1]), float(v[2])


def _quaternion(q: np.ndarray) -> tuple[float, float, float, float]:
    return float(q[0]), float(q[1]), float(q[2]), float(q[3])


def _records(spec: RasterSpec, camera: Camera, renderer: BandRenderer, trajectory: Trajectory,
             rng: np.random.Generator) -> Iterator[tuple[int, object]]:
    """(arrival ns, record) of everything the bag holds, in arrival order."""
    from touchroller_bringup.bags import ImageRecord, TransformRecord

    end = float(trajectory.t[-1])
    t_mount, r_mount = mount(camera)
    q_mount = r_mount.as_quat()
    camera_xyz, camera_q = camera_static(camera)
    yield 0, TransformRecord("tool0", "touchroller_cylinder", EPOCH_NS, _xyz(t_mount), _quaternion(q_mount), True)
    yield 0, TransformRecord("touchroller_cylinder", "touchroller_camera", EPOCH_NS, camera_xyz, camera_q, True)
    period = 1.0 / spec.tf_rate
    tf_times = np.arange(0.0, end, period)
    tf_times = np.clip(tf_times + rng.uniform(-spec.tf_jitter, spec.tf_jitter, len(tf_times)) * period, 0.0, end)
    tf_times = np.sort(tf_times)
    translations, quats = tool_poses(spec, camera, trajectory, tf_times)
    frame_times = np.arange(0.0, end - spec.latency - 0.05, 1.0 / spec.fps) + 0.05
    frame_times = frame_times + rng.normal(0.0, spec.frame_jitter_s, len(frame_times))
    pending = [(int(round((t + 1e-3) * 1e9)), "tf", i) for i, t in enumerate(tf_times)]
    pending += [(int(round((t + spec.latency) * 1e9)), "image", i) for i, t in enumerate(frame_times)]
    pending.sort()
    look = renderer.look
    offsets = (np.arange(look.exposure_samples) + 0.5) / look.exposure_samples - 0.5
    for arrival, kind, i in pending:
        if kind == "tf":
            stamp = EPOCH_NS + int(round(tf_times[i] * 1e9))
            yield arrival, TransformRecord("base", "tool0", stamp, _xyz(translations[i]), _quaternion(quats[i]), False)
            continue
        exposure = frame_times[i] + offsets * look.exposure_s
        u, w, h = trajectory.at(exposure)
        xy = spec.to_base(u, w)
        image = renderer.frame([(xy[k], spec.roll, float(h[k])) for k in range(len(exposure))])
        stamp = EPOCH_NS + int(round((frame_times[i] + spec.latency) * 1e9))
        yield arrival, ImageRecord(stamp, image)


DEFAULT_CAMERA, DEFAULT_LOOK = Camera(), Look()


def sensor(spec: RasterSpec, camera: Camera = DEFAULT_CAMERA, look: Look = DEFAULT_LOOK,
           surface: Surface | None = None, depth: float | None = None) -> BandRenderer:
    """The camera of the roller that films `spec`: its flat field (vignetting, the LEDs' fall-off, the dust
    specks on the gel) and its lifted-roller frame are seeded by `spec.seed`, so this is one sensor. Pressed on
    `surface` (the raster's own by default) at `depth` (the raster's by default): what a calibration of the
    raster's sensor films (its ball presses and its no-contact reference), as a user calibrates the very sensor
    that scans."""
    return BandRenderer(camera, raster_surface(spec) if surface is None else surface, look,
                        depth=spec.motion.depth if depth is None else depth, seed=spec.seed)


def generate(spec: RasterSpec, folder: str | Path, camera: Camera = DEFAULT_CAMERA, look: Look = DEFAULT_LOOK
             ) -> RasterTruth:
    """Film `spec` into `folder` (bag/, truth.json, surface.npy); the folder's bag must not exist yet."""
    from touchroller_bringup.bags import ImageRecord, write_scan

    folder = Path(folder)
    surface = raster_surface(spec)
    trajectory = plan(spec.length, pass_spacing(spec.width, spec.passes), spec.motion)
    renderer = sensor(spec, camera, look, surface)
    rng = np.random.default_rng(np.random.SeedSequence([spec.seed, 2207]))
    frames = 0

    def counted() -> Iterator[object]:
        nonlocal frames
        for _, record in _records(spec, camera, renderer, trajectory, rng):
            frames += isinstance(record, ImageRecord)
            yield record

    folder.mkdir(parents=True, exist_ok=True)
    write_scan(folder / "bag", counted(), storage=spec.storage)   # type: ignore[arg-type]
    truth = RasterTruth(spec, camera, look, surface, trajectory.passes, EPOCH_NS, frames)
    write_truth(folder, truth)
    return truth
