"""One tactile map in the robot's frame: each frame's contact band placed by TF, refined by registration.

`WorldMapper.push(image, stamp_ns)` takes the frames of a scan (any number of passes) and builds one
mosaic in the world frame (`map` frame of nav2: x right, y up) at `config.resolution` m per pixel:

* the band is cut and rectified as the strip stitcher does (`stitching.BandSampler`): rows uniform in
  membrane y, columns in x, so band pixel (row i, column j) is the point (x_j, y_i, r) of the cylinder
  frame, the contact patch pressed flat under the roller; `T_world_cylinder` at the frame's exposure time
  (stamp - latency) puts it in the world;
* which frames are mapped: those with the roller pressed. The pressed height is learnt from the frames
  whose image moves with the arm (the strip stitcher's registration agrees with the arm's motion along
  the roll): frames within `contact_tolerance` of it are in contact; an arm moving above the surface
  (approach, between passes) is not, whatever the image shows. Where the surface has too little texture
  to register, the lowest height the arm moved along at is taken once the band's shading confirms it
  (frames there differ from frames in the air, as pressing changes the band on any surface:
  `contact_timing.ContactTimer.shows_pressing`), or once frames can wait no longer;
* the camera's latency (exposure to stamp): `config.latency` if told, else estimated from the data
  (`touchroller_perception.latency`: the image-registered roll against the arm's around starts and stops
  and over whole passes, opposite passes registered against each other, and when the image shows the
  roller touching down and lifting off, `touchroller_perception.contact_timing`);
* refinement by registration: each pass after the first is registered (2-D, subpixel) against what the
  earlier passes mapped where they overlap, and shifted by the median of its frames' offsets, so a
  residual latency or an arm calibration error does not leave a seam;
* blending: each band is splatted with weights tapered across the band and towards its ends along the
  axis, and the map is sum(w * band) / sum(w * flat field): the static gel pattern divides out and
  overlaps average without seams (`finalise()` re-weights everything with the final flat field).

A frame is taken only once the poses reach its stamp (it waits, in arrival order, up to `wait_frames`
of them): every pose the mapper looks up for it then lies at or before that stamp, so the map does
not depend on whether a frame or its pose arrived first (a live graph where the image may come before
its TF, or a recording read in the order it was written). Frames then wait (a bounded queue) until
their pose, the pressed height and the latency are known. The map
is kept as tiles (`touchroller_perception.tiles`): a bounded cache in memory, the rest on disk, so memory
is bounded by neither the map's area nor the number of frames; frames whose new tiles would not fit on
the disk are left out and counted (`stats.left_out_storage_full`), the map so far kept.
No rclpy here; the caller looks poses up (`touchroller_perception.transforms`).
"""
from __future__ import annotations

import dataclasses
import itertools
import math
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any

import cv2
import numpy as np
from numpy.typing import NDArray

from touchroller_perception.contact_timing import ContactTimer, band_summary
from touchroller_perception.fast_stats import median as _median
from touchroller_perception.fast_stats import percentile as _percentile
from touchroller_perception.geometry import CameraModel
from touchroller_perception.latency import LatencyConfig, LatencyEstimate, LatencyEstimator
from touchroller_perception.stitching import Stitcher, StitcherConfig, StitchStep, taper
from touchroller_perception.tiles import LayerView, StorageFull, TileConfig, pyramid_tile, render_tile
from touchroller_perception.world_canvas import (  # noqa: F401 (WorldCanvas, _Prior: part of this module's API)
    LAYERS,
    WorldCanvas,
    _axis_aligned,
    _blend,
    _orient,
    _orient_into,
    _Placement,
    _Prior,
)

if TYPE_CHECKING:   # imported where used: the height map needs SciPy, a map without one does not
    from touchroller_perception.world_height import BandHeights, HeightBand, HeightMapLayer, HeightSource

FloatArray = NDArray[np.float64]


def _height_module() -> Any:
    """`touchroller_perception.world_height`, imported when a height map is made (it brings SciPy)."""
    from touchroller_perception import world_height

    return world_height
_HELD_FULL = 32   # frames waiting to be placed are kept as float32 up to this many, older ones in 16 bits
#: the canvas's layers of the frames placed provisionally (`WorldMapConfig.provisional`): band, flat field and
#: weight sums as the map's own, and the relief's weighted sum and weights as the pass's (`world_height`)
PROVISIONAL_LAYERS = ("live_band", "live_flat", "live_weight", "live_height", "live_height_w")
_EVENT_CHECK_NS = 250_000_000   # how often (stamp time) the pressed height, starts and stops are looked for
_PASS_REGISTER_EVERY = 12       # after a pass's first ten offsets, one frame in this many is registered
_PASS_FAILED_RUN = 10           # ... and after this many registrations in a row found none
_RESUME_NS = 300_000_000       # pressed again this soon after a pass ended: the same pass (not a new one)
_PLACING_STEP_S = 5e-4          # frames are placed with the latency estimate on this grid, s
_MIN_SCORE = 0.5                # a registration's NCC peak below this is not trusted (too little texture)
_PEAK_MARGIN = 0.1              # a registration's peak stands this much (NCC) above any other 3 px away
_MAX_BAND_PIXELS = 16_000_000   # one band placed on the map may span at most this many map cells
_DELTA_MAD_PX = 1.0             # a pass's offsets agree (median absolute deviation, map px) to be applied
#: T_world_cylinder (N, 4, 4) at each of N stamps (ns), all-NaN where it is not known (yet): e.g.
#: `TransformBuffer.lookup_many(world, cylinder, stamps, missing=True)`.
PoseLookup = Callable[[NDArray[np.int64]], FloatArray]


def least_band_cells(camera: CameraModel, band_rows: int, resolution: float) -> float | None:
    """The fewest map cells one band of `camera`'s frames (`band_rows` rows) spans on a map of `resolution`
    m/px: the band's own area, which its footprint holds at any orientation. None when the camera model
    gives no band (it does not see the contact line: the map says so when it starts)."""
    from touchroller_perception.stitching import BandSampler

    try:
        sampler = BandSampler((camera.height, camera.width), int(band_rows), camera, None, False)
    except ValueError:
        return None
    if sampler.mm_per_px is None or sampler.mm_per_px_cols is None:
        return None
    along = (sampler.rows - 1) * sampler.mm_per_px * 1e-3
    across = (sampler.cols - 1) * sampler.mm_per_px_cols * 1e-3
    return along * across / resolution ** 2


def check_band_fits(camera: CameraModel, band_rows: int, resolution: float) -> None:
    """ValueError (one line) when no band of `camera`'s frames can be placed on a map of `resolution` m/px
    (each would span more than the most map cells a band may, so every frame would be refused)."""
    cells = least_band_cells(camera, band_rows, resolution)
    if cells is not None and cells > _MAX_BAND_PIXELS:
        coarsest_refused = resolution * math.sqrt(cells / _MAX_BAND_PIXELS)
        raise ValueError(f"{resolution:g} m/px puts one band of the sensor on {cells:.3g} map pixels, more than a "
                         f"band may span ({_MAX_BAND_PIXELS:.3g}): use at least {coarsest_refused:.2g} m/px")


class BufferPoses:
    """A PoseLookup over a `touchroller_perception.transforms.TransformBuffer` (unknown frames: NaN), which
    also answers `covers(stamp)`: whether the pose at a stamp is known, without interpolating it (the
    mapper asks that of every frame, often twice, before it looks the pose up)."""

    def __init__(self, buffer: Any, world: str, cylinder: str) -> None:
        self.buffer, self.world, self.cylinder = buffer, world, cylinder

    def __call__(self, stamps: NDArray[np.int64]) -> FloatArray:
        from touchroller_perception.transforms import TransformError

        try:
            return self.buffer.lookup_many(self.world, self.cylinder, stamps, missing=True)
        except TransformError:
            return np.full((len(stamps), 4, 4), np.nan)

    def covers(self, stamp_ns: int) -> bool:
        return bool(self.buffer.covers(self.world, self.cylinder, stamp_ns))


def buffer_lookup(buffer: Any, world: str, cylinder: str) -> BufferPoses:
    """A PoseLookup over a `touchroller_perception.transforms.TransformBuffer` (unknown frames: NaN)."""
    return BufferPoses(buffer, world, cylinder)


@dataclass(frozen=True)
class WorldMapConfig:
    """How a `WorldMapper` works; the perception node's `map.*` world parameters map onto these fields.

    resolution: metres per map pixel.
    bounds: (x_min, y_min, x_max, y_max) of the map in the world frame, m (e.g. the scan's rectangle plus
      a margin); None: it grows with what is mapped (tiles made where bands land, without bound but the disk).
    max_pixels: the most pixels `bounds` may span (a sanity check on a typing error: tiles are made only
      where bands land, but the map's files span the bounds).
    tiles: the tile store (tile size, memory cache, spill folder, disk reserve).
    latency: the camera's latency (s, exposure to stamp) if known; None: estimated from the data
      (`touchroller_perception.latency`).
    latency_fallback: the latency used when the data do not pin it down (a single pass at constant
      speed): the configured one (what `camera.latency` left, 0), said as a warning, never an estimate.
    latency_max_sigma: the estimate is used when its standard deviation is at most this, s.
    max_latency: the largest latency considered, s.
    register: refine each pass's placement by registration against the earlier passes.
    search_px: the largest correction registration looks for, map pixels.
    contact_tolerance: frames with the roller within this of its pressed height are mapped, m.
    edge_taper: the weights fall to zero over this distance at the band's ends along the axis, m.
    steady_stride: while the roll is steady (the image's speed over the last registered frames unchanged,
      and the arm's where it is known agreeing with it) the strip stitcher registers one frame in
      `steady_stride` and the others take that motion; starts, stops and any disagreement are registered
      frame by frame (they are what the latency and the pressed height are learnt from). 1: every frame.
    hold_frames: frames kept while their pose, the pressed height or the latency are not known yet (in
      16 bits: 90 KB each for 640-pixel-wide bands); the latency may need a whole pass's end to be found.
    wait_frames: frames kept until the poses reach their stamp; beyond this many the oldest is taken
      with what is known (poses that stopped coming).
    provisional: while frames wait for the latency estimate (the pressed height known), place them with
      `latency_fallback` on layers of their own (`PROVISIONAL_LAYERS`), for live readers (the live
      findings) only; emptied as soon as frames are placed for good, so the map and its files never hold
      them. Costs a second placement of each frame that waited (a live node's choice, not a recording's).
    """

    resolution: float = 1e-4
    bounds: tuple[float, float, float, float] | None = None
    max_pixels: int = 10 ** 11
    latency: float | None = None
    latency_fallback: float = 0.0
    latency_max_sigma: float = 0.002
    max_latency: float = 0.2
    register: bool = True
    search_px: int = 6
    contact_tolerance: float = 2e-4
    edge_taper: float = 4e-3
    steady_stride: int = 3
    hold_frames: int = 600
    wait_frames: int = 30
    tiles: TileConfig = TileConfig()
    provisional: bool = False

    def __post_init__(self) -> None:
        if not (math.isfinite(self.resolution) and 1e-6 <= self.resolution <= 0.01):
            raise ValueError(f"map resolution must be in [1e-6, 0.01] m per pixel, got {self.resolution}")
        if self.bounds is not None:
            b = [float(v) for v in self.bounds]
            if len(b) != 4 or not all(math.isfinite(v) for v in b) or b[2] <= b[0] or b[3] <= b[1]:
                raise ValueError(f"map bounds are (x_min, y_min, x_max, y_max) with max > min, got {self.bounds}")
            pixels = (b[2] - b[0]) * (b[3] - b[1]) / self.resolution ** 2
            if pixels > self.max_pixels:
                raise ValueError(f"map bounds at {self.resolution} m/px need {pixels:.3g} pixels, more than "
                                 f"max_pixels {self.max_pixels}")
        if self.latency is not None and not (math.isfinite(self.latency) and 0 <= self.latency <= 1.0):
            raise ValueError(f"latency must be in [0, 1] s or None (estimate it), got {self.latency}")
        if not (0 < self.max_latency <= 1.0):
            raise ValueError(f"max_latency must be in (0, 1] s, got {self.max_latency}")
        if not (math.isfinite(self.latency_fallback) and 0 <= self.latency_fallback <= self.max_latency):
            raise ValueError(f"latency_fallback must be in [0, max_latency] s, got {self.latency_fallback}")
        if not (math.isfinite(self.latency_max_sigma) and self.latency_max_sigma > 0):
            raise ValueError(f"latency_max_sigma must be > 0 s, got {self.latency_max_sigma}")
        if (self.search_px < 1 or self.hold_frames < 1 or self.max_pixels < 10_000 or self.steady_stride < 1
                or self.wait_frames < 0):
            raise ValueError("search_px, hold_frames and steady_stride must be >= 1, wait_frames >= 0, "
                             "max_pixels >= 10000")
        if not (self.contact_tolerance > 0 and self.edge_taper >= 0):
            raise ValueError("contact_tolerance must be > 0 and edge_taper >= 0")

    def replace(self, **changes: Any) -> WorldMapConfig:
        return dataclasses.replace(self, **changes)


