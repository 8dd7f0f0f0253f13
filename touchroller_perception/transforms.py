"""Rigid transforms and a time-interpolating transform buffer (what tf2's buffer does, without ROS).

`Transform` is a rotation (unit quaternion x, y, z, w) and a translation, as in
geometry_msgs/Transform: `T_parent_child` maps points given in the child frame into the parent frame.
`TransformBuffer` keeps a tree of frames (one parent per child) with time-stamped transforms, as
received on /tf (dynamic) and /tf_static, and answers `lookup(target, source, stamp_ns)`: the
transform that maps points in `source` into `target` at that time, interpolating each dynamic edge
between its two nearest samples (linear in translation, slerp in rotation). Like tf2 it does not
extrapolate: a time outside an edge's samples is an `ExtrapolationError`, a missing link a
`ConnectivityError`. `lookup_many` does the same for an array of times in one vectorised pass (what
offline mapping and the latency estimate need). No rclpy here: the ROS side converts messages.
"""
from __future__ import annotations

import math
from collections.abc import Iterable, Sequence
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

FloatArray = NDArray[np.float64]


class TransformError(LookupError):
    """A transform cannot be looked up (one line, names the frames and the time)."""


class ConnectivityError(TransformError):
    """The two frames are not connected in the tree (a frame is unknown, or in another tree)."""


class ExtrapolationError(TransformError):
    """The time lies outside the samples of an edge on the path (tf2 does not extrapolate either)."""


# -- quaternion helpers (x, y, z, w), vectorised over leading axes ------------------------------------

def quaternion_multiply(a: ArrayLike, b: ArrayLike) -> FloatArray:
    a, b = np.asarray(a, np.float64), np.asarray(b, np.float64)
    ax, ay, az, aw = np.moveaxis(a, -1, 0)
    bx, by, bz, bw = np.moveaxis(b, -1, 0)
    return np.stack([aw * bx + ax * bw + ay * bz - az * by,
                     aw * by - ax * bz + ay * bw + az * bx,
                     aw * bz + ax * by - ay * bx + az * bw,
                     aw * bw - ax * bx - ay * by - az * bz], axis=-1)


def quaternion_conjugate(q: ArrayLike) -> FloatArray:
    q = np.asarray(q, np.float64)
    return q * np.array([-1.0, -1.0, -1.0, 1.0])


def quaternion_to_matrix(q: ArrayLike) -> FloatArray:
    q = np.asarray(q, np.float64)
    x, y, z, w = q[..., 0], q[..., 1], q[..., 2], q[..., 3]
    xx, yy, zz = x * x, y * y, z * z
    xy, xz, yz, xw, yw, zw = x * y, x * z, y * z, x * w, y * w, z * w
    m = np.empty(q.shape[:-1] + (3, 3))
    m[..., 0, 0] = 1 - 2 * (yy + zz)
    m[..., 0, 1] = 2 * (xy - zw)
    m[..., 0, 2] = 2 * (xz + yw)
    m[..., 1, 0] = 2 * (xy + zw)
    m[..., 1, 1] = 1 - 2 * (xx + zz)
    m[..., 1, 2] = 2 * (yz - xw)
    m[..., 2, 0] = 2 * (xz - yw)
    m[..., 2, 1] = 2 * (yz + xw)
    m[..., 2, 2] = 1 - 2 * (xx + yy)
    return m


def _quaternion_products_to_matrix() -> tuple[FloatArray, FloatArray]:
    """(C, b): a rotation matrix's 9 entries (row-major) as `products @ C + b`, where `products` holds the 16
    products q_a q_b of a quaternion (x, y, z, w) with itself (a * 4 + b). Each entry is two products scaled
    by +-2 (exact) plus 1 on the diagonal, so this gives `quaternion_to_matrix`'s numbers bit for bit."""
    x, y, z, w = range(4)
    terms = [[(-2, y, y), (-2, z, z)], [(2, x, y), (-2, z, w)], [(2, x, z), (2, y, w)],
             [(2, x, y), (2, z, w)], [(-2, x, x), (-2, z, z)], [(2, y, z), (-2, x, w)],
             [(2, x, z), (-2, y, w)], [(2, y, z), (2, x, w)], [(-2, x, x), (-2, y, y)]]
    c = np.zeros((16, 9))
    for k, entry in enumerate(terms):
        for coefficient, a, b in entry:
            c[a * 4 + b, k] = coefficient
    return c, np.array([1.0, 0, 0, 0, 1.0, 0, 0, 0, 1.0])


