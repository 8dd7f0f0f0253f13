"""`touchroller bench [NAME ...] [--quick]`: run the benchmarks in the checkout's `bench/` folder.

Each benchmark is a module `bench/<name>.py`, run as `python -m bench.<name>`, that accepts `--quick` and
records its figures under `bench/results/` with the command that produced them; `--quick` runs write to
`bench/results/quick/` (not committed) so they never replace full-run figures. Benchmarks measure time, so they are not
tests; run them on a quiet machine.
"""
from __future__ import annotations

import argparse
import ast
import subprocess
import sys
import time
from pathlib import Path

from touchroller_bringup.errors import UserError
from touchroller_driver.paths import checkout_dir


def bench_dir() -> Path:
    folder = checkout_dir() / "bench"
    if not folder.is_dir():
        raise UserError("benchmarks live in the source checkout's bench/ folder, which is not here")
    return folder


def available() -> dict[str, Path]:
    return {p.stem: p for p in sorted(bench_dir().glob("*.py"))
            if not p.stem.startswith("_") and p.stem != "table_ii"}   # table_ii is a harness, not a bench


def register(subparsers: argparse._SubParsersAction) -> None:
    parser = subparsers.add_parser("bench", help="run benchmarks (bench/*.py) and record their figures",
                                   description=__doc__.splitlines()[0])
    parser.add_argument("names", nargs="*", metavar="NAME", help="benchmarks to run (default: all)")
    parser.add_argument("--quick", action="store_true",
                        help="small, CI-sized runs (figures go to bench/results/quick/)")
    parser.add_argument("--list", action="store_true", help="list the benchmarks and exit")
    parser.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    scripts = available()
    if args.list:
        for name, path in scripts.items():
            doc = ast.get_docstring(ast.parse(path.read_text(encoding="utf-8"))) or ""
            print(f"{name:28s} {doc.splitlines()[0] if doc else ''}")
        return 0
    unknown = [n for n in args.names if n not in scripts]
    if unknown:
        raise UserError(f"unknown benchmark {unknown[0]!r} (available: {', '.join(scripts)})")
    failed = []
    for name in args.names or list(scripts):
        command = [sys.executable, "-m", f"bench.{name}"] + (["--quick"] if args.quick else [])
        print(f"== {name}: {' '.join(command[1:])}", flush=True)
        start = time.perf_counter()
        result = subprocess.run(command, cwd=checkout_dir())
        print(f"== {name}: exit {result.returncode} after {time.perf_counter() - start:.1f} s", flush=True)
        if result.returncode != 0:
            failed.append(name)
    if failed:
        raise UserError(f"benchmarks failed: {', '.join(failed)}")
    return 0
