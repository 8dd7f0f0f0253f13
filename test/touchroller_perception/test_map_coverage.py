"""The fraction of a requested rectangle a world map covers."""
from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

from touchroller_perception.map_coverage import AreaRectangle, mapped_fraction

RES = 0.001   # 1 mm per pixel


def grid(rows: int, cols: int, value: bool = True) -> np.ndarray:
    return np.full((rows, cols), value)


def test_the_sweep_area_is_a_rectangle_to_the_left_of_the_rolling_direction():
    rect = AreaRectangle.from_sweep_area([0.4, -0.1, 0.2, 0.1], [0.0, 1.0, 0.0])   # rolling along +y
    assert rect is not None and rect.across == pytest.approx((-1.0, 0.0))     # the width runs along -x
    np.testing.assert_allclose(rect.corners(), [[0.4, -0.1], [0.4, 0.1], [0.3, 0.1], [0.3, -0.1]], atol=1e-12)
    assert AreaRectangle.from_sweep_area([0, 0, 0, 0]) is None                   # one roll: no rectangle
    assert AreaRectangle.from_sweep_area([0, 0, 0.1, 0.1], [0, 0, 1]) is None   # no horizontal direction
    with pytest.raises(ValueError, match="4 finite numbers"):
        AreaRectangle.from_sweep_area([0, 0, math.nan, 0.1])


def test_half_the_rectangle_mapped_is_one_half():
    # a 100 x 100 mm map from (0, 0); the left half (x < 50 mm) mapped
    mask = grid(100, 100, False)
    mask[:, :50] = True
    rect = AreaRectangle((0.02, 0.02), (1.0, 0.0), 0.06, 0.04)   # x 20..80 mm: 30 of 60 mm mapped
    assert mapped_fraction(mask, RES, (0.0, 0.0), rect) == pytest.approx(0.5)


def test_rows_count_from_the_top_as_in_map_png():
    mask = grid(100, 100, False)
    mask[:10, :] = True          # row 0 is the top: y from 90 to 100 mm
    assert mapped_fraction(mask, RES, (0.0, 0.0), AreaRectangle((0.0, 0.09), (1.0, 0.0), 0.1, 0.01)) == 1.0
    assert mapped_fraction(mask, RES, (0.0, 0.0), AreaRectangle((0.0, 0.0), (1.0, 0.0), 0.1, 0.01)) == 0.0


def test_outside_the_map_counts_as_not_mapped():
    rect = AreaRectangle((0.05, 0.0), (1.0, 0.0), 0.1, 0.1)   # half of it beyond the map's right edge
    assert mapped_fraction(grid(100, 100), RES, (0.0, 0.0), rect) == pytest.approx(0.5)
    assert math.isnan(mapped_fraction(grid(10, 10), RES, (0.0, 0.0), AreaRectangle((0, 0), (1, 0), 0.1, 0.0)))


@given(st.floats(0.0, 2 * math.pi), st.floats(0.005, 0.03), st.floats(0.005, 0.03),
       st.floats(-0.01, 0.01), st.floats(-0.01, 0.01))
def test_a_rectangle_anywhere_inside_a_fully_mapped_map_is_covered_whole(angle, length, width, x, y):
    heading = (math.cos(angle), math.sin(angle))
    rect = AreaRectangle((x, y), heading, length, width)
    # the map spans -50..50 mm: every turned rectangle of these sizes near the centre lies inside it
    assert mapped_fraction(grid(100, 100), RES, (-0.05, -0.05), rect) == 1.0
    assert mapped_fraction(grid(100, 100, False), RES, (-0.05, -0.05), rect) == 0.0


def test_a_huge_rectangle_is_sampled_not_read_whole():
    rect = AreaRectangle((0.0, 0.0), (1.0, 0.0), 10.0, 10.0)   # 10 x 10 m at 1 mm: 1e8 pixels
    assert mapped_fraction(grid(100, 100), RES, (0.0, 0.0), rect) == pytest.approx(1e-4, rel=0.2)
