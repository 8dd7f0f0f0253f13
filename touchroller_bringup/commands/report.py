"""`touchroller report [--quick] [--out docs/RESULTS.md]`: regenerate the evidence report."""
from __future__ import annotations

import argparse
from pathlib import Path

from touchroller_driver.paths import checkout_dir


def register(subparsers: argparse._SubParsersAction) -> None:
    parser = subparsers.add_parser(
        "report", help="regenerate docs/RESULTS.md: the paper's tables, what accuracy costs in time, speed figures",
        description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="CI-sized runs (minutes); the default is the full run")
    parser.add_argument("--out", type=Path, default=None, help="report file (default: docs/RESULTS.md in the checkout)")
    parser.add_argument("--only", nargs="+", default=(), metavar="SECTION", help="only these sections")
    parser.add_argument("--recorded", nargs="+", default=(), metavar="SECTION",
                        help="render these sections from their bench's recorded result instead of running them "
                             "(e.g. soak, whose full run takes about 45 minutes); `all` for every section")
    parser.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from touchroller_bringup.report import build_report

    out = args.out or checkout_dir() / "docs" / "RESULTS.md"
    from touchroller_bringup.outputs import Output, check_outputs

    check_outputs([Output("--out", out)])
    build_report(out, quick=args.quick, only=tuple(args.only), recorded=tuple(args.recorded))
    return 0
