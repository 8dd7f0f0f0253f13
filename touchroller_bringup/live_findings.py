"""Live findings (docs/inspection.md): the perception node inspects the newly mapped region of its world map
after a map update, at most once per `findings.period`, and publishes every finding so far as
`visualization_msgs/MarkerArray` on `findings`, in the map's frame (`base`).

`LiveFindings` keeps the findings with stable ids: each update inspects the region mapped since the last
one, grown by `reach_m` and over the earlier findings that reach into it (so a crack across its edge is
measured whole), with `margin_m` of context around
it for the local surface (`inspect_region`); a new finding of the same kind within `match_m` of an earlier
one takes its id (its markers are replaced), an earlier finding whose centre lay in the inspected region and
that nothing matched is gone (its markers deleted). Ground mapped again by a later pass is inspected
again only when the map is finished (`whole`). The map's height layer is inspected when it has one,
else its intensity (`scan_findings.height_layer`).

From a world map's tiles (`update_tiles`, what the perception node uses): the node hands over the store
tiles bands touched (`note`), and only those are read to find the newly mapped cells (each tile's
mapped cells at the last inspection kept as bits; all of them again once frames placed provisionally, while
the latency was being estimated, are placed for good); the region is read from the tiles as one window
(`touchroller_perception.map_windows.MapWindows`), never the whole map at full resolution. A finished map
(`whole`) is inspected whole when its extent has at most `WHOLE_CELLS` cells, else window by window
(`WINDOW_CELLS` square, each grown over the findings of the windows before that reach into it, so a crack
across a window's edge is measured whole): memory for a window, however large the map.

`markers(...)`: per finding, a LINE_STRIP along a crack's trunk (and one per branch) or a CYLINDER disc of
the dent's or bump's diameter at half depth, and a TEXT_VIEW_FACING label (id, kind, length, width, depth);
marker ids are `MARKERS_PER_FINDING` x finding id + k, namespace "findings": a finding updated later replaces
its markers, one gone is deleted (DELETE for each of its ids).
"""
from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, field, fields, replace
from typing import Any

import numpy as np
from scipy.spatial import cKDTree

from touchroller_bringup.scan_findings import height_layer
from touchroller_perception.inspection import Finding, InspectionConfig, inspect_region

WHOLE_CELLS = 3000 * 3000    # a finished map up to this many cells is inspected as one window
WINDOW_CELLS = 2048          # else in windows of this many cells square (plus the margin around each)
MARKERS_PER_FINDING = 8       # geometry (k = 0), label (1), branches (2..7)
NAMESPACE = "findings"
COLOURS = {"crack": (1.0, 0.1, 0.1), "dent": (1.0, 0.6, 0.0), "bump": (0.1, 0.8, 0.1)}   # RGB


@dataclass(frozen=True)
class LiveFindingsConfig:
    """When and where the live detector looks. Lengths in metres of the map's frame."""

    enabled: bool = True
    period_s: float = 0.5       # at most one inspection per this much time (the node's clock); 0: every map update
    reach_m: float = 5e-3       # the newly mapped region is grown by this before it is inspected
    margin_m: float = 7.5e-3    # context around it for the local surface (inspect_region's margin)
    match_m: float = 1e-3       # a finding this close to an earlier one of the same kind keeps its id
    text_size_m: float = 1.5e-3  # the labels' letter height
    blur_m: float = 0.0         # the map's point spread beyond its pixel, FWHM (InspectionConfig.blur_fwhm_m)

    def __post_init__(self) -> None:
        for f in fields(self):
            value = getattr(self, f.name)
            if f.name != "enabled" and not (isinstance(value, int | float) and math.isfinite(value) and value >= 0):
                raise ValueError(f"LiveFindingsConfig.{f.name} must be a finite number >= 0, got {value!r}")
        if self.text_size_m <= 0:
            raise ValueError("LiveFindingsConfig.text_size_m must be > 0")


