"""The world height map against the true relief, in place, in our simulator.

A 2-pass raster (4 cm x 9 cm at 20 mm/s, pressed 0.5 mm, filmed 30 ms late, latency told) over the
`large_surface` scene's grained surface (0.3 mm relief) and its `panel` variant (planted cracks and dents
in 2 um of orange peel), mapped with a photometric model calibrated on the fly from the `ball_presses`
scene of the same sensor (`touchroller_driver.sim.photometric`), placed by `WorldMapper` with a
`HeightSource`. Score: the map against `SimulatedSensor.world_truth` (the relief as the membrane follows
it) on the same cells, no alignment, over the cells mapped at least 1 mm inside the mapped area: RMS
error after removing one best plane, and correlation. This rests on our simulator alone (the same light
model calibrated and measured).

The same on a source that shares nothing with the simulator: the second raster generator
(bench/raster_generator: its own contact model, LEDs with a specular highlight, flat field and sensor
noise, each pixel the mean shading over its footprint, its own grained surface with planted grooves and
pits, its own rosbag2 recording). Its sensor (the raster's own camera: the same flat field, dust specks and
lifted-roller frame, `raster_generator.sensor`) is calibrated as a user would: a 4 mm ball cap pressed 0.6 mm
at random places over the band the map is made from (along the axis nearly across the image, around it over
the rows the mapper places: the model learns how a slope looks where it is, and cannot extrapolate where no
press was), rendered by the generator, each press labelled by `find_press` (no truth), the pixel size and the
roller's radius from config/touchroller.yaml's camera model, calibrated as a world map's calibration is
(`touchroller_perception.height.MAP_CALIBRATION`: the features smoothed by 1 px, the position degree chosen on
held-out presses; the map reads its frames with `WorldHeightConfig`'s defaults); its raster is mapped by
`touchroller map --photometric --reference` as a whole command, and height.tif is scored against the
generator's surface (low-passed as its gel is) in place, on the cells 1 mm inside height.tif's mapped area.

Beside the figures, the maps read with other height configurations (`HEIGHT_CONFIGS`: the default, the one it
replaced and the alternatives tried; `WorldHeightConfig.slopes` and `smoothing`): the simulator's grained
surface in process, and the second generator's raster by the same `touchroller map` with its height source given
that configuration; the second generator also on another seed (`SECOND_SEEDS`: its own surface, sensor and
calibration presses), so that a default is not chosen on the scored raster alone; and the second generator's
frames read one at a time against the indentation it pressed (`frame_gains`): where a fine relief's depth is
lost, reading a frame or placing the frames on the map.
"""
from __future__ import annotations

import argparse
import contextlib
import dataclasses
import json
import math
import sys
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from bench._common import ROOT, Provenance, provenance, provenance_markdown, results_path, to_json
from touchroller_perception.files import atomic_write_text

PARAMS = ROOT / "config" / "touchroller.yaml"
GOAL_RMS_UM = 10.0
GOAL_CORRELATION = 0.95
# where the second generator's calibration presses land (m from the contact line's centre): along the axis
# nearly across the image (+-32 mm at the contact line), around it so that the 2.2 mm contacts cover the rows
# the world mapper places (+-3.5 mm)
PRESS_ALONG, PRESS_ACROSS = 0.029, 1.5e-3
# the grained surface's map again with other calibrations (presses, seed): other places of the same count, and
# other counts: the figure must not rest on one lucky draw of the presses
DRAWS = ((24, 1), (24, 2), (24, 3), (16, 0), (48, 0))
# the second generator's calibration ball: radius, cap height above the base, its height field's resolution (m)
CALIBRATION_BALL = (4e-3, 8e-4, 5e-5)


@dataclasses.dataclass(frozen=True)
class WavelengthGain:
    """The map against the true relief over one band of wavelengths (on the largest fully mapped rectangle,
    Hann-windowed): how much of the relief's amplitude there the map reads (the cross-spectrum over the
    truth's power), how well it follows (coherence), and the band's share of the relief's power."""

    shortest_mm: float
    longest_mm: float
    gain: float
    coherence: float
    relief_share: float


#: the wavelength bands of `wavelength_gains`, mm
WAVELENGTH_BANDS = ((0.2, 0.3), (0.3, 0.4), (0.4, 0.5), (0.5, 0.6), (0.6, 0.8), (0.8, 1.0), (1.0, 1.6), (1.6, 3.2),
                    (3.2, 6.4))


@dataclasses.dataclass(frozen=True)
class CutoffCorrelation:
    """The map against the true relief with both low-passed alike (wavelengths longer than `longer_than_mm`
    kept): their correlation and their difference's RMS."""

    longer_than_mm: float
    correlation: float
    rms_um: float


#: the low-pass cut-offs of `cutoff_correlations`, mm
CUTOFFS_MM = (0.2, 0.3, 0.4, 0.5, 0.6, 0.8, 1.0, 1.6, 3.2)


