"""The report's top: goals at a glance and settings per budget, computed from the sections' results."""
from __future__ import annotations

import copy
import dataclasses
import re

import pytest

from touchroller_bringup import report
from touchroller_bringup.report import load_bench_script

sim_bench = load_bench_script("sim_bench")
stability_bench = load_bench_script("geometry_stability")
dds_latency = load_bench_script("dds_latency")
dds_slow_consumer = load_bench_script("dds_slow_consumer")
PROVENANCE = load_bench_script("_common").Provenance("python -m bench.x", "test machine", "now", "0.00 0.00 0.00")


def _sweep(setting: str, ms: float, ssim: float, length: float = 0.01) -> dict:
    return {"setting": setting, "ms_per_frame": ms, "ssim": ssim, "length_error_percent": length,
            "drift_percent": abs(length)}


def _scan(duration: float, method: str, ssim: float, length: float = 0.02) -> dict:
    return {"duration": duration, "method": method, "ssim": ssim, "length_error_percent": length,
            "peak_px_per_frame": 40.0 / duration, "ms_per_frame": 0.5}


def _table_i_row(duration: float, method: str, ssim: list[float], length: list[float]) -> dict:
    return {"duration": duration, "method": method, "ssim": ssim, "length_error_percent": length}


def _stats(rms: float, worst: float) -> dict:
    return {"rms": rms, "max": worst, "n": 3}


def _calibration(second_theta_max: float = 0.07, seen_p95_max: float = 0.45, within: float = 0.95,
                 whole_d_max: float = 0.04, sim_seen_p95_max: float = 0.3):
    """A calib_bench result as its dataclasses hold it (only the figures the report reads matter)."""
    bench = report.load_bench_script("calib_bench")
    check = report.load_bench_script("calib_crosscheck")
    stats = check.Stats

    def views(n, fx, s):
        return bench.IntrinsicsRow(n, "auto", stats(fx, 2 * fx, 3), stats(0.2, 0.3, 3), stats(0.2, 0.3, 3), 0.07, s, 0)

    def presses(m, t, s):
        return bench.PressesRow(m, stats(t, 1.5 * t, 3), stats(0.5, 0.7, 3), stats(0.01, 0.013, 3), 0.06, s)

    full = bench.FullCalibration((), stats(0.04, 0.09, 3), stats(0.5, 0.7, 3), stats(0.03, 0.04, 3),
                                 stats(0.07, 0.08, 3), stats(0.06, 0.1, 3), 0.3, 0.31, 3)
    contacts = tuple(bench.ContactRow("exact sensor", camera, mean, 0.01, 0.1, 50) for camera, mean in
                     (("truth", 0.004), ("ours (seed 0)", 0.065), ("uncalibrated (theta = d = 0)", 1.8)))
    methods = tuple(check.MethodRow(model, check.OURS, stats(0.04, theta, 3), stats(0.01, 0.02, 3), (0.0, 0.0), 3)
                    for model, theta in (("simulator", 0.03), ("second renderer", second_theta_max)))
    rays = tuple(row for renderer, seen in (("second renderer", seen_p95_max), ("simulator", sim_seen_p95_max))
                 for row in (check.RayRow(renderer, "auto", stats(0.35, seen, 3), stats(9.0, 12.0, 3), "k1k2p x3", 3),
                             check.RayRow(renderer, f"{check.FLOOR} (0.03 px per axis)", stats(0.3, 0.4, 3),
                                          stats(9.0, 12.0, 3), "as auto", 0)))
    sigmas = (check.SigmaRow("second renderer", "theta", 100, within, 0.7),)
    whole = tuple(check.WholeRow(renderer, stats(0.04, 0.08, 3), stats(0.02, whole_d_max, 3), stats(0.2, 0.3, 3))
                  for renderer in ("simulator", "second renderer"))
    crosscheck = check.CrosscheckResult(3, 20, methods, rays, sigmas, whole)
    return bench.CalibBenchResult(
        quick=False, seeds=3, provenance=PROVENANCE, goals=bench.Goals(),
        intrinsics_vs_views=tuple(views(n, fx, s) for n, fx, s in ((5, 0.35, 0.02), (10, 0.27, 0.045),
                                                                    (20, 0.17, 0.09), (40, 0.10, 0.19))),
        extrinsics_vs_presses=tuple(presses(m, t, s) for m, t, s in ((2, 0.47, 0.04), (3, 0.03, 0.06),
                                                                     (10, 0.02, 0.19))),
        full=full, neglected_example=None, contacts=contacts, robustness=(), crosscheck=crosscheck)


