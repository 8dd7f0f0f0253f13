"""`touchroller inspect MAP --out DIR`: cracks, dents and bumps in a world map (docs/inspection.md).

MAP is a world map's `map.yaml`: the inspection reads `height.tif` beside it when there is one (depth in
metres), else the intensity `map.png` (depth unavailable: NaN, and it says so); or a recording, which it
maps first as `touchroller map` does (DIR/map.png + map.yaml). Writes DIR/findings.csv and
DIR/findings.png, each whole or not at all.
"""
from __future__ import annotations

import argparse
import math
from dataclasses import replace
from pathlib import Path

from touchroller_bringup.errors import UserError


def register(subparsers: argparse._SubParsersAction) -> None:
    parser = subparsers.add_parser(
        "inspect", help="find cracks, dents and bumps in a world map",
        description="Find cracks, dents and bumps in a world map (map.yaml, with height.tif beside it for depth) "
                    "or in a recording (mapped first); writes DIR/findings.csv and DIR/findings.png.")
    parser.add_argument("map", help="a world map's map.yaml, or a rosbag2 recording folder")
    parser.add_argument("--out", required=True, help="output folder (made if missing)")
    parser.add_argument("--ignore", action="append", default=[], metavar="X0,Y0,X1,Y1",
                        help="a rectangle (metres, map frame) where nothing is reported, such as a declared panel "
                             "joint; repeatable")
    parser.add_argument("--min-depth-um", type=float, default=None,
                        help="the smallest depth reported, micrometres (default: the detector's)")
    parser.add_argument("--blur-mm", type=float, default=None,
                        help="the map's point spread beyond its pixel (the sensor's gel, optics, calibration "
                             "smoothing), FWHM in millimetres: taken out of widths, put back in depths (default 0)")
    parser.add_argument("--params", help="recording only: the calibration YAML `touchroller map` uses")
    parser.set_defaults(func=run)


def _rectangles(values: list[str]) -> list[tuple[float, float, float, float]]:
    out = []
    for value in values:
        try:
            x0, y0, x1, y1 = (float(v) for v in value.split(","))
        except ValueError:
            raise UserError(f"--ignore wants X0,Y0,X1,Y1 in metres, got {value!r}") from None
        if not all(math.isfinite(v) for v in (x0, y0, x1, y1)) or x1 <= x0 or y1 <= y0:
            raise UserError(f"--ignore wants X0 < X1 and Y0 < Y1, finite, got {value!r}")
        out.append((x0, y0, x1, y1))
    return out


def _mask(shape: tuple[int, int], resolution: float, origin: tuple[float, float],
          rectangles: list[tuple[float, float, float, float]]):
    import numpy as np

    rows, cols = shape
    x = origin[0] + (np.arange(cols) + 0.5) * resolution
    y = origin[1] + (rows - np.arange(rows) - 0.5) * resolution
    mask = np.zeros(shape, bool)
    for x0, y0, x1, y1 in rectangles:
        mask |= ((y >= y0) & (y <= y1))[:, None] & ((x >= x0) & (x <= x1))[None, :]
    return mask


def _map_recording(bag: Path, out: Path, params: str | None) -> Path:
    from touchroller_bringup.cli import build_parser

    argv = ["map", str(bag), "--out", str(out / "map.png")] + (["--params", params] if params else [])
    args = build_parser(only="map").parse_args(argv)
    args.func(args)
    yaml_path = out / "map.yaml"
    if not yaml_path.is_file():
        raise UserError(f"{bag} has no /tf and /tf_static to place its frames in the world: a strip map cannot be "
                        "inspected (record the scan with TF)")
    return yaml_path


def run(args: argparse.Namespace) -> int:
    import numpy as np
    import yaml

    from touchroller_bringup.findings_files import read_height_tif, write_findings_csv, write_findings_png
    from touchroller_bringup.map_files import read_world_map
    from touchroller_perception.inspection import InspectionConfig, inspect, inspect_intensity

    source, out = Path(args.map), Path(args.out)
    rectangles = _rectangles(args.ignore)
    config = InspectionConfig()
    if args.min_depth_um is not None:
        if not (math.isfinite(args.min_depth_um) and args.min_depth_um >= 0):
            raise UserError(f"--min-depth-um must be a number >= 0, got {args.min_depth_um}")
        config = replace(config, min_depth_m=args.min_depth_um * 1e-6)
    if args.blur_mm is not None:
        if not (math.isfinite(args.blur_mm) and 0 <= args.blur_mm <= 10):
            raise UserError(f"--blur-mm must be a number from 0 to 10, got {args.blur_mm}")
        config = replace(config, blur_fwhm_m=args.blur_mm * 1e-3)
    if out.exists() and not out.is_dir():
        raise UserError(f"--out {out} is a file; give a folder")
    try:
        out.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise UserError(f"cannot make --out {out}: {exc.strerror or exc}") from None
    if source.is_dir():
        if not (source / "metadata.yaml").is_file() and not any(source.glob("*.db3")) and not any(
                source.glob("*.mcap")):
            raise UserError(f"{source} is a folder but not a recording (no metadata.yaml, .db3 or .mcap)")
        source = _map_recording(source, out, args.params)
    elif not source.is_file():
        raise UserError(f"no such map or recording: {source}")
    elif source.suffix.lower() not in (".yaml", ".yml"):
        raise UserError(f"{source}: give a world map's map.yaml (or a recording folder)")
    try:
        meta = yaml.safe_load(source.read_text(encoding="utf-8"))
        grey, alpha, _ = read_world_map(source)
        resolution = float(meta["resolution"])
        x0, y0, yaw = (float(v) for v in meta["origin"][:3])
    except (OSError, ValueError, KeyError, TypeError, yaml.YAMLError) as exc:
        raise UserError(f"cannot read the world map {source}: {type(exc).__name__}: {exc}") from None
    if abs(yaw) > 1e-9:
        raise UserError(f"{source}: a map turned by a yaw ({yaw}) is not supported; inspect an unrotated map")
    height_path = source.parent / "height.tif"
    if height_path.is_file():
        height, h_res, h_origin = read_height_tif(height_path)
        mask = _mask(height.shape, h_res, h_origin, rectangles)
        result = inspect(height, h_res, h_origin, mask, config)
        what = f"{height_path.name} ({height.shape[1]}x{height.shape[0]} px at {h_res * 1e3:g} mm)"
    else:
        values = np.where(alpha > 0, grey.astype(np.float32), np.float32(np.nan))
        mask = _mask(values.shape, resolution, (x0, y0), rectangles)
        result = inspect_intensity(values, resolution, (x0, y0), mask, config)
        what = (f"{Path(meta['image']).name} (intensity: no height.tif beside {source.name}, so depth is "
                "unavailable: depth_m is nan)")
    try:
        write_findings_csv(out / "findings.csv", result.findings)
        write_findings_png(out / "findings.png", grey, alpha > 0, resolution, (x0, y0), result.findings)
    except OSError as exc:
        raise UserError(f"cannot write the findings to {out}: {exc.strerror or exc}") from None
    counts = {k: sum(f.kind == k for f in result.findings) for k in ("crack", "dent", "bump")}
    d = result.diagnostics
    print(f"{what}: {counts['crack']} crack(s), {counts['dent']} dent(s), {counts['bump']} bump(s) -> "
          f"{out / 'findings.csv'} + findings.png (noise sigma {d.noise_sigma:.3g}, threshold {d.high_threshold:.3g})")
    return 0
