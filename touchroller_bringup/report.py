"""The evidence report, `docs/RESULTS.md`: every number in it is produced by the run that writes it.

A section is a benchmark script in the checkout's `bench/` folder exposing
`run(quick: bool) -> dict` and `to_markdown(result: dict) -> str`, and optionally
`figures(result: dict, out_dir: Path) -> list[Path]` for PNG plots written beside the report.
A section that fails makes the whole report fail: a report with a missing table is not written.
"""
from __future__ import annotations

import importlib.util
import os
import platform
import subprocess
import sys
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from types import ModuleType

from touchroller_bringup.errors import UserError
from touchroller_bringup.paths import checkout_dir


@dataclass(frozen=True)
class Section:
    key: str
    title: str
    script: str          # bench/<script>.py
    intro: str


SECTIONS: tuple[Section, ...] = (
    Section("table_i", "Surface mapping: the paper's Table I reproduced", "map_tradeoffs",
            "An 8 cm x 11 cm fabric rolled in 15 s, 10 s and 5 s in the simulator; map quality against the "
            "simulator's ground-truth surface for the paper's stitching (integer Δy, MAE) and ours, and what "
            "map accuracy costs in compute per frame and in scan time."),
    Section("table_ii", "Contact localisation: the paper's Table II reproduced", "contacts_table_ii",
            "The 3-stick solid tapped at 5 central angles x 3 axial positions in the simulator, with the paper's "
            "error sources modelled; mean ± std of the Euclidean error in mm per cell, beside the paper's."),
    Section("contacts_speed", "Contact detection: accuracy against time", "contacts_bench",
            "Detection + localisation per 640x480 frame, and contact error against detector settings."),
    Section("calibration", "Calibration: accuracy against effort", "calib_bench",
            "theta, d and reprojection error against the number of calibration images and solve time, and the "
            "contact error that remains after calibrating on simulated frames."),
    Section("coverage", "Coverage: a flat sensor by press–lift–shift against one roll", "coverage",
            "Presses and seconds to cover 8 x 11 cm with a flat 1.6 x 1.2 cm sensor, timed from the arm's speed and "
            "acceleration limits, against one roll (the paper: 49 presses, 196 s vs 10 s)."),
    Section("simulator", "Simulator speed and the cost of each effect", "sim_bench",
            "Frames per second of the renderer for the mapping scene at 640x480 on one core, and each effect's cost."),
    Section("stability", "Numerical stability of the camera model", "geometry_stability",
            "The hard cases the property-based tests cover, and what the code returns there."),
)


def machine_description() -> str:
    cpu = platform.processor() or platform.machine()
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                cpu = line.split(":", 1)[1].strip()
                break
    except OSError:
        pass
    return f"{cpu}, {os.cpu_count()} cores, Python {platform.python_version()}, {platform.system()} {platform.release()}"


def _load(script: str) -> ModuleType:
    path = checkout_dir() / "bench" / f"{script}.py"
    if not path.is_file():
        raise UserError(f"report section needs {path.relative_to(checkout_dir())}, which is missing")
    spec = importlib.util.spec_from_file_location(f"bench_{script}", path)
    assert spec and spec.loader
    module = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = module      # dataclasses in a bench script look their module up here
    spec.loader.exec_module(module)
    for name in ("run", "to_markdown"):
        if not callable(getattr(module, name, None)):
            raise UserError(f"bench/{script}.py has no {name}() for the report")
    return module


def _commit() -> str:
    try:
        return subprocess.run(["git", "rev-parse", "--short", "HEAD"], cwd=checkout_dir(), capture_output=True,
                              text=True, check=True).stdout.strip()
    except (OSError, subprocess.CalledProcessError):
        return "unknown"


def build_report(out: Path, quick: bool, only: tuple[str, ...] = (),
                 progress: Callable[[str], None] = print) -> dict[str, dict]:
    """Run the sections and write the report to `out` (Markdown) with figures beside it."""
    sections = [s for s in SECTIONS if not only or s.key in only]
    unknown = set(only) - {s.key for s in SECTIONS}
    if unknown:
        raise UserError(f"unknown report section {sorted(unknown)[0]!r} (sections: {', '.join(s.key for s in SECTIONS)})")
    modules = {s.key: _load(s.script) for s in sections}      # fail before spending minutes
    out.parent.mkdir(parents=True, exist_ok=True)
    started = time.perf_counter()
    results: dict[str, dict] = {}
    body: list[str] = []
    for section in sections:
        progress(f"report: {section.key} ({'quick' if quick else 'full'}) ...")
        t0 = time.perf_counter()
        module = modules[section.key]
        result = module.run(quick=quick)
        seconds = time.perf_counter() - t0
        results[section.key] = result
        body += [f"## {section.title}", "", section.intro, "", module.to_markdown(result).strip(), ""]
        figures = getattr(module, "figures", None)
        for figure in (figures(result, out.parent) if callable(figures) else []):
            body += [f"![{figure.stem}]({figure.relative_to(out.parent).as_posix()})", ""]
        body += [f"*Section produced by `bench/{section.script}.py` in {seconds:.1f} s.*", ""]
    total = time.perf_counter() - started
    command = "touchroller report" + (" --quick" if quick else "")
    header = [
        "# TouchRoller ROS 2: results",
        "",
        "Every number below was produced by the command that wrote this file; nothing is typed in.",
        "",
        f"- Command: `{command}` (took {total:.0f} s, {'quick' if quick else 'full'} mode)",
        f"- Machine: {machine_description()}",
        f"- Commit: {_commit()}",
        "",
    ]
    out.write_text("\n".join(header + body), encoding="utf-8")
    progress(f"report: wrote {out} in {total:.0f} s")
    return results
