"""The inspection bench's scans (`bench.inspection`): `touchroller scan` of the simulator's inspection_panel
scene with the sensor, arm, world map and detector in the loop, scored against the truth_findings.csv the
scan writes; the sensor's line spread read off its height map; how soon live findings follow the frames;
and the time to inspect a square metre. Helpers of `bench.inspection`, not a bench of their own.

* `run_scan(arguments, height, overrides)`: one scan in a ROS domain of its own, with a `Watch` (a node in
  its own rclpy context) recording, as they arrive, the tool poses (`tcp_pose`) and the `findings`
  MarkerArrays.
* `line_spread(height_tif, truth)`: across each true crack, the height map's profile (a line fitted to its
  flanks 1.5-2.5 mm out taken off): its full width at half depth W (the half-depth crossings interpolated
  between the profile's samples) and cross-section area; the blur is sqrt(W² - w² - p²) for the crack's true
  width w and the map's pixel footprint p (`InspectionConfig.footprint_fwhm_px`): the spread beyond the pixel,
  which is what the detector's declared blur means; the area over the true one is how much of a crack's
  cross-section the height map reads. What a user does with a reference sample of known scratches.
* `live_latency(watch, truth, map extent)`: per planted defect, from the arrival of the tool pose of the
  last frame whose mapped band still reached it to the arrival of the first `findings` message with a marker
  of its kind on it (a crack's line along it, a dent's or bump's disc at it; wall clock; and simulated time,
  from the markers' stamps).
* `square_metre(...)`: the arm's plan over 1 m x 1 m with the sweep defaults (config/scan.yaml, the
  planner's pass width and overlap), plus mapping CPU per frame (`touchroller map` of the scan's recording)
  and inspection CPU per megapixel, against the paper's press-lift-shift GelSight figure.
"""
from __future__ import annotations

import math
import tempfile
import threading
import time
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import yaml
from scipy.ndimage import map_coordinates
from scipy.spatial import cKDTree

from bench._scan_graph import own_domain
from touchroller_perception.inspection import Finding

ROOT = Path(__file__).resolve().parent.parent
# the paper's press-lift-shift GelSight scan (touchroller_paper.tex): 49 presses, 196 s, 8 x 11 cm
PAPER_PRESSES, PAPER_S, PAPER_AREA_M2 = 49, 196.0, 0.08 * 0.11


