"""Held-out choice of optional terms and views judged against the set (`calibration.selection`)."""
from __future__ import annotations

import math

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from touchroller_perception import calibration as cal
from touchroller_perception.calibration.selection import not_judged, rms_warning


def test_a_uniformly_worse_set_keeps_every_view():
    rms = [1.12, 1.36, 1.2, 1.25, 1.3, 1.18, 1.22, 1.29, 1.15, 1.33]
    assert cal.gate_by_rms(rms).all()


def test_one_view_far_above_the_set_is_gated():
    rms = [0.1, 0.12, 0.09, 0.11, 0.1, 0.13, 2.5]
    assert cal.gate_by_rms(rms).tolist() == [True] * 6 + [False]


@settings(max_examples=50, deadline=None)
@given(st.lists(st.floats(0.01, 5.0), min_size=3, max_size=30), st.floats(0.1, 100.0))
def test_the_gate_does_not_depend_on_the_units(rms, scale):
    """Relative to the set: scaling every RMS scales the limit (above the floor) and keeps the median view."""
    values = np.array(rms)
    gate = cal.gate_by_rms(values, floor=0.0)
    assert gate[np.argsort(values)[len(values) // 2]]
    assert (cal.gate_by_rms(values * scale, floor=0.0) == gate).all()


def test_non_finite_rms_is_never_kept():
    assert cal.gate_by_rms([0.1, math.nan, 0.1, math.inf, 0.12]).tolist() == [True, False, True, False, True]


def test_a_term_is_kept_when_it_predicts_held_out_presses_better_beyond_the_spread():
    rng = np.random.default_rng(0)
    without = 0.5 + 0.02 * rng.standard_normal(10)
    better = without - 0.3 + 0.02 * rng.standard_normal(10)
    choice = cal.choose_term("row balance", without, better)
    assert choice.kept and choice.margin_px > 0.25 and choice.spread_px < 0.02
    assert choice.line().startswith("row balance: kept, held-out margin +0.")


def test_a_term_whose_gain_is_within_the_spread_is_left_out():
    rng = np.random.default_rng(1)
    without = 0.5 + 0.1 * rng.standard_normal(10)
    noisy = without - 0.01 + 0.2 * rng.standard_normal(10)
    choice = cal.choose_term("row balance", without, noisy)
    assert not choice.kept and "left out" in choice.line()


def test_a_term_that_predicts_worse_is_left_out_however_consistent():
    without = np.full(8, 0.2)
    worse = without + 0.05
    assert not cal.choose_term("t", without, worse, needed=0.0).kept


def test_too_few_presses_cannot_judge_a_term():
    choice = cal.choose_term("t", [0.3, 0.2], [0.1, 0.1])
    assert not choice.kept and choice.presses == 2 and "cannot judge" in choice.line()
    assert not not_judged("t", "switched off").kept


def test_the_rms_warning_says_how_much_worse_and_what_it_costs():
    assert rms_warning(0.2, 0.01, 0.002) is None
    text = rms_warning(1.24, 0.05, 0.004)
    assert text is not None and "8.3x" in text and "sigma" in text and "0.050°" in text
