"""The evidence report runs in quick mode and its tables are complete."""
from __future__ import annotations

import re

import pytest

from touchroller_bringup.report import SECTIONS, build_report


@pytest.mark.slow
@pytest.mark.longest
@pytest.mark.timeout(2700)   # a guard against a hang: 32 min at load 10-15 on 2 cores
def test_quick_report_has_every_section_with_complete_tables(tmp_path):
    out = tmp_path / "RESULTS.md"
    results = build_report(out, quick=True, progress=lambda _line: None)
    text = out.read_text()
    assert set(results) == {s.key for s in SECTIONS}
    assert "touchroller report --quick" in text and "Machine:" in text
    sections = {}
    for section in SECTIONS:
        assert f"## {section.title}" in text, section.key
        sections[section.key] = text.split(f"## {section.title}", 1)[1].split("\n## ", 1)[0]
        assert "Command: `" in sections[section.key], f"{section.key} does not say how to reproduce it"
    # the summary at the top is computed from every section's result, none missing
    goals = text.split("## Goals at a glance", 1)[1].split("\n## ", 1)[0]
    settings = text.split("## Settings per budget", 1)[1].split("\n## ", 1)[0]
    assert "not checked" not in goals and "figure missing" not in goals + settings
    statuses = [line.rsplit("|", 2)[1].strip() for line in goals.splitlines() if line.startswith("| ")][1:]
    assert all(status in ("**met**", "**NOT met**", "—", "see the file") for status in statuses), statuses
    assert statuses.count("**met**") + statuses.count("**NOT met**") >= 15
    # `touchroller map`'s figures come from its own section (a quick run's short bag leaves the verdict to the full run)
    assert "A status — is a figure without a verdict" in goals
    assert "best of 2 new processes" in goals and re.search(r"quick run, \d+ frames: judged by the full run", goals)
    # both map plots reach the report, beside it
    for figure in ("map_tradeoffs", "map_dy_histograms"):
        assert f"![{figure}]({figure}.png)" in sections["table_i"], figure
        assert (tmp_path / f"{figure}.png").stat().st_size > 10_000, figure
    for what in ("map: compute per frame", "map: scan time", "contacts: detector", "calibration: solve time"):
        assert [line.split("|")[2].strip().split(":")[0] for line in settings.splitlines()
                if line.startswith(f"| {what}")] == ["tight", "medium", "generous"], what
    body = text.split("\n## ", 1)[1]
    tables = re.findall(r"((?:^\|.*\|\n)+)", body, flags=re.MULTILINE)
    assert len(tables) >= len(SECTIONS)
    for table in tables:
        rows = [row.strip("|").split("|") for row in table.strip().splitlines()]
        header, data = rows[0], rows[2:]     # rows[1] is the |---| separator
        assert data, f"table without rows: {header}"
        assert all(len(row) == len(header) for row in data), f"ragged table: {header}"
        assert all(cell.strip() for row in data for cell in row[:1]), f"row without a label: {header}"
        assert not any(cell.strip().lower() in ("nan", "none", "") for row in data for cell in row[1:2]), header
    # the paper's reference numbers stand beside ours
    assert "7.66" in text and "2.63" in text          # Table II, paper
    assert "196" in text and "49" in text             # coverage, paper
    for figure in tmp_path.glob("*.png"):
        assert figure.stat().st_size > 0


def test_unknown_section_is_refused(tmp_path):
    from touchroller_bringup.errors import UserError

    with pytest.raises(UserError, match="unknown report section"):
        build_report(tmp_path / "r.md", quick=True, only=("nope",))


def test_a_recorded_section_is_rendered_from_its_bench_result_not_run(tmp_path):
    import json

    from touchroller_driver.paths import checkout_dir
    recording = json.loads((checkout_dir() / "bench" / "results" / "soak.json").read_text())
    out = tmp_path / "RESULTS.md"
    build_report(out, quick=False, only=("soak",), recorded=("soak",), progress=lambda _: None)
    text = out.read_text()
    assert "## Soak: the camera and perception nodes as processes" in text
    assert "rendered from the recorded `bench/results/soak.json`" in text
    assert "`touchroller report --only soak --recorded soak`" in text
    taken = recording["samples"][-1]["processed"]
    assert f"{taken} frames taken by the perception node in {recording['duration_s']:.0f} s" in text


def test_every_section_can_be_rendered_from_its_recording_and_a_missing_one_is_refused_in_one_line(
        tmp_path, monkeypatch):
    from touchroller_bringup import report
    from touchroller_bringup.errors import UserError

    for section in report.SECTIONS:
        assert callable(getattr(report.load_bench_script(section.script), "load", None)), section.script
    monkeypatch.setattr(report, "_recorded_path", lambda *_: tmp_path / "nowhere.json")
    with pytest.raises(UserError, match="no recorded result for section 'stability'.*bench.geometry_stability"):
        build_report(tmp_path / "R.md", quick=False, only=("stability",), recorded=("all",),
                     progress=lambda _: None)
    with pytest.raises(UserError, match="unknown report section 'nonsense'"):
        build_report(tmp_path / "R.md", quick=False, recorded=("nonsense",), progress=lambda _: None)


def test_the_world_map_section_shows_a_picture_of_the_map_it_scores(tmp_path):
    """render_section on a tiny world_map result: the bench's figures write world_map.png beside the report and
    the section shows it by a relative path; a result without its picture (a recorded JSON) shows none."""
    import dataclasses

    import cv2
    import numpy as np

    from bench._common import Provenance
    from touchroller_bringup.report import load_bench_script, render_section

    bench = load_bench_script("world_map")
    section = next(s for s in SECTIONS if s.key == "world_map")
    variant = bench.VariantScore(0.95, 99.0, 20.0, True, 50, 2, [(0.01, 0.0)], 0.01, [])
    scan = bench.ScanScores(20.0, 100, 2, 1.0, 2.0, {k: variant for k in ("tf_only", "latency", "registration")})
    truth = np.tile(np.linspace(0, 255, 40, dtype=np.uint8), (20, 1))     # 20 rows (y) x 40 columns (x)
    mapped = np.ones_like(truth, bool)
    mapped[:, 30:] = False
    picture = bench.MapPicture(20.0, 0.95, [0.4, -0.01, 0.04, 0.02], truth, mapped, truth)
    result = bench.WorldMapResult(Provenance("cmd", "machine", "now", "0 0 0"), True, [0.4, -0.01, 0.04, 0.02], 0.02,
                                  [scan], bench.CommandSpeed(10, 1.0, 1, 1.0, 1.0), [], picture)
    lines = render_section(section, bench, result, tmp_path, "*footer*")
    assert "![world_map](world_map.png)" in lines and lines[-2] == "*footer*"
    figure = cv2.imread(str(tmp_path / "world_map.png"))
    assert figure is not None and figure.shape[1] > 500
    # the not-mapped quarter is drawn dark blue in the left panel, and nowhere in the truth's
    blue = (figure[..., 0].astype(int) - figure[..., 2] > 25) & (figure[..., 0] > 40)
    left, right = blue[:, : figure.shape[1] // 2], blue[:, figure.shape[1] // 2:]
    assert left.sum() > 100 and right.sum() == 0
    recorded = dataclasses.replace(result, picture=None)
    assert not any(line.startswith("![") for line in render_section(section, bench, recorded, tmp_path / "x", ""))
