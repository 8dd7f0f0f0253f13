"""bench/contacts_table_ii.py: the report section shows our calibration's Table II beside the paper's error sources."""
from __future__ import annotations

from types import ModuleType

import cv2
import pytest

from touchroller_bringup.report import load_bench_script


def load_bench() -> ModuleType:
    return load_bench_script("contacts_table_ii")


def test_markdown_and_figure_carry_the_our_calibration_condition(tmp_path):
    pytest.importorskip("touchroller_driver.sim")
    from bench.table_ii import TABLE_II_CAMERA, explain_paper_table, table_ii

    bench = load_bench()
    table = table_ii(taps=1, sim_conditions=("exact",), calibration_seeds=1)
    result = {"table_ii": table, "paper_fit": explain_paper_table(TABLE_II_CAMERA, starts=1), "quick": True}
    text = bench.to_markdown(result)
    worst = table["summary"]["our_calibration"]["max_cell_mean_mm"]
    assert f"Worst cell over the pooled taps: **{worst:.3f} mm**" in text
    assert "| seed | theta err (deg) |" in text and "--quick" in text
    [cells, *_] = bench.figures(result, tmp_path)
    assert cells.name == "contacts_table_ii_cells.png" and cv2.imread(str(cells)) is not None
