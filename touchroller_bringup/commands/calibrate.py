"""`touchroller calibrate`: placeholder until issue 6 lands."""
from __future__ import annotations

import argparse

from touchroller_bringup.errors import UserError


def register(subparsers: argparse._SubParsersAction) -> None:
    parser = subparsers.add_parser("calibrate", help="(not implemented yet: issue 6)")
    parser.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    raise UserError("'touchroller calibrate' is not implemented yet (issue 6)")
