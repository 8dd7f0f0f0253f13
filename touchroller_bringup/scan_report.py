"""`touchroller scan`'s `report.md` and the picture it shows.

- `map_preview.png` beside the report: the map downscaled to at most PREVIEW_MAX_SIDE pixels (grey; not
  mapped dark blue as in `findings.png`), with the requested area outlined in yellow and the findings of
  `findings.csv` (when the scan wrote one) marked and numbered; the report shows it, linked to `map.png`.
- Coverage: the fraction of the requested area (`sweep.area` in the world frame) the world map covers,
  and the passes planned and mapped (`touchroller_perception.map_coverage`).
- Findings: when `findings.csv` is in the output folder, a section with their count per kind and a table.
"""
from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from touchroller_bringup import names
from touchroller_perception.files import atomic_write
from touchroller_perception.map_coverage import AreaRectangle, mapped_fraction

if TYPE_CHECKING:
    from touchroller_bringup.graph import Graph
    from touchroller_bringup.scan import ScanResult

PREVIEW = "map_preview.png"
PREVIEW_MAX_SIDE = 800
FINDINGS = "findings.csv"
UNMAPPED_BGR = (60, 20, 20)      # as findings.png shows what was not mapped
AREA_BGR = (0, 220, 255)         # yellow
FINDING_BGR = {"crack": (0, 0, 255), "dent": (255, 160, 0), "bump": (0, 200, 0)}
MAX_FINDING_ROWS = 50


@dataclass(frozen=True)
class ScanCoverage:
    """What the scan was asked to cover and what its world map covers."""

    rectangle: AreaRectangle | None      # sweep.area (None: one roll of sweep.length, no rectangle)
    fraction: float | None               # of the rectangle's area mapped (0..1); None without both
    passes_planned: int | None
    passes_mapped: int | None
    frame: str = names.BASE_FRAME


def scan_coverage(rectangle: AreaRectangle | None, world: Any, passes_planned: int | None,
                  passes_mapped: int | None, frame: str) -> ScanCoverage:
    """The coverage of `world` (a WorldMapImage, or None) over the requested rectangle."""
    fraction = None
    if rectangle is not None and world is not None and world.grey.size:
        value = mapped_fraction(np.asarray(world.alpha) > 0, world.resolution, world.origin, rectangle)
        fraction = value if math.isfinite(value) else None
    return ScanCoverage(rectangle, fraction, passes_planned, passes_mapped, frame)


def read_findings(out_dir: Path) -> tuple[list[Any] | None, str]:
    """(the findings of out_dir/findings.csv, or None when there is no such file; why it could not be read)."""
    path = out_dir / FINDINGS
    if not path.is_file():
        return None, ""
    from touchroller_bringup.findings_files import read_findings_csv

    try:
        return read_findings_csv(path), ""
    except (OSError, ValueError, IndexError) as exc:
        return None, f"{FINDINGS} could not be read: {' '.join(str(exc).split())}"


# -- the picture ------------------------------------------------------------------------------------

def preview_image(grey: np.ndarray, mapped: np.ndarray | None = None, resolution: float | None = None,
                  origin: Sequence[float] | None = None, rectangle: AreaRectangle | None = None,
                  findings: Sequence[Any] = (), max_side: int = PREVIEW_MAX_SIDE) -> np.ndarray:
    """BGR picture of a map at most `max_side` px: `mapped` False dark blue; with the world grid
    (`resolution`, `origin`), the rectangle outlined and the findings marked. A BGR strip map is shown as is."""
    import cv2

    image = np.ascontiguousarray(np.asarray(grey)[..., :3] if np.ndim(grey) == 3 else grey, dtype=np.uint8)
    rows, cols = image.shape[:2]
    scale = min(1.0, max_side / max(rows, cols, 1))
    shown = None if mapped is None else np.asarray(mapped, bool)
    if scale < 1.0:   # downscaled first: a map of many megapixels is never coloured whole
        size = (max(1, round(cols * scale)), max(1, round(rows * scale)))
        image = cv2.resize(image, size, interpolation=cv2.INTER_AREA)
        if shown is not None:   # a picture pixel is shown as mapped when most of what it covers was
            shown = cv2.resize(shown.astype(np.float32), size, interpolation=cv2.INTER_AREA) >= 0.5
    if image.ndim == 2:
        image = cv2.cvtColor(image, cv2.COLOR_GRAY2BGR)
    if shown is not None:
        image[~shown] = UNMAPPED_BGR
    if resolution is None or origin is None:
        return image
    top = float(origin[1]) + rows * resolution

    def pixels(points: np.ndarray) -> np.ndarray:   # world (N, 2) -> picture pixels, 4 fractional bits
        p = np.asarray(points, np.float64).reshape(-1, 2)
        uv = np.stack([(p[:, 0] - float(origin[0])) / resolution, (top - p[:, 1]) / resolution], axis=1) * scale
        return np.round(uv * 16).astype(np.int32).reshape(-1, 1, 2)

    thickness = max(1, round(max(image.shape[:2]) / 400))
    if rectangle is not None:
        cv2.polylines(image, [pixels(rectangle.corners())], True, AREA_BGR, thickness, cv2.LINE_AA, shift=4)
    for finding in findings:
        colour = FINDING_BGR.get(finding.kind, (255, 255, 255))
        u, v = (pixels(np.array([[finding.x, finding.y]])).reshape(2) / 16).astype(int)
        cv2.circle(image, (int(u), int(v)), 5 * thickness, colour, thickness, cv2.LINE_AA)
        at, label = (int(u) + 6 * thickness, int(v) - 4 * thickness), str(finding.id)
        cv2.putText(image, label, at, cv2.FONT_HERSHEY_SIMPLEX, 0.4 * thickness, (0, 0, 0), 3 * thickness, cv2.LINE_AA)
        cv2.putText(image, label, at, cv2.FONT_HERSHEY_SIMPLEX, 0.4 * thickness, colour, thickness, cv2.LINE_AA)
    return image


