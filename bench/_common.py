"""What every benchmark records beside its figures: the machine, the command, when, and how loaded.

Import it from a bench script as `from bench._common import machine, provenance`; benchmarks run from
the checkout as `python -m bench.NAME`.
"""
from __future__ import annotations

import time
from pathlib import Path
from typing import Any

from touchroller_bringup.report import loadavg
from touchroller_bringup.report import machine_description as machine

ROOT = Path(__file__).resolve().parents[1]
RESULTS = ROOT / "bench" / "results"

__all__ = ["RESULTS", "ROOT", "command", "loadavg", "machine", "provenance", "provenance_markdown", "results_path"]


def results_path(name: str, quick: bool, suffix: str = ".md") -> Path:
    """Where a bench writes its figures by default. Quick runs go to `bench/results/quick/` (not
    committed), so a CI-sized check never overwrites the committed full-run figures."""
    return (RESULTS / "quick" if quick else RESULTS) / f"{name}{suffix}"


def command(script: str, quick: bool = False, *extra: str) -> str:
    """The command that reproduces a bench's figures, as a user types it in the checkout."""
    return " ".join([".venv/bin/python", "-m", f"bench.{script}", *(["--quick"] if quick else []), *extra])


def provenance(script: str, quick: bool = False, *extra: str) -> dict[str, Any]:
    """Taken when a bench starts: stored in its result dict and printed by `provenance_markdown`."""
    return {"command": command(script, quick, *extra), "machine": machine(),
            "measured": time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime()), "loadavg": loadavg()}


def provenance_markdown(stamp: dict[str, Any]) -> str:
    """Two Markdown lines (hard breaks) for the top of a bench's results and its report section."""
    return (f"Command: `{stamp['command']}`  \n"
            f"Machine: {stamp['machine']}; measured {stamp['measured']}, load average at the start "
            f"{stamp['loadavg']}.")