@dataclass(frozen=True)
class WorldMapImage:
    """The map as files want it: grey (uint8) and alpha (255 mapped, 0 not), row 0 the top (largest y),
    `origin` the world (x, y) of the lower-left pixel's corner (nav2 map_server's convention)."""

    grey: np.ndarray
    alpha: np.ndarray
    resolution: float
    origin: tuple[float, float]


class _Recent:
    """The recent confident frames of the strip stitcher: stamps, image positions, and per frame the roller's
    height and the arm's roll (band rows), filled in once their poses are known (NaN until then). Arrays
    with room for twice `capacity`: appending is O(1), the oldest go once `capacity` is exceeded."""

    def __init__(self, capacity: int) -> None:
        self.capacity = capacity
        self._stamps = np.zeros(2 * capacity, np.int64)
        self._values = np.full((2 * capacity, 3), np.nan)   # position, height, arm roll
        self._start = self._end = 0

    def __len__(self) -> int:
        return self._end - self._start

    def append(self, stamp_ns: int, position: float) -> None:
        if self._end == len(self._stamps):   # full: move the newest `capacity` to the front
            keep = slice(self._end - self.capacity, self._end)
            self._stamps[:self.capacity] = self._stamps[keep]
            self._values[:self.capacity] = self._values[keep]
            self._start, self._end = self._start - (self._end - self.capacity), self.capacity
            self._start = max(self._start, 0)
        self._stamps[self._end] = stamp_ns
        self._values[self._end] = (position, np.nan, np.nan)
        self._end += 1
        if self._end - self._start > self.capacity:
            self._start += 1

    @property
    def stamps(self) -> NDArray[np.int64]:
        return self._stamps[self._start:self._end]

    @property
    def positions(self) -> FloatArray:
        return self._values[self._start:self._end, 0]

    @property
    def heights(self) -> FloatArray:
        return self._values[self._start:self._end, 1]

    @property
    def arm_rows(self) -> FloatArray:
        return self._values[self._start:self._end, 2]

    def forget_poses(self) -> None:
        self._values[:, 1:] = np.nan


# ------------------------------------------------------------------------------------------------ mapper
@dataclass
class _Frame:
    stamp_ns: int
    band: np.ndarray
    field: np.ndarray | None
    step: StitchStep
    pose: np.ndarray | None = None        # T_world_cylinder at stamp - pose_latency, once known
    pose_latency: int | None = None
    height: HeightBand | None = None      # its relief on the band (a height map's frames)
    provisional: bool = False             # on the provisional layers (`WorldMapConfig.provisional`)


@dataclass
class _PassRecord:
    """What a pass did, for the latency from opposite passes and the map's final placement: the exposure
    times and positions of its first and last pressed frames, the latencies its frames were placed with,
    its registration offsets (dx, dy map px, the frame's latency ns, its speed m/s, its x, y m),
    its track (x, y m midway between two frames, the velocity between them m/s) and its correction."""

    first: tuple[int, float, float] | None = None
    last: tuple[int, float, float] | None = None
    latency_sum: float = 0.0
    frames: int = 0
    offsets: list[tuple[float, float, float, float, float, float]] = field(default_factory=list)
    track: list[tuple[float, float, float, float]] = field(default_factory=list)   # (x, y, vx, vy) between frames
    delta: tuple[float, float] = (0.0, 0.0)
    trusted: bool = False   # its offsets agreed: the correction was applied
    ended: bool = False
    evidence_given: bool = False   # its opposite-passes evidence was added (once)
    _velocity: tuple[int, np.ndarray | None] | None = field(default=None, repr=False, compare=False)

    def add(self, exposure_ns: int, pose: np.ndarray, latency_ns: int) -> None:
        point = (exposure_ns, float(pose[0, 3]), float(pose[1, 3]))
        if self.first is None:
            self.first = point
        elif self.last is not None and point[0] > self.last[0]:
            seconds = (point[0] - self.last[0]) * 1e-9
            self.track.append((0.5 * (point[1] + self.last[1]), 0.5 * (point[2] + self.last[2]),
                               (point[1] - self.last[1]) / seconds, (point[2] - self.last[2]) / seconds))
        self.last = point
        self.latency_sum += latency_ns * 1e-9
        self.frames += 1

    def latency(self) -> float:
        """The mean latency its frames were placed with, s."""
        return self.latency_sum / max(self.frames, 1)

    def speed_at(self, at: np.ndarray, u: np.ndarray, lag: float = 0.0) -> np.ndarray:
        """Its speed (m/s) where its track passed each of the places `at` (m along the direction `u`),
        interpolated between its frames, its track taken `lag` s earlier than the latency it was placed
        with put it (where it truly was, when the latency is `lag` more); NaN outside the stretch it rolled."""
        track = np.array(self.track, np.float64).reshape(-1, 4)
        speed = np.hypot(track[:, 2], track[:, 3])
        moving = speed > 1e-3
        if moving.sum() < 2:
            return np.full(len(at), np.nan)
        along = track[moving, :2] @ u - lag * (track[moving, 2:] @ u)
        order = np.argsort(along)
        return np.interp(np.asarray(at, np.float64), along[order], speed[moving][order], left=np.nan, right=np.nan)

    def velocity(self) -> np.ndarray | None:
        """Its velocity in the world plane while it rolled, m/s: the median over its frames that moved
        (a pause within the pass does not slow it down); None for a pass that did not move. Kept until the
        pass adds a frame (the pass before is asked at every frame of the next: recomputing it over all
        its frames each time made a frame's cost grow with the length of the passes)."""
        if self._velocity is not None and self._velocity[0] == len(self.track):
            known = self._velocity[1]
            return None if known is None else known.copy()
        steps = np.array(self.track).reshape(-1, 4)[:, 2:]
        moving = steps[np.hypot(steps[:, 0], steps[:, 1]) > 1e-3]
        velocity = None if len(moving) < 3 else np.array([_median(moving[:, 0]), _median(moving[:, 1])])
        self._velocity = (len(self.track), velocity)
        return None if velocity is None else velocity.copy()

    def direction(self) -> np.ndarray | None:
        v = self.velocity()
        return None if v is None else v / float(np.hypot(*v))


@dataclass
class MapStats:
    """What a WorldMapper did (for diagnostics and reports)."""

    frames: int = 0
    mapped: int = 0
    not_in_contact: int = 0
    no_pose: int = 0
    passes: int = 0
    left_out_storage_full: int = 0   # frames left out: their new tiles would not have fitted on the disk
    storage_warning: str | None = None
    pass_corrections_px: list[tuple[float, float]] = field(default_factory=list)
    # each later pass's correction net of the latency: how far registration moved it from where TF and the
    # final latency put it (the raw correction holds the latency's effect when the pass was placed before
    # the latency was known: 2 v L for a pass rolled back); the reports show these
    pass_residuals_px: list[tuple[float, float]] = field(default_factory=list)
    latency_s: float | None = None
    latency_estimated: bool = False
    latency: LatencyEstimate | None = None   # what the data said (value, sigma, sources); None when told
    latency_warning: str | None = None       # set when the data did not pin the latency down
    map_shift_m: tuple[float, float] = (0.0, 0.0)   # the whole map moved at the end by the final estimate
    pressed_height: float | None = None
    pressed_from: str = "image"   # what decided the pressed height: the image moving with the arm, or TF


def latency_summary(stats: MapStats) -> tuple[str, dict[str, object]]:
    """(the words for a summary line: "estimated 35.2 ms (sigma 0.3 ms; ...)", "given 30.0 ms", "not
    observable ...: configured 0.0 ms used"; the same for map.yaml: value_ms, sigma_ms, sources, observable)."""
    if stats.latency is None:
        value = stats.latency_s or 0.0
        return f"given {value * 1e3:.1f} ms", {"value_ms": round(value * 1e3, 3), "sigma_ms": None,
                                               "sources": ["given"], "observable": False}
    return stats.latency.describe(), stats.latency.as_dict()