def write_png(path: Path, image: np.ndarray) -> None:
    """Encoded in memory, written whole or not at all (a full disk is an OSError naming the file)."""
    import cv2

    encoded, data = cv2.imencode(".png", image)
    if not encoded:
        raise OSError(f"cannot encode {path.name} as PNG")
    with atomic_write(path, "wb") as stream:
        stream.write(data.tobytes())


# -- the report -------------------------------------------------------------------------------------

def _world_lines(world: Mapping[str, Any]) -> list[str]:
    latency = "not found" if world["latency_ms"] is None else f"{world['latency_ms']:.1f} ms"
    corrections = ", ".join(f"({dx:+.3f}, {dy:+.3f})" for dx, dy in world["pass_corrections_mm"]) or "none"
    residuals = ", ".join(f"({dx:+.3f}, {dy:+.3f})" for dx, dy in world.get("pass_residuals_mm", ())) or "none"
    return [f"- world map in `{world['frame']}`: `map.png` + `map.yaml`, {world['resolution_m'] * 1e3:g} mm per pixel, "
            f"origin ({world['origin'][0]:.4f}, {world['origin'][1]:.4f}) m; {world['frames_mapped']} frames "
            f"mapped in {world['passes']} pass(es)",
            f"- camera latency {world.get('latency') or latency}; "
            f"passes moved by registration off where TF and the final latency put them (x, y mm): {residuals} "
            f"(as placed, with the latency known then: {corrections})"]


def _picture_lines(result: ScanResult) -> list[str]:
    if "preview" not in result.files:
        return []
    shape = "x".join(str(n) for n in result.map_shape[:2]) if result.map_shape else "?"
    what = ["the requested area outlined in yellow"] if result.coverage and result.coverage.rectangle else []
    what += ["findings marked by number"] if result.findings else []
    return [f"[![the map]({PREVIEW})](map.png)", "",
            f"*`map.png` ({shape} px) at most {PREVIEW_MAX_SIDE} px wide; not mapped: dark blue"
            + "".join(f"; {w}" for w in what) + "*", ""]


def _coverage_lines(coverage: ScanCoverage | None) -> list[str]:
    if coverage is None:
        return []
    lines = ["## Coverage", ""]
    rect = coverage.rectangle
    planned = f"{coverage.passes_planned} pass(es) planned" if coverage.passes_planned is not None else ""
    if rect is None:
        lines.append("- requested: one roll (no `sweep.area`), so no rectangle to measure" + (f"; {planned}"
                                                                                              if planned else ""))
    else:
        lines.append(f"- requested area: {rect.length * 100:.1f} x {rect.width * 100:.1f} cm at ({rect.corner[0]:.4f}, "
                     f"{rect.corner[1]:.4f}) m in `{coverage.frame}`, rolled along ({rect.heading[0]:.3f}, "
                     f"{rect.heading[1]:.3f})" + (f"; {planned}" if planned else ""))
        if coverage.fraction is None:
            lines.append("- mapped: no world map, so not measured")
        else:
            lines.append(f"- mapped: **{coverage.fraction * 100:.1f} %** of it "
                         f"({coverage.fraction * rect.area * 1e4:.1f} of {rect.area * 1e4:.1f} cm²)")
    if coverage.passes_mapped is not None:
        lines.append(f"- passes mapped: {coverage.passes_mapped}"
                     + (f" of {coverage.passes_planned}" if coverage.passes_planned is not None else ""))
    return [*lines, ""]


