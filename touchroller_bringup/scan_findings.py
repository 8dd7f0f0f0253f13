"""The findings of a scan (docs/inspection.md): `touchroller scan ... inspect:=true` inspects the world map it
made and writes `DIR/findings.csv` and `DIR/findings.png` with it; a simulated scan whose scene plants
defects (`surface.defects`) also writes their truth, `DIR/truth_findings.csv`, in the same format and frame.

Which layer: the world map's height (metres, `height_layer`) when the map has one, else its intensity
(grey levels: shapes and places, no depth). `inspect_world` reads the map from its tiles
(`touchroller_perception.map_windows`): whole up to `live_findings.WHOLE_CELLS` cells, else window by
window, so memory stays that of a window however large the map (a square metre at 0.1 mm is 10^8 cells).
"""
from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from touchroller_perception.inspection import Finding, InspectionConfig, InspectionResult, inspect, inspect_intensity

INSPECT_CHOICES = ("auto", "true", "false")


@dataclass(frozen=True)
class ScanFindings:
    findings: list[Finding]
    layer: str                      # "height" or "intensity": what was inspected
    result: InspectionResult

    def summary(self) -> str:
        counts = {kind: sum(f.kind == kind for f in self.findings) for kind in ("crack", "dent", "bump")}
        return (f"{len(self.findings)} finding(s) ({', '.join(f'{n} {k}' for k, n in counts.items())}) "
                f"in the {self.layer} map: `findings.csv` + `findings.png`")


def enabled(arguments: Mapping[str, str]) -> bool:
    """`inspect:=true`, or `auto` (the default) for a raster (`area:=...`)."""
    value = arguments.get("inspect", "auto")
    return value == "true" or (value == "auto" and bool(arguments.get("area")))


@dataclass(frozen=True)
class MapWithHeight:
    """A world map image (grey + alpha, row 0 the largest y, origin its lower-left corner) with its height
    layer on the same grid (float metres, row 0 the largest y, NaN where unmapped)."""

    grey: np.ndarray
    alpha: np.ndarray
    resolution: float
    origin: tuple[float, float]
    height: np.ndarray


def with_height(image: Any, world: Any) -> Any:
    """`image` (the world mapper's `map_image()`) with the mapper's height layer when it has one
    (`height_layer()`, cropped as map_image is; its rows grow with y); else `image` itself."""
    layer = world.height_layer() if hasattr(world, "height_layer") else None
    if layer is None or layer.height.shape != np.asarray(image.grey).shape:
        return image
    return MapWithHeight(image.grey, image.alpha, image.resolution, tuple(image.origin), layer.height[::-1])


def height_layer(image: Any) -> np.ndarray | None:
    """The height layer of a map image from `with_height` (float metres on the grey's grid), else None."""
    height = getattr(image, "height", None)
    if height is None:
        return None
    height = np.asarray(height)
    if height.shape != np.asarray(image.grey).shape or not np.issubdtype(height.dtype, np.floating):
        return None
    return height


def inspect_map(image: Any, config: InspectionConfig | None = None) -> ScanFindings:
    """Inspect a `WorldMapImage` (grey + alpha, row 0 the largest y, origin the lower-left corner): its
    height layer if it has one, else its intensity."""
    config = config or InspectionConfig()
    mapped = np.asarray(image.alpha) > 0
    height = height_layer(image)
    if height is not None:
        values = np.where(mapped, height, np.nan).astype(np.float32)
        result = inspect(values, image.resolution, image.origin, config=config)
        return ScanFindings(result.findings, "height", result)
    grey = np.where(mapped, np.asarray(image.grey, np.float32), np.nan).astype(np.float32)
    result = inspect_intensity(grey, image.resolution, image.origin, config=config)
    return ScanFindings(result.findings, "intensity", result)


def inspect_world(world: Any, blur_m: float = 0.0) -> ScanFindings:
    """Inspect a `WorldMapper`'s finished map from its tiles: as `inspect_map(with_height(world.map_image(),
    world))` for a map of up to `live_findings.WHOLE_CELLS` cells (the same findings), window by window
    beyond (`LiveFindings.inspect_whole`: each window with three background scales of context, a finding
    across a window's edge measured whole by the next). The result's diagnostics: the one window's, or
    the windows' counts summed and their thresholds' largest. `blur_m`: the map's declared blur
    (`findings.blur`), as the live findings have it."""
    from touchroller_bringup.live_findings import LiveFindings, LiveFindingsConfig
    from touchroller_perception.inspection import InspectionConfig
    from touchroller_perception.map_windows import MapWindows

    source = MapWindows(world)
    margin = 3 * InspectionConfig().background_scale_m
    live = LiveFindings(LiveFindingsConfig(period_s=0.0, reach_m=0.0, margin_m=margin, blur_m=blur_m))
    update, results = live.inspect_whole(source, 0.0)
    if update is None or not results:
        empty = inspect(np.full((0, 0), np.nan, np.float32), world.config.resolution, (0.0, 0.0))
        return ScanFindings([], source.layer, empty)
    return ScanFindings(update.findings, source.layer, InspectionResult(update.findings, _merged(results)))


def _merged(results: list[InspectionResult]) -> Any:
    if len(results) == 1:
        return results[0].diagnostics
    from dataclasses import fields, replace

    first = results[0].diagnostics
    values = {}
    for f in fields(first):
        items = [getattr(r.diagnostics, f.name) for r in results]
        values[f.name] = sum(items) if isinstance(items[0], int) else max(items)
    return replace(first, **values)


def write_findings(out_dir: Path, image: Any, found: ScanFindings) -> dict[str, Path]:
    """`findings.csv` and `findings.png` (the map with the findings drawn and numbered; `image` any
    `WorldMapImage` of it, e.g. a pyramid level's `WorldMapper.level_image`)."""
    from touchroller_bringup.findings_files import write_findings_csv, write_findings_png

    write_findings_csv(out_dir / "findings.csv", found.findings)
    write_findings_png(out_dir / "findings.png", np.asarray(image.grey), np.asarray(image.alpha) > 0,
                       image.resolution, image.origin, found.findings)
    return {"findings": out_dir / "findings.csv", "findings_png": out_dir / "findings.png"}


def truth_findings(scene_name: str) -> list[Finding]:
    """The defects a simulator scene plants, as findings in the world frame (the map's `base`): empty when
    it plants none."""
    from touchroller_driver.sim.camera import surface_frame
    from touchroller_driver.sim.defects import surface_defects
    from touchroller_driver.sim.scene import load_scene

    scene = load_scene(scene_name)
    plan = surface_defects(scene.surface)
    return plan.truth(surface_frame(scene)) if plan else []


def plants_defects(scene_name: str) -> bool:
    """The simulator scene asks for `surface.defects` (False for no scene or one that does not load)."""
    from touchroller_driver.sim.scene import load_scene

    if not scene_name:
        return False
    try:
        return bool((load_scene(scene_name).surface or {}).get("defects"))
    except (OSError, ValueError):
        return False


def write_truth(out_dir: Path, scene_name: str) -> Path:
    """`truth_findings.csv`: the scene's planted defects in the world frame (no rows when it plants none)."""
    from touchroller_bringup.findings_files import write_findings_csv

    write_findings_csv(out_dir / "truth_findings.csv", truth_findings(scene_name))
    return out_dir / "truth_findings.csv"
