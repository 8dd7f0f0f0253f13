"""The `touchroller` command line: one subcommand per module in `touchroller_bringup.commands`.

Each command module defines `register(subparsers)`, which adds its parser and sets
`func=run` on it. Errors on bad input are one line on stderr and a non-zero exit.
"""
from __future__ import annotations

import argparse
import importlib
import os
import signal
import sys
from collections.abc import Sequence

from touchroller_bringup.errors import UserError

# Order is the order shown in `touchroller --help`.
COMMANDS = (
    "scan",
    "contacts",
    "map",
    "inspect",
    "simulate",
    "calibrate",
    "record",
    "reindex",
    "replay",
    "bench",
    "report",
)


class _Parser(argparse.ArgumentParser):
    def error(self, message: str) -> None:  # one line, exit 2, like argparse but without the usage dump
        raise SystemExit(_fail(f"{self.prog}: {message}", code=2))


def _fail(message: str, code: int = 1) -> int:
    message = " ".join(message.split())   # one line, whatever the message (a YAML error spans several)
    print(f"touchroller: error: {message}" if not message.startswith("touchroller") else message,
          file=sys.stderr)
    return code


def build_parser(only: str | None = None) -> argparse.ArgumentParser:
    """The command line's parser; `only`: with that subcommand alone (a command line naming one then
    imports none of the others' modules: start-up time)."""
    parser = _Parser(prog="touchroller", description="TouchRoller rolling tactile sensor tools.")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND", parser_class=_Parser)
    sub.required = True
    for name in COMMANDS if only is None else (only,):
        importlib.import_module(f"touchroller_bringup.commands.{name}").register(sub)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else list(argv)
    parser = build_parser(only=argv[0] if argv and argv[0] in COMMANDS else None)
    args = parser.parse_args(argv)
    try:
        result = args.func(args)
    except UserError as exc:
        return _fail(str(exc), code=2)
    except KeyboardInterrupt:
        return _fail("interrupted", code=130)
    except BrokenPipeError:
        # The reader went away (`touchroller bench --list | head`): stop quietly, as a shell tool does.
        # Python would report the pipe again when it flushes stdout at exit, so point stdout at /dev/null.
        os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())
        return 128 + signal.SIGPIPE
    except Exception as exc:  # noqa: BLE001 - the CLI contract is one line, never a traceback
        if os.environ.get("TOUCHROLLER_DEBUG"):
            raise
        return _fail(f"{type(exc).__name__}: {exc} (set TOUCHROLLER_DEBUG=1 for a traceback)")
    return int(result or 0)


if __name__ == "__main__":
    sys.exit(main())