@pytest.fixture
def results() -> dict[str, dict]:
    table_i = {
        "sweep_duration": 10.0,
        "sweep": [_sweep("cheap", 0.3, 0.90), _sweep("good", 0.8, 0.970), _sweep("costly tie", 2.0, 0.972),
                  _sweep("drifts", 0.4, 0.99, length=5.0)],
        "table_i": {f"{d:g}/{m}": _table_i_row(d, m, [0.2 if m == "paper" else s], [3.0 if m == "paper" else 0.1])
                    for d, s in ((15.0, 0.98), (10.0, 0.97), (5.0, 0.88)) for m in ("paper", "default")},
        "scan_times": [_scan(d, m, s if m == "default" else 0.2) for d, s in ((4.0, 0.7), (5.0, 0.88), (10.0, 0.97),
                                                                           (15.0, 0.98)) for m in ("paper", "default")],
        "live": {"median_ms": 0.4, "p90_ms": 0.6},
    }
    map_speed = {"quick": False, "goal_fps": 1000.0, "goal_read_ratio": 2.0,
                 "summary": {"frames": 1021, "repeats": 5, "command_fps": 1200.0, "process_fps": 900.0,
                             "read_fps": 5000.0, "read_process_fps": 2500.0, "process_read_ratio": 2.78,
                             "in_process_read_ratio": 4.17}}
    contacts = {
        "speed": [{"workload": "no contact (gaps)", "median_ms": 0.2, "contacts_per_frame": 0.0},
                  {"workload": "3 contacts (taps)", "median_ms": 0.9, "contacts_per_frame": 3.0},
                  {"workload": "rolling over fabric", "median_ms": 2.0, "contacts_per_frame": 9.0}],
        "settings": [{"setting": "paper", "median_ms": 0.9, "error_mm": 0.5, "matched": 30, "missed": 0},
                     {"setting": "colour", "median_ms": 0.95, "error_mm": 0.004, "matched": 30, "missed": 0},
                     {"setting": "colour fine", "median_ms": 1.5, "error_mm": 0.0039, "matched": 30, "missed": 0},
                     {"setting": "misses", "median_ms": 0.95, "error_mm": 0.001, "matched": 20, "missed": 10}],
    }
    calibration = _calibration()
    simulator = sim_bench.SimBenchResult(
        "surface_mapping/medium", "640x480 bgr8",
        (sim_bench.RenderRow("core only", (), 0.1, 300, 1.2, 1.2, 1.4, 830.0, 0.0),
         sim_bench.RenderRow("scene default [...]", ("noise",), 0.1, 300, 1.5, 1.5, 1.7, 650.0, 0.3)),
        700.0, 300, 200.0, ("noise",), PROVENANCE, 1, False, "0.00 0.00 0.00")
    table_ii = {"table_ii": {"summary": {"exact": {"mean_mm": 0.004, "max_cell_mean_mm": 0.007},
                                         "error_sources": {"mean_mm": 0.89, "max_cell_mean_mm": 1.18},
                                         "our_calibration": {"mean_mm": 0.34, "max_cell_mean_mm": 0.41,
                                                             "worst_seed_max_cell_mean_mm": 0.61,
                                                             "max_tap_mm": 0.62}}}}
    stability = stability_bench.StabilityResult(
        (stability_bench.StabilityCase("nominal", 100, 1.0, 1e-12, 1e-17, 1e-18, True, "NaN point, valid=False", 0.1),),
        stability_bench.NonFiniteInputs("NaN, +inf, -inf, finite", (False, False, False, True), True), 8, PROVENANCE)
    return {"table_i": table_i, "map_speed": map_speed, "contacts_speed": contacts, "calibration": calibration,
            "simulator": simulator, "table_ii": table_ii, "stability": stability}


def _rows(markdown: str, first_cell: str) -> list[list[str]]:
    return [[c.strip() for c in line.strip("|").split("|")] for line in markdown.splitlines()
            if line.startswith(f"| {first_cell}")]


def test_map_pick_is_the_best_quality_within_each_compute_budget(results):
    rows = _rows(report.settings_markdown(results), "map: compute per frame")
    picks = [row[2] for row in rows]
    # tight (0.5 ms): "drifts" is cheaper and sharper but breaks the 1 % length goal; medium: "good";
    # generous: "costly tie" is only 0.002 SSIM better, so the cheaper "good" wins
    assert picks == ["cheap", "good", "good"]
    assert "SSIM 0.970" in rows[1][3] and "0.80 ms/frame" in rows[1][3]


def test_map_budget_follows_the_measurements(results):
    results["table_i"]["sweep"][2]["ssim"] = 0.99         # now clearly better: the generous budget buys it
    picks = [row[2] for row in _rows(report.settings_markdown(results), "map: compute per frame")]
    assert picks == ["cheap", "good", "costly tie"]


