"""What every benchmark records beside its figures: the machine, the command, when, and how loaded.

Import it from a bench script as `from _common import machine, provenance` (a script's own folder is
on `sys.path` when it runs as `python bench/<name>.py`, and the report generator puts `bench/` there
before it loads a section). Importing it also puts the checkout on `sys.path`, so the scripts run from
a source checkout without an install.
"""
from __future__ import annotations

import sys
import time
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parents[1]
RESULTS = ROOT / "bench" / "results"
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

from touchroller_bringup.report import loadavg  # noqa: E402
from touchroller_bringup.report import machine_description as machine  # noqa: E402

__all__ = ["RESULTS", "ROOT", "command", "loadavg", "machine", "provenance", "provenance_markdown", "results_path"]


def results_path(name: str, quick: bool, suffix: str = ".md") -> Path:
    """Where a bench writes its figures by default. Quick runs go to `bench/results/quick/` (not
    committed), so a CI-sized check never overwrites the committed full-run figures."""
    return (RESULTS / "quick" if quick else RESULTS) / f"{name}{suffix}"


def command(script: str, quick: bool = False, *extra: str) -> str:
    """The command that reproduces a bench's figures, as a user types it in the checkout."""
    return " ".join([".venv/bin/python", f"bench/{script}.py", *(["--quick"] if quick else []), *extra])


def provenance(script: str, quick: bool = False, *extra: str) -> dict[str, Any]:
    """Taken when a bench starts: stored in its result dict and printed by `provenance_markdown`."""
    return {"command": command(script, quick, *extra), "machine": machine(),
            "measured": time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime()), "loadavg": loadavg()}


def provenance_markdown(stamp: dict[str, Any]) -> str:
    """Two Markdown lines (hard breaks) for the top of a bench's results and its report section."""
    return (f"Command: `{stamp['command']}`  \n"
            f"Machine: {stamp['machine']}; measured {stamp['measured']}, load average at the start "
            f"{stamp['loadavg']}.")