_PRODUCTS_TO_MATRIX, _MATRIX_DIAGONAL = _quaternion_products_to_matrix()


def transforms_to_matrices(translations: FloatArray, rotations: FloatArray) -> FloatArray:
    """(N, 4, 4) homogeneous matrices of N translations (N, 3) and unit quaternions (N, 4): the rotations as
    `quaternion_to_matrix` gives them, in a few numpy calls (one matrix product) instead of a score: the
    mapper's lookups of a few stamps at a time pay per call, not per number."""
    n = len(rotations)
    m = np.empty((n, 4, 4))
    products = (rotations[:, :, None] * rotations[:, None, :]).reshape(n, 16)
    m[:, :3, :3] = (products @ _PRODUCTS_TO_MATRIX + _MATRIX_DIAGONAL).reshape(n, 3, 3)
    m[:, :3, 3] = translations
    m[:, 3] = (0.0, 0.0, 0.0, 1.0)
    return m


def matrix_to_quaternion(m: ArrayLike) -> FloatArray:
    """Unit quaternion of a 3x3 rotation matrix (Shepperd's method: stable for every rotation)."""
    m = np.asarray(m, np.float64)
    trace = m[0, 0] + m[1, 1] + m[2, 2]
    if trace > 0:
        s = 2.0 * math.sqrt(trace + 1.0)
        q = [(m[2, 1] - m[1, 2]) / s, (m[0, 2] - m[2, 0]) / s, (m[1, 0] - m[0, 1]) / s, 0.25 * s]
    elif m[0, 0] > m[1, 1] and m[0, 0] > m[2, 2]:
        s = 2.0 * math.sqrt(1.0 + m[0, 0] - m[1, 1] - m[2, 2])
        q = [0.25 * s, (m[0, 1] + m[1, 0]) / s, (m[0, 2] + m[2, 0]) / s, (m[2, 1] - m[1, 2]) / s]
    elif m[1, 1] > m[2, 2]:
        s = 2.0 * math.sqrt(1.0 + m[1, 1] - m[0, 0] - m[2, 2])
        q = [(m[0, 1] + m[1, 0]) / s, 0.25 * s, (m[1, 2] + m[2, 1]) / s, (m[0, 2] - m[2, 0]) / s]
    else:
        s = 2.0 * math.sqrt(1.0 + m[2, 2] - m[0, 0] - m[1, 1])
        q = [(m[0, 2] + m[2, 0]) / s, (m[1, 2] + m[2, 1]) / s, 0.25 * s, (m[1, 0] - m[0, 1]) / s]
    out = np.asarray(q, np.float64)
    return out / np.linalg.norm(out)


def slerp(a: ArrayLike, b: ArrayLike, fraction: ArrayLike) -> FloatArray:
    """Spherical interpolation from unit quaternion a (fraction 0) to b (1), the short way round."""
    a, b = np.asarray(a, np.float64), np.asarray(b, np.float64)
    f = np.asarray(fraction, np.float64)[..., None]
    dot = np.einsum("...i,...i->...", a, b)[..., None]
    if (dot < 0).any():
        b = np.where(dot < 0, -b, b)
        dot = np.abs(dot)
    if (dot > 1.0 - 1e-10).all():   # samples of a smooth motion: normalised lerp is exact to ~1e-15
        q = a + f * (b - a)
        return q / np.sqrt(np.einsum("...i,...i->...", q, q))[..., None]
    theta = np.arccos(np.clip(dot, -1.0, 1.0))
    sin = np.sin(theta)
    near = sin < 1e-9   # (almost) the same rotation: linear interpolation is exact enough
    safe = np.where(near, 1.0, sin)
    wa = np.where(near, 1.0 - f, np.sin((1.0 - f) * theta) / safe)
    wb = np.where(near, f, np.sin(f * theta) / safe)
    q = wa * a + wb * b
    return q / np.linalg.norm(q, axis=-1, keepdims=True)


