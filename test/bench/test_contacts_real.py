"""bench/contacts_real.py: the report's real-press section (ours vs the paper's pipeline, per press, the
labels' scatter)."""
from __future__ import annotations

import cv2

from touchroller_bringup.report import load_bench_script


def test_section_reports_both_sensors_and_methods(real_presses, tmp_path, monkeypatch):
    real_presses()                                       # skips without the taxim wheel
    bench = load_bench_script("contacts_real")
    result = bench.run(quick=True)
    text = bench.to_markdown(result)
    for needle in ("| gelsight_mini, all 24 | ours (colour) | 24/24 |", "| gelsight, all 48 | paper's pipeline |",
                   "held out (odd)", "no false contact: **met**", "### How precise are the labels?"):
        assert needle in text
    mini = bench.ours(result)
    assert mini["found"] == 24 and mini["false_contacts"] == 0 and mini["median_mm"] > 0
    # the labels of one indenter position scatter more than our centres (the floor under the error)
    assert all(r["ours_u_std"] < 1.0 < r["labels_u_std"] for r in result["label_scatter"])
    [figure] = bench.figures(result, tmp_path)
    assert cv2.imread(str(figure)) is not None