def test_scan_time_budgets_are_the_papers_speeds_and_name_the_fastest_good_roll(results):
    text = report.settings_markdown(results)
    rows = _rows(text, "map: scan time")
    assert [row[1].split(":")[0] for row in rows] == ["tight", "medium", "generous"]
    assert "5 s" in rows[0][1] and "SSIM 0.880" in rows[0][3] and "paper SSIM 0.200" in rows[0][3]
    assert "Fastest roll measured that keeps SSIM >= 0.85 and length error <= 1 %: 5 s" in text


def test_contact_pick_needs_every_contact_found_and_says_when_nothing_fits(results):
    rows = _rows(report.settings_markdown(results), "contacts:")
    assert rows[0][2] == "nothing measured fits" and "cheapest: paper" in rows[0][3]   # 0.75 ms
    assert rows[1][2] == "colour"          # "misses" is more accurate on what it finds, but misses contacts
    assert rows[2][2] == "colour"          # "colour fine" is within the 10 % tie and costs more


def test_calibration_pick_meets_the_theta_goal_first(results):
    rows = _rows(report.settings_markdown(results), "calibration:")
    assert rows[0][2] == "5 chessboard views + 3 hemisphere presses"       # 0.08 s: 2 presses miss theta
    assert "(within 0.1°)" in rows[0][3]
    assert rows[2][2] == "40 chessboard views + 10 hemisphere presses"
    text = report.settings_markdown(results)
    assert "uncalibrated (theta = d = 0) 1.800 mm" in text and "0.065 mm" in text
    assert "keep theta within 0.1° on every seed: 3." in text


def test_goals_are_judged_from_the_results(results, tmp_path):
    text = report.goals_markdown(results, tmp_path)
    status = {row[0]: row[3] for row in _rows(text, "")[2:]}
    assert status["Map length (drift) error <= 1 %"] == "**met**"
    assert status["`touchroller map` >= 1000 frames/s as a whole command (a new process)"] == "**NOT met**"
    assert status["`touchroller map` >= 1000 frames/s in-process (without interpreter start)"] == "**met**"
    assert status["`touchroller map` within 2x of reading the bag alone (new processes)"] == "**NOT met**"  # 2.78x
    ours = next(k for k in status if k.startswith("Aim: sub-millimetre everywhere, whole pipeline"))
    papers = next(k for k in status if k.startswith("The same aim with the paper's calibration error"))
    assert status[ours] == "**met**" and status[papers] == "**NOT met**"   # 0.41 / 0.61 / 0.62 mm vs 1.18 mm
    one_bad_tap = copy.deepcopy(results)
    one_bad_tap["table_ii"]["table_ii"]["summary"]["our_calibration"]["max_tap_mm"] = 1.02
    status_bad = {row[0]: row[3] for row in _rows(report.goals_markdown(one_bad_tap, tmp_path), "")[2:]}
    assert status_bad[ours] == "**NOT met**"     # "everywhere" means every tap, not just the cell means
    worse = copy.deepcopy(results)
    worse["table_i"]["table_i"]["5/default"]["ssim"] = [0.80]
    status = {row[0]: row[3] for row in _rows(report.goals_markdown(worse, tmp_path), "")[2:]}
    assert status["Map SSIM vs ground truth >= 0.85 at 15 s / 10 s / 5 s (worst seed)"] == "**NOT met**"


def test_calibration_cross_check_goals_are_judged_from_the_results(results, tmp_path):
    starts = ("Calibration on both imprint models", "Whole calibration on both renderers",
              "Intrinsics on both renderers", "Calibration sigmas")

    def statuses(calibration) -> list[str]:
        rows = _rows(report.goals_markdown({**results, "calibration": calibration}, tmp_path), "")
        return [next(row[3] for row in rows if row[0].startswith(start)) for start in starts]

    met, failed = "**met**", "**NOT met**"
    assert statuses(results["calibration"]) == [met] * 4
    assert statuses(_calibration(second_theta_max=0.12)) == [failed, met, met, met]
    assert statuses(_calibration(whole_d_max=0.06)) == [met, failed, met, met]
    assert statuses(_calibration(seen_p95_max=0.6)) == [met, met, failed, met]
    assert statuses(_calibration(sim_seen_p95_max=0.6)) == [met, met, failed, met]
    assert statuses(_calibration(within=0.8)) == [met, met, met, failed]
    assert statuses(_calibration(within=1.0)) == [met, met, met, failed]       # sigmas too large


def test_map_speed_goals_follow_the_best_of_n_new_process_figures(results, tmp_path):
    summary = results["map_speed"]["summary"]
    summary.update(process_fps=1100.0, process_read_ratio=1.9)
    rows = {row[0]: row for row in _rows(report.goals_markdown(results, tmp_path), "`touchroller map`")}
    whole = rows["`touchroller map` >= 1000 frames/s as a whole command (a new process)"]
    ratio = rows["`touchroller map` within 2x of reading the bag alone (new processes)"]
    assert whole[3] == "**met**" and "1100 frames/s, best of 5 new processes" in whole[2]
    assert ratio[3] == "**met**" and "1.90x as new processes" in ratio[2] and "in-process 4.17x" in ratio[2]


