"""Median and percentile of finite values, numpy's numbers without numpy's import of numpy.ma (tens of
milliseconds of a command's start-up): the world map and its latency estimate use them per frame batch."""
from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np


def median(values: Sequence[float] | np.ndarray) -> float:
    """np.median of finite values, the same number, without np.median's import of numpy.ma (tens of
    milliseconds of a command's start-up)."""
    v = np.asarray(values, np.float64).reshape(-1)
    half = len(v) // 2
    if len(v) % 2:
        return float(np.partition(v, half)[half])
    part = np.partition(v, [half - 1, half])
    return float(np.mean(part[half - 1:half + 1]))


def percentile(values: np.ndarray, q: float) -> float:
    """np.percentile(values, q) (linear interpolation, finite values): the same number, without numpy.ma."""
    v = np.sort(np.asarray(values, np.float64).reshape(-1))
    virtual = (q / 100) * (len(v) - 1)
    lo = min(max(math.floor(virtual), 0), len(v) - 1)
    hi = min(lo + 1, len(v) - 1)
    t = virtual - lo
    a, b = float(v[lo]), float(v[hi])
    return b - (b - a) * (1 - t) if t >= 0.5 else a + (b - a) * t


