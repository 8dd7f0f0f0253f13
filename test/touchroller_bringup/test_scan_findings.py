"""A scan's findings: when it inspects, which layer, the files, and the simulated scene's truth."""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import pytest

from touchroller_bringup import scan_findings
from touchroller_bringup.findings_files import HEADER, read_findings_csv

RES = 1e-4


@dataclass
class MapImage:
    grey: np.ndarray
    alpha: np.ndarray
    resolution: float
    origin: tuple[float, float]


@dataclass
class HeightMapImage(MapImage):
    height: np.ndarray | None = None


def dented(shape=(200, 300)):
    rows, cols = shape
    yy, xx = np.mgrid[0:rows, 0:cols]
    r = np.hypot((xx + 0.5) * RES - 0.015, (rows - yy - 0.5) * RES - 0.01)
    bell = np.where(r < 1e-3, 0.5 * (1 + np.cos(np.pi * r / 1e-3)), 0)
    h = np.random.default_rng(0).normal(0, 0.3e-6, shape) - 50e-6 * bell
    gy, gx = np.gradient(h, RES)
    grey = np.clip(np.rint(128 + 400 * (0.8 * gx + 0.6 * gy)), 0, 255).astype(np.uint8)
    return h.astype(np.float32), grey


@pytest.mark.parametrize("arguments, expected", [
    ({}, False), ({"area": "0.4,-0.1,0.2,0.2"}, True), ({"inspect": "auto", "area": ""}, False),
    ({"inspect": "true"}, True), ({"inspect": "false", "area": "0.4,-0.1,0.2,0.2"}, False)])
def test_inspect_is_on_for_a_raster_unless_told(arguments, expected):
    assert scan_findings.enabled(arguments) is expected


def test_the_height_layer_is_inspected_when_the_map_has_one(tmp_path):
    h, grey = dented()
    alpha = np.full(h.shape, 255, np.uint8)
    with_height = scan_findings.inspect_map(HeightMapImage(grey, alpha, RES, (0.4, 0.0), h))
    assert with_height.layer == "height"
    (dent,) = with_height.findings
    assert dent.kind == "dent" and dent.depth_m == pytest.approx(50e-6, rel=0.1)
    assert (dent.x, dent.y) == pytest.approx((0.415, 0.01), abs=1e-4)
    # a height layer of another grid or type is not taken for one
    assert scan_findings.height_layer(HeightMapImage(grey, alpha, RES, (0.4, 0.0), h[:10])) is None
    assert scan_findings.height_layer(HeightMapImage(grey, alpha, RES, (0.4, 0.0), grey)) is None
    only_grey = scan_findings.inspect_map(MapImage(grey, alpha, RES, (0.4, 0.0)))
    assert only_grey.layer == "intensity" and len(only_grey.findings) == 1
    assert math.isnan(only_grey.findings[0].depth_m)
    assert (only_grey.findings[0].x, only_grey.findings[0].y) == pytest.approx((0.415, 0.01), abs=2e-4)
    files = scan_findings.write_findings(tmp_path, MapImage(grey, alpha, RES, (0.4, 0.0)), with_height)
    assert read_findings_csv(files["findings"])[0].kind == "dent" and files["findings_png"].stat().st_size > 0
    assert "1 finding(s) (0 crack, 1 dent, 0 bump) in the height map" in with_height.summary()


def test_the_truth_of_a_scene_with_defects_and_of_one_without(tmp_path):
    path = scan_findings.write_truth(tmp_path, "inspection_panel")
    truth = read_findings_csv(path)
    assert path.read_text().splitlines()[0] == ",".join(HEADER)
    assert {f.kind for f in truth} == {"crack", "dent", "bump"}
    # in base: the scene's surface starts at x 0.4 and is 8 cm across the roller (world y)
    assert all(0.4 < f.x < 0.46 and -0.04 < f.y < 0.04 for f in truth)
    assert scan_findings.plants_defects("inspection_panel") and not scan_findings.plants_defects("surface_mapping")
    assert not scan_findings.plants_defects("no_such_scene") and not scan_findings.plants_defects("")