# ROS parameter -> (LiveFindingsConfig field, description, min, max)
LIVE_FINDINGS_PARAMETERS: dict[str, tuple[str, str, float | None, float | None]] = {
    "findings.enabled": ("enabled", "Inspect the world map as it grows and publish `findings` (MarkerArray in "
                         "world_frame)", None, None),
    "findings.period": ("period_s", "Inspect the newly mapped region at most once per this many seconds (on a "
                        "timer of its own when shorter than the map's publication period; 0: at every map "
                        "publication)", 0.0, 3600.0),
    "findings.reach": ("reach_m", "Grow the newly mapped region by this before inspecting it, m (a defect across "
                       "its edge is measured whole)", 0.0, 0.1),
    "findings.margin": ("margin_m", "Context inspected around that region for the local surface, m", 0.0, 0.1),
    "findings.match_distance": ("match_m", "A finding this close to an earlier one of the same kind replaces it "
                                "(same marker ids), m", 0.0, 0.05),
    "findings.text_size": ("text_size_m", "Height of the findings' labels, m", 1e-4, 0.1),
    "findings.blur": ("blur_m", "The map's point spread beyond its pixel (the sensor's gel, optics, calibration "
                      "smoothing), FWHM, m: taken out of widths, put back in depths (docs/inspection.md)", 0.0, 0.01),
}


@dataclass(frozen=True)
class FindingsUpdate:
    findings: list[Finding]           # every current finding, stable ids
    removed: list[int]                # ids of findings gone since the last update
    region: tuple[float, float, float, float] | None   # what was inspected (None: nothing new)
    layer: str                        # "height" or "intensity"


@dataclass
class _Grid:
    mapped: np.ndarray
    origin: tuple[float, float]
    resolution: float


