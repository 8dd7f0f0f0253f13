"""Inspection files (docs/inspection.md, DESIGN "Map files"): `findings.csv` (header `id,kind,x,y,length_m,
width_m,depth_m,confidence,geometry`, metres in the map's frame, geometry as WKT), `findings.png` (the map
with the findings drawn and numbered), and the reader of a world map's `height.tif` (float32 metres,
GeoTIFF ModelPixelScale and ModelTiepoint, pixels as areas). Written whole or not at all.
"""
from __future__ import annotations

import csv
import math
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from touchroller_bringup.errors import UserError
from touchroller_perception.files import atomic_path, atomic_write
from touchroller_perception.inspection import Finding, parse_wkt

HEADER = ("id", "kind", "x", "y", "length_m", "width_m", "depth_m", "confidence", "geometry")
MODEL_PIXEL_SCALE, MODEL_TIEPOINT = 33550, 33922
PNG_MAX_SIDE = 4096
COLOURS = {"crack": (0, 0, 255), "dent": (255, 160, 0), "bump": (0, 200, 0)}   # BGR


def _number(value: float, digits: int = 6) -> str:
    return "nan" if not math.isfinite(value) else f"{value:.{digits}g}"


def write_findings_csv(path: str | Path, findings: Sequence[Finding]) -> None:
    """`findings.csv`, whole or not at all."""
    path = Path(path)
    with atomic_write(path, newline="") as stream:
        writer = csv.writer(stream)
        writer.writerow(HEADER)
        for f in findings:
            writer.writerow((f.id, f.kind, f"{f.x:.7f}", f"{f.y:.7f}", _number(f.length_m), _number(f.width_m),
                             _number(f.depth_m), f"{f.confidence:.3f}", f.wkt))


def read_findings_csv(path: str | Path) -> list[Finding]:
    """The findings of a `findings.csv` (area_m2 is not in the file: NaN). ValueError on a bad file."""
    findings = []
    with open(path, newline="", encoding="utf-8") as stream:
        reader = csv.reader(stream)
        header = tuple(next(reader, ()))
        if header != HEADER:
            raise ValueError(f"{path}: header {','.join(header)!r} is not {','.join(HEADER)!r}")
        for row in reader:
            kind_name, parts = parse_wkt(row[8])
            points = tuple(tuple(part) for part in parts)
            lines = points if kind_name != "POLYGON" else ()
            findings.append(Finding(int(row[0]), row[1], float(row[2]), float(row[3]),  # type: ignore[arg-type]
                                    float(row[4]), float(row[5]), float(row[6]), math.nan, float(row[7]),
                                    polylines=lines, polygon=points[0] if kind_name == "POLYGON" else ()))
    return findings


def read_height_tif(path: str | Path) -> tuple[np.ndarray, float, tuple[float, float]]:
    """(height float32 metres with row 0 the largest y, resolution m/px, origin of the lower-left pixel's
    corner) of a GeoTIFF height map, its full-resolution level. UserError, one line, on a bad file."""
    import tifffile

    path = Path(path)
    try:
        with tifffile.TiffFile(path) as tif:
            page = tif.pages[0]
            tags = {tag.code: tag.value for tag in page.tags.values()}   # type: ignore[union-attr]
            height = tif.asarray(key=0)
    except (OSError, ValueError, tifffile.TiffFileError) as exc:
        raise UserError(f"cannot read {path}: {exc}") from None
    if height.ndim != 2 or not np.issubdtype(height.dtype, np.floating):
        raise UserError(f"{path}: a height map is one float band, got {height.dtype} of shape {height.shape}")
    if MODEL_PIXEL_SCALE not in tags or MODEL_TIEPOINT not in tags:
        raise UserError(f"{path} has no GeoTIFF ModelPixelScale and ModelTiepoint tags: where it lies is unknown")
    sx, sy = (float(v) for v in tags[MODEL_PIXEL_SCALE][:2])
    i, j, _, x, y, _ = (float(v) for v in tags[MODEL_TIEPOINT][:6])
    if not (math.isfinite(sx) and sx > 0 and math.isclose(sx, sy, rel_tol=1e-6)):
        raise UserError(f"{path}: pixels must be square and positive, got a scale of {sx} x {sy}")
    rows = height.shape[0]
    left, top = x - i * sx, y + j * sy
    return height.astype(np.float32, copy=False), sx, (left, top - rows * sy)


def write_findings_png(path: str | Path, grey: np.ndarray, mapped: np.ndarray, resolution: float,
                       origin: tuple[float, float], findings: Sequence[Finding]) -> None:
    """The map (grey uint8, `mapped` False shown dark blue) with each finding drawn (cracks red along the
    centreline, dents orange and bumps green around their outline) and numbered; at most PNG_MAX_SIDE px."""
    import cv2

    rows, cols = grey.shape
    scale = min(1.0, PNG_MAX_SIDE / max(rows, cols, 1))
    image = cv2.cvtColor(np.asarray(grey, np.uint8), cv2.COLOR_GRAY2BGR)
    image[~mapped] = (60, 20, 20)
    if scale < 1.0:
        image = cv2.resize(image, (max(1, round(cols * scale)), max(1, round(rows * scale))),
                           interpolation=cv2.INTER_AREA)
    top = origin[1] + rows * resolution

    def pixels(points: Sequence[tuple[float, float]]) -> np.ndarray:
        p = np.asarray(points, np.float64)
        uv = np.stack([(p[:, 0] - origin[0]) / resolution * scale, (top - p[:, 1]) / resolution * scale], axis=1)
        return np.round(uv * 16).astype(np.int32).reshape(-1, 1, 2)

    thickness = max(1, round(max(image.shape[:2]) / 800))
    for f in findings:
        colour = COLOURS.get(f.kind, (255, 255, 255))
        shapes = list(f.polylines) if f.kind == "crack" else [f.polygon]
        for shape in shapes:
            if len(shape) >= 2:
                cv2.polylines(image, [pixels(shape)], f.kind != "crack", colour, thickness, cv2.LINE_AA, shift=4)
        (u, v), = (pixels([(f.x, f.y)]).reshape(-1, 2) / 16).astype(int)
        label, font, size = str(f.id), cv2.FONT_HERSHEY_SIMPLEX, 0.4 * thickness
        at = (int(u) + 4 * thickness, int(v) - 4 * thickness)
        cv2.putText(image, label, at, font, size, (0, 0, 0), 3 * thickness, cv2.LINE_AA)
        cv2.putText(image, label, at, font, size, colour, thickness, cv2.LINE_AA)
    with atomic_path(path) as temporary:
        if not cv2.imwrite(str(temporary), image):
            raise OSError(f"cv2.imwrite failed for {path}")