@dataclasses.dataclass(frozen=True)
class SurfaceScore:
    surface: str
    relief_rms_um: float      # the true relief on the scored cells, its best plane removed
    rms_um: float             # the error, its best plane removed
    correlation: float
    cells: int
    passes: int
    fine_cells: int           # cells where the true relief departs from its 2 mm-smoothed self by > 3 um
    fine_scale: float         # there, the map's departure against the truth's (least squares): read / true
    fine_correlation: float
    frames_mapped: int        # mapped (simulator) or filmed (second generator)
    map_cpu_s: float          # mapping CPU s (simulator) or `touchroller map`'s wall s (second generator)
    wavelengths: list[WavelengthGain] = dataclasses.field(default_factory=list)   # the map by wavelength band
    cutoffs: list[CutoffCorrelation] = dataclasses.field(default_factory=list)    # low-passed alike, by cut-off


@dataclasses.dataclass(frozen=True)
class PressDraw:
    """The grained surface's map with the calibration of another press count or other press places."""

    presses: int
    seed: int
    position_degree: int      # the degree the calibration chose on its held-out presses
    rms_um: float
    correlation: float


#: the map read with other `WorldHeightConfig`s: (label, its fields other than the defaults). The first is the
#: default; the others are what it replaced and the alternatives tried, kept as rows of the bench's table
HEIGHT_CONFIGS: tuple[tuple[str, dict[str, Any]], ...] = (
    ("footprint slopes, image smoothed 0.5 px (default)", {}),
    ("centre slopes, 0.5 px (the earlier default)", {"slopes": "centre"}),
    ("footprint slopes, no smoothing", {"smoothing": 0.0}),
    ("centre slopes, the model's 1 px", {"slopes": "centre", "smoothing": None}),
)
#: the second generator's other raster (its own surface, sensor and calibration presses): the defaults must hold
#: beyond the raster scored
SECOND_SEEDS = (0, 1)


@dataclasses.dataclass(frozen=True)
class ConfigScore:
    """One surface's map read with one `HEIGHT_CONFIGS` entry: the error after one best plane, the correlation,
    and the gain at the 0.3-0.4, 0.4-0.5 and 0.5-0.6 mm wavelengths."""

    config: str
    surface: str
    seed: int
    rms_um: float
    correlation: float
    fine_gains: list[float] = dataclasses.field(default_factory=list)


@dataclasses.dataclass(frozen=True)
class FrameGain:
    """The second generator's frames read one at a time with one `HEIGHT_CONFIGS` entry, against the indentation
    the generator pressed (at the pixel centres, its gel's low pass included): the gain and coherence by
    wavelength (`WAVELENGTH_BANDS`), pooled over the frames. Set beside the map's, it tells what is lost reading
    a frame (smoothing, colour to slope, integration) from what is lost placing the frames on the map."""

    config: str
    seed: int
    frames: int
    gains: list[float]
    coherences: list[float]


#: the second generator's frames read one at a time (`FrameGain`): how many, pressed along the raster's first pass,
#: and the image window scored (rows around the contact line, columns in from the image's sides)
FRAME_COUNT, FRAME_ROWS, FRAME_COLUMNS = 12, 40, 40


@dataclasses.dataclass(frozen=True)
class HeightMapResult:
    provenance: Provenance
    quick: bool
    presses: int
    normal_error_deg: float   # the calibration's in-sample fit
    surfaces: list[SurfaceScore]
    second_normal_error_deg: float = math.nan   # the second generator's calibration, in-sample
    position_degree: int = -1                   # the simulator's calibration's chosen position degree
    second_position_degree: int = -1            # the second generator's
    draws: list[PressDraw] = dataclasses.field(default_factory=list)
    configs: list[ConfigScore] = dataclasses.field(default_factory=list)   # the maps with other height configs
    frames: list[FrameGain] = dataclasses.field(default_factory=list)      # the frames read one at a time


def _config_score(config: str, surface: str, seed: int, score: SurfaceScore) -> ConfigScore:
    gains = [w.gain for w in score.wavelengths if 0.3 <= w.shortest_mm < 0.6]
    return ConfigScore(config, surface, seed, score.rms_um, score.correlation, gains)


def _detrended(values: np.ndarray, rows: np.ndarray, cols: np.ndarray) -> np.ndarray:
    A = np.c_[np.ones(len(values)), rows, cols]
    coef, *_ = np.linalg.lstsq(A, values, rcond=None)
    out: np.ndarray = values - A @ coef
    return out


