"""What a set of chessboard views covers: ROS camera_calibration's X / Y / size / skew bars, plus
the image corners and a coarse map of where the board has been.

The bars follow image_pipeline's camera_calibration (`Calibrator.get_parameters` and
`compute_goodenough`): per view, X and Y are the board's mean corner position within the image
shrunk by half the board's size on each side (so a large board is not penalised), size is
sqrt(board area / image area), skew is how far the board's top-right corner angle is from 90°
(x2, capped at 1). A bar's progress is the spread (max - min) over the views, divided by
0.7, 0.7, 0.4 and 0.5; size and skew count from 0, so only large and tilted views fill them.

The bars say nothing about the image corners, which is where an unconstrained distortion model
goes wrong: boards kept in the middle of the image leave k2 and k3 to extrapolate. So the corners
and the reach (how far towards the corners any board corner was seen) are reported beside them.
"""
from __future__ import annotations

import dataclasses
import math
from collections.abc import Sequence

import numpy as np

from touchroller_perception.calibration.common import FloatArray

#: camera_calibration's `param_ranges`: the spread a bar needs to be full
BAR_RANGES = {"X": 0.7, "Y": 0.7, "size": 0.4, "skew": 0.5}
#: an image corner counts as seen when a board corner lies in this share of the width and height
CORNER_SHARE = 0.2
GRID = (8, 6)        # columns, rows of the coarse coverage map


@dataclasses.dataclass(frozen=True)
class CoverageBar:
    name: str
    low: float          # smallest value over the views
    high: float         # largest
    progress: float     # (high - low) / range, capped at 1

    def text(self, width: int = 20) -> str:
        filled = int(round(self.progress * width))
        return f"{self.name:>4} [{'#' * filled}{'-' * (width - filled)}] {100 * self.progress:3.0f} %"


@dataclasses.dataclass(frozen=True)
class BoardCoverage:
    views: int
    bars: tuple[CoverageBar, ...]                      # X, Y, size, skew
    corners_seen: tuple[bool, bool, bool, bool]        # top-left, top-right, bottom-left, bottom-right
    reach: float        # farthest board corner from the image centre, share of the half-diagonal
    grid: tuple[str, ...]   # GRID rows of '#' (a board corner seen in the cell) and '.'

    @property
    def bars_full(self) -> bool:
        return all(bar.progress >= 1.0 for bar in self.bars)

    @property
    def corners_covered(self) -> bool:
        return all(self.corners_seen)

    def warnings(self) -> list[str]:
        """One line per problem a user can fix by capturing more views."""
        out = []
        missing = [name for name, seen in zip(("top-left", "top-right", "bottom-left", "bottom-right"),
                                              self.corners_seen, strict=True) if not seen]
        if missing:
            out.append(f"image corners not covered ({', '.join(missing)}; boards reach {100 * self.reach:.0f} % of "
                       "the way to the corners): the distortion there is extrapolated, so contacts near the image's "
                       "edges are less accurate; hold the board into each corner")
        short = [bar.name for bar in self.bars if bar.progress < 1.0]
        if short:
            out.append(f"views vary too little in {', '.join(short)} (bars below full): move, tilt and bring the "
                       "board closer between views")
        return out

    def lines(self) -> list[str]:
        """The bars, the corners and the coverage map as text (for logs, the CLI and service replies)."""
        corner_marks = "".join("#" if seen else "." for seen in self.corners_seen)
        return ([f"coverage of {self.views} view(s):"] + [bar.text() for bar in self.bars]
                + [f"corners TL TR BL BR: {' '.join(corner_marks)}  reach {100 * self.reach:.0f} %",
                   "map (# = board seen):"] + [f"  {row}" for row in self.grid])

    def one_line(self) -> str:
        bars = ", ".join(f"{bar.name} {100 * bar.progress:.0f}%" for bar in self.bars)
        corners = sum(self.corners_seen)
        return f"coverage: {bars}; image corners {corners}/4, reach {100 * self.reach:.0f}%"


def view_parameters(corners: FloatArray, columns: int, rows: int, size: tuple[int, int]) -> tuple[float, ...]:
    """(X, Y, size, skew) of one view, as camera_calibration computes them."""
    width, height = size
    grid = np.asarray(corners, dtype=np.float64).reshape(rows, columns, 2)
    up_left, up_right, down_right, down_left = grid[0, 0], grid[0, -1], grid[-1, -1], grid[-1, 0]
    a, b, c = up_right - up_left, down_right - up_right, down_left - down_right
    p, q = b + c, a + b
    area = abs(p[0] * q[1] - p[1] * q[0]) / 2.0
    border = math.sqrt(area)
    x = min(1.0, max(0.0, (float(grid[..., 0].mean()) - border / 2) / max(width - border, 1e-9)))
    y = min(1.0, max(0.0, (float(grid[..., 1].mean()) - border / 2) / max(height - border, 1e-9)))
    ab, cb = up_left - up_right, down_right - up_right
    cosine = float(np.dot(ab, cb) / max(np.linalg.norm(ab) * np.linalg.norm(cb), 1e-12))
    skew = min(1.0, 2.0 * abs(math.pi / 2 - math.acos(max(-1.0, min(1.0, cosine)))))
    return x, y, math.sqrt(area / (width * height)), skew


def board_coverage(corner_sets: Sequence[FloatArray], columns: int, rows: int, size: tuple[int, int]) -> BoardCoverage:
    """Coverage of the views whose inner corners are `corner_sets` ((columns*rows, 2) each)."""
    width, height = size
    params = np.array([view_parameters(c, columns, rows, size) for c in corner_sets]).reshape(-1, 4)
    bars = []
    for index, (name, span) in enumerate(BAR_RANGES.items()):
        values = params[:, index]
        low = float(values.min()) if values.size else 0.0
        high = float(values.max()) if values.size else 0.0
        floor = 0.0 if name in ("size", "skew") else low      # small or flat views earn nothing
        bars.append(CoverageBar(name, low, high, min((high - floor) / span, 1.0) if values.size else 0.0))
    points = np.concatenate([np.asarray(c, dtype=np.float64).reshape(-1, 2) for c in corner_sets]) \
        if corner_sets else np.zeros((0, 2))
    corners_seen = tuple(bool(np.any((np.abs(points[:, 0] - cu) <= CORNER_SHARE * width)
                                     & (np.abs(points[:, 1] - cv) <= CORNER_SHARE * height)))
                         for cv in (0.0, height - 1.0) for cu in (0.0, width - 1.0))
    centre = np.array([(width - 1) / 2.0, (height - 1) / 2.0])
    reach = min(float(np.max(np.linalg.norm(points - centre, axis=1)) / np.linalg.norm(centre)), 1.0) \
        if len(points) else 0.0
    columns_g, rows_g = GRID
    cells = np.zeros((rows_g, columns_g), dtype=bool)
    if len(points):
        cu = np.clip((points[:, 0] / width * columns_g).astype(int), 0, columns_g - 1)
        cv = np.clip((points[:, 1] / height * rows_g).astype(int), 0, rows_g - 1)
        cells[cv, cu] = True
    grid = tuple("".join("#" if seen else "." for seen in row) for row in cells)
    return BoardCoverage(views=len(corner_sets), bars=tuple(bars),
                         corners_seen=(corners_seen[0], corners_seen[1], corners_seen[2], corners_seen[3]),
                         reach=reach, grid=grid)
