"""The evidence report runs in quick mode and its tables are complete."""
from __future__ import annotations

import re

import pytest

from touchroller_bringup.report import SECTIONS, build_report


@pytest.mark.slow
@pytest.mark.timeout(900)   # every section's quick run: ~5 min on a shared 2-core machine
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
