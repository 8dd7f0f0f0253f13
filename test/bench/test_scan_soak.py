"""bench/scan_soak.py: growth less the world map's own, and steadiness, from the samples (no scan here)."""
from __future__ import annotations

import pytest

from touchroller_bringup.report import load_bench_script


def test_the_maps_own_growth_is_taken_out_and_a_leak_is_not():
    bench = load_bench_script("scan_soak")
    # 20 MB per 1000 frames of map, 3 MB per 1000 of something else; 10 frames/s throughout
    samples = [bench.Sample(k * 10.0, k * 100, 300.0 + k * 0.1 * 23, k * 0.1 * 20) for k in range(40)]
    slope, raw, first, last = bench.summarise(samples, 500)
    assert slope == pytest.approx(3.0) and raw == pytest.approx(23.0)
    assert first == pytest.approx(10.0) and last == pytest.approx(10.0)
    assert all(v != v for v in bench.summarise(samples[:3], 0))   # too few samples: NaN
