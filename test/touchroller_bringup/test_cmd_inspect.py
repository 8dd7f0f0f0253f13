"""`touchroller inspect MAP --out DIR`: files written whole, read back (WKT parsed), one-line errors."""
from __future__ import annotations

import csv
import importlib.util
import math
from pathlib import Path

import numpy as np
import pytest
import tifffile

from touchroller_bringup.cli import main
from touchroller_bringup.findings_files import HEADER, read_findings_csv, read_height_tif, write_findings_csv
from touchroller_bringup.map_files import write_world_map
from touchroller_perception.inspection import Finding, parse_wkt
from touchroller_perception.world_map import WorldMapImage

_spec = importlib.util.spec_from_file_location(
    "sim_scans", Path(__file__).parents[1] / "touchroller_driver" / "sim" / "sim_scans.py")
assert _spec is not None and _spec.loader is not None
sim_scans = importlib.util.module_from_spec(_spec)
_spec.loader.exec_module(sim_scans)

RES = 1e-4
ORIGIN = (0.40, -0.02)


def _height(rows=300, cols=400):
    rng = np.random.default_rng(3)
    h = rng.normal(0, 0.5e-6, (rows, cols)).astype(np.float32)
    yy, xx = np.mgrid[0:rows, 0:cols]
    x, y = ORIGIN[0] + (xx + 0.5) * RES, ORIGIN[1] + (rows - yy - 0.5) * RES
    crack_y = -0.005                                               # a crack along x at y = -5 mm
    h -= (60e-6 * np.exp(-4 * math.log(2) * ((y - crack_y) / 0.3e-3) ** 2) * ((x > 0.405) & (x < 0.430))
          ).astype(np.float32)
    r = np.hypot(x - 0.432, y - 0.005)
    h -= (50e-6 * np.where(r < 1e-3, 0.5 * (1 + np.cos(np.pi * r / 1e-3)), 0)).astype(np.float32)
    return h


def _write_map(folder, with_height=True, rows=300, cols=400):
    grey = np.full((rows, cols), 128, np.uint8)
    alpha = np.full((rows, cols), 255, np.uint8)
    png, yaml_path = write_world_map(folder / "map.png", WorldMapImage(grey, alpha, RES, ORIGIN), "base")
    if with_height:
        top = ORIGIN[1] + rows * RES
        tifffile.imwrite(folder / "height.tif", _height(rows, cols),
                         extratags=[(33550, 12, 3, (RES, RES, 0.0), False),
                                    (33922, 12, 6, (0.0, 0.0, 0.0, ORIGIN[0], top, 0.0), False)])
    return yaml_path


def test_height_map_to_findings_csv_and_png(tmp_path, capsys):
    yaml_path = _write_map(tmp_path)
    out = tmp_path / "out"
    assert main(["inspect", str(yaml_path), "--out", str(out)]) == 0
    assert "1 crack(s), 1 dent(s), 0 bump(s)" in capsys.readouterr().out
    with open(out / "findings.csv", newline="") as stream:
        rows = list(csv.reader(stream))
    assert tuple(rows[0]) == HEADER
    findings = {f.kind: f for f in read_findings_csv(out / "findings.csv")}
    crack, dent = findings["crack"], findings["dent"]
    assert crack.y == pytest.approx(-0.005, abs=1e-4) and crack.x == pytest.approx(0.4175, abs=5e-4)
    assert crack.length_m == pytest.approx(0.025, rel=0.05) and crack.depth_m == pytest.approx(60e-6, rel=0.15)
    assert (dent.x, dent.y) == pytest.approx((0.432, 0.005), abs=1e-4) and dent.depth_m > 0
    kind, parts = parse_wkt(rows[1][8] if rows[1][1] == "crack" else rows[2][8])
    assert kind == "LINESTRING" and all(abs(y + 0.005) < 2e-4 for _, y in parts[0])
    import cv2

    image = cv2.imread(str(out / "findings.png"))
    assert image.shape == (300, 400, 3)
    assert (image[..., 2] > 200).sum() > 100 and (image[..., 1] < 60).sum() > 100   # red crack drawn


def test_a_masked_rectangle_is_silenced(tmp_path):
    yaml_path = _write_map(tmp_path)
    out = tmp_path / "out"
    assert main(["inspect", str(yaml_path), "--out", str(out), "--ignore", "0.40,-0.008,0.44,-0.002"]) == 0
    assert [f.kind for f in read_findings_csv(out / "findings.csv")] == ["dent"]


def test_without_height_the_intensity_is_inspected_and_depth_is_nan(tmp_path, capsys):
    rows, cols = 300, 400
    grey = np.full((rows, cols), 128, np.uint8)
    grey[100:104, 50:300] = 60                                 # a dark line
    alpha = np.full((rows, cols), 255, np.uint8)
    alpha[:, :20] = 0
    _, yaml_path = write_world_map(tmp_path / "map.png", WorldMapImage(grey, alpha, RES, ORIGIN), "base")
    out = tmp_path / "out"
    assert main(["inspect", str(yaml_path), "--out", str(out)]) == 0
    assert "depth is unavailable" in capsys.readouterr().out
    found = read_findings_csv(out / "findings.csv")
    assert [f.kind for f in found] == ["crack"] and math.isnan(found[0].depth_m)


