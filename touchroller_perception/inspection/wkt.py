"""Findings' geometry as WKT (what shapely, GDAL and GIS tools read), and back."""
from __future__ import annotations

import re
from collections.abc import Sequence

from touchroller_perception.inspection.types import Finding, Point


def _coords(points: Sequence[Point]) -> str:
    return ", ".join(f"{x:.7f} {y:.7f}" for x, y in points)


def finding_wkt(finding: Finding) -> str:
    if finding.kind == "crack":
        lines = [line for line in finding.polylines if len(line) >= 2]
        if not lines:
            raise ValueError(f"crack {finding.id} has no centreline")
        if len(lines) == 1:
            return f"LINESTRING ({_coords(lines[0])})"
        return "MULTILINESTRING (" + ", ".join(f"({_coords(line)})" for line in lines) + ")"
    ring = list(finding.polygon)
    if len(ring) < 4 or ring[0] != ring[-1]:
        raise ValueError(f"{finding.kind} {finding.id} has no closed outline")
    return f"POLYGON (({_coords(ring)}))"


_NUMBER_PAIR = re.compile(r"\s*([-+0-9.eEnaif]+)\s+([-+0-9.eEnaif]+)\s*")


def parse_wkt(text: str) -> tuple[str, list[list[Point]]]:
    """(type, parts) of the WKT this module writes: LINESTRING, MULTILINESTRING (one part per line) or
    POLYGON (one part per ring). ValueError on anything else."""
    match = re.fullmatch(r"\s*(LINESTRING|MULTILINESTRING|POLYGON)\s*(\(.*\))\s*", text, re.IGNORECASE | re.DOTALL)
    if match is None:
        raise ValueError(f"not a LINESTRING, MULTILINESTRING or POLYGON: {text[:60]!r}")
    kind, body = match.group(1).upper(), match.group(2)
    inner = body[1:-1].strip()
    groups = [inner] if kind == "LINESTRING" else re.findall(r"\(([^()]*)\)", inner)
    if not groups:
        raise ValueError(f"empty {kind}")
    parts: list[list[Point]] = []
    for group in groups:
        points: list[Point] = []
        for pair in group.split(","):
            found = _NUMBER_PAIR.fullmatch(pair)
            if found is None:
                raise ValueError(f"bad coordinate pair {pair!r} in {kind}")
            points.append((float(found.group(1)), float(found.group(2))))
        parts.append(points)
    return kind, parts