def score_surface(variant: str | None, presses: int, draws: tuple[tuple[int, int], ...] = (),
                  configs: tuple[tuple[str, dict[str, Any]], ...] = ()
                  ) -> tuple[SurfaceScore, float, int, list[PressDraw], list[ConfigScore]]:
    """The surface's map with the default calibration (seed 0, `presses`): its score, the calibration's
    in-sample fit and chosen position degree; the same raster mapped with the calibrations of `draws`
    ((presses, seed) each: other press counts and other places of the presses); and with the default
    calibration read with the `WorldHeightConfig`s of `configs` (label, fields)."""
    from bench.world_map import map_events
    from touchroller_driver.arm import (
        DEFAULT_MOUNT_RPY,
        DEFAULT_MOUNT_XYZ,
        DEFAULT_START_POSE,
        mount_transform,
        plan_raster,
    )
    from touchroller_driver.sim import SimulatedSensor, load_scene
    from touchroller_driver.sim.camera import surface_frame
    from touchroller_driver.sim.photometric import SimPhotometric, sim_photometric
    from touchroller_driver.sim.sweep import simulate_sweep
    from touchroller_perception.transforms import TransformBuffer
    from touchroller_perception.world_height import HeightSource, WorldHeightConfig
    from touchroller_perception.world_map import WorldMapConfig, WorldMapper, buffer_lookup

    sensor = SimulatedSensor(load_scene("large_surface", variant=variant), seed=0)
    mount = mount_transform(DEFAULT_MOUNT_XYZ, DEFAULT_MOUNT_RPY)
    area = [0.42, -0.045, 0.04, 0.09]
    plan = plan_raster(np.array(DEFAULT_START_POSE), area=area, mount=mount, speed=0.02, accel=0.1, depth=5e-4,
                       clearance=0.002, approach_speed=0.005)
    events = list(simulate_sweep(sensor, plan, np.array(plan.segments[0].target), mount, latency_s=0.03))
    bounds = (area[0] - 0.01, area[1] - 0.04, area[0] + area[2] + 0.01, area[1] + area[3] + 0.04)
    name = "grain" if variant is None else variant
    truths: dict[tuple[object, ...], np.ndarray] = {}

    def mapped(photometric: SimPhotometric, config: WorldHeightConfig | None = None) -> SurfaceScore:
        buffer = TransformBuffer(cache_ns=None)
        buffer.set_transform("tool0", "touchroller_cylinder", 0, mount, static=True)
        mapper = WorldMapper(sensor.camera, buffer_lookup(buffer, "base", "touchroller_cylinder"),
                             WorldMapConfig(bounds=bounds, latency=0.03),
                             height=HeightSource(photometric.calibration.model, photometric.reference,
                                                 config or WorldHeightConfig()))
        cpu = map_events(mapper, buffer, events)
        layer = mapper.height_layer(crop=False)
        if layer is None:
            raise RuntimeError("no height was mapped")
        height = layer.height
        key = (layer.origin, height.shape, layer.resolution)
        if key not in truths:
            truths[key], _ = sensor.world_truth(surface_frame(sensor.scene), layer.origin, height.shape,
                                                layer.resolution)
        return _score(name, height, truths[key], mapper.stats.passes, mapper.stats.mapped, cpu, layer.resolution)

    photometric = sim_photometric(sensor, presses=presses)
    score = mapped(photometric)
    others = []
    for count, seed in draws:
        other = sim_photometric(sensor, seed=seed, presses=count)
        result = mapped(other)
        others.append(PressDraw(count, seed, other.calibration.model.config.position_degree, result.rms_um,
                                result.correlation))
    rows = [_config_score(label, name, 0, score if not fields else mapped(photometric, WorldHeightConfig(**fields)))
            for label, fields in configs]
    chosen = photometric.calibration.model.config.position_degree
    return score, float(photometric.calibration.normal_error_deg), chosen, others, rows


def second_raster_spec(seed: int = 0) -> object:
    """The second generator's raster this bench maps (a `RasterSpec`; its seed is also its surface's and its
    sensor's)."""
    from bench.raster_generator import MotionConfig, RasterSpec

    return RasterSpec(surface="grained", corner=(0.42, -0.045), length=0.04, width=0.09, passes=2, latency=0.03,
                      tf_rate=125.0, motion=dataclasses.replace(MotionConfig(), profile="blend"), seed=seed)


def _calibration_renderer(camera: object, look: object, seed: int = 0) -> object:
    """The second generator's raster's own sensor (`raster_generator.sensor`: the same flat field, dust specks
    and lifted-roller frame as the raster's frames) pressing the calibration ball, the roller held 0.2 mm above
    the base (a 0.8 mm cap: 0.6 mm pressed). A no-contact reference is of the sensor that scans (docs/height.md):
    one of another sensor (its dust elsewhere) reads every speck of either as a slope that stays put in the image,
    a streak along the passes in the map."""
    from bench.raster_generator import sensor
    from bench.raster_generator.surfaces import Surface

    radius, cap, resolution = CALIBRATION_BALL
    n = int(12e-3 / resolution)
    yy, xx = (np.mgrid[0:n, 0:n] + 0.5) * resolution - 6e-3
    height = np.maximum(np.sqrt(np.maximum(radius**2 - xx**2 - yy**2, 0.0)) - (radius - cap), 0.0)
    surface = Surface("grained", height.astype(np.float32), resolution, (0.5 - 6e-3, -6e-3, 0.0), 0.0, ())
    return sensor(second_raster_spec(seed), camera, look, surface, depth=-2e-4)   # type: ignore[arg-type]


