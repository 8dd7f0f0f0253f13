"""bench/map_speed.py: the report section's figures and goal verdicts come from the measured times."""
from __future__ import annotations

import sys
from types import ModuleType

import pytest

from touchroller_bringup.report import load_bench_script


def load_bench() -> ModuleType:
    return load_bench_script("map_speed")


def fake_result(bench: ModuleType, quick: bool, command_process_s: float, read_process_s: float = 0.5,
                frames: int = 1000) -> dict:
    """A result as `run` returns it, with chosen wall times (no timing here: the verdicts are under test)."""
    speed = {"frames": frames, "command": "/venv/bin/touchroller map BAG --out map.png",
             "read_s": 0.2, "command_s": 0.6, "read_process_s": read_process_s, "command_process_s": command_process_s,
             "read_cpu_s": 0.2, "command_cpu_s": 0.8, "read_process_cpu_s": 0.4, "command_process_cpu_s": 1.0}
    result = {"provenance": {"command": ".venv/bin/python bench/map_speed.py", "machine": "test machine",
                             "measured": "now", "loadavg": "0.00 0.00 0.00"},
              "quick": quick, "goal_fps": bench.GOAL_FPS, "goal_read_ratio": bench.GOAL_READ_RATIO,
              "bag_frames": frames, "bag_mb": 900.0, "repeats": 5, "speed": speed, "took_s": 30.0,
              "loadavg_after": "0.00 0.00 0.00",
              "imports": {"imports_s": 0.2, "interpreter_s": 0.05, "heavy_loaded": [], "top_imports_ms": {"cv2": 130}},
              "stages": {"band_ms": 0.25, "push_band_ms": 0.3, "finalise_png_ms": 8.0, "frames": 300}}
    result["summary"] = bench.summary(result)
    return result


def test_summary_is_frames_over_best_times():
    bench = load_bench()
    m = fake_result(bench, False, command_process_s=0.8, read_process_s=0.5)["summary"]
    assert m["process_fps"] == pytest.approx(1250.0) and m["command_fps"] == pytest.approx(1000 / 0.6)
    assert m["process_read_ratio"] == pytest.approx(1.6) and m["in_process_read_ratio"] == pytest.approx(3.0)


@pytest.mark.parametrize(("command_process_s", "fps_verdict", "ratio_verdict"),
                         [(0.8, "**met**", "**met**"),            # 1250 frames/s, 1.6x
                          (1.2, "**NOT met**", "**NOT met**")])   # 833 frames/s, 2.4x
def test_full_run_judges_the_new_process_figures(command_process_s, fps_verdict, ratio_verdict):
    bench = load_bench()
    text = bench.to_markdown(fake_result(bench, False, command_process_s))
    goals = text.split("### Goals", 1)[1].strip().splitlines()
    assert goals[0].startswith("- >= 1000 frames/s as a whole command") and fps_verdict in goals[0]
    assert goals[1].startswith("- Within 2x of reading the bag")
    assert goals[1].split(" as new")[0].endswith(ratio_verdict)
    assert "Command: `.venv/bin/python bench/map_speed.py`" in text and "test machine" in text


def test_quick_run_shows_the_figures_without_a_verdict():
    bench = load_bench()
    text = bench.to_markdown(fake_result(bench, True, command_process_s=0.6, frames=300))
    goals = text.split("### Goals", 1)[1]
    assert "500 frames/s" in goals and "not judged on this quick run" in goals
    assert "met**" not in goals
    # the table has the four timed rows; the quick run has no run without a bytecode cache
    assert text.count("\n| ") == 5 and "PYTHONDONTWRITEBYTECODE" not in text


def test_cli_refuses_a_bag_without_frames(capsys):
    with pytest.raises(SystemExit) as exit_info:
        load_bench().main(["--frames", "0"])
    assert exit_info.value.code == 2 and "--frames and --repeats must be >= 1" in capsys.readouterr().err


@pytest.mark.parametrize(("argv", "written", "untouched"), [(["--quick"], "quick/map_speed.md", "map_speed.md"),
                                                           ([], "map_speed.md", "quick/map_speed.md")])
def test_a_quick_run_never_overwrites_the_committed_full_figures(monkeypatch, tmp_path, argv, written, untouched):
    bench = load_bench()
    monkeypatch.setattr(sys.modules["bench._common"], "RESULTS", tmp_path)  # where results_path() writes
    monkeypatch.setattr(bench, "run", lambda quick, frames, repeats: fake_result(bench, quick, 0.8))
    assert bench.main(argv) == 0
    assert (tmp_path / written).is_file() and (tmp_path / written).with_suffix(".json").is_file()
    assert not (tmp_path / untouched).exists()


@pytest.mark.parametrize("split", [True, False])
def test_the_world_section_splits_the_cpu_by_process_when_measured(split):
    bench = load_bench()
    result = fake_result(bench, False, command_process_s=0.8)
    world = {"frames": 820, "bag_mb": 757.0, "repeats": 5, "read_s": 0.43, "map_s": 0.60, "read_cpu_s": 0.42,
             "map_cpu_s": 0.9, "read_ratio": 0.60 / 0.43, "cpu_ratio": 0.9 / 0.42, "map_fps": 820 / 0.60}
    if split:   # results recorded before the split have no such keys: the section is rendered without it
        world.update({"mapping_cpu_s": 0.612, "reader_cpu_s": 0.298})
    text = bench.to_markdown({**result, "goal_world_ratio": bench.GOAL_WORLD_RATIO, "world": world})
    section = text.split("### The world map (issue 22)", 1)[1]
    assert ("the mapping process 0.612 s" in section and "its forked reader 0.298 s" in section) == split
    assert "Within 1.5x of reading the bag (new processes): **met** (1.40x)" in section