@dataclass
class Watch:
    """Arrivals (time.monotonic) of `tcp_pose` (stamp ns, x, y, z) and `findings` (arrival, the markers'
    stamp ns, each ADDed geometry marker's (kind, points): the kind from its finding's label) in `namespace`,
    from a node in an rclpy context of its own."""

    namespace: str = "touchroller"
    poses: list[tuple[float, int, float, float, float]] = field(default_factory=list)
    findings: list[tuple[float, int, list[tuple[str, np.ndarray]]]] = field(default_factory=list)
    _stop: threading.Event = field(default_factory=threading.Event)
    _thread: threading.Thread | None = None

    def start(self) -> None:
        ready = threading.Event()
        self._thread = threading.Thread(target=self._spin, args=(ready,), daemon=True)
        self._thread.start()
        ready.wait(10.0)

    def stop(self) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join(10.0)

    def _spin(self, ready: threading.Event) -> None:
        import rclpy
        from geometry_msgs.msg import PoseStamped
        from rclpy.context import Context
        from rclpy.executors import SingleThreadedExecutor
        from rclpy.qos import QoSProfile, ReliabilityPolicy
        from visualization_msgs.msg import Marker, MarkerArray

        context = Context()
        rclpy.init(context=context)
        node = rclpy.create_node("inspection_bench_watch", context=context)
        executor = SingleThreadedExecutor(context=context)
        executor.add_node(node)

        def on_pose(msg: Any) -> None:
            p = msg.pose.position
            self.poses.append((time.monotonic(), msg.header.stamp.sec * 10**9 + msg.header.stamp.nanosec,
                               p.x, p.y, p.z))

        def on_findings(msg: Any) -> None:
            now = time.monotonic()
            shapes, stamp = [], 0
            # "#3 crack 12.1 x 0.21 mm, ..." (live_findings.label): the kind of finding id // 8's markers
            kinds = {m.id // 8: m.text.split()[1] for m in msg.markers
                     if m.action == Marker.ADD and m.id % 8 == 1 and len(m.text.split()) > 1}
            for m in msg.markers:
                stamp = max(stamp, m.header.stamp.sec * 10**9 + m.header.stamp.nanosec)
                if m.action != Marker.ADD or m.id % 8 == 1:       # DELETEs and the labels
                    continue
                kind = kinds.get(m.id // 8, "")
                if m.type == Marker.LINE_STRIP:
                    shapes.append((kind, np.array([[q.x, q.y] for q in m.points], np.float64).reshape(-1, 2)))
                else:
                    shapes.append((kind, np.array([[m.pose.position.x, m.pose.position.y]])))
            self.findings.append((now, stamp, shapes))

        node.create_subscription(PoseStamped, f"/{self.namespace}/tcp_pose", on_pose, 100)
        node.create_subscription(MarkerArray, f"/{self.namespace}/findings", on_findings,
                                 QoSProfile(depth=50, reliability=ReliabilityPolicy.RELIABLE))
        ready.set()
        try:
            while not self._stop.is_set():
                executor.spin_once(timeout_sec=0.02)
        finally:
            executor.shutdown()
            node.destroy_node()
            rclpy.shutdown(context=context)


@dataclass(frozen=True)
class Scanned:
    out: Path
    result: Any          # touchroller_bringup.scan.ScanResult
    seconds: float
    watch: Watch
    command: str


def command_line(arguments: Mapping[str, str], height: bool, overrides: Mapping[str, Any]) -> str:
    parts = [f"{k}:={v}" for k, v in {**arguments, **overrides}.items()]
    return "touchroller scan " + " ".join(parts) + (" --height" if height else "")


def run_scan(arguments: Mapping[str, str], height: bool = False, overrides: Mapping[str, Any] | None = None,
             record: bool = False) -> Scanned:
    """One simulated scan in a domain of its own (another graph would stop it), watched."""
    from touchroller_bringup.scan import ScanOptions
    from touchroller_bringup.scan import run_scan as scan

    overrides = dict(overrides or {})
    out = Path(tempfile.mkdtemp(prefix="inspection_scan_"))
    watch = Watch()
    with own_domain():
        watch.start()
        started = time.monotonic()
        try:
            result = scan(ScanOptions(out_dir=out, arguments=dict(arguments), overrides=overrides, progress=None,
                                      height=height, record=record, compress=False))
        finally:
            seconds = time.monotonic() - started
            time.sleep(0.5)       # the last findings message on its way
            watch.stop()
    if not result.ok:
        raise RuntimeError(f"the scan {command_line(arguments, height, overrides)} ended {result.outcome}: "
                           f"{result.message}")
    return Scanned(out, result, seconds, watch, command_line(arguments, height, overrides))


def densify(lines: Sequence[Sequence[tuple[float, float]]], step: float = 2e-5) -> np.ndarray:
    """Points every `step` along polylines (a single point stays one)."""
    out = []
    for line in lines:
        p = np.asarray(line, np.float64).reshape(-1, 2)
        if len(p) == 1:
            out.append(p)
            continue
        for a, b in zip(p[:-1], p[1:], strict=True):
            n = max(1, int(math.ceil(np.hypot(*(b - a)) / step)))
            out.append(a + (b - a) * np.linspace(0, 1, n, endpoint=False)[:, None])
        out.append(p[-1:])
    return np.vstack(out) if out else np.zeros((0, 2))


def geometry(f: Finding) -> np.ndarray:
    """A finding's points: its centrelines, else its centre."""
    return densify(f.polylines) if f.polylines else np.array([[f.x, f.y]])


# -- the sensor's line spread off the height map ---------------------------------------------------

@dataclass(frozen=True)
class LineSpread:
    width_mm: float           # the crack's true width (FWHM)
    depth_um: float
    map_fwhm_mm: float        # the height map's FWHM across it (median along its middle 60 %)
    blur_fwhm_mm: float       # sqrt(map² - true² - pixel²): the spread beyond the map's pixel, as the detector's
                              # blur_fwhm_m means it (it adds its pixel footprint back in quadrature)
    area_ratio: float         # the map's cross-section area / the true one (a Gaussian's: 1.0645 w d)


def half_depth_width(offsets: np.ndarray, depth: np.ndarray) -> float:
    """The profile's full width at half its deepest sample (`offsets` evenly spaced), each side's crossing
    interpolated as the detector's `across` does (`centreline.half_width`), not the outermost samples past half
    depth: those read the width short by up to a sample spacing on each side, in steps of it; NaN where a side
    never rises above half depth."""
    from touchroller_perception.inspection.centreline import half_width

    k = int(np.argmax(depth))
    samples = half_width(np.asarray(depth, np.float64)[None, :], np.array([k]), np.array([float(depth[k])]))[0]
    return float(samples * (offsets[1] - offsets[0]))


def line_spread(height_tif: Path, truth: Sequence[Finding], footprint_px: float | None = None) -> list[LineSpread]:
    from touchroller_bringup.findings_files import read_height_tif
    from touchroller_perception.inspection import InspectionConfig

    h, res, origin = read_height_tif(height_tif)
    # the detector's own pixel footprint, which it adds to the declared blur in quadrature
    pixel = (InspectionConfig().footprint_fwhm_px if footprint_px is None else footprint_px) * res
    rows = h.shape[0]
    out = []
    offsets = np.arange(-2.5e-3, 2.5e-3 + 1e-9, 2e-5)
    flank, core = np.abs(offsets) > 1.5e-3, np.abs(offsets) < 1.2e-3
    for t in truth:
        if t.kind != "crack":
            continue
        line = np.asarray(t.polylines[0], np.float64)
        seg = np.diff(line, axis=0)
        lengths = np.hypot(*seg.T)
        s = np.concatenate([[0.0], np.cumsum(lengths)])
        widths, areas = [], []
        for q in np.linspace(0.2, 0.8, 31) * s[-1]:
            k = min(int(np.searchsorted(s, q, side="right")) - 1, len(seg) - 1)
            if lengths[k] <= 0:
                continue
            tangent = seg[k] / lengths[k]
            p = line[k] + seg[k] * (q - s[k]) / lengths[k]
            pts = p + offsets[:, None] * np.array([-tangent[1], tangent[0]])
            col, row = (pts[:, 0] - origin[0]) / res - 0.5, rows - (pts[:, 1] - origin[1]) / res - 0.5
            prof = map_coordinates(h.astype(np.float64), [row, col], order=1, cval=np.nan)
            if not np.isfinite(prof).all():
                continue
            a, b = np.polyfit(offsets[flank], prof[flank], 1)
            depth = -(prof - (a * offsets + b))
            width = half_depth_width(offsets, depth)
            if not math.isfinite(width):
                continue
            widths.append(width)
            areas.append(float(np.trapezoid(np.clip(depth[core], 0, None), offsets[core])))
        if not widths:
            continue
        w_map = float(np.median(widths))
        out.append(LineSpread(t.width_m * 1e3, t.depth_m * 1e6, w_map * 1e3,
                              math.sqrt(max(w_map**2 - t.width_m**2 - pixel**2, 0.0)) * 1e3,
                              float(np.median(areas)) / (1.0645 * t.width_m * t.depth_m)))
    return out


# -- live findings: latency from the frames ---------------------------------------------------------

@dataclass(frozen=True)
class Latency:
    kind: str
    wall_s: float             # first findings message with it, from the last frame reaching it (NaN: never)
    sim_s: float              # the same in simulated time (the message's stamp)
    final: bool               # first shown by the finished map's inspection (after the roll)


def live_latency(watch: Watch, truth: Sequence[Finding], extent: tuple[float, float, float, float]) -> list[Latency]:
    """Per planted defect (`truth`): see the module's docstring. `extent`: the map's (x0, y0, x1, y1). The
    mapped band's offset and half length along the roll come from the map's extent and the tool's range
    while pressed (the roll is along x)."""
    poses = np.array([(a, s, x, y, z) for a, s, x, y, z in watch.poses], np.float64)
    if poses.size == 0 or not watch.findings:
        return [Latency(t.kind, math.nan, math.nan, False) for t in truth]
    pressed = poses[:, 4] <= poses[:, 4].min() + 2e-5
    rolled = poses[pressed]
    a, b = float(rolled[:, 2].min()), float(rolled[:, 2].max())
    offset = (extent[0] + extent[2] - a - b) / 2
    half = (extent[2] - extent[0] - (b - a)) / 2
    last_pressed = rolled[-1]
    out = []
    for t in truth:
        points = geometry(t) if t.kind == "crack" else np.asarray(t.polygon or [(t.x, t.y)], np.float64)
        x0, x1 = float(points[:, 0].min()), float(points[:, 0].max())
        reaching = rolled[(rolled[:, 2] + offset - half <= x1) & (rolled[:, 2] + offset + half >= x0)]
        last = reaching[-1] if len(reaching) else last_pressed
        tree = cKDTree(geometry(t))
        tolerance = max(1e-3, t.width_m)
        shown = None
        for arrival, stamp, shapes in watch.findings:
            if any(float(np.median(tree.query(s)[0])) <= tolerance for kind, s in shapes if kind == t.kind and len(s)):
                shown = (arrival, stamp)
                break
        if shown is None:
            out.append(Latency(t.kind, math.nan, math.nan, False))
            continue
        out.append(Latency(t.kind, float(shown[0] - last[0]), float((shown[1] - last[1]) * 1e-9),
                           bool(shown[0] > last_pressed[0])))
    return out


# -- a square metre ----------------------------------------------------------------------------------

@dataclass(frozen=True)
class SquareMetre:
    speed_m_s: float                 # sweep.speed (config/scan.yaml)
    measured_speed_m_s: float        # the tool's speed over the middle of the scan's roll (its poses)
    pass_width_m: float              # the planner's usable width and overlap: pass spacing
    pass_spacing_m: float
    passes: int
    arm_s: float                     # plan_duration of the 1 m x 1 m raster (every move)
    rolling_s: float                 # of which rolling
    fps: float
    frames: int                      # frames filmed while rolling over the square metre
    map_cpu_ms_per_frame: float      # `touchroller map` (world map with height) of the scan's recording
    map_frames: int
    map_cpu_s: float                 # frames x the above
    megapixels: float                # 1 m² at the map's resolution
    inspect_cpu_s: float             # megapixels / the detector's megapixels per second
    total_s: float                   # arm + mapping beyond the rolling (one core) + the inspection at the end
    paper_s: float                   # the paper's 196 s for 8 x 11 cm, scaled to 1 m² (presses x 4 s)
    paper_presses: float


def _params(path: Path) -> dict[str, Any]:
    data = yaml.safe_load(path.read_text(encoding="utf-8"))
    return dict(data["/**"]["ros__parameters"])


def measured_speed(watch: Watch) -> float:
    """The tool's speed along the roll over the middle half of its pressed poses."""
    poses = np.array([(s, x, z) for _, s, x, _, z in watch.poses], np.float64)
    pressed = poses[poses[:, 2] <= poses[:, 2].min() + 2e-5]
    n = len(pressed)
    middle = pressed[n // 4: 3 * n // 4]
    if len(middle) < 2:
        return math.nan
    return abs(float(middle[-1, 1] - middle[0, 1])) / ((middle[-1, 0] - middle[0, 0]) * 1e-9)


def map_cpu(scanned: Scanned) -> tuple[float, int]:
    """(CPU ms per mapped frame, mapped frames) of `touchroller map` (a world map with its height layer, in
    this process, its imports done by a first run) over the scan's recording, with the photometric model the
    scan made: all of its CPU time (reading the bag included) charged to the frames it mapped."""
    import contextlib
    import io
    import re

    from touchroller_bringup.cli import main

    out = scanned.out
    argv = ["map", str(out / "recording"), "--out", str(out / "remap" / "map.png"), "--photometric",
            str(out / "photometric.npz"), "--reference", str(out / "reference.png")]
    printed = io.StringIO()
    with contextlib.redirect_stdout(printed), contextlib.redirect_stderr(io.StringIO()):
        main(argv)                      # the imports and caches
        started = time.process_time()
        code = main(argv)
        cpu = time.process_time() - started
    mapped = re.search(r"(\d+) frames mapped", printed.getvalue())
    if code != 0 or mapped is None:
        raise RuntimeError(f"touchroller map of {out / 'recording'} failed: {printed.getvalue()[-400:]}")
    frames = int(mapped.group(1))
    return 1e3 * cpu / max(frames, 1), frames


def square_metre(watch: Watch, map_ms_per_frame: float, map_frames: int, megapixels_per_s: float,
                 resolution: float = 1e-4) -> SquareMetre:
    from touchroller_driver.arm import SweepPlan, mount_transform, plan_duration, plan_raster, raster_pass_count

    geometry_params, scan = _params(ROOT / "config" / "touchroller.yaml"), _params(ROOT / "config" / "scan.yaml")
    mount = mount_transform(geometry_params["mount.xyz"], geometry_params["mount.rpy"])
    start = scan["sweep.start_pose"]
    speed = float(scan["sweep.speed"])
    plan = plan_raster(start, area=[0.0, 0.0, 1.0, 1.0], mount=mount, speed=speed, accel=float(scan["sweep.accel"]),
                       depth=float(scan["sweep.depth"]), direction=scan["sweep.direction"],
                       approach_speed=float(scan["sweep.approach_speed"]), clearance=float(scan["sweep.clearance"]),
                       profile=str(scan["sweep.profile"]))
    width, overlap = 0.06, 0.25     # plan_raster's defaults, the sweep node's sweep.usable_width and overlap
    passes = raster_pass_count(1.0, width, overlap)
    assert passes == len(plan.passes)
    arm_s = plan_duration(plan)
    rolling_s = sum(plan_duration(SweepPlan((plan.segments[k],), (0,), (1.0,)), from_pose=plan.segments[k - 1].target)
                    for k in plan.rolls)
    fps = float(scan["fps"])
    frames = round(rolling_s * fps)
    map_cpu_s = frames * map_ms_per_frame * 1e-3
    megapixels = 1.0 / resolution**2 / 1e6
    inspect_s = megapixels / megapixels_per_s
    total = arm_s + max(0.0, map_cpu_s - rolling_s) + inspect_s
    presses = PAPER_PRESSES / PAPER_AREA_M2
    return SquareMetre(speed, float(measured_speed(watch)), width, width * (1 - overlap), passes, arm_s, rolling_s, fps,
                       frames, map_ms_per_frame, map_frames, map_cpu_s, megapixels, inspect_s, total,
                       PAPER_S / PAPER_AREA_M2, presses)
