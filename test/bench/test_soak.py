"""bench/soak.py: growth, steadiness and the report's goal verdicts come from the samples (no processes here)."""
from __future__ import annotations

from types import ModuleType

import numpy as np
import pytest

from touchroller_bringup.report import GOALS, load_bench_script


def load_bench() -> ModuleType:
    return load_bench_script("soak")


def fake_result(bench: ModuleType, frames: int, mb_per_1000: float, late_ms: float) -> object:
    """A run whose perception RSS grows `mb_per_1000` MB per 1000 frames after warm-up and whose time per
    frame goes from 5 ms to `late_ms` ms along it."""
    warmup = min(5000, frames // 2)
    samples = []
    for k in range(41):
        processed = frames * k // 40
        grown = max(processed - warmup, 0) / 1000.0 * mb_per_1000
        ms = 5.0 + (late_ms - 5.0) * k / 40
        samples.append(bench.Sample(2.0 * k, processed, processed + 50, 300.0 + grown, 166.0, ms, 0, 0, "ok"))
    samples = tuple(samples)
    x = np.array([s.processed for s in samples], float)
    memory = (bench.trend(bench.PERCEPTION, x, np.array([s.perception_mb for s in samples]), warmup),
              bench.trend(bench.CAMERA, x, np.array([s.camera_mb for s in samples]), warmup))
    first_ms, last_ms, first_fps, last_fps = bench.quarters(samples, warmup)
    stamp = bench.Provenance(".venv/bin/python -m bench.soak", "test machine", "now", "0.00 0.00 0.00")
    return bench.SoakResult(stamp, frames < bench.FRAMES, frames, 3.0, warmup, samples, memory, 80.0, first_ms,
                            last_ms, first_fps, last_fps, ("ok",), (0, 0), "0.00 0.00 0.00")


def verdicts(result) -> list[bool | None]:
    return [goal.measure(result)[1] for goal in GOALS if goal.section == "soak"]


def test_growth_is_the_slope_after_warm_up():
    bench = load_bench()
    flat, leaking = fake_result(bench, 54_000, 0.0, 5.0), fake_result(bench, 54_000, 20.0, 5.0)
    assert flat.perception.slope_mb_per_1000 == pytest.approx(0.0, abs=1e-9)
    assert leaking.perception.slope_mb_per_1000 == pytest.approx(20.0, rel=1e-6)
    assert flat.memory_met and not leaking.memory_met
    assert verdicts(flat) == [True, True] and verdicts(leaking) == [False, True]


def test_a_node_that_slows_down_is_not_steady():
    bench = load_bench()
    slowing = fake_result(bench, 54_000, 0.0, 40.0)
    assert slowing.steady > bench.GOAL_STEADY and not slowing.steady_met
    assert verdicts(slowing) == [True, False]
    assert "NOT met" in bench.to_markdown(slowing)


def test_a_short_run_shows_its_figures_without_a_verdict():
    bench = load_bench()
    short = fake_result(bench, bench.QUICK_FRAMES, 0.0, 5.0)
    assert verdicts(short) == [None, None]
    assert all("judged by a run of 54 000" in goal.measure(short)[0] for goal in GOALS if goal.section == "soak")
    text = bench.to_markdown(short)
    assert "| perception |" in text and "Command: `" in text
