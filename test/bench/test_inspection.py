"""The inspection bench's generator and scoring on one small map: truth in the findings' format, a planted
crack found and scored, a missed one scored as missed."""
from __future__ import annotations

import math

import pytest

from bench.inspection import densify, score
from bench.inspection_maps import CrackSpec, make_map
from touchroller_bringup.findings_files import read_findings_csv, write_findings_csv
from touchroller_perception.inspection import inspect_height


@pytest.fixture(scope="module")
def small_map():
    return make_map("painted", 7, size_m=(0.03, 0.03), crack_specs=[CrackSpec(0.3e-3, 60e-6, 12e-3)], blobs=1,
                    branch_probability=0)


def test_truth_is_written_and_read_as_findings(small_map, tmp_path):
    assert [t.kind for t in small_map.truth][0] == "crack" and len(small_map.truth) == 2
    crack = small_map.truth[0]
    assert crack.length_m == pytest.approx(12e-3, rel=0.02)
    trunk = densify(crack.polylines[:1])
    assert (trunk >= 0).all() and (trunk <= 0.03).all()
    write_findings_csv(tmp_path / "truth.csv", small_map.truth)
    back = read_findings_csv(tmp_path / "truth.csv")
    assert [b.kind for b in back] == [t.kind for t in small_map.truth]
    assert back[0].x == pytest.approx(crack.x, abs=1e-7)


def test_a_planted_crack_is_found_and_scored(small_map):
    found = inspect_height(small_map.height, small_map.resolution, small_map.origin)
    cracks, blobs, false = score(small_map.truth, found, small_map.background, 7)
    assert false == 0 and cracks[0].found
    assert cracks[0].centreline_mm < 0.1 and abs(cracks[0].width_err_mm) < 0.05
    missed, _, _ = score(small_map.truth, [], small_map.background, 7)
    assert not missed[0].found and math.isnan(missed[0].centreline_mm)


def test_the_recorded_result_reads_back_and_renders_the_same():
    from bench.inspection import load, to_markdown
    from touchroller_driver.paths import checkout_dir

    path = checkout_dir() / "bench" / "results" / "inspection.json"
    result = load(path)
    assert result.summary.cracks_in_scope > 0 and result.end_to_end is not None
    text = to_markdown(result)
    assert f"| {result.seeds[0]}-{result.seeds[-1]} | {result.summary.cracks_in_scope} |" in text
    assert "End to end" in text


def test_the_live_latency_rows_say_whether_the_latency_was_estimated_or_known():
    """Both live rows: the scored scan's (the latency estimated: frames wait for the estimate) and the one with
    the latency known; a recording made before the known row existed renders it as not run."""
    import dataclasses

    from bench.inspection import end_to_end_markdown, load
    from bench.inspection_scan import Latency
    from touchroller_driver.paths import checkout_dir

    e2e = load(checkout_dir() / "bench" / "results" / "inspection.json").end_to_end
    assert e2e is not None
    known = dataclasses.replace(e2e, latency=[Latency("crack", 5.0, 0.9, True)],
                                latency_known=[Latency("dent", 0.8, 0.2, False)],
                                latency_known_command="touchroller scan map.latency_estimate:=False")
    text = end_to_end_markdown(known)
    assert "| estimated | crack | 5.00 | 0.90 | the finished map (after the roll) |" in text
    assert "| known | dent | 0.80 | 0.20 | the live inspection |" in text
    assert "`touchroller scan map.latency_estimate:=False`" in text
    old = end_to_end_markdown(dataclasses.replace(e2e, latency_known=[], latency_known_command=""))
    assert "`not run`" in old and "| known |" not in old


def test_speed_measured_again_replaces_the_speed_and_the_square_metres_inspection_time(monkeypatch, tmp_path):
    """`--speed`: the recorded run keeps everything but the detector's speed, which comes with its own provenance,
    and the square metre's inspection time and total follow the new speed."""
    import bench.inspection as bench_inspection
    from bench._common import ROOT, load_json, to_json

    recorded = bench_inspection.load(ROOT / "bench" / "results" / "inspection.json")
    new = bench_inspection.Speed(9.6, 0.5, 19.2, 3)
    monkeypatch.setattr(bench_inspection, "measure_speed", lambda tiles, repeats, config: new)
    again = bench_inspection.remeasure_speed(recorded, quick=False)
    assert again.speed == new and again.speed_provenance is not None
    assert again.cracks == recorded.cracks and again.summary == recorded.summary
    if recorded.end_to_end is not None:
        old, q = recorded.end_to_end.square_metre, again.end_to_end.square_metre
        assert q.inspect_cpu_s == pytest.approx(q.megapixels / 19.2)
        assert q.total_s == pytest.approx(old.total_s - old.inspect_cpu_s + q.inspect_cpu_s)
        assert again.end_to_end.latency == recorded.end_to_end.latency
    assert "measured again by `--speed`" in bench_inspection.to_markdown(again)
    (tmp_path / "inspection.json").write_text(to_json(again))
    assert load_json(bench_inspection.InspectionBenchResult, tmp_path / "inspection.json") == again
