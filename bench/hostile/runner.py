"""The hostile bench's runner: every probe of every probe module in `bench.hostile`, each in a scratch folder.

A probe module is any module of the package (other than this runner, the contract `probe` and `__main__`)
with a `probes() -> list[Probe]`; a module added later (e.g. `arm.py`) is picked up by name. A probe's
check returns None when its expectation held, else one line; a check that raises did not hold either
(the exception is its line). The result counts held / total, per area and in all.
"""
from __future__ import annotations

import argparse
import importlib
import json
import pkgutil
import shutil
import sys
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path

from bench._common import Provenance, loadavg, provenance, provenance_markdown, results_path, to_json
from bench.hostile.probe import Probe

QUICK_AREAS = ("outputs", "results")   # a CI-sized run (`--quick`, the quick report): seconds, not minutes
NOT_PROBE_MODULES = {"probe", "runner", "__main__", "_kit"}


@dataclass(frozen=True)
class Outcome:
    name: str
    area: str
    module: str
    expect: str
    held: bool
    got: str          # "" when it held, else what happened instead
    seconds: float


@dataclass(frozen=True)
class HostileResult:
    provenance: Provenance
    outcomes: tuple[Outcome, ...]
    loadavg_after: str
    quick: bool

    @property
    def held(self) -> int:
        return sum(o.held for o in self.outcomes)

    @property
    def total(self) -> int:
        return len(self.outcomes)


def probe_modules() -> list[str]:
    """The package's probe modules, by name, sorted."""
    import bench.hostile as package

    return sorted(m.name for m in pkgutil.iter_modules(package.__path__)
                  if m.name not in NOT_PROBE_MODULES and not m.name.startswith("_"))


def collect(areas: tuple[str, ...] = ()) -> list[tuple[str, Probe]]:
    found: list[tuple[str, Probe]] = []
    for name in probe_modules():
        module = importlib.import_module(f"bench.hostile.{name}")
        make = getattr(module, "probes", None)
        if not callable(make):
            continue
        found += [(name, p) for p in make() if not areas or p.area in areas]
    names = [p.name for _, p in found]
    duplicates = {n for n in names if names.count(n) > 1}
    if duplicates:
        raise ValueError(f"probe names must be unique; repeated: {', '.join(sorted(duplicates))}")
    return found


def run_probe(module: str, probe: Probe) -> Outcome:
    scratch = Path(tempfile.mkdtemp(prefix="hostile_"))
    started = time.perf_counter()
    try:
        got = probe.check(scratch)
    except Exception as exc:  # noqa: BLE001 - a probe that raises did not hold; its line says why
        got = f"the probe raised {type(exc).__name__}: {' '.join(str(exc).split())}"
    finally:
        shutil.rmtree(scratch, ignore_errors=True)
    return Outcome(probe.name, probe.area, module, probe.expect, got is None, got or "",
                   time.perf_counter() - started)


def run(quick: bool = False, areas: tuple[str, ...] = (), progress=None) -> HostileResult:
    stamp = provenance("hostile", quick, *(["--area", *areas] if areas else []))
    if quick and not areas:
        areas = QUICK_AREAS
    outcomes = []
    for module, probe in collect(areas):
        outcome = run_probe(module, probe)
        outcomes.append(outcome)
        if progress is not None:
            progress(f"{'held  ' if outcome.held else 'FAILED'} [{probe.area}] {probe.name}"
                     + ("" if outcome.held else f": {outcome.got}"))
    return HostileResult(stamp, tuple(outcomes), loadavg(), quick)


def load(path: Path) -> HostileResult:
    """A result written by `write` (its JSON)."""
    data = json.loads(Path(path).read_text())
    return HostileResult(Provenance(**data["provenance"]), tuple(Outcome(**o) for o in data["outcomes"]),
                         data["loadavg_after"], data["quick"])


def to_markdown(result: HostileResult) -> str:
    areas: dict[str, list[Outcome]] = {}
    for o in result.outcomes:
        areas.setdefault(o.area, []).append(o)
    lines = [provenance_markdown(result.provenance) + "  ", f"Load average at the end: {result.loadavg_after}.", "",
             *([f"A quick run: the probes of {', '.join(QUICK_AREAS)} only (all areas: `python -m bench.hostile`).",
                ""] if result.quick and set(areas) <= set(QUICK_AREAS) else []),
             f"**{result.held} / {result.total} probes held** "
             f"({', '.join(f'{area} {sum(o.held for o in os_)}/{len(os_)}' for area, os_ in areas.items())}).", "",
             "| area | probe | expectation | held | what happened instead |", "|---|---|---|---|---|"]
    for o in result.outcomes:
        lines.append(f"| {o.area} | {o.name} | {o.expect} | {'yes' if o.held else '**no**'} | "
                     f"{o.got.replace('|', '/') or '-'} |")
    return "\n".join(lines) + "\n"


def write(result: HostileResult, out: Path | None = None) -> Path:
    path = out or results_path("hostile", result.quick)
    path.parent.mkdir(parents=True, exist_ok=True)
    path.with_suffix(".json").write_text(to_json(result, indent=2))
    path.write_text("# Hostile bench: probes of what users and machines do wrong (`python -m bench.hostile`)\n\n"
                    + to_markdown(result))
    return path


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m bench.hostile", description=__doc__.splitlines()[0])
    parser.add_argument("--area", nargs="+", default=(), help="only the probes of these areas")
    parser.add_argument("--list", action="store_true", help="list the probes and their expectations, run none")
    parser.add_argument("--quick", action="store_true", help="write to bench/results/quick/ (not committed)")
    parser.add_argument("--out", type=Path, default=None, help="results file (default bench/results/hostile.md)")
    args = parser.parse_args(argv)
    if args.list:
        for module, probe in collect(tuple(args.area)):
            print(f"[{probe.area}] {probe.name} ({module}): {probe.expect}")
        return 0
    result = run(args.quick, tuple(args.area), progress=lambda line: print(line, flush=True))
    if args.area and args.out is None:   # a part of the probes never replaces the whole run's record
        args.out = results_path("hostile", True)
    path = write(result, args.out)
    print(f"{result.held} / {result.total} held -> {path}")
    return 0 if result.held == result.total else 1


if __name__ == "__main__":
    sys.exit(main())
