"""`touchroller replay`: placeholder until issue 7 lands."""
from __future__ import annotations

import argparse

from touchroller_bringup.errors import UserError


def register(subparsers: argparse._SubParsersAction) -> None:
    parser = subparsers.add_parser("replay", help="(not implemented yet: issue 7)")
    parser.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    raise UserError("'touchroller replay' is not implemented yet (issue 7)")