def rotate(q: ArrayLike, v: ArrayLike) -> FloatArray:
    """Vectors v (..., 3) rotated by unit quaternions q (..., 4)."""
    q, v = np.asarray(q, np.float64), np.asarray(v, np.float64)
    u = q[..., :3]
    w = q[..., 3:4]
    t = 2.0 * np.cross(u, v)
    return v + w * t + np.cross(u, t)


@dataclass(frozen=True)
class Transform:
    """T_parent_child: p_parent = R p_child + t. `rotation` is a unit quaternion (x, y, z, w)."""

    translation: tuple[float, float, float] = (0.0, 0.0, 0.0)
    rotation: tuple[float, float, float, float] = (0.0, 0.0, 0.0, 1.0)

    def __post_init__(self) -> None:
        t = tuple(float(v) for v in _flat(self.translation))
        q = tuple(float(v) for v in _flat(self.rotation))
        norm = math.sqrt(sum(v * v for v in q)) if len(q) == 4 else 0.0
        if len(t) != 3 or not all(math.isfinite(v) for v in t):
            raise ValueError(f"a translation is 3 finite numbers, got {self.translation}")
        if not (math.isfinite(norm) and norm > 1e-9):
            raise ValueError(f"a rotation is a non-zero quaternion (x, y, z, w), got {self.rotation}")
        object.__setattr__(self, "translation", t)
        object.__setattr__(self, "rotation", (q[0] / norm, q[1] / norm, q[2] / norm, q[3] / norm))

    @staticmethod
    def identity() -> Transform:
        return Transform()

    @staticmethod
    def from_matrix(matrix: ArrayLike) -> Transform:
        m = np.asarray(matrix, np.float64)
        if m.shape != (4, 4):
            raise ValueError(f"expected a 4x4 matrix, got shape {m.shape}")
        return Transform(_vec3(m[:3, 3]), _quat(matrix_to_quaternion(m[:3, :3])))

    @staticmethod
    def from_rpy(translation: Sequence[float], rpy: Sequence[float]) -> Transform:
        """Fixed-axis roll (x), pitch (y), yaw (z), applied in that order (URDF's and tf2's rpy)."""
        roll, pitch, yaw = (float(v) for v in rpy)
        qx = (math.sin(roll / 2), 0.0, 0.0, math.cos(roll / 2))
        qy = (0.0, math.sin(pitch / 2), 0.0, math.cos(pitch / 2))
        qz = (0.0, 0.0, math.sin(yaw / 2), math.cos(yaw / 2))
        q = quaternion_multiply(qz, quaternion_multiply(qy, qx))
        return Transform(_vec3(translation), _quat(q))

    @staticmethod
    def from_rotation_vector(translation: Sequence[float], rotation_vector: Sequence[float]) -> Transform:
        """A UR pose (x, y, z and the axis-angle rotation vector rx, ry, rz)."""
        v = np.asarray(rotation_vector, np.float64)
        angle = float(np.linalg.norm(v))
        if angle < 1e-12:
            return Transform(_vec3(translation))
        axis = v / angle * math.sin(angle / 2)
        return Transform(_vec3(translation), (axis[0], axis[1], axis[2], math.cos(angle / 2)))

    def matrix(self) -> FloatArray:
        m = np.eye(4)
        m[:3, :3] = quaternion_to_matrix(self.rotation)
        m[:3, 3] = self.translation
        return m

    def inverse(self) -> Transform:
        q = quaternion_conjugate(self.rotation)
        return Transform(_vec3(-rotate(q, self.translation)), _quat(q))

    def __matmul__(self, other: Transform) -> Transform:
        """T_a_b @ T_b_c = T_a_c."""
        q = quaternion_multiply(self.rotation, other.rotation)
        t = rotate(self.rotation, other.translation) + np.asarray(self.translation)
        return Transform(_vec3(t), _quat(q))

    def apply(self, points: ArrayLike) -> FloatArray:
        """Points (..., 3) in the child frame -> the parent frame."""
        return rotate(self.rotation, points) + np.asarray(self.translation)

    def rpy(self) -> tuple[float, float, float]:
        m = quaternion_to_matrix(self.rotation)
        pitch = math.asin(max(-1.0, min(1.0, -float(m[2, 0]))))
        return math.atan2(float(m[2, 1]), float(m[2, 2])), pitch, math.atan2(float(m[1, 0]), float(m[0, 0]))


