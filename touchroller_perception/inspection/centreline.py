"""A crack's centreline: the skeleton of its region as a graph, the longest path through it (the trunk),
the side branches that leave it, and the profiles across the trunk that give the width and the depth."""
from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numpy as np
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components, dijkstra
from skimage.morphology import skeletonize

# forward neighbour offsets (row, col) and their step lengths: each edge of the 8-neighbour graph once
_OFFSETS = ((0, 1, 1.0), (1, 0, 1.0), (1, 1, math.sqrt(2.0)), (1, -1, math.sqrt(2.0)))


@dataclass(frozen=True)
class Skeleton:
    trunk: np.ndarray                 # (n, 2) float (row, col) along the longest path
    branches: list[np.ndarray]        # each (m, 2), starting at the trunk pixel it leaves from
    trunk_px: float                   # path length of the trunk, px


def _graph(skeleton: np.ndarray) -> tuple[np.ndarray, coo_matrix]:
    padded = np.pad(skeleton, 1)
    rows, cols = np.nonzero(padded)
    index = np.full(padded.shape, -1, np.int64)
    index[rows, cols] = np.arange(rows.size)
    a, b, w = [], [], []
    for dr, dc, length in _OFFSETS:
        other = index[rows + dr, cols + dc]
        has = other >= 0
        a.append(index[rows[has], cols[has]])
        b.append(other[has])
        w.append(np.full(int(has.sum()), length))
    i, j, d = np.concatenate(a), np.concatenate(b), np.concatenate(w)
    graph = coo_matrix((np.concatenate([d, d]), (np.concatenate([i, j]), np.concatenate([j, i]))),
                       shape=(rows.size, rows.size)).tocsr()
    return np.stack([rows - 1, cols - 1], axis=1).astype(np.float64), graph


def _path(predecessors: np.ndarray, end: int) -> list[int]:
    path = [end]
    while predecessors[path[-1]] >= 0:
        path.append(int(predecessors[path[-1]]))
    return path[::-1]


def trace(region: np.ndarray, min_branch_px: float) -> Skeleton | None:
    """The trunk and branches of a region's skeleton; None when the skeleton is empty."""
    skeleton = skeletonize(region.astype(bool))
    if not skeleton.any():
        return None
    points, graph = _graph(skeleton)
    n = points.shape[0]
    if n == 1:
        return Skeleton(points.copy(), [], 0.0)
    degree = np.diff(graph.indptr)
    start = int(np.flatnonzero(degree == 1)[0]) if (degree == 1).any() else 0
    dist = dijkstra(graph, indices=start)
    a = int(np.nanargmax(np.where(np.isfinite(dist), dist, -1)))
    dist, pred = dijkstra(graph, indices=a, return_predecessors=True)
    finite = np.where(np.isfinite(dist), dist, -1)
    b = int(np.argmax(finite))
    trunk = _path(pred, b)
    on_trunk = np.zeros(n, bool)
    on_trunk[trunk] = True
    branches: list[np.ndarray] = []
    rest = np.flatnonzero(~on_trunk & (finite >= 0))
    if rest.size:
        sub = graph[rest][:, rest]
        count, labels = connected_components(sub, directed=False)
        to_trunk = graph[rest][:, np.flatnonzero(on_trunk)]
        attached = np.asarray(to_trunk.sum(axis=1)).ravel() > 0
        trunk_nodes = np.flatnonzero(on_trunk)
        for label in range(count):
            members = np.flatnonzero(labels == label)
            roots = members[attached[members]]
            if roots.size == 0:
                continue
            root = int(roots[0])
            d, p = dijkstra(sub, indices=root, return_predecessors=True)
            d_members = np.where(np.isfinite(d[members]), d[members], -1)
            far = int(members[int(np.argmax(d_members))])
            local = _path(p, far)
            joint = int(trunk_nodes[to_trunk[root].indices[0]])
            length = float(d[far]) + float(graph[rest[root], joint])
            if length >= min_branch_px:
                branches.append(np.vstack([points[joint], points[rest[local]]]))
    return Skeleton(points[trunk], branches, float(dist[b]))


