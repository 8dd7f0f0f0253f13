"""A printed chessboard held in front of the bare camera (intrinsic calibration, Zhang's method).

The board is a plane; for each output pixel the undistorted normalised ray (precomputed once with
`CameraModel.undistort_normalised`, so the lens distortion is the geometry module's) is intersected
with the board through the inverse homography, and the board texture is sampled with `cv2.remap`.
`pattern_size` counts inner corners (OpenCV's convention): 7x7 inner corners = 8x8 squares.
"""
from __future__ import annotations

import math
from collections.abc import Iterator
from typing import TYPE_CHECKING

import cv2
import numpy as np

from touchroller_perception.geometry import CameraModel

if TYPE_CHECKING:
    from touchroller_driver.sim.scene import Scene

_TEXELS_PER_SQUARE = 48


class ChessboardRenderer:
    def __init__(self, camera: CameraModel, scene: Scene, rng: np.random.Generator) -> None:
        m = scene.motion
        self.camera = camera
        self.pattern_size = tuple(int(v) for v in m.get("pattern_size", [7, 7]))
        self.square = float(m.get("square_size", 1.2e-2))
        self.distance = tuple(float(v) for v in m.get("distance", [0.14, 0.26]))
        self.max_tilt = math.radians(float(m.get("max_tilt_deg", 35.0)))
        # the board (with its white margin) stays inside this central share of the image in each direction
        self.region = float(m.get("region", 1.0))
        if not 0.1 <= self.region <= 1.0:
            raise ValueError(f"chessboard: motion.region must be in [0.1, 1], got {self.region}")
        self.paper, self.ink, self.wall = (float(v) for v in m.get("levels", [215.0, 30.0, 90.0]))
        cols, rows = self.pattern_size[0] + 1, self.pattern_size[1] + 1    # squares
        margin = 1
        self.margin = margin
        tex = np.full(((rows + 2 * margin) * _TEXELS_PER_SQUARE, (cols + 2 * margin) * _TEXELS_PER_SQUARE),
                      self.paper, np.float32)
        for r in range(rows):
            for c in range(cols):
                if (r + c) % 2 == 0:
                    y0 = (r + margin) * _TEXELS_PER_SQUARE
                    x0 = (c + margin) * _TEXELS_PER_SQUARE
                    tex[y0:y0 + _TEXELS_PER_SQUARE, x0:x0 + _TEXELS_PER_SQUARE] = self.ink
        self.texture = cv2.GaussianBlur(tex, (0, 0), 0.6)
        self.texel = self.square / _TEXELS_PER_SQUARE
        # board origin (first inner corner) sits `margin + 1` squares in from the texture's corner
        self.origin_texel = (margin + 1) * _TEXELS_PER_SQUARE
        H, W = camera.height, camera.width
        # a pixel integrates the light over its area: `supersample`^2 rays per pixel, averaged (one ray
        # per pixel point-samples the board's edges, which moves detected corners by ~0.1 px)
        self.supersample = int(m.get("supersample", 3))
        if not 1 <= self.supersample <= 8:
            raise ValueError(f"chessboard: motion.supersample must be in [1, 8], got {self.supersample}")
        s = self.supersample
        offsets = (np.arange(s) + 0.5) / s - 0.5
        us = (np.arange(W, dtype=np.float64)[:, None] + offsets[None, :]).ravel()
        vs = (np.arange(H, dtype=np.float64)[:, None] + offsets[None, :]).ravel()
        uu, vv = np.meshgrid(us, vs)
        xn, yn, valid = camera.undistort_normalised(np.stack([uu, vv], axis=-1))
        self._rays = np.stack([np.where(valid, xn, 0.0), np.where(valid, yn, 0.0), valid.astype(np.float64)], -1)
        small = rng.standard_normal((3, 4)).astype(np.float32)
        self._light = 1.0 + 0.12 * cv2.resize(small, (W, H), interpolation=cv2.INTER_CUBIC) / max(
            float(np.abs(small).max()), 1e-6)

    def object_points(self) -> np.ndarray:
        """Inner corners in the board frame (N, 3), row-major as cv2.findChessboardCorners orders them."""
        nx, ny = self.pattern_size
        grid = np.array([(i * self.square, j * self.square, 0.0) for j in range(ny) for i in range(nx)])
        return grid

    def corner_pixels(self, rvec: np.ndarray, tvec: np.ndarray) -> np.ndarray:
        """True pixel positions of the inner corners through the geometry module's distortion model."""
        R, _ = cv2.Rodrigues(np.asarray(rvec, np.float64))
        pc = self.object_points() @ R.T + np.asarray(tvec, np.float64)
        uv, _ = self.camera.project_normalised(pc[:, 0] / pc[:, 2], pc[:, 1] / pc[:, 2])
        return uv

    def poses(self, count: int, rng: np.random.Generator) -> Iterator[tuple[np.ndarray, np.ndarray]]:
        """Varied board poses that keep the whole board in view, or inside the central `region` of
        the image (rejection sampling)."""
        nx, ny = self.pattern_size
        centre = np.array([(nx - 1) * self.square / 2.0, (ny - 1) * self.square / 2.0, 0.0])
        half = (np.array([nx + 1, ny + 1]) / 2.0 + self.margin) * self.square
        outline = np.array([[-half[0], -half[1], 0], [half[0], -half[1], 0], [half[0], half[1], 0],
                            [-half[0], half[1], 0]]) + centre
        produced = 0
        attempts = 0
        while produced < count:
            attempts += 1
            if attempts > 1000 * count:
                raise ValueError("chessboard: cannot fit the board in view; reduce square_size or raise distance")
            tilt = rng.uniform(-self.max_tilt, self.max_tilt, size=2)
            spin = rng.uniform(-math.radians(20.0), math.radians(20.0))
            R = _rot_z(spin) @ _rot_y(tilt[1]) @ _rot_x(tilt[0])
            distance = rng.uniform(*self.distance)
            shift = rng.uniform(-0.25, 0.25, size=2) * distance * self.region
            tvec = np.array([shift[0], shift[1], distance]) - R @ centre
            pc = outline @ R.T + tvec
            if np.any(pc[:, 2] <= 0.02):
                continue
            uv, ok = self.camera.project_normalised(pc[:, 0] / pc[:, 2], pc[:, 1] / pc[:, 2])
            if not ok.all() or not self.camera.in_image(uv, margin=8.0).all() or not self._in_region(uv):
                continue
            rvec, _ = cv2.Rodrigues(R)
            produced += 1
            yield rvec.ravel(), tvec

    def _in_region(self, uv: np.ndarray) -> bool:
        size = np.array([self.camera.width, self.camera.height], dtype=np.float64)
        lo, hi = size * (0.5 - self.region / 2), size * (0.5 + self.region / 2)
        return bool(np.all((uv >= lo) & (uv <= hi)))

    def render(self, rvec: np.ndarray, tvec: np.ndarray) -> np.ndarray:
        R, _ = cv2.Rodrigues(np.asarray(rvec, np.float64))
        H_board_to_norm = np.column_stack([R[:, 0], R[:, 1], np.asarray(tvec, np.float64)])
        inv = np.linalg.inv(H_board_to_norm)
        board = self._rays @ inv.T          # homogeneous board coords per pixel (rays with w=0 are invalid)
        w = board[..., 2]
        ahead = (w > 1e-12) & (self._rays[..., 2] > 0)
        with np.errstate(divide="ignore", invalid="ignore"):
            bx = np.where(ahead, board[..., 0] / w, -1e3)
            by = np.where(ahead, board[..., 1] / w, -1e3)
        mx = (bx / self.texel + self.origin_texel - 0.5).astype(np.float32)
        my = (by / self.texel + self.origin_texel - 0.5).astype(np.float32)
        grey = cv2.remap(self.texture, mx, my, cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT,
                         borderValue=self.wall)
        if self.supersample > 1:
            grey = cv2.resize(grey, (self.camera.width, self.camera.height), interpolation=cv2.INTER_AREA)
        grey = cv2.convertScaleAbs(grey * self._light)
        return cv2.merge([grey, grey, grey])


def _rot_x(a: float) -> np.ndarray:
    c, s = math.cos(a), math.sin(a)
    return np.array([[1, 0, 0], [0, c, -s], [0, s, c]])


def _rot_y(a: float) -> np.ndarray:
    c, s = math.cos(a), math.sin(a)
    return np.array([[c, 0, s], [0, 1, 0], [-s, 0, c]])


def _rot_z(a: float) -> np.ndarray:
    c, s = math.cos(a), math.sin(a)
    return np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]])