def test_a_declared_blur_is_taken_out_of_the_widths(tmp_path):
    # the map's crack is 0.3 mm wide: declaring a 0.25 mm blur reads it narrower and deeper
    yaml_path = _write_map(tmp_path)
    assert main(["inspect", str(yaml_path), "--out", str(tmp_path / "plain")]) == 0
    assert main(["inspect", str(yaml_path), "--out", str(tmp_path / "blur"), "--blur-mm", "0.25"]) == 0
    plain, blur = ({f.kind: f for f in read_findings_csv(tmp_path / d / "findings.csv")} for d in ("plain", "blur"))
    assert blur["crack"].width_m < plain["crack"].width_m - 0.08e-3
    assert blur["crack"].depth_m > plain["crack"].depth_m * 1.2


@pytest.mark.parametrize("argv, message", [
    (["inspect", "{tmp}/missing.yaml", "--out", "{tmp}/o"], "no such map or recording"),
    (["inspect", "{tmp}/notes.txt", "--out", "{tmp}/o"], "map.yaml"),
    (["inspect", "{tmp}", "--out", "{tmp}/o"], "not a recording"),
    (["inspect", "{tmp}/map.yaml", "--out", "{tmp}/o", "--ignore", "1,2,3"], "--ignore"),
    (["inspect", "{tmp}/map.yaml", "--out", "{tmp}/notes.txt"], "is a file"),
    (["inspect", "{tmp}/bad/map.yaml", "--out", "{tmp}/o"], "height"),
    (["inspect", "{tmp}/map.yaml", "--out", "{tmp}/o", "--blur-mm", "-1"], "--blur-mm"),
])
def test_bad_input_is_one_line_and_writes_nothing(tmp_path, capsys, argv, message):
    _write_map(tmp_path)
    (tmp_path / "notes.txt").write_text("x")
    (tmp_path / "bad").mkdir()
    _write_map(tmp_path / "bad", with_height=False)
    tifffile.imwrite(tmp_path / "bad" / "height.tif", np.zeros((4, 4), np.float32))     # no GeoTIFF tags
    code = main([a.replace("{tmp}", str(tmp_path)) for a in argv])
    err = capsys.readouterr().err
    assert code != 0 and message in err and len(err.strip().splitlines()) == 1
    assert not (tmp_path / "o" / "findings.csv").exists()


def test_height_tif_grid_is_read_from_its_geotiff_tags(tmp_path):
    _write_map(tmp_path)
    height, resolution, origin = read_height_tif(tmp_path / "height.tif")
    assert height.shape == (300, 400) and resolution == pytest.approx(RES)
    assert origin == pytest.approx(ORIGIN)


def test_findings_csv_round_trip_and_failed_write_keeps_the_old_file(tmp_path):
    crack = Finding(1, "crack", 0.1, 0.2, 0.01, 2e-4, 3e-5, 2e-6, 0.9,
                    polylines=(((0.1, 0.2), (0.11, 0.2)), ((0.105, 0.2), (0.105, 0.21))))
    dent = Finding(2, "dent", 0.3, 0.2, 1e-3, 1e-3, float("nan"), 1e-6, 0.5,
                   polygon=((0.3, 0.2), (0.301, 0.2), (0.301, 0.201), (0.3, 0.2)))
    path = tmp_path / "findings.csv"
    write_findings_csv(path, [crack, dent])
    back = read_findings_csv(path)
    assert [b.kind for b in back] == ["crack", "dent"]
    assert back[0].polylines == crack.polylines and back[1].polygon == dent.polygon
    assert math.isnan(back[1].depth_m) and back[0].depth_m == pytest.approx(3e-5)
    before = path.read_bytes()
    broken = Finding(3, "crack", 0, 0, 0, 0, 0, 0, 0)                 # no centreline: cannot be written
    with pytest.raises(ValueError):
        write_findings_csv(path, [crack, broken])
    assert path.read_bytes() == before and list(tmp_path.glob(".findings*")) == []


@pytest.mark.slow
def test_a_recording_is_mapped_first_then_inspected(tmp_path, capsys):
    from touchroller_bringup.bags import write_scan

    sensor = sim_scans.large_surface(seed=1)
    plan = sim_scans.raster([0.45, -0.02, 0.015, 0.04])
    bag = tmp_path / "bag"
    write_scan(bag, sim_scans.bag_records(sim_scans.sweep(sensor, plan, 0.02)))
    out = tmp_path / "out"
    assert main(["inspect", str(bag), "--out", str(out)]) == 0
    printed = capsys.readouterr().out
    assert "map.yaml" in printed and "depth is unavailable" in printed, printed
    assert (out / "map.png").is_file() and (out / "map.yaml").is_file() and (out / "findings.png").is_file()
    with open(out / "findings.csv", newline="") as stream:
        assert tuple(next(csv.reader(stream))) == HEADER
    assert all(math.isnan(f.depth_m) for f in read_findings_csv(out / "findings.csv"))