def smooth_path(path: np.ndarray, window: int = 5) -> np.ndarray:
    """A moving average along the path (the pixel staircase out), ends kept in place."""
    if path.shape[0] <= 2 or window < 2:
        return path.astype(np.float64)
    half = min(window // 2, (path.shape[0] - 1) // 2)
    if half < 1:
        return path.astype(np.float64)
    kernel = np.ones(2 * half + 1) / (2 * half + 1)
    padded = np.pad(path.astype(np.float64), ((half, half), (0, 0)), mode="edge")
    out = np.stack([np.convolve(padded[:, k], kernel, mode="valid") for k in range(2)], axis=1)
    out[0], out[-1] = path[0], path[-1]
    return out


def path_length(path: np.ndarray) -> float:
    return float(np.hypot(*np.diff(path, axis=0).T).sum()) if path.shape[0] > 1 else 0.0


@dataclass(frozen=True)
class Profiles:
    centre: np.ndarray        # (n, 2) (row, col) of the profile peaks: the refined centreline
    fwhm_px: np.ndarray       # (n,) full width at half the peak, NaN where a side never falls to half
    peak: np.ndarray          # (n,) the profile's peak (depth), in the residual's unit


def half_width(values: np.ndarray, k: np.ndarray, peak: np.ndarray) -> np.ndarray:
    """Per profile (a row of `values`, its peak `peak` at sample `k`), the full width where it falls to half of
    the peak, in samples: each side's crossing interpolated linearly between the samples either side of it;
    NaN where a side never falls to half, or the peak is not positive."""
    n, size = values.shape
    half = 0.5 * peak
    idx = np.arange(size)[None, :]
    below = values < half[:, None]
    right_mask = below & (idx > k[:, None])
    left_mask = below & (idx < k[:, None])
    has_right, has_left = right_mask.any(axis=1), left_mask.any(axis=1)
    r = np.argmax(right_mask, axis=1)
    l_ = size - 1 - np.argmax(left_mask[:, ::-1], axis=1)
    rr = np.arange(n)

    def crossing(i_out: np.ndarray, i_in: np.ndarray) -> np.ndarray:
        v_out, v_in = values[rr, i_out], values[rr, i_in]
        with np.errstate(divide="ignore", invalid="ignore"):
            t = np.where(v_in != v_out, (v_in - half) / (v_in - v_out), 0.5)
        return i_in + np.clip(t, 0, 1) * (i_out - i_in)

    right = crossing(r, np.maximum(r - 1, 0))
    left = crossing(l_, np.minimum(l_ + 1, size - 1))
    out: np.ndarray = np.where(has_right & has_left & (peak > 0), right - left, np.nan)
    return out


def across(depth: np.ndarray, path: np.ndarray, half_width_px: float, step: float = 0.25) -> Profiles:
    """Profiles of `depth` (a depression positive, NaN-free) across the path at each of its points: the peak
    near the path (parabola-refined), and the full width where the profile falls to half of it."""
    n = path.shape[0]
    tangent = np.gradient(smooth_path(path, 7), axis=0) if n > 1 else np.array([[0.0, 1.0]])
    norm = np.hypot(tangent[:, 0], tangent[:, 1])
    norm[norm == 0] = 1.0
    normal = np.stack([tangent[:, 1], -tangent[:, 0]], axis=1) / norm[:, None]   # (row, col) turned a quarter
    offsets = np.arange(-half_width_px, half_width_px + step / 2, step)
    rows = path[:, 0:1] + normal[:, 0:1] * offsets[None, :]
    cols = path[:, 1:2] + normal[:, 1:2] * offsets[None, :]
    source = depth if depth.dtype == np.float32 else depth.astype(np.float32)    # no copy of a whole map per crack
    values = cv2.remap(source, cols.astype(np.float32), rows.astype(np.float32),
                       cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE).astype(np.float64)
    middle = offsets.size // 2
    near = np.abs(offsets) <= 1.5
    masked = np.where(near[None, :], values, -np.inf)
    k = np.argmax(masked, axis=1)
    k = np.clip(k, 1, offsets.size - 2)
    y0, y1, y2 = (values[np.arange(n), k + d] for d in (-1, 0, 1))
    curvature = y0 - 2 * y1 + y2
    with np.errstate(divide="ignore", invalid="ignore"):
        shift = np.where(curvature < 0, 0.5 * (y0 - y2) / curvature, 0.0)
    shift = np.clip(shift, -0.5, 0.5)
    peak = y1 - 0.25 * (y0 - y2) * shift
    at = (k + shift - middle) * step
    fwhm = half_width(values, k, peak) * step
    centre = path + normal * at[:, None]
    return Profiles(centre, fwhm, peak)