def _second_generator_calibration(presses: int, seed: int = 0) -> tuple[object, np.ndarray, float]:
    """(photometric model, reference, in-sample fit deg) of the second generator's sensor, from ball caps."""
    from bench.raster_generator import Look, load_camera
    from touchroller_bringup.commands import read_calibration
    from touchroller_perception.height import (
        MAP_CALIBRATION,
        BallPress,
        calibrate_photometric,
        find_press,
        pixel_size_at,
    )

    camera, look = load_camera(str(PARAMS)), dataclasses.replace(Look(), exposure_samples=1)
    model_camera = read_calibration(PARAMS)
    radius = CALIBRATION_BALL[0]
    renderer: Any = _calibration_renderer(camera, look, seed)
    rng = np.random.default_rng(5)
    roll, axis = np.array([1.0, 0.0]), np.array([0.0, 1.0])
    reference = np.median(np.stack([renderer.frame([(np.array([0.3, 0.3]), roll, 5e-3)]) for _ in range(5)]),
                          axis=0).astype(np.uint8)
    items = []
    for k in range(presses):
        along, across = rng.uniform(-PRESS_ALONG, PRESS_ALONG), rng.uniform(-PRESS_ACROSS, PRESS_ACROSS)
        image = renderer.frame([(np.array([0.5, 0.0]) - along * axis - across * roll, roll, 0.0)])
        u, v, r = find_press(image, reference)
        items.append(BallPress(image, u, v, r, pixel_size_at(model_camera, u, v), str(k), float(model_camera.radius)))
    calibration = calibrate_photometric(items, reference, radius, MAP_CALIBRATION)
    return calibration.model, reference, float(calibration.normal_error_deg)


def _band_gains(pairs: list[tuple[np.ndarray, np.ndarray]]) -> tuple[list[float], list[float]]:
    """Gain and coherence of read against true by `WAVELENGTH_BANDS` (frequency in cycles per pixel of 0.1 mm),
    each pair less its mean and Hann-windowed, the spectra pooled over the pairs."""
    cross = np.zeros(len(WAVELENGTH_BANDS), complex)
    power, mine = np.zeros(len(WAVELENGTH_BANDS)), np.zeros(len(WAVELENGTH_BANDS))
    for read, true in pairs:
        window = np.outer(np.hanning(read.shape[0]), np.hanning(read.shape[1]))
        a = np.fft.rfft2((read - read.mean()) * window)
        b = np.fft.rfft2((true - true.mean()) * window)
        f = np.hypot(np.fft.fftfreq(read.shape[0])[:, None], np.fft.rfftfreq(read.shape[1])[None, :])
        for k, (short, long) in enumerate(WAVELENGTH_BANDS):
            band = (f > 0.1 / long) & (f <= 0.1 / short)
            cross[k] += complex((a[band] * b[band].conj()).sum())
            power[k] += float((np.abs(b[band]) ** 2).sum())
            mine[k] += float((np.abs(a[band]) ** 2).sum())
    ok = (power > 0) & (mine > 0)
    gains = np.where(ok, cross.real / np.where(ok, power, 1.0), math.nan)
    coherence = np.where(ok, np.abs(cross) / np.sqrt(np.where(ok, power * mine, 1.0)), math.nan)
    return [float(g) for g in gains], [float(c) for c in coherence]