def _findings_lines(findings: Sequence[Any] | None, problem: str) -> list[str]:
    if findings is None:
        return ["## Findings", "", f"- {problem}", ""] if problem else []
    counts: dict[str, int] = {}
    for f in findings:
        counts[f.kind] = counts.get(f.kind, 0) + 1
    kinds = ", ".join(f"{kind} {n}" for kind, n in sorted(counts.items())) or "none"
    lines = ["## Findings", "", f"{len(findings)} finding(s) ({kinds}) in `{FINDINGS}`; drawn whole in "
             "`findings.png`; metres in the map's frame, depth positive for a depression.", ""]
    if findings:
        lines += ["| id | kind | x m | y m | length mm | width mm | depth mm | confidence |",
                  "|---|---|---|---|---|---|---|---|"]
        for f in findings[:MAX_FINDING_ROWS]:
            lines.append(f"| {f.id} | {f.kind} | {f.x:.4f} | {f.y:.4f} | {_mm(f.length_m)} | {_mm(f.width_m)} | "
                         f"{_mm(f.depth_m, 3)} | {f.confidence:.2f} |")
        if len(findings) > MAX_FINDING_ROWS:
            lines.append(f"\n{len(findings) - MAX_FINDING_ROWS} more in `{FINDINGS}`.")
        lines.append("")
    return lines


def _mm(value: float, digits: int = 2) -> str:
    return f"{value * 1e3:.{digits}f}" if math.isfinite(value) else "-"


def report_markdown(result: ScanResult, graph: Graph) -> str:
    """report.md: the picture, the run's figures, the coverage, the findings and the graph."""
    skipped = result.frames_published - result.frames_processed
    if skipped >= 0:
        not_processed = f"{skipped} not processed"
    else:   # perception took frames the camera did not publish: another publisher on image_raw
        not_processed = (f"{-skipped} more than the camera published: another publisher on "
                         f"{names.topic(names.IMAGE, graph.namespace)}")
    during = result.frames_during_sweep
    rate = during / result.duration_s if during is not None and result.duration_s > 0 else float("nan")
    sweep_frames = f"; {during} during the sweep, {rate:.1f} Hz" if during is not None else ""
    lines = [
        "# TouchRoller scan report",
        "",
        *_picture_lines(result),
        f"- outcome: **{result.outcome}** ({result.message})",
        f"- {result.sweep or 'sweep'}; {'simulated' if graph.arguments['use_sim'] == 'true' else 'UR5'} arm",
        f"- sweep duration: {result.duration_s:.2f} s (from ~/start to the end of the sweep)",
        f"- frames published by the camera: {result.frames_published} (from its start to the end of the scan"
        f"{sweep_frames})",
        f"- frames processed by perception: {result.frames_processed} over the same time ({not_processed}; with a "
        f"camera its keep-last depth-1 queue skips stale frames when it is busy, simulated the clock waits "
        f"for it); publication-sequence gaps it "
        f"counted as dropped: {result.frames_dropped}; malformed: {result.frames_malformed}",
        f"- contacts: {result.contacts}",
        f"- map: {'x'.join(str(n) for n in result.map_shape) + ' px' if result.map_shape else 'none published'}",
        *(_world_lines(result.world_map) if result.world_map else []),
        *([f"- recording: `recording/` ({', '.join(f'{t} {n}' for t, n in result.recorded.items())})"]
          if result.recorded else []),
        *([f"- **{result.recording_warning}**"] if result.recording_warning else []),
        *([f"- not written: {', '.join(f'{name} ({why})' for name, why in result.failed.items())}"]
          if result.failed else []),
        "",
        *_coverage_lines(result.coverage),
        *_findings_lines(result.findings, result.findings_problem),
        "## Graph",
        "",
        "| node | parameters from the graph |",
        "|---|---|",
        *(f"| {spec.name} | {', '.join(f'{k}={v}' for k, v in spec.parameters.items()) or '-'} |"
          for spec in graph.nodes),
        "",
        f"Launch arguments: {', '.join(f'{k}:={v}' for k, v in graph.arguments.items() if v)}",
        "",
        "Params files, in order: " + ", ".join(f"`{f}`" for f in graph.nodes[0].params_files),
        "",
    ]
    return "\n".join(lines)
