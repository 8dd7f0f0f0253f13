"""`touchroller bench`: listing, running one benchmark, refusing unknown names."""
from __future__ import annotations

from touchroller_bringup.cli import main


def test_lists_benchmarks_with_their_summaries(capsys):
    assert main(["bench", "--list"]) == 0
    out = capsys.readouterr().out
    assert "geometry_stability" in out and "Numerical stability" in out


def test_runs_a_benchmark_in_quick_mode(capfd):
    assert main(["bench", "geometry_stability", "--quick"]) == 0
    out = capfd.readouterr().out
    assert "| theta = +60 deg |" in out and "exit 0" in out


def test_unknown_benchmark_is_one_line_and_exit_2(capsys):
    assert main(["bench", "no_such_bench"]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "unknown benchmark 'no_such_bench'" in err
