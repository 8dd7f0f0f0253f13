"""`touchroller simulate`: placeholder until issue 3 lands."""
from __future__ import annotations

import argparse

from touchroller_bringup.errors import UserError


def register(subparsers: argparse._SubParsersAction) -> None:
    parser = subparsers.add_parser("simulate", help="(not implemented yet: issue 3)")
    parser.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    raise UserError("'touchroller simulate' is not implemented yet (issue 3)")
