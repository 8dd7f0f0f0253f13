"""One probe of the hostile bench: what is done, what must happen, and the check that runs it."""
from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path


@dataclass(frozen=True)
class Probe:
    """`check(scratch)` runs the probe in an empty scratch folder of its own and returns None when the
    expectation held, else one line saying what happened instead."""

    name: str                      # unique, short: "contacts --out into the bag's storage file"
    area: str                      # "outputs", "parameters", "arm", "signals", "disk", ...
    expect: str                    # what must happen, in one line
    check: Callable[[Path], str | None]
