"""`touchroller report`: placeholder until issue 8 lands."""
from __future__ import annotations

import argparse

from touchroller_bringup.errors import UserError


def register(subparsers: argparse._SubParsersAction) -> None:
    parser = subparsers.add_parser("report", help="(not implemented yet: issue 8)")
    parser.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    raise UserError("'touchroller report' is not implemented yet (issue 8)")