def test_a_quick_map_speed_run_shows_its_figures_without_a_verdict(results, tmp_path):
    results["map_speed"]["quick"] = True
    results["map_speed"]["summary"]["frames"] = 300
    rows = [row for row in _rows(report.goals_markdown(results, tmp_path), "`touchroller map`")]
    timed = [row for row in rows if row[1] == "#5"]
    assert len(timed) == 3
    for row in timed:
        assert row[3] == "—" and "quick run, 300 frames: judged by the full run" in row[2]
    # issue 25's compressed recording: the quick run has no such section; said, not judged
    compressed = [row for row in rows if "compressed recording" in row[0]]
    assert len(compressed) == 1 and compressed[0][3] == "—" and "quick runs" in compressed[0][2]


def test_goals_without_a_section_link_their_bench_result(results, tmp_path):
    text = report.goals_markdown(results, tmp_path)
    soak = next(row for row in _rows(text, "20 000-frame soak"))
    assert "bench/dds_soak.py" in soak[2]
    dds = next(row for row in _rows(text, "DDS image -> contact"))
    assert re.search(r"dds_latency", dds[2]) and dds[3] == "see the file"


def test_a_changed_result_shows_as_unchecked_not_as_a_crash(results, tmp_path):
    del results["table_i"]["live"]
    del results["contacts_speed"]["settings"]
    goals = report.goals_markdown(results, tmp_path)
    assert "| Live map update <= 1 ms per frame | #5 | figure missing" in goals and "**not checked**" in goals
    assert "figure missing from the section's result" in report.settings_markdown(results)


def test_timing_noise_does_not_pick_a_non_default_twin(results):
    results["table_i"]["sweep"] += [_sweep("default", 0.62, 0.975), _sweep("no lateral tracking", 0.58, 0.975)]
    rows = _rows(report.settings_markdown(results), "map: compute per frame")
    assert [row[2] for row in rows][1:] == ["default", "default"]      # 0.58 vs 0.62 ms is within 10 %
    results["table_i"]["sweep"][-1]["ms_per_frame"] = 0.40                # clearly cheaper: it wins
    rows = _rows(report.settings_markdown(results), "map: compute per frame")
    assert [row[2] for row in rows] == ["no lateral tracking"] * 3


def _dds_run(transport: str, processes: int, fps: float, p50: float, p99: float, lost: float) -> object:
    stats = dds_latency.LatencyStats(p50, p99, p99 + 1.0, p50)
    return dds_latency.RateRun(transport, processes, fps, 1.0, stats, missing=0, sent=60, published=90,
                               camera_late=0, received=88.0, lost=lost, gaps=3.0 + lost, skipped=3.0, busy_skips=0.0,
                               callback_p50_ms=2.0, callback_p99_ms=4.0, busy_fraction=0.1, qos="best_effort depth 1")


def _dds(runs: list, slow: list) -> object:
    return dds_latency.DdsSection(False, "python -m bench.dds_latency", "test machine", "now", (0.0,), 1.0, 10.0,
                                  tuple(runs), tuple(slow))


def test_dds_goals_are_judged_on_the_shared_memory_runs(results, tmp_path):
    slow = dds_slow_consumer.SlowConsumerRun(2, "shm", 8.0, 50.0, 216.7, True, 480, 160,
                                             dds_latency.LatencyStats(60.0, 120.0, 130.0, 61.0), 60.0, 61.0)
    runs = [_dds_run("shm", 2, 30.0, 3.0, 12.0, 0), _dds_run("default", 2, 30.0, 4.0, 20.0, 0),
            _dds_run("shm", 2, 60.0, 3.0, 11.0, 1)]
    results["dds"] = _dds(runs, [slow])
    status = {row[0]: (row[2], row[3]) for row in _rows(report.goals_markdown(results, tmp_path), "")[2:]}
    latency = status["DDS image -> contact p50 <= 5 ms and p99 <= 15 ms at 30 Hz (shared-memory transport)"]
    assert latency[1] == "**met**" and "p99 12.00 ms" in latency[0] and "20.00" not in latency[0]
    drops = status["DDS: no drops at 60 Hz (shared-memory transport)"]
    assert drops[1] == "**NOT met**" and "1 of 60 dropped" in drops[0]
    assert status["A slow consumer skips stale frames instead of queueing them"][1] == "**met**"
    runs[2] = dataclasses.replace(runs[2], lost=float("nan"))           # the RMW did not report losses
    results["dds"] = _dds(runs, [slow])
    status = {row[0]: row[3] for row in _rows(report.goals_markdown(results, tmp_path), "")[2:]}
    assert status["DDS: no drops at 60 Hz (shared-memory transport)"] == "—"