class WorldMapper:
    """See the module docstring. `poses` looks T_world_cylinder up at stamps (ns); `camera` is the
    sensor's calibrated model (the band's metric geometry)."""

    def __init__(self, camera: CameraModel, poses: PoseLookup, config: WorldMapConfig | None = None,
                 stitcher: StitcherConfig | None = None, height: HeightSource | None = None) -> None:
        self.config = config = config or WorldMapConfig()
        # the height map (`world_height`): with a photometric model, two more pairs of canvas layers
        self.height_source = height
        self._height_layer = None if height is None else _height_module().HeightLayer(height.config)
        self._band_heights: BandHeights | None = None
        self.camera = camera
        self.poses = poses
        # The strip stitcher measures the image's roll (latency, contact) and keeps the flat field; it
        # places nothing, so it needs no lateral tracking and registers on coarser columns (speed).
        strip = stitcher or StitcherConfig(lateral=False, column_bin=8)
        # The whole mean divides out (flat_sigma_cols 0): a fine column feature of the gel left in the field
        # would draw a line along every pass, at the same band column (seams at a fixed offset from each
        # pass's centre).
        self.strip = Stitcher(strip.replace(history=1, live_map=False, keep_map=False, flat_sigma_cols=0.0),
                              camera=camera)
        self.canvas = WorldCanvas(config.resolution, config.bounds, config.tiles)
        if self._height_layer is not None:
            self._height_layer.add_layers(self.canvas)
        if config.provisional:
            for name in PROVISIONAL_LAYERS:
                self.canvas.add_layer(name, np.float32)
        self._provisional_frames = 0   # frames on the provisional layers now
        self.replacements = 0          # times the provisional layers were emptied (their frames placed for good)
        self.stats = MapStats(latency_s=config.latency)
        self.latency_ns: int | None = None if config.latency is None else round(config.latency * 1e9)
        # frames whose stamp the poses do not reach yet
        self._inbox: deque[tuple[np.ndarray, int, HeightBand | None, np.ndarray | None]] = deque()
        self._pending: deque[_Frame] = deque()
        self._pressed_height: float | None = None
        self._tf_heights: deque[tuple[int, float, float, float]] = deque(maxlen=3000)   # (stamp, x, y, z)
        self._agree_heights: deque[float] = deque(maxlen=200)   # heights at which the image moved with the arm
        self._heights: list[float] = []
        self._weights: np.ndarray | None = None   # band weights (rows x columns)
        self._level = 1.0
        self._placements: list[_Placement] = []   # where each band went, for finalise
        self._weighted_field: tuple[np.ndarray, np.ndarray, dict] | None = None   # (field, w field, oriented)
        self._oriented_weights: dict[tuple[bool, bool, bool], np.ndarray] = {}
        # per orientation: (the w field it holds, the stacked planes `_blend_stack` blends)
        self._stacks: dict[tuple[bool, bool, bool], tuple[np.ndarray, np.ndarray]] = {}
        self._level_field: np.ndarray | None = None
        self._prior_weight_max = 1.0
        # latency windows: the recent confident (stamp, position) of the strip stitcher, and roll events
        self._recent = _Recent(600)
        self._events: list[int] = []   # arm times of starts and stops (ns)
        self._last_event_check = 0
        self._latest_stamp = 0
        self._track_latency: int | None = None
        self._reference_point: np.ndarray | None = None
        self._previous_stamp: int | None = None
        self._previous_prior_pose: tuple[np.ndarray, int] | None = None
        self._registered: tuple[int, float, float | None] | None = None   # the last registered frame's
        # (stamp, image position, image speed px/ns since the one before) while registrations are confident
        self._steady = False      # the image's speed is unchanged over the last registered frames
        self._steady_skipped = 0  # frames since the last registered one
        self._frame_dt: int | None = None   # ns since the previous frame
        self._estimator: LatencyEstimator | None = None
        self._contacts: ContactTimer | None = None   # touchdowns and lift-offs the image shows (latency)
        self._last_contact_check = 0
        self._placing_ns: int | None = None        # the latency frames are placed with (see _latency)
        self._placing_sigma: float | None = None   # its sigma when it is an estimate
        self._pass_windows_until = 0               # pass_roll windows were taken up to this stamp
        self._pass_log: list[_PassRecord] = []     # per pass: for the opposite passes and the final shift
        # passes and their registration against the earlier ones
        self._in_contact = False
        self._last_contact_ns: int | None = None
        self._prior: _Prior | None = None   # the map as the earlier passes left it, for registration
        self._pass_offsets: list[tuple[float, float, float]] = []   # (dx, dy, score) this pass
        self._pass_delta = np.zeros(2)
        self._delta_offsets = 0   # how many of the pass's offsets `_pass_delta` is the median of
        self._pass_buffer: list[tuple[_Frame, np.ndarray]] = []
        self._pass_frames = 0
        self._pass_failed = 0   # registrations in a row this pass that found no offset

    # -- public --------------------------------------------------------------------------------------
    def push(self, image: np.ndarray, stamp_ns: int) -> None:
        """Take one frame (any image the strip stitcher takes; a colour one for a height map)."""
        band = self.strip.band(image)
        self.push_band(band, stamp_ns, self.height_band(image))

    def height_band(self, image: np.ndarray, row0: int = 0, frame_height: int | None = None) -> HeightBand | None:
        """The frame's relief on the band `push_band` takes with it (None without a photometric model), from
        a frame or from its rows from `row0` on (they must hold `height_rows`; stateless after the first)."""
        if self.height_source is None:
            return None
        image = np.asarray(image)
        shape = (int(image.shape[0] if frame_height is None else frame_height), int(image.shape[1]))
        return self._height_maker(shape)(image, row0)

    def height_rows(self, shape: tuple[int, int]) -> tuple[int, int] | None:
        """(first, end): the rows of a frame of `shape` its height is made from; None without a height map."""
        return None if self.height_source is None else self._height_maker(shape).rows

    def _height_maker(self, shape: tuple[int, int]) -> BandHeights:
        if self._band_heights is None:
            assert self.height_source is not None
            self.strip.source_rows(shape)
            source = self.height_source
            self._band_heights = _height_module().BandHeights(source.model, source.reference, self.camera,
                                                              self.strip.sampler, source.config)
        return self._band_heights

    def height_layer(self, crop: bool = True) -> HeightMapLayer | None:
        """The world height map (`world_height`): float32 metres, rows growing with y, NaN where unmapped,
        with its origin (lower-left corner of cell (0, 0)) and resolution; `crop`: to the cells
        `map_image(crop)` and map.tif keep (the same grid), read from the tiles over that window only.
        None without a photometric model or before a pass has ended (or `finalise`)."""
        if self._height_layer is None:
            return None
        box = None
        if crop and not self.canvas.fixed:
            box = self.canvas.mapped_extent()
        return self._height_layer.layer(self.canvas, box)

    def height_view(self) -> LayerView | None:
        """The height map as a `tiles.LayerView` (what height.tif is streamed from, a tile at a time, over
        the cells map.tif spans); None without a photometric model or before a pass has a height."""
        if self._height_layer is None or self._height_layer.passes == 0:
            return None
        return self._height_layer.view(self.canvas)

    def height_level(self, level: int) -> HeightMapLayer | None:
        """The height map over the map's extent (`level_extent`) at pyramid level `level` (each cell the
        weighted mean of 2^level x 2^level cells; level 0: `height_layer()`), read from the tiles a tile at
        a time: memory for the result alone. None without a height map or before a pass has ended."""
        view = self.height_view()
        box = self.level_extent(level)
        if view is None or box is None:
            return None
        r0, r1, c0, c1 = box
        t = self.canvas.tile
        out = np.full((r1 - r0, c1 - c0), np.nan, np.float32)
        for iy in range(r0 // t, (r1 - 1) // t + 1):
            for ix in range(c0 // t, (c1 - 1) // t + 1):
                y0, y1, x0, x1 = max(r0, iy * t), min(r1, (iy + 1) * t), max(c0, ix * t), min(c1, (ix + 1) * t)
                value, weight = pyramid_tile(view, level, ix, iy)
                part = (slice(y0 - iy * t, y1 - iy * t), slice(x0 - ix * t, x1 - ix * t))
                known = weight[part] > view.mapped_weight
                out[y0 - r0:y1 - r0, x0 - c0:x1 - c0][known] = value[part][known]
        res = self.config.resolution * 2 ** level
        anchor = self.canvas.anchor
        return _height_module().HeightMapLayer(out, (anchor[0] + c0 * res, anchor[1] + r0 * res), res)

    def _end_height_pass(self) -> None:
        assert self._height_layer is not None
        try:
            self._height_layer.end_pass(self.canvas)
        except StorageFull as exc:   # the finished passes keep what they had
            self.stats.storage_warning = f"a pass's height was left out: {exc}"

    def band(self, image: np.ndarray, row0: int = 0, frame_height: int | None = None) -> np.ndarray:
        """The band `push_band` wants, cut from a frame or from the frame's rows from `row0` on (see
        `Stitcher.band`; stateless after the first: another thread may cut)."""
        return self.strip.band(image, row0, frame_height)

    def source_rows(self, shape: tuple[int, int]) -> tuple[int, int]:
        """(first, end): the rows of a frame of `shape` (rows, columns) its band is cut from."""
        return self.strip.source_rows(shape)

    @property
    def band_shape(self) -> tuple[int, int]:
        """(rows, columns) of the bands `band()` cuts; known once it or `source_rows` saw a frame's size."""
        sampler = self.strip.sampler
        if sampler is None:
            raise ValueError("the band's size is known once a frame's size is (source_rows or band)")
        return sampler.rows, sampler.cols

    def push_band(self, band: np.ndarray, stamp_ns: int, height: HeightBand | None = None,
                  summary: np.ndarray | None = None) -> None:
        """`push` for a band cut with `band()` (and its relief, `height_band()`, for a height map; and its
        `contact_summary()` when the process that cut it made that too)."""
        if self._weights is None:
            self._setup()
        self._inbox.append((band, int(stamp_ns), height, summary))
        while self._inbox:
            band, stamp_ns, height, summary = self._inbox[0]
            if len(self._inbox) <= self.config.wait_frames and not self._pose_known(stamp_ns):
                return   # its pose has not arrived yet
            self._inbox.popleft()
            self._take_band(band, stamp_ns, height, summary)

    @staticmethod
    def contact_summary(band: np.ndarray) -> np.ndarray | None:
        """What the mapper's contact timing keeps of a band (`contact_timing.band_summary`): it depends on the
        band alone, so the process cutting the bands may make it and pass it to `push_band`."""
        return band_summary(band)

    def _pose_known(self, stamp_ns: int) -> bool:
        covers = getattr(self.poses, "covers", None)   # a BufferPoses answers without interpolating
        if covers is not None:
            return bool(covers(stamp_ns))
        return bool(np.isfinite(self.poses(np.array([stamp_ns], np.int64))).all())

    def _take_band(self, band: np.ndarray, stamp_ns: int, height: HeightBand | None = None,
                   summary: np.ndarray | None = None) -> None:
        prior, pose, pose_latency = self._arm_prior(int(stamp_ns))
        self.stats.frames += 1
        if self._contacts is not None and (self._estimator is not None or self._pressed_height is None):
            self._contacts.push(int(stamp_ns), band, summary)
        if self._previous_prior_pose is not None:
            seen = self._previous_prior_pose[0]
            self._tf_heights.append((int(stamp_ns), float(seen[0, 3]), float(seen[1, 3]), float(seen[2, 3])))
        self._latest_stamp = max(self._latest_stamp, int(stamp_ns))
        if self._clearly_lifted(pose if pose is not None else self._previous_prior_pose):
            # an arm moving above the surface (between passes): nothing to map, nothing to register
            self.stats.not_in_contact += 1
            self._drain(final=False)
            return
        register = self._register_strip(prior, int(stamp_ns))
        step = self.strip.push_band(band, int(stamp_ns), prior, register=register)
        if register:
            self._steady_after(step, int(stamp_ns))
        frame = _Frame(int(stamp_ns), band, self.strip.flat_field_now(), step, pose, pose_latency, height)
        if step.confidence >= self.strip.config.min_confidence and not step.used_prior:
            self._recent.append(frame.stamp_ns, step.position_px)
        self._pending.append(frame)
        self._drain(final=False)
        if len(self._pending) > _HELD_FULL:   # a long wait (the latency not known yet): hold in 16 bits
            held = self._pending[-_HELD_FULL - 1]
            if held.band.dtype != np.uint16:   # grey 0..255 in steps of 1/256
                held.band = cv2.multiply(held.band, 256.0, dtype=cv2.CV_16U)
                held.height = None if held.height is None else held.height.compact()

    def _register_strip(self, prior: float | None, stamp_ns: int) -> bool:
        """Whether the strip stitcher registers this frame (`WorldMapConfig.steady_stride`): not while the
        roll is steady and fewer than stride - 1 frames were left unregistered since the last registered
        one; the arm's motion, where known, must agree with the image's speed."""
        if not self._steady or self._steady_skipped >= self.config.steady_stride - 1 or self._registered is None:
            self._steady_skipped = 0
            return True
        _, _, speed = self._registered
        if speed is None:
            self._steady_skipped = 0
            return True
        if prior is not None and self._frame_dt is not None:
            expected = speed * self._frame_dt
            if abs(prior - expected) > 0.1 * abs(expected) + 0.3:
                self._steady_skipped = 0
                return True
        self._steady_skipped += 1
        return False

    def _steady_after(self, step: StitchStep, stamp_ns: int) -> None:
        """Track the image's speed over the registered frames (`_register_strip`)."""
        confident = not step.used_prior and step.confidence >= self.strip.config.min_confidence
        last, self._registered = self._registered, None
        self._steady = False
        if confident:
            speed = None
            if last is not None and stamp_ns > last[0]:
                span = stamp_ns - last[0]
                speed = (step.position_px - last[1]) / span
                previous = last[2]
                # moving at least a pixel a frame, the speed within 5 % (+ 0.1 px) of the one before
                self._steady = (previous is not None and abs(speed) * span >= 1.0
                                and abs(speed - previous) * span <= 0.05 * abs(previous) * span + 0.1)
            self._registered = (stamp_ns, step.position_px, speed)

    def _clearly_lifted(self, pose: Any) -> bool:
        """The roller is more than a millimetre above its pressed height (known once a roll was seen)."""
        if isinstance(pose, tuple):
            pose = pose[0]
        if pose is None or self._pressed_height is None:
            return False
        return float(pose[2, 3]) > self._pressed_height + 1e-3

    def _arm_prior(self, stamp_ns: int) -> tuple[float | None, np.ndarray | None, int | None]:
        """The arm's roll since the previous frame, band rows: the strip stitcher's motion prior, so a
        roll that starts before the flat field is known is not taken for the static gel pattern standing
        still. At the latency estimate, or the largest latency while there is none (a pose known by now).
        Also (the frame's pose, its latency) when that is the latency the frame will be placed with."""
        previous, self._previous_stamp = self._previous_stamp, stamp_ns
        self._frame_dt = None if previous is None else stamp_ns - previous
        latency = self._latency()
        shift = round(self.config.max_latency * 1e9) if latency is None else latency
        pose = self.poses(np.array([stamp_ns - shift], np.int64))[0]
        known = bool(np.isfinite(pose).all())
        before, self._previous_prior_pose = self._previous_prior_pose, (pose, shift) if known else None
        placed = (pose, shift) if known and latency is not None else (None, None)
        if previous is None or not known or before is None or before[1] != shift:
            return None, *placed
        offset = before[0][:3, 3] - pose[:3, 3]   # where the earlier pose's origin lies along this one's rows
        return float(pose[:3, 1] @ offset) / self.m_per_row, *placed

    def finalise(self) -> None:
        """Place what is still waiting, and re-weight the whole map with the final flat field."""
        while self._inbox:
            self._take_band(*self._inbox.popleft())
        self._drain(final=True)
        if self._provisional_frames:   # (all were placed by the drain: none stays provisional)
            self._clear_provisional()
        self._flush_pass_buffer()
        if self._height_layer is not None:   # the pass under way is levelled with what it has (it may go on)
            self._end_height_pass()
        if self._in_contact and self._pass_log:   # the pass under way says what it can (it may go on)
            self._pass_log[-1].delta = (float(self._pass_delta[0]), float(self._pass_delta[1]))
            self._opposite_passes()
        self._final_latency()
        field = self.strip.flat_field_final()
        if field is None or self._weights is None or not self._placements:
            return
        weighted = cv2.multiply(field.astype(np.float32), self._weights)
        oriented: dict[tuple[bool, bool, bool], np.ndarray] = {}
        box = self.canvas.used()
        if box is not None:
            try:
                self.canvas.clear("flat")   # (copies the tiles aside first while a pass registers: may not fit)
            except StorageFull as exc:   # nothing cleared: the map keeps the flat field it was built with
                self.stats.storage_warning = f"not re-weighted with the final flat field: {exc}"
                return
        for placement in self._placements:
            if placement.axes is not None:
                if placement.axes not in oriented:
                    oriented[placement.axes] = _orient(weighted, placement.axes)
                assert placement.kernel is not None
                plane = _blend(oriented[placement.axes], placement.kernel)
            else:
                assert placement.matrix is not None
                plane = cv2.warpAffine(weighted, placement.matrix, placement.size, flags=cv2.INTER_LINEAR,
                                       borderMode=cv2.BORDER_CONSTANT, borderValue=0)
            self.canvas.add([None, plane, None], placement.c0, placement.r0)
        self._level = float(field.mean())

    def _final_latency(self) -> None:
        """The final estimate; the map moved by what it says of the first pass's placement (every later pass
        was registered against the first's), or a warning when the data did not pin it down."""
        if self._estimator is None:
            return
        self._estimator.solve(self.poses)
        self._use_estimate()
        estimate = self.stats.latency
        if estimate is None or not estimate.observable:
            fallback = self.config.latency_fallback if self._placing_ns is None else self._placing_ns * 1e-9
            if estimate is None:
                estimate = LatencyEstimate(fallback, None, ("configured",), False)
            self.stats.latency = estimate
            self.stats.latency_s = fallback
            self.stats.latency_estimated = False
            self.stats.latency_warning = (f"camera latency not observable from this scan (no start or stop in "
                                          f"contact, no speed variation, no opposite passes that registered): "
                                          f"{fallback * 1e3:.1f} ms as configured")
            return
        first = self._pass_log[0] if self._pass_log else None
        # (a few frames at a pass's end placed with a newer latency may count as a pass of their own)
        later_registered = all(p.trusted for p in self._pass_log[1:] if p.frames >= 15) and self.config.register
        velocity = None if first is None else first.velocity()
        if first is None or velocity is None or not later_registered:
            return
        shift = (estimate.value - first.latency()) * velocity   # where the first pass (and the map) lies off
        if float(np.hypot(*shift)) <= 0.1 * self.config.resolution:
            shift = np.zeros(2)
        # finalise may run more than once (a live map saved, then more frames): move by what is not moved yet
        done = -np.asarray(self.stats.map_shift_m)
        ox, oy = self.canvas.origin
        self.canvas.origin = (ox - float(shift[0] - done[0]), oy - float(shift[1] - done[1]))
        self.stats.map_shift_m = (-float(shift[0]), -float(shift[1]))
        self._net_corrections(estimate.value, first.latency(), velocity)

    def _net_corrections(self, latency: float, first_latency: float, first_velocity: np.ndarray) -> None:
        """`stats.pass_residuals_px`: a pass placed with latency L_p and moved by registration by delta_p
        lies, after the map's final shift, delta_p + (L - L_p) v_p - (L - L_1) v_1 from where TF and the
        final latency L put it."""
        residuals = []
        for record in self._pass_log[1:]:
            velocity = record.velocity()
            if velocity is None:   # a pass that did not roll
                continue
            net = (np.asarray(record.delta) * self.config.resolution + (latency - record.latency()) * velocity
                   - (latency - first_latency) * first_velocity) / self.config.resolution
            residuals.append((float(net[0]), float(net[1])))
        self.stats.pass_residuals_px = residuals

    def map_image(self, crop: bool = True) -> WorldMapImage:
        """The map for files and topics; `crop`: to what was mapped (a growing map's spare room goes;
        a map with `bounds` keeps them)."""
        origin = self.canvas.origin
        box = self.canvas.used()
        if box is None:
            grey, weight = self.canvas.value(self._level)
            box = (0, grey.shape[0], 0, grey.shape[1])
        else:   # the value where bands were added: zero elsewhere
            grey, weight = self.canvas.value_in(self._level, box)
        mapped = weight > 0.05
        b0, c0 = box[0], box[2]
        if crop and not self.canvas.fixed and mapped.any():
            rows, cols = np.flatnonzero(mapped.any(axis=1)), np.flatnonzero(mapped.any(axis=0))
            r0, r1, k0, k1 = rows[0], rows[-1] + 1, cols[0], cols[-1] + 1
            grey, mapped = grey[r0:r1, k0:k1], mapped[r0:r1, k0:k1]
            origin = (origin[0] + (c0 + k0) * self.config.resolution, origin[1] + (b0 + r0) * self.config.resolution)
            image, alpha = _grey_alpha(grey, mapped)
        else:   # the whole canvas
            shape = self.canvas.shape
            image, alpha = np.zeros(shape, np.uint8), np.zeros(shape, np.uint8)
            flipped = (slice(shape[0] - box[1], shape[0] - box[0]), slice(box[2], box[3]))
            image[flipped], alpha[flipped] = _grey_alpha(grey, mapped)
        return WorldMapImage(image, alpha, self.config.resolution, origin)

    def coverage(self, bounds: tuple[float, float, float, float]) -> float:
        """Percent of the rectangle (x_min, y_min, x_max, y_max) mapped."""
        c0, r0 = (int(v) for v in np.floor(self.canvas.to_grid(np.array(bounds[:2])) + 0.5))
        c1, r1 = (int(v) for v in np.floor(self.canvas.to_grid(np.array(bounds[2:])) + 0.5))
        total = max((c1 - c0) * (r1 - r0), 1)
        rows, cols = self.canvas.shape
        box = (max(r0, 0), min(r1, rows), max(c0, 0), min(c1, cols))
        if box[1] <= box[0] or box[3] <= box[2]:
            return 0.0
        _, weight = self.canvas.value_in(self._level, box)
        return 100.0 * float(np.count_nonzero(weight > 0.05)) / total

    # -- tiles: files and live views --------------------------------------------------------------------
    def view(self) -> LayerView:
        """The map (flat-field-corrected grey, weights) as a `tiles.LayerView` on the tile store's absolute
        cells: what the GeoTIFF writer streams and live views render, a tile at a time."""
        return self.canvas.view(self._level)

    def touched_tiles(self) -> set[tuple[int, int]]:
        """(ix, iy) of the level-0 tiles bands changed since the last call (absolute tile indices)."""
        return self.canvas.store.touched()

    def render_tile(self, level: int, ix: int, iy: int, low: float = 0.0,
                    high: float = 255.0) -> tuple[np.ndarray, np.ndarray]:
        """Tile (level, ix, iy) of the map's pyramid as (grey uint8, alpha uint8), image rows (row 0 the
        largest y); see `tiles.render_tile`. Its lower-left corner lies at world `tile_corner(level, ix, iy)`."""
        return render_tile(self.view(), level, ix, iy, low, high)

    def tile_corner(self, level: int, ix: int, iy: int) -> tuple[float, float]:
        """World (x, y) of the lower-left corner of tile (level, ix, iy); its side is tile * 2^level * res."""
        side = self.canvas.tile * 2 ** level * self.config.resolution
        return self.canvas.anchor[0] + ix * side, self.canvas.anchor[1] + iy * side

    def level_extent(self, level: int) -> tuple[int, int, int, int] | None:
        """(row0, row1, column0, column1) of pyramid level `level`'s cells (absolute, 2^level grid cells
        each) that hold the map's extent (`view().extent()`); None: nothing mapped."""
        box = self.view().extent()
        if box is None:
            return None
        f = 2 ** level
        return box[0] // f, -(-box[1] // f), box[2] // f, -(-box[3] // f)

    def level_image(self, level: int) -> WorldMapImage | None:
        """The map's extent at pyramid level `level` (downscaled by 2^level, weighted means; level 0: the
        map cropped as map.tif holds it) as one image, rendered a tile at a time from the tile store
        (`render_tile`): memory is the image, not the map. None: nothing mapped."""
        box = self.level_extent(level)
        if box is None:
            return None
        r0, r1, c0, c1 = box
        t = self.canvas.tile
        grey, alpha = np.zeros((r1 - r0, c1 - c0), np.uint8), np.zeros((r1 - r0, c1 - c0), np.uint8)
        view = self.view()
        for iy in range(r0 // t, (r1 - 1) // t + 1):
            for ix in range(c0 // t, (c1 - 1) // t + 1):
                y0, y1, x0, x1 = max(r0, iy * t), min(r1, (iy + 1) * t), max(c0, ix * t), min(c1, (ix + 1) * t)
                tile_grey, tile_alpha = render_tile(view, level, ix, iy)   # image rows: row 0 the top
                rows = slice((iy + 1) * t - y1, (iy + 1) * t - y0)
                target = (slice(r1 - y1, r1 - y0), slice(x0 - c0, x1 - c0))
                grey[target] = tile_grey[rows, x0 - ix * t:x1 - ix * t]
                alpha[target] = tile_alpha[rows, x0 - ix * t:x1 - ix * t]
        res = self.config.resolution * 2 ** level
        anchor = self.canvas.anchor
        return WorldMapImage(grey, alpha, res, (anchor[0] + c0 * res, anchor[1] + r0 * res))

    def close(self) -> None:
        """Remove the tiles spilled to disk (the mapper is not used after)."""
        self.canvas.store.close()

    # -- setup ---------------------------------------------------------------------------------------
    def _setup(self) -> None:
        sampler = self.strip.sampler
        if sampler is None or sampler.mm_per_px is None or sampler.mm_per_px_cols is None or sampler.centre_u is None:
            raise ValueError("a world map needs the camera model's rectified band (default method)")
        self.m_per_row, self.m_per_col = sampler.mm_per_px * 1e-3, sampler.mm_per_px_cols * 1e-3
        rows, cols = sampler.rows, sampler.cols
        across = taper(rows)
        x = (np.arange(cols) - sampler.centre_u) * self.m_per_col
        half = 0.5 * self.camera.length
        if self.config.edge_taper:
            ends = np.clip((half - np.abs(x)) / max(self.config.edge_taper, 1e-9), 0.0, 1.0)
        else:
            ends = (np.abs(x) <= half).astype(np.float64)
        ends = np.minimum(ends, np.clip(np.minimum(np.arange(cols) + 1, cols - np.arange(cols)) / 8.0, 0.0, 1.0))
        self._weights = (across[:, None] * ends[None, :]).astype(np.float32)
        latency = LatencyConfig(max_latency=self.config.max_latency, max_sigma=self.config.latency_max_sigma)
        self._estimator = LatencyEstimator(self.m_per_row, latency) if self.latency_ns is None else None
        # the band's shading when pressed: touchdowns and lift-offs for the latency, and with the latency
        # told too, the pressed height TF shows confirmed without texture (`_pressed_from_tf`)
        self._contacts = ContactTimer(self.config.max_latency)

    # -- the queue -----------------------------------------------------------------------------------
    def _drain(self, final: bool) -> None:
        self._find_events(final)
        forced = final or len(self._pending) > self.config.hold_frames
        if self._pressed_height is None and (forced or self.stats.frames % 10 == 0):   # every 10 frames: cost
            self._pressed_from_tf(forced)
        if final and self._pressed_height is None and self._pending:
            # nothing agreed on the pressed height (a short or textureless roll): the lowest the roller went
            stamps = np.array([f.stamp_ns for f in self._pending], np.int64) - (self._latency() or 0)
            heights = self.poses(stamps)[:, 2, 3]
            if np.isfinite(heights).any():
                self._pressed_height = float(np.nanmin(heights))
                self.stats.pressed_height = self._pressed_height
        self._contact_events(final)
        self._prefetch_poses()
        while self._pending:
            frame = self._pending[0]
            ready = self._ready(frame)
            if (ready is None and not final and len(self._pending) <= self.config.hold_frames
                    and not self._never_posed(frame)):
                self._place_provisionally()
                return
            self._pending.popleft()
            if self._provisional_frames:   # placing for good: nothing provisional beside it
                self._clear_provisional()
            if self._pressed_height is None:   # held too long and nothing rolled yet: a lead-in, not mapped
                self.stats.not_in_contact += 1
                continue
            pose = ready if ready is not None else self._pose_now(frame)   # the end: with what is known
            if pose is None:
                self.stats.no_pose += 1
                continue
            self._take(frame, pose)

    def _place_provisionally(self) -> None:
        """The waiting frames not yet on the provisional layers, with the fallback latency, while it is the
        latency alone they wait for (`WorldMapConfig.provisional`); no registration, no pass records."""
        if not self.config.provisional or self._pressed_height is None or self._latency() is not None:
            return
        latency = round(self.config.latency_fallback * 1e9)
        waiting = [f for f in self._pending if not f.provisional]
        if not waiting:
            return
        poses = self.poses(np.array([f.stamp_ns - latency for f in waiting], np.int64))
        for frame, pose in zip(waiting, poses, strict=True):
            if not np.isfinite(pose).all():
                break   # its pose has not come yet: it and those after it next time
            frame.provisional = True
            if float(pose[2, 3]) > self._pressed_height + self.config.contact_tolerance:
                continue
            placement = self._locate(pose, np.zeros(2))
            planes = self._planes(frame, placement, float(pose[2, 3]) - self._pressed_height)
            live = dict(zip(PROVISIONAL_LAYERS, (planes["band"], planes["flat"], planes["weight"],
                                                 planes.get("height_pass"), planes.get("height_pass_w")),
                            strict=True))
            try:
                self.canvas.add_named(live, placement.c0, placement.r0)
            except StorageFull:
                continue
            self._provisional_frames += 1

    def _clear_provisional(self) -> None:
        """Empty the provisional layers (their frames are being placed for good); their tiles count as touched."""
        store = self.canvas.store
        tiles: set[tuple[int, int]] = set()
        for name in PROVISIONAL_LAYERS:
            tiles |= store.tiles(name)
            store.drop_layer(name)
            store.add_layer(name, np.float32)
        store.note_touched(tiles)
        self._provisional_frames = 0
        self.replacements += 1

    def _never_posed(self, frame: _Frame) -> bool:
        """Everything but the frame's pose is known and a later frame has its pose: TF began after this
        frame's exposure (or has a gap there), so the frame will not be placed and holds no one back."""
        latency = self._latency()
        if latency is None or self._pressed_height is None:
            return False
        return any(later.pose is not None and later.pose_latency == latency
                   for later in itertools.islice(self._pending, 1, None))

    def _latency(self) -> int | None:
        """The latency frames are placed with now (ns): told, the estimate once observable, or the fallback
        once frames could wait no longer; None while undecided."""
        if self.latency_ns is not None:
            return self.latency_ns
        return self._placing_ns

    def _latency_or_fallback(self) -> int:
        """`_latency()`, deciding on the configured fallback when nothing was decided yet (frames waited
        as long as they may, or the scan ended)."""
        latency = self._latency()
        if latency is None:
            latency = self._placing_ns = round(self.config.latency_fallback * 1e9)
            self.stats.latency_s = self.config.latency_fallback
        return latency

    def _prefetch_poses(self) -> None:
        """Look up, in one go, the poses of the waiting frames that will need them at the current latency."""
        latency = self._latency()
        if latency is None or self._pressed_height is None:
            return
        frames = [f for f in self._pending if f.pose is None or f.pose_latency != latency]
        if len(frames) < 2:
            return
        poses = self.poses(np.array([f.stamp_ns - latency for f in frames], np.int64))
        for frame, pose in zip(frames, poses, strict=True):
            if np.isfinite(pose).all():
                frame.pose, frame.pose_latency = pose, latency

    def _pose_now(self, frame: _Frame) -> np.ndarray | None:
        """The frame's pose at the current latency (looked up once per latency)."""
        latency = self._latency_or_fallback()
        if frame.pose is not None and frame.pose_latency == latency:
            return frame.pose
        pose = self.poses(np.array([frame.stamp_ns - latency], np.int64))[0]
        if not np.isfinite(pose).all():
            return None
        frame.pose, frame.pose_latency = pose, latency
        return pose

    def _ready(self, frame: _Frame) -> np.ndarray | None:
        """The frame's pose when everything it needs is known, else None."""
        if self._latency() is None or self._pressed_height is None:
            return None
        return self._pose_now(frame)

    # -- contact, events and latency --------------------------------------------------------------------
    def _pressed_from_tf(self, forced: bool) -> None:
        """The pressed height from TF alone, for a surface with too little texture for the image to agree
        with the arm: the lowest height at which the arm moved along the surface for at least 20 frames
        (within half the contact tolerance). Taken when a frame whose image moved with the arm lies at
        it, or when frames can wait no longer (the roller then rolled there: an arm moving in the air
        between passes is higher)."""
        if len(self._tf_heights) < 20:
            return
        track = np.array(self._tf_heights)
        dt = np.diff(track[:, 0]) * 1e-9
        ok = dt > 0
        speed = np.zeros(len(track))
        speed[1:][ok] = np.hypot(*np.diff(track[:, 1:3], axis=0)[ok].T) / dt[ok]
        moving = speed > 2e-3
        if moving.sum() < 20:
            return
        z = track[moving, 3]
        level = float(z.min())
        near = np.abs(z - level) <= 0.5 * self.config.contact_tolerance
        if near.sum() < 20:
            return
        plateau = _median(z[near])
        confirmed = any(abs(h - plateau) <= self.config.contact_tolerance for h in self._agree_heights)
        shaded = (not confirmed and self._contacts is not None
                  and self._contacts.shows_pressing(self.poses, plateau, self._latest_stamp))
        if confirmed or shaded or forced:
            self._pressed_height = plateau
            self.stats.pressed_height = plateau
            self.stats.pressed_from = ("tf, confirmed by the image" if confirmed else
                                       "tf, confirmed by the pressed band's shading" if shaded else "tf")

    def _find_events(self, final: bool) -> None:
        """Learn the pressed height, find starts and stops of the roll, and (re)estimate the latency."""
        if len(self._recent) < 3:
            return
        newest = self._latest_stamp
        if newest - self._last_event_check < _EVENT_CHECK_NS and not final:
            return
        self._last_event_check = int(newest)
        stamps, positions, heights, arm_rows = self._track()
        known = np.isfinite(heights)
        if known.sum() < 3:
            return
        stamps, positions, heights, arm_rows = stamps[known], positions[known], heights[known], arm_rows[known]
        dt = np.diff(stamps) * 1e-9
        valid = dt > 0
        if not valid.any():
            return
        arm_speed = np.zeros(len(stamps))
        image_speed = np.zeros(len(stamps))
        arm_speed[1:][valid] = np.diff(arm_rows)[valid] / dt[valid]
        image_speed[1:][valid] = np.diff(positions)[valid] / dt[valid]
        fast = np.abs(arm_speed) > 3.0   # rows per second: the arm rolls, not just settles
        agree = fast & (np.abs(image_speed - arm_speed) < 0.3 * np.abs(arm_speed) + 1.0)
        self._agree_heights.extend(float(h) for h in heights[agree][-20:])
        if agree.sum() >= 3:
            self._pressed_height = _median(heights[agree])
        elif final and self._pressed_height is None and fast.any():
            # a roll too short (or too textureless) to agree on: the lowest height the arm moved at
            self._pressed_height = float(heights[fast].min())
        self.stats.pressed_height = self._pressed_height
        if self._estimator is None:
            return
        # starts and stops: the arm's speed along the rows crossing half its cruise, in agreeing stretches
        moving = np.abs(arm_speed) > max(0.5 * _percentile(np.abs(arm_speed), 90), 3.0)
        windows = len(self._estimator.windows)
        # the speed is measured from the frame before: not at the track's first frame nor across a gap (a
        # pass that touched down at speed begins moving, which is no start)
        measured = np.zeros(len(stamps), bool)
        measured[1:] = valid & (dt <= 0.2)
        for k in np.flatnonzero((moving[1:] != moving[:-1]) & measured[1:] & measured[:-1]) + 1:
            event = int(stamps[k])
            if all(abs(event - e) > 300_000_000 for e in self._events):
                self._events.append(event)
                self._add_window(event)
        self._add_pass_windows(stamps, positions, heights, arm_speed, final)
        pending = any(not w.solved for w in self._estimator.windows)
        if self._estimator.windows and (len(self._estimator.windows) > windows or pending or final):
            self._estimator.solve(self.poses)
            self._use_estimate()

    def _contact_events(self, final: bool) -> None:
        """Touchdowns and lift-offs the image shows, once the pressed height is known (the latency from
        contact timing: `touchroller_perception.contact_timing`)."""
        if self._contacts is None or self._estimator is None or self._pressed_height is None:
            return
        if self._latest_stamp - self._last_contact_check < _EVENT_CHECK_NS and not final:
            return
        self._last_contact_check = self._latest_stamp
        found = self._contacts.update(self.poses, self._pressed_height, self._latest_stamp, final)
        if found:
            self._estimator.add_contact_events(found)
            self._estimator.solve(self.poses)
            self._use_estimate()

    def _use_estimate(self) -> None:
        """Place the frames still to come with the estimate when the evidence pins it down."""
        assert self._estimator is not None
        estimate = self._estimator.result(self.config.latency_fallback)
        self.stats.latency = estimate
        if estimate is not None and estimate.observable:
            # placed on a 0.5 ms grid (10 um at 20 mm/s): the same frames seen from a slightly different
            # first frame (a live map against its recording) give estimates a few microseconds apart,
            # which would move every band by a hundredth of a pixel and change the map's rounding
            self._placing_ns = round(estimate.value / _PLACING_STEP_S) * round(_PLACING_STEP_S * 1e9)
            self._placing_sigma = estimate.sigma
            self.stats.latency_s = estimate.value
            self.stats.latency_estimated = True

    def _add_pass_windows(self, stamps: NDArray[np.int64], positions: FloatArray, heights: FloatArray,
                          arm_speed: FloatArray, final: bool) -> None:
        """The steady rolling of each pass that ended (pressed stretches of one direction, away from the
        start/stop windows) as `pass_roll` evidence, each stretch once."""
        assert self._estimator is not None
        if self._pressed_height is None:
            return
        pressed = heights <= self._pressed_height + self.config.contact_tolerance
        direction = np.sign(arm_speed) * (np.abs(arm_speed) > 3.0)
        # stretches: pressed, one direction, no gap of more than half a second
        breaks = ~pressed[1:] | ~pressed[:-1] | (direction[1:] != direction[:-1]) | (np.diff(stamps) > 500_000_000)
        edges = np.concatenate([[0], np.flatnonzero(breaks) + 1, [len(stamps)]])
        horizon = self._latest_stamp - self._estimator.after_ns - _EVENT_CHECK_NS
        for a, b in zip(edges[:-1], edges[1:], strict=True):
            if b - a < 20 or not pressed[a] or direction[a] == 0:
                continue
            end = int(stamps[b - 1])
            if end <= self._pass_windows_until or (end > horizon and not final):
                continue
            self._pass_windows_until = end
            keep = np.ones(b - a, bool)
            for event in self._events:
                keep &= ~((stamps[a:b] >= event - self._estimator.before_ns)
                          & (stamps[a:b] <= event + self._estimator.after_ns))
            self._estimator.add_pass_window([int(v) for v in stamps[a:b][keep]],
                                            [float(v) for v in positions[a:b][keep]])

    def _track(self) -> tuple[NDArray[np.int64], FloatArray, FloatArray, FloatArray]:
        """(stamps, image positions, roller heights, arm roll in rows) of the recent confident frames, the
        poses at the current latency, looked up once per frame (again only when the latency changes)."""
        latency = self._latency() or 0
        recent = self._recent
        if latency != self._track_latency:
            self._track_latency = latency
            recent.forget_poses()
        stamps, heights, rows = recent.stamps, recent.heights, recent.arm_rows
        missing = np.flatnonzero(np.isnan(heights))
        if len(missing):
            poses = self.poses(stamps[missing] - latency)
            known = np.isfinite(poses).all(axis=(1, 2))
            if known.any():
                found, poses = missing[known], poses[known]
                if self._reference_point is None:
                    self._reference_point = poses[0, :3, 3].copy()
                offsets = self._reference_point[None, :] - poses[:, :3, 3]
                heights[found] = poses[:, 2, 3]
                rows[found] = np.einsum("ni,ni->n", poses[:, :3, 1], offsets) / self.m_per_row
        return stamps.copy(), recent.positions.copy(), heights.copy(), rows.copy()

    def _add_window(self, event_ns: int) -> None:
        """The frames around a start or stop of the arm, the roller pressed (an arm moving above the
        surface, between passes, starts and stops too: its frames do not follow it)."""
        assert self._estimator is not None
        lo = event_ns - self._estimator.before_ns
        hi = event_ns + self._estimator.after_ns
        inside = (self._recent.stamps >= lo) & (self._recent.stamps <= hi)
        if not inside.any() or self._latest_stamp < hi or self._pressed_height is None:
            self._events.remove(event_ns)   # not enough known yet: found again later
            return
        stamps = self._recent.stamps[inside]
        poses = self.poses(stamps - (self._latency() or 0))
        heights = np.where(np.isfinite(poses).all(axis=(1, 2)), poses[:, 2, 3], np.inf)
        pressed = heights <= self._pressed_height + self.config.contact_tolerance
        if pressed.sum() < 12:
            return   # the roller was not down around it: no window (and not looked at again)
        positions = self._recent.positions[inside]
        self._estimator.add_window([int(v) for v in stamps[pressed]], [float(v) for v in positions[pressed]])

    # -- placing -----------------------------------------------------------------------------------------
    def _take(self, frame: _Frame, pose: np.ndarray) -> None:
        height = float(pose[2, 3])
        assert self._pressed_height is not None
        if height > self._pressed_height + self.config.contact_tolerance:
            self.stats.not_in_contact += 1
            if self._in_contact:
                self._end_pass()
                self._last_contact_ns = frame.stamp_ns
            return
        if not self._in_contact and not (self._last_contact_ns is not None and self._pass_log
                                         and frame.stamp_ns - self._last_contact_ns < _RESUME_NS):
            self._start_pass()
        self._in_contact = True
        self._pass_log[-1].add(frame.stamp_ns - (frame.pose_latency or 0), pose, frame.pose_latency or 0)
        if self._prior is None or not self.config.register:
            self._place(frame, pose, np.zeros(2))
            return
        # register the first frames of the pass, then one in _PASS_REGISTER_EVERY (the correction is one
        # shift per pass, the median of its frames' offsets); after _PASS_FAILED_RUN registrations in a row
        # found nothing (no texture, no overlap with the earlier passes) one in _PASS_REGISTER_EVERY too, until
        # one finds an offset: a registration costs several times the frame's placing
        self._pass_frames += 1
        first = len(self._pass_offsets) < 10 and self._pass_failed < _PASS_FAILED_RUN
        if first or self._pass_frames % _PASS_REGISTER_EVERY == 0:
            offset = self._register(frame, pose)
            self._pass_failed = self._pass_failed + 1 if offset is None else 0
            if offset is not None:
                self._pass_offsets.append(offset[:3])
                self._pass_log[-1].offsets.append((offset[0], offset[1], offset[3], offset[4],
                                                   float(pose[0, 3]), float(pose[1, 3])))
        if len(self._pass_offsets) < 10 and len(self._pass_buffer) < 45:
            self._pass_buffer.append((frame, pose))
            return
        self._update_delta()
        self._flush_pass_buffer()
        self._place(frame, pose, self._pass_delta)

    def _start_pass(self) -> None:
        self.stats.passes += 1
        self._pass_log.append(_PassRecord())
        self._pass_offsets, self._pass_buffer, self._pass_delta = [], [], np.zeros(2)
        self._delta_offsets = 0
        self._pass_frames = 0
        self._pass_failed = 0
        if self.stats.passes > 1 and self.config.register:
            # the map as it is now, kept copy-on-write as the pass's bands change its tiles
            self._prior = _Prior(self.canvas, self._level)
            self._prior_weight_max = self._prior.weight_max or 1.0

    def _end_pass(self) -> None:
        self._flush_pass_buffer()
        if self._height_layer is not None:
            self._end_height_pass()
        if self._prior is not None and not (self._pass_log and self._pass_log[-1].ended):
            self.stats.pass_corrections_px.append((float(self._pass_delta[0]), float(self._pass_delta[1])))
        self._in_contact = False
        if self._pass_log:
            self._pass_log[-1].ended = True
            self._pass_log[-1].delta = (float(self._pass_delta[0]), float(self._pass_delta[1]))
            self._opposite_passes()

    def _opposite_passes(self) -> None:   # once per pass (a pass resumed, or finalised and going on)
        """The latency the pass that ended and the one before it say, when they were rolled in opposite
        directions and this one was registered against the earlier ones (`latency` module docstring).
        Pass k placed at latency L_k lands (L - L_k) v_k u_k off; registered against pass k - 1 (placed at
        L_{k-1}, moved by delta_{k-1}), its offset o along u_k = -u_{k-1} is
        delta_{k-1}.u - (L - L_{k-1}) v_{k-1} - (L - L_k) v_k, so
        L = (L_{k-1} v_{k-1} + L_k v_k + (delta_{k-1} - o).u) / (v_{k-1} + v_k), v_{k-1} the earlier pass's
        speed where it rolled over the same ground: a speed that varies along the passes (a blend, an arm's
        ripple) differs between them there, and taking this pass's speed for both biased L by
        L (v_{k-1} - v_k) / 2 v."""
        if self._estimator is None or len(self._pass_log) < 2 or self._pass_log[-1].evidence_given:
            return
        this, before = self._pass_log[-1], self._pass_log[-2]
        u, u_before = this.direction(), before.direction()
        if u is None or u_before is None or float(u @ u_before) > -0.9 or len(this.offsets) < 5 or not this.trusted:
            return
        res = self.config.resolution
        offsets = np.array(this.offsets)   # (dx, dy, latency ns, speed m/s, x, y m)
        speed = offsets[:, 3]   # this frame's, from the arm's poses around it
        ok = speed > 1e-3
        if ok.sum() < 5:
            return
        along = (np.asarray(before.delta) - offsets[ok, :2]) @ u * res      # m
        v1, placed, before_latency = speed[ok], offsets[ok, 2] * 1e-9, before.latency()
        here = offsets[ok, 4:6] @ u   # where this frame's pose (at the latency it was placed with) lies along u
        # the earlier pass's speed over the same ground: both passes' poses were looked up at the latencies
        # they were placed with, (L - L_p) v off where the arm truly was, so the ground is matched with the
        # estimate itself (from both passes' speeds taken alike, then again with the one found)
        latency = None
        for _ in range(3):
            if latency is None:
                v0 = v1
            else:
                v0 = before.speed_at(here - (latency - placed) * v1, u, latency - before_latency)
                v0 = np.where(np.isfinite(v0), v0, v1)   # beyond where the earlier pass rolled: this one's
            good = v0 > 1e-3
            if good.sum() < 5:
                return
            values = (before_latency * v0[good] + placed[good] * v1[good] + along[good]) / (v0[good] + v1[good])
            latency = _median(values)
        v0, v1 = v0[good], v1[good]
        assert latency is not None   # set by every pass of the loop above: the median of these values
        centre = latency
        spread = 1.4826 * _median(np.abs(values - centre))
        # a registration is good to about 0.05 map pixel: the least spread a median can have
        floor = 0.05 * res / _median(v0 + v1)
        # neighbouring frames' values are not independent (they share the speed profile and the map they
        # matched): the spread of their median inflated by their lag-1 correlation, as a window's fit is
        residuals = values - centre
        rho = 0.0
        if len(residuals) > 4 and float(residuals @ residuals) > 0:
            rho = min(max(float(residuals[1:] @ residuals[:-1]) / float(residuals @ residuals), 0.0), 0.95)
        sigma = spread / math.sqrt(len(values)) * math.sqrt((1 + rho) / (1 - rho))
        this.evidence_given = True
        self._estimator.add_opposite_passes(centre, max(sigma, floor))
        self._use_estimate()

    def _update_delta(self) -> None:
        """The pass's correction: the median of its offsets once five or more agree (MAD within
        `_DELTA_MAD_PX`); none (TF alone) while they do not."""
        if self._pass_offsets and len(self._pass_offsets) != self._delta_offsets:   # new offsets since
            offsets = np.array(self._pass_offsets)
            centre = np.array([_median(offsets[:, 0]), _median(offsets[:, 1])])
            spread = max(_median(np.abs(offsets[:, 0] - centre[0])), _median(np.abs(offsets[:, 1] - centre[1])))
            trusted = len(offsets) >= 5 and spread <= _DELTA_MAD_PX
            self._pass_delta = centre if trusted else np.zeros(2)
            if self._pass_log:
                self._pass_log[-1].trusted = trusted
            self._delta_offsets = len(self._pass_offsets)

    def _flush_pass_buffer(self) -> None:
        if not self._pass_buffer:
            return
        self._update_delta()
        buffered, self._pass_buffer = self._pass_buffer, []
        for frame, pose in buffered:
            self._place(frame, pose, self._pass_delta)

    def _affine(self, pose: np.ndarray) -> np.ndarray:
        """2x3: band (column j, row i) -> map grid (column, row), pixel centres on whole numbers."""
        sampler = self.strip.sampler
        assert sampler is not None and sampler.centre_u is not None
        # plain floats (per frame placed: numpy's calls on 3-vectors cost more than their arithmetic)
        (r00, r01, r02, tx), (r10, r11, r12, ty), _, _ = pose.tolist()
        r, mc, mr, res = self.camera.radius, self.m_per_col, self.m_per_row, self.config.resolution
        # cylinder point of band pixel (j, i): (x0 + j mc, y0 + i mr, r)
        x0, y0 = -sampler.centre_u * mc, -(sampler.rows - 1) / 2.0 * mr
        ox, oy = self.canvas.origin
        return np.array([[r00 * mc / res, r01 * mr / res, (r00 * x0 + r01 * y0 + r02 * r + tx - ox) / res - 0.5],
                         [r10 * mc / res, r11 * mr / res, (r10 * x0 + r11 * y0 + r12 * r + ty - oy) / res - 0.5]])

    def _footprint(self, matrix: np.ndarray) -> tuple[int, int, int, int]:
        """(c0, r0, c1, r1): the map cells the band's corners fall in, with a cell to spare around."""
        sampler = self.strip.sampler
        assert sampler is not None
        (a, b, c), (d, e, f) = matrix.tolist()
        w, h = sampler.cols - 1, sampler.rows - 1
        xs = (c, a * w + c, b * h + c, a * w + b * h + c)
        ys = (f, d * w + f, e * h + f, d * w + e * h + f)
        return math.floor(min(xs)) - 1, math.floor(min(ys)) - 1, math.ceil(max(xs)) + 2, math.ceil(max(ys)) + 2

    def _band_planes(self, frame: _Frame) -> tuple[np.ndarray, np.ndarray]:
        """(w band, w field) in band coordinates; w field is shared while the flat field stays the same."""
        assert self._weights is not None
        band = _grey_levels(frame.band)
        weighted = cv2.multiply(band, self._weights)
        if frame.field is None:
            return weighted, self._weights * np.float32(band.mean())
        return weighted, self._weighted_field_of(frame.field)

    def _weighted_field_of(self, field: np.ndarray) -> np.ndarray:
        """w field, computed once per flat field (the frames share it while it stays)."""
        assert self._weights is not None
        if self._weighted_field is None or self._weighted_field[0] is not field:
            self._weighted_field = (field, cv2.multiply(field, self._weights), {})
        return self._weighted_field[1]

    def _oriented(self, key: str, plane: np.ndarray, axes: tuple[bool, bool, bool]) -> np.ndarray:
        """The constant planes (w; w field while the field stays) oriented once per orientation."""
        cache = self._oriented_weights if key == "w" else (self._weighted_field[2] if self._weighted_field else {})
        out = cache.get(axes)
        if out is None:
            out = cache[axes] = _orient(plane, axes)
        return out

    def _blend_stack(self, frame: _Frame, placement: _Placement) -> np.ndarray:
        """(3, h + 1, w + 1): the frame's w band, w field and w on the map grid at an axis-aligned
        `placement` (a frame with a flat field): the same numbers as `_on_map` of each, in one bilinear
        blend of the three oriented planes stacked in a buffer kept per orientation."""
        assert self._weights is not None and placement.axes is not None and placement.kernel is not None
        assert frame.field is not None
        axes = placement.axes
        weighted_field = self._weighted_field_of(frame.field)
        stack = self._stacks.get(axes)
        if stack is None or stack[0] is not weighted_field:
            buffer = stack[1] if stack is not None else None
            oriented_w = self._oriented("w", self._weights, axes)
            h, w = oriented_w.shape
            if buffer is None:
                buffer = np.zeros((3, h, w), np.float32)   # each plane with its zero border
                buffer[2] = oriented_w
            buffer[1] = self._oriented("field", weighted_field, axes)
            self._stacks[axes] = stack = (weighted_field, buffer)
        buffer = stack[1]
        _, h, w = buffer.shape
        inner = buffer[0, 1:-1, 1:-1]
        _orient_into(_grey_levels(frame.band), axes, inner)
        cv2.multiply(inner, buffer[2, 1:-1, 1:-1], dst=inner)
        blended = cv2.filter2D(buffer.reshape(3 * h, w), -1, placement.kernel, anchor=(0, 0),
                               borderType=cv2.BORDER_CONSTANT)
        return blended.reshape(3, h, w)[:, :-1, :-1]

    def _on_map(self, placement: _Placement, plane: np.ndarray, constant: str | None = None) -> np.ndarray:
        """A plane in band coordinates on the map grid at `placement`; `constant` names a plane that stays
        the same over frames ("w", "field": oriented once per orientation)."""
        if placement.axes is not None:
            assert placement.kernel is not None
            oriented = _orient(plane, placement.axes) if constant is None else self._oriented(constant, plane,
                                                                                               placement.axes)
            return _blend(oriented, placement.kernel)
        assert placement.matrix is not None
        return cv2.warpAffine(plane, placement.matrix, placement.size, flags=cv2.INTER_LINEAR,
                              borderMode=cv2.BORDER_CONSTANT, borderValue=0)

    def _locate(self, pose: np.ndarray, delta: np.ndarray) -> _Placement:
        """Where the band of a frame at `pose`, moved by `delta` map pixels, lands (the map grown to hold it)."""
        assert self._weights is not None
        matrix = self._affine(pose)
        matrix[:, 2] += delta
        c0, r0, c1, r1 = self._footprint(matrix)
        if (c1 - c0) * (r1 - r0) > _MAX_BAND_PIXELS:
            raise MemoryError(f"one band needs {(c1 - c0) * (r1 - r0):.3g} pixels at {self.config.resolution:g} m/px "
                              f"(at most {_MAX_BAND_PIXELS:.3g})")
        shift = self.canvas.ensure(c0, r0, c1, r1)
        if shift != (0, 0):
            matrix[:, 2] += shift
            self._placements = [placement.moved(*shift) for placement in self._placements]
            if self._prior is not None:
                self._prior = self._prior.moved(*shift)
        aligned = _axis_aligned(matrix, self._weights.shape)
        if aligned is not None:
            # an axis-aligned roller at the band's own scale: turn the band, then one bilinear 2x2 blend (the
            # affine kept for the height's interpolated relief: the same cells, (h + 1) x (w + 1) oriented)
            axes, c0, r0, kernel = aligned
            rows, cols = self._weights.shape[::-1] if axes[0] else self._weights.shape
            local = matrix.copy()
            local[:, 2] -= (c0, r0)
            return _Placement(c0, r0, axes, kernel=kernel, matrix=local, size=(cols + 1, rows + 1))
        c0, r0, c1, r1 = self._footprint(matrix)
        local = matrix.copy()
        local[:, 2] -= (c0, r0)
        return _Placement(c0, r0, None, matrix=local, size=(c1 - c0, r1 - r0))

    def _place(self, frame: _Frame, pose: np.ndarray, delta: np.ndarray) -> None:
        placement = self._locate(pose, delta)
        lift = 0.0 if self._pressed_height is None else float(pose[2, 3]) - self._pressed_height
        planes = self._planes(frame, placement, lift)
        try:   # one call: the band and its height land together or not at all
            self.canvas.add_named(planes, placement.c0, placement.r0)
        except StorageFull as exc:   # the map keeps what it has; the caller sees the count and the reason
            self.stats.left_out_storage_full += 1
            self.stats.storage_warning = str(exc)
            return
        self._placements.append(placement)
        self.stats.mapped += 1
        if frame.height is not None and self._height_layer is not None:   # after its planes: not read against itself
            self._height_layer.observe(frame.height)
        if frame.field is not None:
            self._level = float(frame.field.mean()) if frame.field is not self._level_field else self._level
            self._level_field = frame.field

    def _planes(self, frame: _Frame, placement: _Placement, lift: float = 0.0) -> dict[str, np.ndarray | None]:
        """The frame's planes on the map grid at `placement`, by canvas layer name (its height's too; `lift`: the
        roller's height above its pressed height, m, for the height's `follow_arm`)."""
        planes: dict[str, np.ndarray | None]
        if placement.axes is not None and frame.field is not None:
            planes = dict(zip(LAYERS, self._blend_stack(frame, placement), strict=True))
        else:
            assert self._weights is not None
            weighted_band, weighted_field = self._band_planes(frame)
            planes = {"band": self._on_map(placement, weighted_band),
                      "flat": self._on_map(placement, weighted_field, "field"),
                      "weight": self._on_map(placement, self._weights, "w")}
        if frame.height is not None and self._height_layer is not None:
            assert self._weights is not None
            layer = self._height_layer
            interpolation = _height_module().RESAMPLING[layer.config.resampling]
            if interpolation is None:   # "linear": the weighted relief splatted as the intensity is
                weighted, weights = layer.planes(self._weights, frame.height, lift)
                planes.update(layer.pass_planes(self._on_map(placement, weighted), self._on_map(placement, weights)))
            else:   # the relief interpolated onto the cells, times the weights placed there
                assert placement.matrix is not None
                on_map = self._on_map(placement, layer.contact_weights(self._weights, frame.height))
                relief = cv2.warpAffine(layer.relief(frame.height, lift), placement.matrix, placement.size,
                                        flags=interpolation, borderMode=cv2.BORDER_REPLICATE)
                planes.update(layer.pass_planes(cv2.multiply(relief, on_map), on_map))
        return planes

    def _search(self, frame: _Frame, pose: np.ndarray) -> tuple[int, int, float, tuple[int, int], float]:
        """(columns, rows) registration searches, the frame's speed (m/s), where the search is centred
        (columns, rows) and the extra search along the roll (map px): `search_px`, plus along the roll
        twice what the placing latency may be off times the speed (the whole `max_latency` while it is the
        configured fallback, three sigma once estimated), around the offset the estimate predicts
        (`_predicted_px`)."""
        latency = frame.pose_latency or 0
        # the poses up to the frame's own (known once it is: a later one may not have arrived yet, live)
        around = self.poses(np.array([frame.stamp_ns - latency - 40_000_000, frame.stamp_ns - latency], np.int64))
        base = self.config.search_px
        if not np.isfinite(around).all():
            return base, base, 0.0, (0, 0), 0.0
        velocity = (around[1, :2, 3] - around[0, :2, 3]) / 0.04
        speed = float(np.hypot(*velocity))
        if self.latency_ns is not None:
            doubt = 0.0
        elif self._placing_sigma is not None:
            doubt = 3.0 * self._placing_sigma
        else:
            doubt = self.config.max_latency
        extra = min(2.0 * speed * doubt / self.config.resolution, 120.0)
        if speed > 0:
            ux, uy = abs(float(velocity[0])) / speed, abs(float(velocity[1])) / speed
        else:
            ux = uy = 0.0
        return (base + math.ceil(extra * ux), base + math.ceil(extra * uy), speed,
                self._predicted_px(frame, velocity), extra)

    def _predicted_px(self, frame: _Frame, velocity: np.ndarray) -> tuple[int, int]:
        """The offset (columns, rows) of a frame against the pass before, as the current estimate L says:
        each lies (L - L_placed) v off, the pass before also moved by its correction. (0, 0) while the
        latency is told or not estimated."""
        if self.latency_ns is not None or self._placing_sigma is None or self._placing_ns is None \
                or len(self._pass_log) < 2:
            return 0, 0
        before = self._pass_log[-2]
        v_before = before.velocity()
        if v_before is None:
            return 0, 0
        latency, res = self._placing_ns * 1e-9, self.config.resolution
        prior_error = (latency - before.latency()) * v_before + np.asarray(before.delta) * res
        own_error = (latency - (frame.pose_latency or 0) * 1e-9) * velocity
        predicted = (prior_error - own_error) / res
        if not np.isfinite(predicted).all() or float(np.abs(predicted).max()) > 500:
            return 0, 0
        return round(float(predicted[0])), round(float(predicted[1]))

    def _register(self, frame: _Frame, pose: np.ndarray) -> tuple[float, float, float, float, float] | None:
        """This frame's offset (columns, rows, score) against the earlier passes where they overlap, with
        the latency it was placed with (ns) and its speed (m/s). The template is the band where it and
        the earlier passes overlap at every shift searched. A band turned on the map (a raster not along
        the world's axes) is registered on a grid turned with it (`_register_turned`)."""
        assert self._prior is not None and self._weights is not None
        placement = self._locate(pose, np.zeros(2))
        sx, sy, speed, (pc, pr), extra = self._search(frame, pose)
        if placement.axes is None:
            return self._register_turned(frame, placement, speed, (pc, pr), extra)
        # the overlap is judged on the weights alone; the band is put on the map only when it is usable
        weights = self._on_map(placement, self._weights, "w")
        c0, r0 = placement.c0, placement.r0
        h, w = weights.shape
        patch = self._prior.patch(r0 - sy + pr, c0 - sx + pc, h + 2 * sy, w + 2 * sx)
        if patch is None:
            return None

        def band() -> np.ndarray:
            weighted_band, weighted_field = (self._on_map(placement, plane, constant)
                                             for plane, constant in zip(self._band_planes(frame), (None, "field"),
                                                                        strict=True))
            return np.divide(weighted_band, weighted_field, out=np.zeros((h, w), np.float32),
                             where=weighted_field > 1e-6)

        found = self._match(patch[0], patch[1], weights, band, sx, sy)
        if found is None:
            return None
        dx, dy, best = found
        return float(dx + pc), float(dy + pr), best, float(frame.pose_latency or 0), speed

    def _register_turned(self, frame: _Frame, placement: _Placement, speed: float, predicted: tuple[int, int],
                         extra: float) -> tuple[float, float, float, float, float] | None:
        """`_register` for a band turned on the map by other than quarter turns: the band and the earlier
        passes resampled onto a grid at the map's resolution whose columns run along the band's columns
        (the roller's axis) and rows along its rows (the roll), where their overlap is a rectangle again;
        the offset found there turned back to the map's columns and rows."""
        assert self._prior is not None and self._weights is not None and placement.matrix is not None
        matrix = placement.matrix.astype(np.float64)
        matrix[:, 2] += (placement.c0, placement.r0)   # band -> map grid
        scale_c, scale_r = float(np.hypot(*matrix[:, 0])), float(np.hypot(*matrix[:, 1]))
        if not (scale_c > 1e-9 and scale_r > 1e-9):
            return None
        turn = np.stack([matrix[:, 0] / scale_c, matrix[:, 1] / scale_r], axis=1)   # grid step -> map step
        rows, cols = self._weights.shape
        w, h = math.ceil((cols - 1) * scale_c) + 3, math.ceil((rows - 1) * scale_r) + 3
        to_grid = np.array([[scale_c, 0.0, 1.0], [0.0, scale_r, 1.0]])   # band -> grid (a cell to spare)
        base = self.config.search_px
        sx, sy = base, base + math.ceil(extra)
        local = turn.T @ np.asarray(predicted, np.float64)   # the predicted offset on the grid
        pl = np.round(local)
        # grid (x, y) of the searched region -> map: turn @ ((x, y) - (sx, sy) + pl - 1) + origin
        origin = matrix[:, 2] + turn @ (pl - np.array([sx + 1.0, sy + 1.0]))
        W, H = w + 2 * sx, h + 2 * sy
        corners = np.array([[0, 0], [W - 1, 0], [0, H - 1], [W - 1, H - 1]], np.float64) @ turn.T + origin
        c0, r0 = math.floor(corners[:, 0].min()) - 1, math.floor(corners[:, 1].min()) - 1
        c1, r1 = math.ceil(corners[:, 0].max()) + 2, math.ceil(corners[:, 1].max()) + 2
        patch = self._prior.patch(r0, c0, r1 - r0, c1 - c0)
        if patch is None:
            return None
        inverse = np.concatenate([turn, (origin - (c0, r0))[:, None]], axis=1)   # grid -> patch
        flags = cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP
        prior, prior_weight = (cv2.warpAffine(plane, inverse, (W, H), flags=flags, borderMode=cv2.BORDER_CONSTANT,
                                              borderValue=0) for plane in patch)

        def on_grid(plane: np.ndarray) -> np.ndarray:
            return cv2.warpAffine(plane, to_grid, (w, h), flags=cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT,
                                  borderValue=0)

        weights = on_grid(self._weights)

        def band() -> np.ndarray:
            weighted_band, weighted_field = (on_grid(plane) for plane in self._band_planes(frame))
            return np.divide(weighted_band, weighted_field, out=np.zeros((h, w), np.float32),
                             where=weighted_field > 1e-6)

        found = self._match(prior, prior_weight, weights, band, sx, sy)
        if found is None:
            return None
        dx, dy, best = found
        offset = turn @ (np.array([dx, dy]) + pl)
        return float(offset[0]), float(offset[1]), best, float(frame.pose_latency or 0), speed

    def _match(self, prior: np.ndarray, prior_weight: np.ndarray, weights: np.ndarray,
               band: Callable[[], np.ndarray], sx: int, sy: int) -> tuple[float, float, float] | None:
        """(columns, rows, score): where the band (`band()`, weights `weights`, h x w) lies in the prior
        (value and weight, h + 2 sy x w + 2 sx, searched +-sx, +-sy around its centre). The template is
        the band where it and the prior overlap at every shift searched; None when that overlap is not a
        rectangle of some size, or the match is not confident."""
        assert self._weights is not None
        h, w = weights.shape
        known = (prior_weight > 0.3 * self._prior_weight_max).view(np.uint8)
        # known at every shift: eroded by the search's extent
        known = cv2.erode(known, np.ones((2 * sy + 1, 2 * sx + 1), np.uint8), borderType=cv2.BORDER_CONSTANT,
                          borderValue=0)[sy:sy + h, sx:sx + w].view(bool)
        mine = weights > 0.3 * float(self._weights.max())
        both = known & mine
        if np.count_nonzero(both) < 400:
            return None
        # the overlap's bounding rows and columns (np.nonzero's index arrays cost 5x as much)
        ys, xs = np.flatnonzero(both.any(axis=1)), np.flatnonzero(both.any(axis=0))
        a0, a1, b0, b1 = int(ys[0]), int(ys[-1]) + 1, int(xs[0]), int(xs[-1]) + 1
        base = self.config.search_px
        for _ in range(3):   # the weights' corners are rounded: shrink until it is a full rectangle
            if a1 - a0 < 12 or b1 - b0 < 12 or both[a0:a1, b0:b1].all():
                break
            a0, a1, b0, b1 = a0 + base, a1 - base, b0 + base, b1 - base
        if a1 - a0 < 12 or b1 - b0 < 12 or not both[a0:a1, b0:b1].all():
            return None   # the overlap is not a full rectangle
        template = _highpass(band()[a0:a1, b0:b1])
        # the search region: the template's rectangle grown by the search, in the patch's cells
        search = _highpass(prior[a0:a1 + 2 * sy, b0:b1 + 2 * sx])
        scores = cv2.matchTemplate(search, template, cv2.TM_CCOEFF_NORMED)
        _, best, _, (bx, by) = cv2.minMaxLoc(scores)
        if best < _MIN_SCORE or not (0 < bx < scores.shape[1] - 1 and 0 < by < scores.shape[0] - 1):
            return None
        # confidence, not presence: the peak must stand out of the next best one 3 px or more away (too
        # little texture, or a periodic one whose neighbouring period scores alike, is not trusted)
        others = scores.copy()
        others[max(by - 3, 0):by + 4, max(bx - 3, 0):bx + 4] = -1.0
        if others.size and float(others.max()) > best - _PEAK_MARGIN:
            return None
        fx = _parabola_peak(scores[by, bx - 1:bx + 2])
        fy = _parabola_peak(scores[by - 1:by + 2, bx])
        # the template sits at (bx + fx - sx, by + fy - sy) in the prior: move the frame by that much
        return float(bx + fx - sx), float(by + fy - sy), float(best)


def _grey_levels(band: np.ndarray) -> np.ndarray:
    """A band in 8-bit grey levels: one held in 16 bits scaled down (float32), others as they are."""
    return band if band.dtype != np.uint16 else cv2.multiply(band, 1.0 / 256, dtype=cv2.CV_32F)


def _grey_alpha(grey: np.ndarray, mapped: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Image rows (row 0 the top, largest y) of a value and its mapped cells: grey rounded to uint8
    (clipped to 0..255), alpha 255 where mapped."""
    image = np.add(grey, np.float32(0.5))
    np.clip(image, 0, 255, out=image)
    if image.size == 0:   # nothing mapped yet: cv2.flip of an empty array returns None
        return np.zeros(image.shape, np.uint8), np.zeros(image.shape, np.uint8)
    return cv2.flip(image.astype(np.uint8), 0), cv2.flip(mapped.view(np.uint8), 0) * np.uint8(255)


def _highpass(image: np.ndarray) -> np.ndarray:
    image = image.astype(np.float32)
    return cv2.subtract(image, cv2.GaussianBlur(image, (0, 0), 3.0))


def _parabola_peak(values: np.ndarray) -> float:
    a, b, c = (float(v) for v in values)
    den = a - 2 * b + c
    return float(np.clip(0.5 * (a - c) / den, -0.5, 0.5)) if den < 0 else 0.0