def frame_gains(model: object, reference: np.ndarray, seed: int, configs: tuple[tuple[str, dict[str, Any]], ...]
                ) -> list[FrameGain]:
    """The second generator's raster sensor (of `seed`) pressed on its surface at `FRAME_COUNT` places along the
    first pass, each frame read by `BandHeights` with each of `configs` and scored against the indentation the
    generator pressed there, at the pixel centres (the membrane's depth under the tube, its gel's low pass as the
    generator applies it), over `FRAME_ROWS` rows either side of the contact line."""
    from bench.raster_generator import Look, load_camera, sensor
    from touchroller_bringup.commands import read_calibration
    from touchroller_perception.stitching import BandSampler
    from touchroller_perception.world_height import BandHeights, WorldHeightConfig

    camera, look = load_camera(str(PARAMS)), dataclasses.replace(Look(), exposure_samples=1)
    spec: Any = second_raster_spec(seed)
    renderer = sensor(spec, camera, look)
    model_camera = read_calibration(PARAMS)
    sampler = BandSampler((camera.height, camera.width), 70, model_camera, None, True)   # as `touchroller map`
    n = look.pixel_samples
    roll = np.asarray(spec.roll, np.float32)
    axis = np.array([-roll[1], roll[0]], np.float32)
    frames = []
    for u in np.linspace(0.1, 0.9, FRAME_COUNT) * spec.length:
        position = spec.to_base(u, 0.0).astype(np.float32)
        image = renderer.frame([(position, roll, 0.0)])
        xy = position + renderer.x_axial[..., None] * axis + renderer.y_roll[..., None] * roll
        pressed = renderer.tube - renderer.membrane(-renderer.surface.sample(xy))
        if look.gel_blur_px:
            pressed = cv2.GaussianBlur(pressed, (0, 0), look.gel_blur_px * n)
        frames.append((image, pressed[n // 2::n, n // 2::n], renderer.rows.start))
    centre = int(round(camera.cy - camera.fy * math.tan(camera.theta)))
    out = []
    for label, fields in configs:
        reader = BandHeights(model, reference, model_camera, sampler, WorldHeightConfig(**fields))  # type: ignore[arg-type]
        v0 = reader.rows[0]
        pairs = []
        for image, pressed, first in frames:
            read = reader.indentation(image)
            rows = slice(centre - FRAME_ROWS, centre + FRAME_ROWS)
            cols = slice(FRAME_COLUMNS, camera.width - FRAME_COLUMNS)
            pairs.append((read[rows.start - v0:rows.stop - v0, cols].astype(np.float64),
                          pressed[rows.start - first:rows.stop - first, cols].astype(np.float64)))
        gains, coherences = _band_gains(pairs)
        out.append(FrameGain(label, seed, len(pairs), gains, coherences))
    return out


@contextlib.contextmanager
def _height_config(config: object | None) -> Iterator[None]:
    """`touchroller map` reads its frames' height with `config` (a `WorldHeightConfig`; the command itself takes
    the defaults): its height source, loaded by the command as always, given that config. None: as it is."""
    from touchroller_bringup.commands import map as command

    if config is None:
        yield
        return
    original = command._height_source

    def source(args: argparse.Namespace) -> Any:
        found = original(args)
        return None if found is None else dataclasses.replace(found, config=config)

    command._height_source = source
    try:
        yield
    finally:
        command._height_source = original


def second_generator(presses: int, seed: int = 0, configs: tuple[tuple[str, dict[str, Any]], ...] = ()
                     ) -> tuple[SurfaceScore, float, int, list[ConfigScore], list[FrameGain]]:
    """The second generator's grained raster (of `seed`: its surface and sensor) mapped by `touchroller map` with
    its own calibration: the score with the defaults, the calibration's fit and position degree, the same bag
    mapped with the `WorldHeightConfig`s of `configs` (label, fields), and its frames read one at a time with
    each (`frame_gains`)."""
    import shutil
    import tempfile

    from bench.raster_generator import Look, generate, load_camera
    from touchroller_bringup.cli import main as cli
    from touchroller_bringup.map_files import read_height_tif
    from touchroller_perception.world_height import WorldHeightConfig

    model, reference, fit = _second_generator_calibration(presses, seed)
    camera, look = load_camera(str(PARAMS)), dataclasses.replace(Look(), exposure_samples=1)
    tmp = Path(tempfile.mkdtemp(prefix="height_map_"))
    name = "grained (second generator)"
    try:
        model.save(tmp / "photometric.npz")   # type: ignore[attr-defined]
        cv2.imwrite(str(tmp / "reference.png"), reference)
        truth = generate(second_raster_spec(seed), tmp / "raster", camera=camera, look=look)   # type: ignore[arg-type]
        sigma_m = look.gel_blur_px * camera.radius / camera.fx   # the gel's low pass, as the generator's
        true_heights: dict[tuple[object, ...], np.ndarray] = {}

        def mapped(config: object | None) -> SurfaceScore:
            out = tmp / "map.png"
            begin = time.perf_counter()
            with _height_config(config):
                code = cli(["map", str(tmp / "raster" / "bag"), "--out", str(out), "--latency", "0.03",
                            "--photometric", str(tmp / "photometric.npz"), "--reference", str(tmp / "reference.png")])
            seconds = time.perf_counter() - begin
            if code != 0:
                raise RuntimeError(f"touchroller map failed on the second generator's raster ({code})")
            top_down, (x0, y_top), resolution = read_height_tif(tmp / "height.tif")
            height = top_down[::-1]
            key = (x0, y_top, height.shape, resolution)
            if key not in true_heights:
                rows, cols = height.shape
                xs = x0 + (np.arange(cols) + 0.5) * resolution
                ys = y_top - rows * resolution + (np.arange(rows) + 0.5) * resolution
                grid = np.stack(np.meshgrid(xs, ys), axis=-1)
                true_heights[key] = cv2.GaussianBlur(truth.surface.sample(grid).astype(np.float64), (0, 0),
                                                     sigma_m / resolution)
            return _score(name, height, true_heights[key], 2, truth.frames, seconds, resolution)

        score = mapped(None)
        rows = [_config_score(label, name, seed, score if not fields else mapped(WorldHeightConfig(**fields)))
                for label, fields in configs]
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    per_frame = frame_gains(model, reference, seed, configs) if configs else []
    return score, fit, int(model.config.position_degree), rows, per_frame   # type: ignore[attr-defined]


def _spectra(height: np.ndarray, truth: np.ndarray
             ) -> tuple[np.ndarray, np.ndarray, np.ndarray, tuple[int, int]] | None:
    """(map's, truth's rfft2, frequency in cycles per cell, the rectangle's shape) on the rectangle of the rows
    mapped nearly as widely as the widest and the columns mapped throughout on them (20 cells in from its edges),
    each less its mean and Hann-windowed; None when too little is mapped."""
    known = np.isfinite(height)
    share = known.mean(axis=1)
    rows = np.flatnonzero(share >= 0.9 * share.max()) if share.max() > 0 else np.zeros(0, int)
    if len(rows) < 80:
        return None
    r0, r1 = int(rows.min()) + 20, int(rows.max()) - 20
    cols = np.flatnonzero(known[r0:r1].all(axis=0))
    if len(cols) < 80 or r1 - r0 < 40:
        return None
    c0, c1 = int(cols.min()) + 20, int(cols.max()) - 20
    mine = np.nan_to_num(height[r0:r1, c0:c1].astype(np.float64), nan=float(np.nanmean(height[r0:r1, c0:c1])))
    true = truth[r0:r1, c0:c1].astype(np.float64)
    window = np.outer(np.hanning(r1 - r0), np.hanning(c1 - c0))
    a = np.fft.rfft2((mine - mine.mean()) * window)
    b = np.fft.rfft2((true - true.mean()) * window)
    f = np.hypot(np.fft.fftfreq(r1 - r0)[:, None], np.fft.rfftfreq(c1 - c0)[None, :])
    return a, b, f, (r1 - r0, c1 - c0)


def wavelength_gains(height: np.ndarray, truth: np.ndarray, resolution: float) -> list[WavelengthGain]:
    """The map's gain and coherence against the truth by wavelength band (`WAVELENGTH_BANDS`, mm), on the
    rectangle `_spectra` takes, Hann-windowed."""
    spectra = _spectra(height, truth)
    if spectra is None:
        return []
    a, b, f, _ = spectra
    cross, power, mine_power = (a * b.conj()), np.abs(b) ** 2, np.abs(a) ** 2
    total = float(power[f > 0].sum())
    out = []
    for short, long in WAVELENGTH_BANDS:
        band = (f > resolution * 1e3 / long) & (f <= resolution * 1e3 / short)   # cycles per cell
        p = float(power[band].sum())
        c = complex(cross[band].sum())
        out.append(WavelengthGain(short, long, c.real / p if p else math.nan,
                                  abs(c) / math.sqrt(p * float(mine_power[band].sum())) if p else math.nan,
                                  p / total if total else math.nan))
    return out


def cutoff_correlations(height: np.ndarray, truth: np.ndarray, resolution: float) -> list[CutoffCorrelation]:
    """The map's correlation with the truth (and their difference's RMS) with both low-passed alike: only the
    wavelengths longer than each of `CUTOFFS_MM` kept (an ideal low pass), on the rectangle `_spectra` takes
    (Hann-windowed; the RMS divided by the window's): where the correlation is lost, at the short wavelengths or
    the long."""
    spectra = _spectra(height, truth)
    if spectra is None:
        return []
    a, b, f, shape = spectra
    # the window's RMS: the difference's RMS read back in the relief's units
    scale = 1e6 / math.sqrt(float(np.mean(np.outer(np.hanning(shape[0]), np.hanning(shape[1])) ** 2)))
    out = []
    for cut in CUTOFFS_MM:
        keep = f <= resolution * 1e3 / cut   # cycles per cell
        x = np.fft.irfft2(a * keep, s=shape)
        y = np.fft.irfft2(b * keep, s=shape)
        out.append(CutoffCorrelation(cut, float(np.corrcoef(x.ravel(), y.ravel())[0, 1]),
                                     float(np.sqrt(np.mean((x - y) ** 2)) * scale)))
    return out


def _score(name: str, height: np.ndarray, truth: np.ndarray, passes: int, frames: int, seconds: float,
           resolution: float) -> SurfaceScore:
    known = np.isfinite(height)
    # 1 mm in from the mapped area's edge, also where it reaches the raster's edge (height.tif spans the mapped
    # cells alone: beyond the raster nothing is mapped, not everything)
    inside = cv2.erode(known.astype(np.uint8), np.ones((21, 21), np.uint8), borderType=cv2.BORDER_CONSTANT,
                       borderValue=0) > 0
    rows, cols = np.nonzero(inside)
    mine, true = height[inside].astype(np.float64), truth[inside].astype(np.float64)
    error = _detrended(mine - true, rows, cols)
    relief = _detrended(true, rows, cols)
    # the fine relief (planted cracks, dents, grooves, pits and the grain's finer part): each against its
    # own 2 mm (20 cell) Gaussian, on the mapped cells
    weight = cv2.GaussianBlur(inside.astype(np.float32), (0, 0), 20.0)

    def fine(values: np.ndarray) -> np.ndarray:
        filled = np.where(inside, values, 0.0).astype(np.float32)
        smooth = cv2.GaussianBlur(filled, (0, 0), 20.0) / np.maximum(weight, 1e-6)
        return (filled - smooth)[inside].astype(np.float64)

    fine_mine, fine_true = fine(height), fine(truth)
    planted = np.abs(fine_true) > 3e-6
    a, b = fine_mine[planted], fine_true[planted]
    scale = float(a @ b / (b @ b)) if planted.sum() > 10 else math.nan
    corr = float(np.corrcoef(a, b)[0, 1]) if planted.sum() > 10 else math.nan
    return SurfaceScore(name, float(relief.std() * 1e6), float(np.sqrt(np.mean(error**2)) * 1e6),
                        float(np.corrcoef(_detrended(mine, rows, cols), relief)[0, 1]), int(inside.sum()), passes,
                        int(planted.sum()), scale, corr, frames, seconds, wavelength_gains(height, truth, resolution),
                        cutoff_correlations(height, truth, resolution))


def _second_presses(quick: bool) -> int:
    """The second generator's calibration presses: they cover the whole band, as many as a full set."""
    return 16 if quick else 32


def run(quick: bool = False) -> HeightMapResult:
    import inspect

    from touchroller_driver.sim.photometric import sim_photometric

    stamp = provenance("height_map", quick)
    # the simulator's model from as many presses as `touchroller scan --height` makes it from (the default):
    # how the presses land moves the map's smooth error along the axis (see docs/height.md)
    presses = 8 if quick else int(inspect.signature(sim_photometric).parameters["presses"].default)
    configs = HEIGHT_CONFIGS if not quick else HEIGHT_CONFIGS[:2]
    scores, fit, degree, draws, rows = [], math.nan, -1, [], []
    for variant in ((None,) if quick else (None, "panel")):
        score, error, chosen, others, by_config = score_surface(
            variant, presses, DRAWS if variant is None and not quick else (), configs if variant is None else ())
        scores.append(score)
        rows += by_config
        if variant is None:
            fit, degree, draws = error, chosen, others
    second, second_fit, second_degree, by_config, per_frame = second_generator(_second_presses(quick), 0, configs)
    scores.append(second)
    rows += by_config
    for seed in SECOND_SEEDS[1:] if not quick else ():
        other = second_generator(_second_presses(quick), seed, configs)
        rows += other[3]
        per_frame += other[4]
    return HeightMapResult(stamp, quick, presses, fit, scores, second_fit, degree, second_degree, draws, rows,
                           per_frame)


def goals(r: HeightMapResult) -> list[tuple[str, str, bool | None]]:
    grain = next((s for s in r.surfaces if s.surface == "grain"), None)
    second = next((s for s in r.surfaces if "second" in s.surface), None)
    rows = []
    if second is not None:
        rows += [("World height map, second generator's grained surface: RMS error after one best plane",
                  f"{second.rms_um:.1f} um (goal <= {GOAL_RMS_UM:g} um)", second.rms_um <= GOAL_RMS_UM),
                 ("World height map, second generator's grained surface: correlation with the true relief",
                  f"{second.correlation:.3f} (goal >= {GOAL_CORRELATION:g})", second.correlation >= GOAL_CORRELATION)]
    if grain is None:
        return rows
    return rows + [("World height map, grained surface (simulator): RMS error after one best plane",
             f"{grain.rms_um:.1f} um (goal <= {GOAL_RMS_UM:g} um)", grain.rms_um <= GOAL_RMS_UM),
            ("World height map, grained surface (simulator): correlation with the true relief",
             f"{grain.correlation:.3f} (goal >= {GOAL_CORRELATION:g})", grain.correlation >= GOAL_CORRELATION)]


def to_markdown(r: HeightMapResult) -> str:
    lines = [provenance_markdown(r.provenance), "",
             f"2-pass raster (4 x 9 cm, 20 mm/s, 0.5 mm pressed) of `large_surface`, photometric model from "
             f"{r.presses} simulated ball presses of the same sensor, placed evenly over the band (in-sample fit "
             f"{r.normal_error_deg:.2f} deg, position degree {r.position_degree} chosen on held-out presses); "
             "the height map against the true relief in place, on the cells 1 mm inside the mapped area; "
             "the second generator (shares nothing with the simulator) calibrated on "
             f"{_second_presses(r.quick)} of its own ball caps over the band (in-sample fit "
             f"{r.second_normal_error_deg:.2f} deg, position degree {r.second_position_degree}), its raster mapped by "
             "`touchroller map`.", "",
             "| surface | true relief RMS, um | error RMS (one best plane removed), um | correlation | cells | "
             "fine relief cells | fine relief read / true | fine relief correlation | passes | frames | s |",
             "|---|---|---|---|---|---|---|---|---|---|---|"]
    for s in r.surfaces:
        lines.append(f"| {s.surface} | {s.relief_rms_um:.1f} | {s.rms_um:.1f} | {s.correlation:.3f} | {s.cells} | "
                     f"{s.fine_cells} | {s.fine_scale:.2f} | {s.fine_correlation:.3f} | {s.passes} | "
                     f"{s.frames_mapped} | {s.map_cpu_s:.1f} |")
    if r.draws:
        worst = max(r.draws, key=lambda d: d.rms_um)
        lines += ["", "The grained surface's map with other calibrations (other press places and counts; the "
                  "position degree each chose on its held-out presses):", "",
                  "| presses | seed | position degree | error RMS, um | correlation |", "|---|---|---|---|---|",
                  f"| {r.presses} | 0 (the figure above) | {r.position_degree} | {grain_rms(r):.1f} | "
                  f"{grain_corr(r):.3f} |"]
        lines += [f"| {d.presses} | {d.seed} | {d.position_degree} | {d.rms_um:.1f} | {d.correlation:.3f} |"
                  for d in r.draws]
        lines += ["", f"Worst of these: {worst.rms_um:.1f} um, correlation "
                  f"{min(d.correlation for d in r.draws):.3f} (lowest)."]
    banded = [x for x in r.surfaces if x.wavelengths and x.surface != "panel"]
    if banded:
        lines += ["", "The maps against their true relief by wavelength (on the largest rectangle mapped throughout): "
                  "each band's share of the relief's power, how much of its amplitude the map reads there (gain) and "
                  "how well it follows (coherence):", "",
                  "| wavelength, mm | " + " | ".join(f"{x.surface}: relief power share | gain | coherence"
                                                     for x in banded) + " |",
                  "|---|" + "---|---|---|" * len(banded)]
        for k, w in enumerate(banded[0].wavelengths):
            cells = " | ".join(f"{x.wavelengths[k].relief_share:.2f} | {x.wavelengths[k].gain:.2f} | "
                               f"{x.wavelengths[k].coherence:.2f}" for x in banded)
            lines.append(f"| {w.shortest_mm:.2g}-{w.longest_mm:.2g} | {cells} |")
    cut = [x for x in r.surfaces if x.cutoffs and x.surface != "panel"]
    if cut:
        lines += ["", "The maps against their true relief with both low-passed alike (only the wavelengths longer than "
                  "the cut-off kept; the same rectangle): the correlation and the difference's RMS, um. Where it rises "
                  "as the cut-off lengthens, the short wavelengths lose it; where it falls, the long ones:", "",
                  "| longer than, mm | " + " | ".join(f"{x.surface}: correlation | RMS, um" for x in cut) + " |",
                  "|---|" + "---|---|" * len(cut)]
        for k, c in enumerate(cut[0].cutoffs):
            cells = " | ".join(f"{x.cutoffs[k].correlation:.3f} | {x.cutoffs[k].rms_um:.1f}" for x in cut)
            lines.append(f"| {c.longer_than_mm:g} | {cells} |")
    if r.configs:
        columns = list(dict.fromkeys((c.surface, c.seed) for c in r.configs))
        lines += ["", "The maps read with other height configurations (`WorldHeightConfig`: what a pixel's slope is "
                  "taken to be when a frame is integrated, `slopes`, and the image's smoothing before its colours are "
                  "read, `smoothing`); each cell: error RMS after one best plane (um), correlation, and the gain at "
                  "0.3-0.4 / 0.4-0.5 / 0.5-0.6 mm wavelengths:", "",
                  "| configuration | " + " | ".join(f"{surface}, seed {seed}" for surface, seed in columns) + " |",
                  "|---|" + "---|" * len(columns)]
        for label in dict.fromkeys(c.config for c in r.configs):
            cells = []
            for surface, seed in columns:
                c = next((c for c in r.configs if (c.config, c.surface, c.seed) == (label, surface, seed)), None)
                cells.append("" if c is None else f"{c.rms_um:.1f} um, {c.correlation:.3f}, "
                              + " / ".join(f"{g:.2f}" for g in c.fine_gains))
            lines.append(f"| {label} | " + " | ".join(cells) + " |")
    if r.frames:
        fine = [k for k, (short, _) in enumerate(WAVELENGTH_BANDS) if 0.3 <= short < 0.6]
        lines += ["", f"The second generator's frames read one at a time ({r.frames[0].frames} frames pressed along "
                  "its first pass, each against the indentation the generator pressed there, at the pixel centres, "
                  f"{FRAME_ROWS} rows either side of the contact line): the gain (coherence) at 0.3-0.4 / 0.4-0.5 / "
                  "0.5-0.6 mm, and the map's gain there (the table above). What a frame loses is read there (the "
                  "smoothing, colour to slope, the integration); what the map loses beyond it, in placing the "
                  "frames (the band's resampling, the interpolation onto the cells, the blending of overlapping "
                  "frames and their misplacement):", "",
                  "| configuration | seed | per frame | in the map |", "|---|---|---|---|"]
        for g in r.frames:
            placed = next((c for c in r.configs if c.config == g.config and c.seed == g.seed and "second" in c.surface),
                          None)
            per_frame = " / ".join(f"{g.gains[k]:.2f} ({g.coherences[k]:.2f})" for k in fine)
            in_map = "" if placed is None else " / ".join(f"{x:.2f}" for x in placed.fine_gains)
            lines.append(f"| {g.config} | {g.seed} | {per_frame} | {in_map} |")
    lines += ["", "Fine relief: where the true relief departs from its own 2 mm Gaussian by more than 3 um (the "
              "planted cracks, dents, grooves and pits, and the grain's finer part), the map's departure from its "
              "own 2 mm Gaussian against the truth's: how much of a feature's depth the map reads, and how well "
              "it follows.", ""]
    for goal, value, met in goals(r):
        lines.append(f"- {goal}: {value}: **{'met' if met else 'NOT met'}**")
    return "\n".join(lines) + "\n"


def grain_rms(r: HeightMapResult) -> float:
    return next((s.rms_um for s in r.surfaces if s.surface == "grain"), math.nan)


def grain_corr(r: HeightMapResult) -> float:
    return next((s.correlation for s in r.surfaces if s.surface == "grain"), math.nan)


def load(path: Path) -> HeightMapResult:
    raw = json.loads(Path(path).read_text())
    raw["provenance"] = Provenance(**raw["provenance"])
    raw["surfaces"] = [SurfaceScore(**{**s, "wavelengths": [WavelengthGain(**w) for w in s.get("wavelengths", [])],
                                       "cutoffs": [CutoffCorrelation(**c) for c in s.get("cutoffs", [])]})
                       for s in raw["surfaces"]]
    raw["draws"] = [PressDraw(**d) for d in raw.get("draws", [])]
    raw["configs"] = [ConfigScore(**c) for c in raw.get("configs", [])]
    raw["frames"] = [FrameGain(**f) for f in raw.get("frames", [])]
    return HeightMapResult(**raw)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="the grained surface only, 8 presses")
    args = parser.parse_args(argv)
    result = run(quick=args.quick)
    out = results_path("height_map", args.quick)
    out.parent.mkdir(parents=True, exist_ok=True)
    text = "# World height map in the simulator\n\n" + to_markdown(result)
    atomic_write_text(out, text)
    atomic_write_text(out.with_suffix(".json"), to_json(result, indent=1))
    print(text)
    return 0 if all(math.isfinite(s.rms_um) for s in result.surfaces) else 1


if __name__ == "__main__":
    sys.exit(main())