def interpolate(a: Transform, b: Transform, fraction: float) -> Transform:
    t = (1.0 - fraction) * np.asarray(a.translation) + fraction * np.asarray(b.translation)
    return Transform(_vec3(t), _quat(slerp(a.rotation, b.rotation, fraction)))


class _Edge:
    """The transforms of one child frame relative to its parent, sorted by stamp, in growable arrays
    (appending in time order, the usual case, is amortised O(1); lookups need no conversion)."""

    def __init__(self, parent: str, static: bool) -> None:
        self.parent = parent
        self.static = static
        self._n = 0
        self._stamps = np.zeros(16, np.int64)
        self._translations = np.zeros((16, 3))
        self._rotations = np.zeros((16, 4))
        self._matrix: FloatArray | None = None

    @property
    def stamps(self) -> NDArray[np.int64]:
        return self._stamps[:self._n]

    def add(self, stamp_ns: int, transform: Transform) -> None:
        self._matrix = None
        if self.static:
            self._n = 0
        n = self._n
        if n and stamp_ns <= self._stamps[n - 1]:
            i = int(np.searchsorted(self._stamps[:n], stamp_ns))
            if self._stamps[i] == stamp_ns:   # the same stamp again: the newer wins
                self._translations[i], self._rotations[i] = transform.translation, transform.rotation
                return
        else:
            i = n
        if n == len(self._stamps):
            self._stamps = np.concatenate([self._stamps, np.zeros(n, np.int64)])
            self._translations = np.concatenate([self._translations, np.zeros((n, 3))])
            self._rotations = np.concatenate([self._rotations, np.zeros((n, 4))])
        if i < n:   # out of order: shift the later samples up by one
            for array in (self._stamps, self._translations, self._rotations):
                array[i + 1:n + 1] = array[i:n].copy()
        self._stamps[i] = stamp_ns
        self._translations[i] = transform.translation
        self._rotations[i] = transform.rotation
        self._n = n + 1

    def prune(self, oldest_ns: int) -> None:
        """Drop samples before `oldest_ns`, keeping the one just before it (to interpolate from)."""
        i = int(np.searchsorted(self.stamps, oldest_ns)) - 1
        if i > 0 and not self.static:
            keep = self._n - i
            for array in (self._stamps, self._translations, self._rotations):
                array[:keep] = array[i:self._n].copy()
            self._n = keep

    def covers(self, stamp_ns: int) -> bool:
        """Whether `at(..., missing=True)` has a value at `stamp_ns` (within the samples; a static edge always)."""
        n = self._n
        if self.static:
            return True
        if n >= 2:
            return int(self._stamps[0]) <= stamp_ns <= int(self._stamps[n - 1])
        return n == 1 and stamp_ns == int(self._stamps[0])

    def matrix(self) -> FloatArray:
        """The 4x4 of a static edge (its one sample)."""
        if self._matrix is None:
            t, q = self._translations[0], self._rotations[0]
            self._matrix = Transform((t[0], t[1], t[2]), (q[0], q[1], q[2], q[3])).matrix()
        return self._matrix

    def arrays(self) -> tuple[NDArray[np.int64], FloatArray, FloatArray]:
        n = self._n
        return self._stamps[:n], self._translations[:n], self._rotations[:n]

    def at(self, stamps: NDArray[np.int64], child: str,
           missing: bool = False) -> tuple[FloatArray, FloatArray]:
        """(translations (N, 3), rotations (N, 4)) at each stamp, interpolated; with `missing`, NaN at
        stamps outside the samples instead of an ExtrapolationError."""
        times, translations, rotations = self.arrays()
        n = len(stamps)
        lo, hi = int(times[0]), int(times[-1])
        first, last = (int(stamps.min()), int(stamps.max())) if n else (lo, hi)
        if missing and not self.static and (first < lo or last > hi):
            inside = (stamps >= lo) & (stamps <= hi)
            trans = np.full((n, 3), np.nan)
            rots = np.full((n, 4), np.nan)
            if inside.any():
                trans[inside], rots[inside] = self.at(stamps[inside], child)
            return trans, rots
        if self.static or len(times) == 1:
            if not self.static and (first != lo or last != lo):
                raise ExtrapolationError(f"{self.parent} -> {child} has one sample (at {times[0]} ns); "
                                         f"cannot interpolate at {_first_outside(stamps, times[0], times[0])} ns")
            return np.repeat(translations[:1], n, axis=0), np.repeat(rotations[:1], n, axis=0)
        if first < lo or last > hi:
            raise ExtrapolationError(f"{self.parent} -> {child} is known over [{lo}, {hi}] ns; "
                                     f"asked for {_first_outside(stamps, lo, hi)} ns")
        i = np.clip(np.searchsorted(times, stamps, side="right") - 1, 0, len(times) - 2)
        t0, t1 = times[i], times[i + 1]
        f = (stamps - t0) / (t1 - t0).astype(np.float64)
        trans = translations[i] + f[:, None] * (translations[i + 1] - translations[i])
        return trans, slerp(rotations[i], rotations[i + 1], f)


    def at_one(self, stamp: int, child: str, missing: bool = False) -> FloatArray:
        """The 4x4 T_parent_child of a dynamic edge at one stamp (`at` for one time, in plain floats:
        the perception node looks up one frame's pose at a time); all-NaN when `missing` allows."""
        times, translations, rotations = self.arrays()
        n = len(times)
        if n == 1 and stamp == int(times[0]):
            i, f = 0, 0.0
        elif n >= 2 and int(times[0]) <= stamp <= int(times[-1]):
            i = min(max(int(np.searchsorted(times, stamp, side="right")) - 1, 0), n - 2)
            t0, t1 = int(times[i]), int(times[i + 1])
            f = (stamp - t0) / (t1 - t0)
        elif missing:
            return np.full((4, 4), np.nan)
        else:
            self.at(np.array([stamp], np.int64), child)   # raises the ExtrapolationError
            raise AssertionError("unreachable")
        ta, qa = translations[i].tolist(), rotations[i].tolist()
        if f == 0.0:
            t, q = ta, qa
        else:
            tb, qb = translations[i + 1].tolist(), rotations[i + 1].tolist()
            t = [a + f * (b - a) for a, b in zip(ta, tb, strict=True)]
            dot = sum(a * b for a, b in zip(qa, qb, strict=True))
            if dot < 0:
                qb, dot = [-v for v in qb], -dot
            if dot > 1.0 - 1e-10:   # normalised lerp, as `slerp` does for close samples
                q = [a + f * (b - a) for a, b in zip(qa, qb, strict=True)]
            else:
                theta = math.acos(min(dot, 1.0))
                sin = math.sin(theta)
                wa, wb = math.sin((1.0 - f) * theta) / sin, math.sin(f * theta) / sin
                q = [wa * a + wb * b for a, b in zip(qa, qb, strict=True)]
            norm = math.sqrt(sum(v * v for v in q))
            q = [v / norm for v in q]
        x, y, z, w = q
        return np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w), t[0]],
                         [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w), t[1]],
                         [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y), t[2]],
                         [0.0, 0.0, 0.0, 1.0]])


