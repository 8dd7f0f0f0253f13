"""`touchroller contacts`: placeholder until issue 4 lands."""
from __future__ import annotations

import argparse

from touchroller_bringup.errors import UserError


def register(subparsers: argparse._SubParsersAction) -> None:
    parser = subparsers.add_parser("contacts", help="(not implemented yet: issue 4)")
    parser.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    raise UserError("'touchroller contacts' is not implemented yet (issue 4)")
