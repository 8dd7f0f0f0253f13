"""What chessboard views cover: camera_calibration's bars, the image corners, the warnings."""
from __future__ import annotations

import math

import numpy as np
import pytest

from touchroller_perception import calibration as cal

SIZE = (640, 480)


def square_board(centre: tuple[float, float], side: float, columns: int = 7, rows: int = 7,
                 shear: float = 0.0) -> np.ndarray:
    """Inner corners of an axis-aligned board (row-major), optionally sheared along u."""
    u = np.linspace(-side / 2, side / 2, columns)
    v = np.linspace(-side / 2, side / 2, rows)
    uu, vv = np.meshgrid(u, v)
    return np.stack([uu.ravel() + centre[0] + shear * vv.ravel(), vv.ravel() + centre[1]], axis=-1)


def test_view_parameters_follow_camera_calibration():
    x, y, size, skew = cal.coverage.view_parameters(square_board((320, 240), 120), 7, 7, SIZE)
    assert x == pytest.approx(0.5) and y == pytest.approx(0.5)
    assert size == pytest.approx(math.sqrt(120 * 120 / (640 * 480)))
    assert skew == pytest.approx(0.0, abs=1e-12)
    # a sheared board: the top-right corner's angle leaves 90 degrees
    _, _, _, skew = cal.coverage.view_parameters(square_board((320, 240), 120, shear=0.3), 7, 7, SIZE)
    assert skew == pytest.approx(min(1.0, 2 * math.atan(0.3)), rel=1e-6)


def test_boards_in_the_middle_leave_the_corners_uncovered_and_say_so():
    views = [square_board((320 + du, 240 + dv), 100) for du in (-60, 0, 60) for dv in (-40, 0, 40)]
    coverage = cal.board_coverage(views, 7, 7, SIZE)
    assert coverage.corners_seen == (False, False, False, False) and not coverage.corners_covered
    assert coverage.reach < 0.5
    warnings = coverage.warnings()
    assert any("image corners not covered" in w and "top-left" in w for w in warnings)
    assert any("vary too little" in w for w in warnings)
    text = "\n".join(coverage.lines())
    assert "   X [" in text and "skew [" in text and "corners TL TR BL BR: . . . ." in text
    assert coverage.grid[0] == "........" and "#" in coverage.grid[2]


def test_views_into_every_corner_and_tilted_fill_the_bars():
    views = [square_board((u, v), 150, shear=s) for u, v in ((100, 100), (540, 100), (100, 380), (540, 380))
             for s in (0.0, 0.35)] + [square_board((320, 240), 420)]
    coverage = cal.board_coverage(views, 7, 7, SIZE)
    assert coverage.corners_covered and coverage.reach > 0.8
    assert [bar.name for bar in coverage.bars] == ["X", "Y", "size", "skew"]
    assert coverage.bars_full and coverage.warnings() == []
    assert "image corners 4/4" in coverage.one_line()


def test_no_views_cover_nothing():
    coverage = cal.board_coverage([], 7, 7, SIZE)
    assert coverage.views == 0 and all(bar.progress == 0.0 for bar in coverage.bars)
    assert not coverage.corners_covered and coverage.reach == 0.0