def _first_outside(stamps: NDArray[np.int64], lo: int, hi: int) -> int:
    outside = stamps[(stamps < lo) | (stamps > hi)]
    return int(outside[0]) if outside.size else int(stamps[0])


class TransformBuffer:
    """A tree of frames with time-stamped transforms; see the module docstring.

    cache_ns: dynamic samples older than the newest one minus this are dropped (None keeps all:
    offline, a whole recording). Static transforms never expire.
    """

    def __init__(self, cache_ns: int | None = 10_000_000_000) -> None:
        if cache_ns is not None and cache_ns <= 0:
            raise ValueError(f"cache_ns must be > 0 or None, got {cache_ns}")
        self.cache_ns = cache_ns
        self._edges: dict[str, _Edge] = {}
        self._chains: dict[tuple[str, str], tuple[list[str], list[str]]] = {}   # until the tree changes

    @property
    def frames(self) -> set[str]:
        return set(self._edges) | {edge.parent for edge in self._edges.values()}

    def set_transform(self, parent: str, child: str, stamp_ns: int, transform: Transform,
                      static: bool = False) -> None:
        """T_parent_child at `stamp_ns`. A child gets a new parent (the tree was rewired) by replacing
        its history, as tf2 does."""
        parent, child = _frame(parent), _frame(child)
        if parent == child:
            raise ValueError(f"a frame cannot be its own parent: {parent}")
        edge = self._edges.get(child)
        if edge is None or edge.parent != parent or edge.static != static:
            edge = self._edges[child] = _Edge(parent, static)
            self._chains.clear()
        edge.add(int(stamp_ns), transform)
        if self.cache_ns is not None and not static:
            edge.prune(int(edge.stamps[-1]) - self.cache_ns)

    def parent(self, child: str) -> str | None:
        edge = self._edges.get(_frame(child))
        return None if edge is None else edge.parent

    def time_range(self, child: str) -> tuple[int, int] | None:
        """(first, last) stamp of the child's dynamic transforms (None: unknown or static)."""
        edge = self._edges.get(_frame(child))
        if edge is None or edge.static or not len(edge.stamps):
            return None
        return int(edge.stamps[0]), int(edge.stamps[-1])

    def _path(self, frame: str) -> list[str]:
        path = [frame]
        while frame in self._edges:
            frame = self._edges[frame].parent
            if frame in path:
                raise ConnectivityError(f"the frames form a loop at {frame}")
            path.append(frame)
        return path

    def _chain(self, target: str, source: str) -> tuple[list[str], list[str]]:
        """(frames from source up to the common ancestor, frames from target up to it), ancestors excluded."""
        cached = self._chains.get((target, source))
        if cached is not None:
            return cached
        chain = self._find_chain(target, source)
        self._chains[(target, source)] = chain
        return chain

    def _find_chain(self, target: str, source: str) -> tuple[list[str], list[str]]:
        target, source = _frame(target), _frame(source)
        known = self.frames
        for name in (target, source):
            if name not in known:
                raise ConnectivityError(f"frame {name} does not exist (known: {', '.join(sorted(known)) or 'none'})")
        up_source, up_target = self._path(source), self._path(target)
        common = next((f for f in up_source if f in set(up_target)), None)
        if common is None:
            raise ConnectivityError(f"{source} and {target} are not connected (roots {up_source[-1]} and "
                                    f"{up_target[-1]})")
        return up_source[:up_source.index(common)], up_target[:up_target.index(common)]

    def latest_common_stamp(self, target: str, source: str) -> int | None:
        """The newest time at which every dynamic edge between the frames has data (None: all static)."""
        up_source, up_target = self._chain(target, source)
        ends = [int(self._edges[f].stamps[-1]) for f in up_source + up_target if not self._edges[f].static]
        return min(ends) if ends else None

    def covers(self, target: str, source: str, stamp_ns: int) -> bool:
        """Whether `lookup_many(target, source, [stamp_ns], missing=True)` finds the transform (no NaN): the
        frames are connected and every moving edge between them has samples around the stamp. Nothing is
        interpolated: a caller that only asks whether TF has reached a time pays for no lookup."""
        try:
            up_source, up_target = self._chain(target, source)
        except TransformError:
            return False
        return all(self._edges[child].covers(stamp_ns) for child in up_source + up_target)

    def can_transform(self, target: str, source: str, stamp_ns: int | None = None) -> bool:
        try:
            self.lookup(target, source, stamp_ns)
        except TransformError:
            return False
        return True

    def lookup(self, target: str, source: str, stamp_ns: int | None = None) -> Transform:
        """T_target_source at `stamp_ns` (None: the latest time all edges have)."""
        if stamp_ns is None:
            stamp_ns = self.latest_common_stamp(target, source) or 0
        translation, rotation = self._compose(target, source, np.asarray([int(stamp_ns)], np.int64))
        return Transform(_vec3(translation[0]), _quat(rotation[0]))

    def lookup_many(self, target: str, source: str, stamps_ns: Iterable[int], missing: bool = False) -> FloatArray:
        """T_target_source at each stamp as (N, 4, 4) matrices; with `missing`, all-NaN matrices at the
        stamps some edge has no data for (instead of an ExtrapolationError). Static edges are composed
        once, so a chain with one moving edge costs one interpolation and two matrix products."""
        stamps = np.asarray(list(stamps_ns) if not isinstance(stamps_ns, np.ndarray) else stamps_ns, np.int64)
        stamps = stamps.reshape(-1)
        up_source, up_target = self._chain(target, source)
        common_source = self._chain_matrices(up_source, stamps, missing)
        if not up_target:   # the target is the common ancestor (a lookup in the world frame)
            out = common_source
            return np.broadcast_to(out, (len(stamps), 4, 4)).copy() if out.ndim == 2 else out
        common_target = self._chain_matrices(up_target, stamps, missing)
        inverse = np.zeros_like(common_target)
        rotation_t = np.swapaxes(common_target[..., :3, :3], -1, -2)
        inverse[..., :3, :3] = rotation_t
        inverse[..., :3, 3] = -np.einsum("...ij,...j->...i", rotation_t, common_target[..., :3, 3])
        inverse[..., 3, 3] = 1.0
        out = np.matmul(inverse, common_source)
        if out.ndim == 2:
            out = np.broadcast_to(out, (len(stamps), 4, 4)).copy()
        return out

    def _chain_matrices(self, frames: list[str], stamps: NDArray[np.int64], missing: bool) -> FloatArray:
        """T_common_frame0 for the path frames[0] -> ... -> the common ancestor: (4, 4) when all edges are
        static, else (N, 4, 4)."""
        out: FloatArray | None = None   # None: the identity
        for child in frames:
            edge = self._edges[child]
            if edge.static:
                out = edge.matrix() if out is None else edge.matrix() @ out
                continue
            if len(stamps) == 1:
                one = edge.at_one(int(stamps[0]), child, missing)[None]
                out = one if out is None else np.matmul(one, out)
                continue
            m = transforms_to_matrices(*edge.at(stamps, child, missing))
            out = m if out is None else np.matmul(m, out)
        return np.eye(4) if out is None else out

    def _compose(self, target: str, source: str, stamps: NDArray[np.int64],
                 missing: bool = False) -> tuple[FloatArray, FloatArray]:
        up_source, up_target = self._chain(target, source)
        n = len(stamps)
        # T_common_source: walk up from the source, composing parent-of-each on the left
        t_cs, q_cs = np.zeros((n, 3)), np.tile([0.0, 0.0, 0.0, 1.0], (n, 1))
        for child in up_source:
            t, q = self._edges[child].at(stamps, child, missing)
            t_cs, q_cs = rotate(q, t_cs) + t, quaternion_multiply(q, q_cs)
        t_ct, q_ct = np.zeros((n, 3)), np.tile([0.0, 0.0, 0.0, 1.0], (n, 1))
        for child in up_target:
            t, q = self._edges[child].at(stamps, child, missing)
            t_ct, q_ct = rotate(q, t_ct) + t, quaternion_multiply(q, q_ct)
        # T_target_source = inverse(T_common_target) T_common_source
        q_tc = quaternion_conjugate(q_ct)
        return rotate(q_tc, t_cs - t_ct), quaternion_multiply(q_tc, q_cs)


def _flat(values: ArrayLike) -> Sequence[float]:
    """Numbers as a flat sequence (a tuple or list of numbers as it is, else through numpy)."""
    if isinstance(values, (tuple, list)) and all(isinstance(v, (int, float)) for v in values):
        return values
    return np.asarray(values, np.float64).reshape(-1).tolist()


def _vec3(values: ArrayLike) -> tuple[float, float, float]:
    x, y, z = (float(v) for v in np.asarray(values, np.float64).reshape(3))
    return x, y, z


def _quat(values: ArrayLike) -> tuple[float, float, float, float]:
    x, y, z, w = (float(v) for v in np.asarray(values, np.float64).reshape(4))
    return x, y, z, w


def _frame(name: str) -> str:
    """tf2 frame ids carry no leading slash."""
    name = str(name).strip().lstrip("/")
    if not name:
        raise ValueError("a frame id must not be empty")
    return name