@dataclass
class LiveFindings:
    """The findings of a growing world map, updated region by region (see the module's docstring)."""

    config: LiveFindingsConfig = field(default_factory=LiveFindingsConfig)
    inspection: InspectionConfig = field(default_factory=InspectionConfig)
    findings: dict[int, Finding] = field(default_factory=dict)
    _seen: _Grid | None = None
    _next_id: int = 1
    _next_s: float = -math.inf    # when the next inspection is due (on the period's grid)
    inspections: int = 0
    _pending: set[tuple[int, int]] = field(default_factory=set)        # tiles touched since the last look
    _tiles_seen: dict[tuple[int, int], np.ndarray] = field(default_factory=dict)   # their mapped cells, bits
    _extent: tuple[int, int, int, int] | None = None                  # of the mapped cells seen (absolute)
    _replacements: int = 0            # the source's `replacements` at the last look

    def reset(self) -> list[int]:
        """Forget everything (a new map): the ids to delete."""
        gone = sorted(self.findings)
        self.findings.clear()
        self._seen = None
        self._next_s = -math.inf
        self._pending, self._tiles_seen, self._extent = set(), {}, None
        self._replacements = 0
        return gone

    def inspection_config(self) -> InspectionConfig:
        """The detector's configuration with the declared blur (`findings.blur`): what the scan's own
        inspection of the finished map uses too."""
        return replace(self.inspection, blur_fwhm_m=self.config.blur_m)

    def note(self, touched: set[tuple[int, int]]) -> None:
        """The store tiles bands changed (`WorldMapper.touched_tiles()`): looked at by the next `update_tiles`."""
        self._pending |= touched

    def update_tiles(self, source: Any, now_s: float, force: bool = False,
                     whole: bool = False) -> FindingsUpdate | None:
        """`update` from a world map's tiles (`source`: a `MapWindows`): the cells mapped since the last
        inspection found in the tiles `note`d since, the region read as one window; `whole`: every cell,
        window by window when the map is large (see the module docstring)."""
        if not self.config.enabled or not (force or self.due(now_s)):
            return None
        res, (ax, ay), t = source.resolution, source.anchor, source.tile
        replacements = int(getattr(source, "replacements", 0))
        if replacements != self._replacements:
            # frames placed provisionally (the latency not known yet) are placed for good: every cell of the
            # tiles touched counts as new, and their findings are measured again where the frames now lie
            self._replacements = replacements
            self._tiles_seen.clear()
        pending, self._pending = self._pending, set()
        new: tuple[int, int, int, int] | None = None
        for ix, iy in sorted(pending):
            mapped = source.mapped_tile(ix, iy)
            if mapped is None:
                continue
            seen = self._tiles_seen.get((ix, iy))
            fresh = mapped if seen is None else mapped & ~np.unpackbits(seen, count=mapped.size).reshape(
                mapped.shape).view(bool)
            self._tiles_seen[(ix, iy)] = np.packbits(mapped)
            self._extent = _union(self._extent, _cells(mapped, iy * t, ix * t))
            new = _union(new, _cells(fresh, iy * t, ix * t))
        if whole:
            return self.inspect_whole(source, now_s)[0]
        if new is None:
            return None
        self._schedule(now_s)
        r0, r1, c0, c1 = new
        reach = self.config.reach_m
        region = (ax + c0 * res - reach, ay + r0 * res - reach, ax + c1 * res + reach, ay + r1 * res + reach)
        update, _ = self._inspect_window(source, self._whole(region), self.config.margin_m,
                                         source.fixed or self._extent)
        return update

    def _inspect_window(self, source: Any, region: tuple[float, float, float, float], margin: float,
                        extent: tuple[int, int, int, int] | None) -> tuple[FindingsUpdate, Any]:
        """Inspect `region` (world) with `margin` around it, read as one window clipped to `extent`."""
        res, (ax, ay) = source.resolution, source.anchor
        box = (math.floor((region[1] - margin - ay) / res), math.ceil((region[3] + margin - ay) / res),
               math.floor((region[0] - margin - ax) / res), math.ceil((region[2] + margin - ax) / res))
        if extent is not None:
            box = (max(box[0], extent[0]), min(box[1], extent[1]), max(box[2], extent[2]), min(box[3], extent[3]))
        if box[1] <= box[0] or box[3] <= box[2]:   # nothing of the map there
            self.inspections += 1
            return FindingsUpdate(*self._merge([], region), region, source.layer), None
        values, origin = source.window(box)
        result = inspect_region(values, res, origin, region, margin, config=self.inspection_config(),
                                intensity=source.layer == "intensity")
        self.inspections += 1
        return FindingsUpdate(*self._merge(result.findings, region), region, source.layer), result

    def inspect_whole(self, source: Any, now_s: float,
                      margin: float | None = None) -> tuple[FindingsUpdate | None, list[Any]]:
        """Every mapped cell of `source` (a `MapWindows`) inspected: (the update, each window's
        `InspectionResult`). `margin`: around each window (default `config.margin_m`)."""
        extent = source.extent()
        if extent is None:
            return None, []
        self._schedule(now_s)
        res, (ax, ay) = source.resolution, source.anchor
        margin = self.config.margin_m if margin is None else margin
        r0, r1, c0, c1 = extent
        if (r1 - r0) * (c1 - c0) <= WHOLE_CELLS:
            cores = [extent]
        else:
            w = WINDOW_CELLS
            cores = [(a, min(a + w, r1), b, min(b + w, c1)) for a in range(r0, r1, w) for b in range(c0, c1, w)]
        reach = self.config.reach_m if len(cores) == 1 else 0.0
        removed: list[int] = []
        results = []
        update = None
        for a0, a1, b0, b1 in cores:
            region = (ax + b0 * res - reach, ay + a0 * res - reach, ax + b1 * res + reach, ay + a1 * res + reach)
            update, result = self._inspect_window(source, self._whole(region), margin, extent)
            removed += [i for i in update.removed if i not in removed]
            if result is not None:
                results.append(result)
        assert update is not None
        region = (ax + c0 * res, ay + r0 * res, ax + c1 * res, ay + r1 * res)
        kept = sorted(self.findings.values(), key=lambda f: f.id)
        return FindingsUpdate(kept, [i for i in removed if i not in self.findings], region, source.layer), results

    def _schedule(self, now_s: float) -> None:
        """An inspection ran at `now_s`: the next one a period after this one's due time (its grid: no
        drift), or a period after now when far behind."""
        period = self.config.period_s
        self._next_s = self._next_s + period if abs(now_s - self._next_s) < period else now_s + period

    def due(self, now_s: float) -> bool:
        # a tenth of a period early is on time: the map timer that calls this has the same period, and its
        # jitter must not skip a tick (which would double the latency)
        return self.config.enabled and now_s >= self._next_s - 0.1 * self.config.period_s

    def update(self, image: Any, now_s: float, force: bool = False, whole: bool = False) -> FindingsUpdate | None:
        """Inspect what `image` (a `WorldMapImage`) mapped since the last update; None when not due (the
        period; `force`: now) or nothing new was mapped. `whole`: the whole map (a finished map: ground
        mapped again by a later pass is inspected again too)."""
        if not self.config.enabled or not (force or self.due(now_s)):
            return None
        mapped = np.asarray(image.alpha) > 0
        resolution = float(image.resolution)
        origin = (float(image.origin[0]), float(image.origin[1]))
        new = mapped if whole else mapped & ~self._previous(mapped.shape, origin, resolution)
        if not new.any():
            return None
        self._schedule(now_s)
        self._seen = _Grid(mapped.copy(), origin, resolution)
        rows = mapped.shape[0]
        rr, cc = np.nonzero(new)
        reach = self.config.reach_m
        region = (origin[0] + cc.min() * resolution - reach, origin[1] + (rows - rr.max() - 1) * resolution - reach,
                  origin[0] + (cc.max() + 1) * resolution + reach, origin[1] + (rows - rr.min()) * resolution + reach)
        region = self._whole(region)
        height = height_layer(image)
        layer = "height" if height is not None else "intensity"
        source = height if height is not None else np.asarray(image.grey, np.float32)
        values = np.where(mapped, source, np.nan).astype(np.float32)
        result = inspect_region(values, resolution, origin, region, self.config.margin_m,
                                config=self.inspection_config(), intensity=height is None)
        self.inspections += 1
        return FindingsUpdate(*self._merge(result.findings, region), region, layer)

    def _whole(self, region: tuple[float, float, float, float]) -> tuple[float, float, float, float]:
        """`region` grown over the earlier findings that reach into it: each is measured again whole."""
        x0, y0, x1, y1 = region
        reach = self.config.reach_m
        for finding in self.findings.values():
            p = _points(finding)
            inside = (p[:, 0] >= region[0]) & (p[:, 0] <= region[2]) & (p[:, 1] >= region[1]) & (p[:, 1] <= region[3])
            if inside.any():
                x0, y0 = min(x0, float(p[:, 0].min()) - reach), min(y0, float(p[:, 1].min()) - reach)
                x1, y1 = max(x1, float(p[:, 0].max()) + reach), max(y1, float(p[:, 1].max()) + reach)
        return x0, y0, x1, y1

    def _previous(self, shape: tuple[int, ...], origin: tuple[float, float], resolution: float) -> np.ndarray:
        """The pixels mapped at the last update, on the current grid (the map grows: its origin moves)."""
        out = np.zeros(shape, bool)
        seen = self._seen
        if seen is None or not math.isclose(seen.resolution, resolution, rel_tol=1e-9):
            return out
        rows, cols = shape
        dc = round((seen.origin[0] - origin[0]) / resolution)
        top, seen_top = origin[1] + rows * resolution, seen.origin[1] + seen.mapped.shape[0] * resolution
        dr = round((top - seen_top) / resolution)
        r0, c0 = max(0, dr), max(0, dc)
        r1, c1 = min(rows, dr + seen.mapped.shape[0]), min(cols, dc + seen.mapped.shape[1])
        if r1 > r0 and c1 > c0:
            out[r0:r1, c0:c1] = seen.mapped[r0 - dr:r1 - dr, c0 - dc:c1 - dc]
        return out

    def _merge(self, found: Sequence[Finding],
               region: tuple[float, float, float, float]) -> tuple[list[Finding], list[int]]:
        x0, y0, x1, y1 = region
        replaced: set[int] = set()
        kept: list[Finding] = []
        for finding in found:
            match = self._match(finding, replaced)
            if match is None:
                match, self._next_id = self._next_id, self._next_id + 1
            replaced.add(match)
            kept.append(replace(finding, id=match))
        removed = [i for i, f in self.findings.items()
                   if i not in replaced and x0 <= f.x <= x1 and y0 <= f.y <= y1]
        for i in removed:
            del self.findings[i]
        for finding in kept:
            self.findings[finding.id] = finding
        return sorted(self.findings.values(), key=lambda f: f.id), removed

    def _match(self, finding: Finding, taken: set[int]) -> int | None:
        points = _points(finding)
        tree = cKDTree(points)
        best, best_distance = None, math.inf
        for i, old in self.findings.items():
            if i in taken or old.kind != finding.kind:
                continue
            distance = float(tree.query(_points(old))[0].min())
            if distance <= self.config.match_m and distance < best_distance:
                best, best_distance = i, distance
        return best


