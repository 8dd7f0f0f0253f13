"""bench/contacts_real.py: the report's real-press section (ours vs the paper's pipeline, per press, the
labels' scatter and the floor it puts under any detector's error, the model check)."""
from __future__ import annotations

import dataclasses

import cv2
import numpy as np
import pytest

from touchroller_bringup.report import load_bench_script


def test_section_reports_both_sensors_and_methods(real_presses, tmp_path, monkeypatch):
    real_presses()                                       # skips without the taxim wheel
    bench = load_bench_script("contacts_real")
    result = bench.run(quick=True, model=False)
    text = bench.to_markdown(result)
    for needle in ("| gelsight_mini, all 24 | ours (colour) | 24/24 |", "| gelsight, all 48 | paper's pipeline |",
                   "held out (odd)", "no false contact: **met**", "### How precise are the labels?",
                   "CPU ms per frame (stream)"):
        assert needle in text
    mini = bench.ours(result)
    assert mini["found"] == 24 and mini["false_contacts"] == 0 and mini["median_mm"] > 0
    assert 0 < mini["cpu_ms"] and 0 < mini["median_ms"]
    # the labels of one indenter position scatter more than our centres (the floor under the error)
    assert all(r["ours_u_std"] < 1.0 < r["labels_u_std"] for r in result["label_scatter"])
    labels = next(s for s in result["sensors"] if s["sensor"] == "gelsight_mini")["labels"]
    # within a run the pressed pattern stays put while the labels wander by several pixels
    assert labels["image_shift_max"] < 0.5
    for r in labels["runs"]:
        assert r["labels_std"][0] > 4.0 > 1.0 > r["ours_std"][0]
        assert r["labels_std"][1] > 2.0 * r["ours_std"][1]
    # so no detector that follows the image reaches the goal's 5 px against these labels
    assert 5.0 < labels["floor_median_px"] < mini["median_px"]
    [figure] = bench.figures(result, tmp_path)
    assert cv2.imread(str(figure)) is not None


def test_error_floor_is_the_least_radius_covering_that_many_labels():
    bench = load_bench_script("contacts_real")
    # one run: four labels on a square of side 2 around (0, 0), one far away
    labels = np.array([[1.0, 1.0], [1.0, -1.0], [-1.0, 1.0], [-1.0, -1.0], [20.0, 0.0]])
    runs = (range(0, 5),)
    assert bench.error_floor(labels, runs, 1) == pytest.approx(0.0, abs=1e-6)
    assert bench.error_floor(labels, runs, 2) == pytest.approx(1.0, abs=1e-6)        # an edge's midpoint
    assert bench.error_floor(labels, runs, 4) == pytest.approx(np.sqrt(2.0), abs=1e-6)
    # two runs choose their points independently
    two = np.vstack([labels[:2], labels[:2] + 100.0])
    assert bench.error_floor(two, (range(0, 2), range(2, 4)), 4) == pytest.approx(1.0, abs=1e-6)


def test_the_frames_support_our_centres_over_the_mini_labels(real_presses):
    bench = load_bench_script("contacts_real")
    from bench.real_presses import score

    presses = real_presses("gelsight_mini")
    card = score(presses)
    ours = np.array([(r.contact.u, r.contact.v) for r in card.results])
    # the first ten presses (five fitted, five held out) keep the appearance fits short
    keep = slice(0, 10)
    few = dataclasses.replace(presses, presses=presses.presses[keep], centres=presses.centres[keep],
                              radii=presses.radii[keep])
    check = bench.model_check(few, ours[keep], rounds=1)
    assert check["rms_ours"] < check["rms_labels"]
    # centres found by the model alone (held-out presses) lie nearer ours than the labels
    assert check["ours_vs_model_held_out_median_px"] < 0.5 * check["labels_vs_model_held_out_median_px"]
