"""bench/contacts_table_ii.py: the report section shows our calibration's Table II beside the paper's error sources."""
from __future__ import annotations

import importlib.util
import sys
from pathlib import Path
from types import ModuleType

import cv2
import pytest

BENCH = Path(__file__).resolve().parents[2] / "bench"


def load_bench() -> ModuleType:
    spec = importlib.util.spec_from_file_location("bench_contacts_table_ii_under_test", BENCH / "contacts_table_ii.py")
    assert spec and spec.loader
    module = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = module
    spec.loader.exec_module(module)
    return module


def test_markdown_and_figure_carry_the_our_calibration_condition(tmp_path):
    pytest.importorskip("touchroller_driver.sim")
    from touchroller_perception.localisation import TABLE_II_CAMERA, explain_paper_table, table_ii

    bench = load_bench()
    table = table_ii(taps=1, sim_conditions=("exact",), calibration_seeds=1)
    result = {"table_ii": table, "paper_fit": explain_paper_table(TABLE_II_CAMERA, starts=1), "quick": True}
    text = bench.to_markdown(result)
    worst = table["summary"]["our_calibration"]["max_cell_mean_mm"]
    assert f"Worst cell over the pooled taps: **{worst:.3f} mm**" in text
    assert "| seed | theta err (deg) |" in text and "--quick" in text
    [cells, *_] = bench.figures(result, tmp_path)
    assert cells.name == "contacts_table_ii_cells.png" and cv2.imread(str(cells)) is not None
