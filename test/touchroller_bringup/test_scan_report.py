"""The scan's report.md: the map as a picture beside it, the coverage of the requested area, the findings."""
from __future__ import annotations

import math
from pathlib import Path
from types import SimpleNamespace

import cv2
import numpy as np

from touchroller_bringup.findings_files import write_findings_csv
from touchroller_bringup.graph import build_graph
from touchroller_bringup.scan import ScanResult, _Collected, _write_outputs
from touchroller_bringup.scan_report import AREA_BGR, PREVIEW, PREVIEW_MAX_SIDE, UNMAPPED_BGR, report_markdown
from touchroller_perception.inspection.types import Finding
from touchroller_perception.world_map import WorldMapImage

RES = 0.0002   # m per pixel


def world(rows: int = 500, cols: int = 1500) -> SimpleNamespace:
    """A perception node stand-in whose world map covers x 0.40..0.70 m, y -0.05..0.05 m, mapped where
    x < 0.55 (the left half)."""
    grey = np.random.default_rng(0).integers(40, 200, (rows, cols), np.uint8)
    alpha = np.zeros((rows, cols), np.uint8)
    alpha[:, : cols // 2] = 255
    image = WorldMapImage(grey, alpha, RES, (0.40, -0.05))
    # a world mapper holding that image on its tiles (the scan reads its map from them)
    from touchroller_perception.geometry import CameraModel
    from touchroller_perception.world_map import WorldMapConfig, WorldMapper

    camera = CameraModel(fx=200.0, fy=200.0, cx=159.5, cy=119.5, width=320, height=240)
    bounds = (0.40, -0.05, 0.40 + (cols - 0.5) * RES, -0.05 + (rows - 0.5) * RES)
    mapper = WorldMapper(camera, lambda stamps: np.zeros((len(stamps), 4, 4)), WorldMapConfig(resolution=RES,
                                                                                              bounds=bounds))
    values = np.flipud(grey).astype(np.float32)[:, : cols // 2]   # rows growing with y, the mapped half
    mapper.canvas.add([values, np.ones_like(values), np.ones_like(values)], 0, 0)
    assert mapper.canvas.shape == (rows, cols)
    np.testing.assert_array_equal(mapper.map_image().grey[alpha > 0], image.grey[alpha > 0])
    mapper.stats.mapped, mapper.stats.passes, mapper.stats.latency_s = 120, 2, 0.03
    mapper.stats.latency_estimated = True
    return SimpleNamespace(world=mapper, world_frame="base", camera=None, received=100, dropped=0, malformed=0,
                           has_parameter=lambda name: False)


def sweep(area: list[float], passes: int = 3) -> SimpleNamespace:
    values = {"sweep.area": area, "sweep.direction": [1.0, 0.0, 0.0]}
    return SimpleNamespace(has_parameter=values.__contains__,
                           get_parameter=lambda name: SimpleNamespace(value=values[name]),
                           sequencer=SimpleNamespace(plan=SimpleNamespace(rolls=tuple(range(passes)))))


def outputs(out: Path, area: list[float], monkeypatch) -> ScanResult:
    import touchroller_perception.world_map as world_map

    # the stand-in's stats are not a mapper's: its latency line is given
    monkeypatch.setattr(world_map, "latency_summary", lambda stats: ("30.0 ms (estimated)", {}))
    return _write_outputs(out, build_graph("scan", {}, []), world(), _Collected(), "done", "sweep complete", 10.0,
                          "3 passes", sweep=sweep(area))


def test_the_report_shows_the_map_its_coverage_and_the_findings(tmp_path, monkeypatch):
    findings = [Finding(1, "crack", 0.45, 0.0, 0.012, 0.0004, 0.0001, math.nan, 0.9,
                        polylines=(((0.44, 0.0), (0.46, 0.0)),)),
                Finding(2, "dent", 0.50, 0.02, 0.003, 0.002, 0.0002, math.nan, 0.7,
                        polygon=((0.49, 0.01), (0.51, 0.01), (0.51, 0.03), (0.49, 0.01)))]
    write_findings_csv(tmp_path / "findings.csv", findings)
    # the requested area: x 0.45..0.65, y -0.03..0.03; the map covers x < 0.55 of it: half
    result = outputs(tmp_path, [0.45, -0.03, 0.20, 0.06], monkeypatch)
    assert result.coverage is not None and abs(result.coverage.fraction - 0.5) < 0.01
    report = (tmp_path / "report.md").read_text()
    assert f"[![the map]({PREVIEW})](map.png)" in report
    assert "- mapped: **50.0 %** of it (60.0 of 120.0 cm²)" in report
    assert "requested area: 20.0 x 6.0 cm at (0.4500, -0.0300) m in `base`" in report
    assert "3 pass(es) planned" in report and (tmp_path / "map.png").is_file()
    assert "- passes mapped: 2 of 3" in report
    assert "2 finding(s) (crack 1, dent 1) in `findings.csv`" in report
    assert "| 1 | crack | 0.4500 | 0.0000 | 12.00 | 0.40 | 0.100 | 0.90 |" in report
    # the picture: downscaled, not mapped dark blue, the requested area outlined
    picture = cv2.imread(str(tmp_path / PREVIEW))
    assert max(picture.shape[:2]) == PREVIEW_MAX_SIDE and picture.shape[1] == PREVIEW_MAX_SIDE
    scale = PREVIEW_MAX_SIDE / 1500
    assert tuple(picture[10, PREVIEW_MAX_SIDE - 10]) == UNMAPPED_BGR            # the right half: not mapped
    edge_u = round((0.65 - 0.40) / RES * scale)                                  # the area's far edge x = 0.65
    column = picture[:, edge_u - 1: edge_u + 2].reshape(-1, 3)
    assert (np.abs(column.astype(int) - AREA_BGR).sum(axis=1) < 60).sum() > 100   # drawn along the edge


def test_without_findings_or_an_area_the_report_says_what_it_could_not_measure(tmp_path, monkeypatch):
    result = outputs(tmp_path, [0.0, 0.0, 0.0, 0.0], monkeypatch)   # one roll of sweep.length
    report = (tmp_path / "report.md").read_text()
    assert result.coverage.rectangle is None
    assert "requested: one roll (no `sweep.area`), so no rectangle to measure" in report
    assert "## Findings" not in report and (tmp_path / PREVIEW).is_file()


def test_an_unreadable_findings_file_is_one_line_in_the_report(tmp_path):
    (tmp_path / "findings.csv").write_text("not,a,findings,file\n")
    from touchroller_bringup.scan_report import read_findings

    findings, problem = read_findings(tmp_path)
    assert findings is None and problem.startswith("findings.csv could not be read:") and "\n" not in problem
    result = ScanResult(tmp_path, "done", "ok", 1.0, 1, 1, 0, 0, 0, None, {}, findings_problem=problem)
    assert f"## Findings\n\n- {problem}" in report_markdown(result, build_graph("scan", {}, []))


def test_frames_the_recording_misses_are_said_in_the_report():
    recorded = {"/touchroller/image_raw/compressed": 90, "/touchroller/image_raw": 4, "/touchroller/contacts": 7}
    result = ScanResult(Path("."), "done", "ok", 1.0, 100, 100, 0, 0, 0, None, {}, recorded=recorded)
    assert result.images_not_recorded == 6   # raw and PNG images both count; contacts do not
    report = report_markdown(result, build_graph("scan", {}, []))
    assert "the recording misses 6 of the 100 frames published" in report
    whole = ScanResult(Path("."), "done", "ok", 1.0, 94, 94, 0, 0, 0, None, {}, recorded=recorded)
    assert whole.images_not_recorded == 0 and "recording misses" not in report_markdown(whole,
                                                                                        build_graph("scan", {}, []))
    unrecorded = ScanResult(Path("."), "done", "ok", 1.0, 100, 100, 0, 0, 0, None, {})
    assert unrecorded.images_not_recorded == 0


def test_what_the_recorder_itself_counted_lost_is_the_reason_given():
    """#25: the report says why frames are missing with the recorder's own count (refused at its queue's bound,
    lost before it took them), and says a loss on another topic even when every image is there."""
    lost = ("recording lost 6 messages (6 on /touchroller/image_raw): 6 refused at the queue's bound of "
            "256 MiB (the writer fell behind)")
    recorded = {"/touchroller/image_raw": 94}
    result = ScanResult(Path("."), "done", "ok", 1.0, 100, 100, 0, 0, 0, None, {}, recorded=recorded,
                        recording_lost=lost)
    report = report_markdown(result, build_graph("scan", {}, []))
    assert f"**the recording misses 6 of the 100 frames published ({lost})**" in report
    other = "recording lost 2 messages (2 on /tf): 2 lost before the recorder took them"
    whole = ScanResult(Path("."), "done", "ok", 1.0, 94, 94, 0, 0, 0, None, {}, recorded=recorded,
                       recording_lost=other)
    assert whole.images_not_recorded == 0 and f"**{other}**" in report_markdown(whole, build_graph("scan", {}, []))
