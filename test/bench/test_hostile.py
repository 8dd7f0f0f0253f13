"""The hostile bench's runner: it picks up every probe module of the package, counts held / total, and a
probe that raises did not hold."""
from __future__ import annotations

import bench.hostile as package
from bench.hostile import runner


def test_any_probe_module_in_the_package_is_run_and_counted(tmp_path, monkeypatch):
    (tmp_path / "extra_probes.py").write_text(
        "from bench.hostile.probe import Probe\n"
        "def _boom(scratch):\n"
        "    raise RuntimeError('no')\n"
        "def probes():\n"
        "    return [Probe('holds', 'extra', 'nothing', lambda scratch: None),\n"
        "            Probe('fails', 'extra', 'nothing', lambda scratch: 'something happened'),\n"
        "            Probe('raises', 'extra', 'nothing', _boom)]\n")
    monkeypatch.setattr(package, "__path__", [*package.__path__, str(tmp_path)])
    assert "extra_probes" in runner.probe_modules() and "cli" in runner.probe_modules()
    result = runner.run(areas=("extra",))
    assert (result.held, result.total) == (1, 3)
    got = {o.name: o.got for o in result.outcomes}
    assert got["fails"] == "something happened" and "RuntimeError: no" in got["raises"]
    path = runner.write(result, tmp_path / "hostile.md")
    again = runner.load(path.with_suffix(".json"))
    assert again == result and "**1 / 3 probes held**" in runner.to_markdown(again)


def test_every_probe_states_its_expectation_and_names_are_unique():
    found = runner.collect()
    assert len(found) >= 30
    assert all(p.expect and p.area and p.name for _, p in found)