def _cells(mask: np.ndarray, r0: int, c0: int) -> tuple[int, int, int, int] | None:
    """(row0, row1, column0, column1) around the True cells of `mask` (its cell (0, 0) at (r0, c0))."""
    rows, cols = np.flatnonzero(mask.any(axis=1)), np.flatnonzero(mask.any(axis=0))
    if not len(rows):
        return None
    return r0 + int(rows[0]), r0 + int(rows[-1]) + 1, c0 + int(cols[0]), c0 + int(cols[-1]) + 1


_Box = tuple[int, int, int, int]


def _union(a: _Box | None, b: _Box | None) -> _Box | None:
    if a is None or b is None:
        return a if b is None else b
    return min(a[0], b[0]), max(a[1], b[1]), min(a[2], b[2]), max(a[3], b[3])


def _points(finding: Finding) -> np.ndarray:
    shapes = [np.asarray(line, np.float64) for line in finding.polylines if len(line)]
    if finding.polygon:
        shapes.append(np.asarray(finding.polygon, np.float64))
    shapes.append(np.array([[finding.x, finding.y]]))
    return np.vstack(shapes)


def label(finding: Finding) -> str:
    """`#3 crack 12.1 x 0.21 mm, 45 um deep` (bumps: high; no depth from an intensity map)."""
    if finding.kind == "crack":
        size = f"{finding.length_m * 1e3:.1f} x {finding.width_m * 1e3:.2f} mm"
    else:
        size = f"{finding.width_m * 1e3:.1f} mm"
    if math.isfinite(finding.depth_m):
        size += f", {abs(finding.depth_m) * 1e6:.0f} um {'high' if finding.depth_m < 0 else 'deep'}"
    return f"#{finding.id} {finding.kind} {size}"


