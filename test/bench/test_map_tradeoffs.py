"""bench/map_tradeoffs.py: the report gets both plots (quality against compute and scan time; Δy histograms)."""
from __future__ import annotations

from types import ModuleType

import cv2

from touchroller_bringup.report import load_bench_script


def load_bench() -> ModuleType:
    return load_bench_script("map_tradeoffs")


def small_result(bench: ModuleType) -> dict:
    sweep = [{"setting": name, "ms_per_frame": 0.3 + 0.1 * i, "ssim": 0.2 if name.startswith("paper") else 0.9,
              "length_error_percent": 6.5 if name.startswith("paper") else 0.01} for i, name in enumerate(bench.SWEEP)]
    scan_times = [{"duration": d, "method": m, "ssim": 0.9 if m == "default" else 0.3,
                   "length_error_percent": 0.02 if m == "default" else 4.0}
                  for d in (5.0, 10.0, 15.0) for m in ("paper", "default")]
    table_i = {f"{variant}/{method}": {"shifts": [-3.0, -4.0, -4.0] if method == "paper" else [-3.6, -3.7, -3.8]}
               for variant in bench.SPEEDS for method in ("paper", "default")}
    return {"sweep": sweep, "sweep_duration": 10.0, "scan_times": scan_times, "table_i": table_i}


def test_figures_writes_both_plots_into_the_report_folder(tmp_path):
    bench = load_bench()
    paths = bench.figures(small_result(bench), tmp_path / "docs")
    assert [p.name for p in paths] == ["map_tradeoffs.png", "map_dy_histograms.png"]
    for path in paths:
        assert path.parent == tmp_path / "docs"
        image = cv2.imread(str(path))
        assert image is not None and image.shape[0] > 200 and image.shape[1] > 800
        assert image.std() > 10       # not a blank canvas
