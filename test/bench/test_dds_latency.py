"""bench/dds_latency.py: the report section renders every figure of a tiny real run over DDS."""
from __future__ import annotations

import math
from types import ModuleType

import pytest

from touchroller_bringup.report import load_bench_script


def load_bench() -> ModuleType:
    return load_bench_script("dds_latency")


def test_prelude_rejects_an_unknown_reliability():
    with pytest.raises(ValueError, match="BEST_EFFORT or RELIABLE"):
        load_bench().image_qos_parameters(2, "SOMETIMES")


@pytest.mark.ros
@pytest.mark.slow
def test_a_real_run_is_accounted_for_and_rendered_whole():
    pytest.importorskip("rclpy")
    dds = load_bench()
    # one second at 60 Hz with the perception node in its own process and a non-default image QoS
    row = dds.measure("shm", 2, 60.0, 1.0, depth=2, reliability="RELIABLE")

    assert row.qos == "reliable depth 2"           # the override reached the perception node
    assert row.sent == 60 and row.published == 60 + dds.REFERENCE_FRAMES
    assert 0 < row.received <= row.published
    # every frame between the first and last processed one was either processed or is a counted gap
    assert row.received + row.gaps <= row.published
    assert math.isfinite(row.lost) and row.lost >= 0   # the RMW reports lost samples
    assert row.skipped == max(0, row.gaps - row.lost)
    assert 0 <= row.busy_skips <= row.gaps
    assert 0 < row.busy_fraction < 1
    assert 0 < row.callback_p50_ms <= row.callback_p99_ms
    assert row.sent - row.missing > 0 and 0 < row.stats.p50 <= row.stats.max
    assert row.dropped == row.lost + row.camera_late

    result = dds.DdsSection(False, "python bench/dds_latency.py (test)", dds.machine(), "today", (0.0,), 1.0, 1.0,
                            (row,))
    text = dds.to_markdown(result)
    header, _, data = (line for line in text.splitlines() if line.startswith("| transport") or
                       line.startswith("|---") or line.startswith("| shm"))
    cells = [cell.strip() for cell in data.strip("|").split("|")]
    assert len(cells) == len(header.strip("|").split("|"))
    assert cells[:5] == ["shm", "2", "reliable depth 2", "60", "60"]
    assert "n/a" not in cells and all(cells)
    assert cells[-1] == dds.latency_goal(row)