def markers(update_findings: Sequence[Finding], removed: Sequence[int], frame_id: str, stamp: Any, z: float,
            config: LiveFindingsConfig) -> Any:
    """The MarkerArray of every current finding (ADD) and the DELETEs of those gone (`removed`): a late
    subscriber to the last message has them all."""
    from geometry_msgs.msg import Point
    from visualization_msgs.msg import Marker, MarkerArray

    out = MarkerArray()

    def marker(finding_id: int, k: int, kind: int) -> Any:
        m = Marker()
        m.header.frame_id = frame_id
        if stamp is not None:
            m.header.stamp = stamp
        m.ns = NAMESPACE
        m.id = MARKERS_PER_FINDING * finding_id + k
        m.type = kind
        m.action = Marker.ADD
        m.pose.orientation.w = 1.0
        return m

    for f in update_findings:
        r, g, b = COLOURS.get(f.kind, (1.0, 1.0, 1.0))
        if f.kind == "crack":
            lines = list(f.polylines)[: MARKERS_PER_FINDING - 1]
            for j, line in enumerate(lines):
                m = marker(f.id, 0 if j == 0 else j + 1, Marker.LINE_STRIP)
                m.scale.x = max(float(f.width_m), 1e-4) if math.isfinite(f.width_m) else 2e-4
                m.points = [Point(x=float(x), y=float(y), z=z) for x, y in line]
                m.color.r, m.color.g, m.color.b, m.color.a = r, g, b, 1.0
                out.markers.append(m)
            for j in range(len(lines) + 1, MARKERS_PER_FINDING):     # branches this finding no longer has
                if j >= 2:
                    gone = marker(f.id, j, Marker.LINE_STRIP)
                    gone.action = Marker.DELETE
                    out.markers.append(gone)
        else:
            m = marker(f.id, 0, Marker.CYLINDER)
            m.pose.position.x, m.pose.position.y, m.pose.position.z = float(f.x), float(f.y), z
            diameter = float(max(f.length_m, f.width_m)) if math.isfinite(f.length_m) else 1e-3
            m.scale.x = m.scale.y = diameter
            m.scale.z = 2e-4
            m.color.r, m.color.g, m.color.b, m.color.a = r, g, b, 0.8
            out.markers.append(m)
        text = marker(f.id, 1, Marker.TEXT_VIEW_FACING)
        text.pose.position.x, text.pose.position.y = float(f.x), float(f.y)
        text.pose.position.z = z + 2 * config.text_size_m
        text.scale.z = config.text_size_m
        text.text = label(f)
        text.color.r = text.color.g = text.color.b = text.color.a = 1.0
        out.markers.append(text)
    for finding_id in removed:
        for k in range(MARKERS_PER_FINDING):
            gone = marker(finding_id, k, Marker.LINE_STRIP)
            gone.action = Marker.DELETE
            out.markers.append(gone)
    return out
