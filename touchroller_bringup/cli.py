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
    "height",
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


class Terminated(BaseException):
    """SIGTERM or SIGHUP to a command without handlers of its own: unwinds like Ctrl-C, so outputs being
    written are removed (never left as hidden temporaries) and the exit code is 128 + the signal."""

    def __init__(self, signum: int) -> None:
        super().__init__(signum)
        self.signum = signum


def _terminate(signum: int, _frame: object) -> None:
    raise Terminated(signum)


# What to do about an operating-system error, by errno name.
_OS_ADVICE = {
    "ENOSPC": "the disk is full: free some space or write elsewhere",
    "EDQUOT": "the disk quota is used up: free some space or write elsewhere",
    "EFBIG": "the file is larger than this system allows here: write elsewhere",
    "EROFS": "the file system is read-only: write elsewhere",
    "EACCES": "permission denied: choose a path you can write to (or read)",
    "EPERM": "not permitted: choose a path you can write to (or read)",
    "EISDIR": "it is a directory: give a file name",
    "ENOTDIR": "a part of the path is a file, not a folder",
    "ENOENT": "no such file or folder: check the path",
    "EEXIST": "it exists already: choose another path",
}


def describe_os_error(exc: OSError) -> str:
    """One sentence for an operating-system error: the file, what happened, what to do."""
    import errno as errno_names

    name = errno_names.errorcode.get(exc.errno or 0, "")
    where = f"{exc.filename}: " if exc.filename else ""
    advice = _OS_ADVICE.get(name)
    what = exc.strerror or str(exc)
    return f"{where}{what} ({advice})" if advice else f"{where}{what}"


def describe_sqlite_error(exc: Exception) -> str:
    text = str(exc)
    if "full" in text:
        return f"SQLite: {text} (free some space or write elsewhere)"
    if "readonly" in text or "read-only" in text:
        return f"SQLite: {text} (the bag's folder is read-only: copy the bag somewhere writable)"
    return f"SQLite: {text} (is the bag's .db3 file damaged? `touchroller reindex BAG` may help)"


def main(argv: Sequence[str] | None = None) -> int:
    ends_the_process = argv is None   # the `touchroller` console script: the process exits when this returns
    argv = sys.argv[1:] if argv is None else list(argv)
    # Ctrl-C may come at any time, even while the parser and the command's imports are built: all inside
    previous = {}
    for sig in (signal.SIGTERM, signal.SIGHUP):
        try:
            previous[sig] = signal.signal(sig, _terminate)
        except (ValueError, OSError):   # not the main thread (a test): the caller's handlers stay
            pass
    try:
        return _run(argv)
    except KeyboardInterrupt:
        return _fail("interrupted", code=130)
    except Terminated as exc:
        return _fail(f"stopped by {signal.Signals(exc.signum).name}", code=128 + exc.signum)
    finally:
        for sig, handler in previous.items():
            signal.signal(sig, handler)
        if ends_the_process:
            _leave_objects_to_the_os()


def _leave_objects_to_the_os() -> None:
    """Before the process exits: every object alive now (the imported modules', a command's own) moved out
    of the garbage collector's reach, so the interpreter's last collection at exit does not walk them all
    (tens to hundreds of milliseconds of a short command's run with numpy and OpenCV imported); the
    operating system frees the memory. Exit handlers still run, and the commands close what they write.
    Only for the console script (`main()` without arguments), never for a caller that goes on running."""
    import gc

    gc.freeze()


def _run(argv: list[str]) -> int:
    parser = build_parser(only=argv[0] if argv and argv[0] in COMMANDS else None)
    args = parser.parse_args(argv)
    try:
        result = args.func(args)
    except UserError as exc:
        return _fail(str(exc), code=2)
    except (KeyboardInterrupt, Terminated):
        raise
    except BrokenPipeError:
        # The reader went away (`touchroller bench --list | head`): stop quietly, as a shell tool does.
        # Python would report the pipe again when it flushes stdout at exit, so point stdout at /dev/null.
        os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())
        return 128 + signal.SIGPIPE
    except OSError as exc:
        if os.environ.get("TOUCHROLLER_DEBUG"):
            raise
        return _fail(describe_os_error(exc))
    except Exception as exc:  # noqa: BLE001 - the CLI contract is one line, never a traceback
        if os.environ.get("TOUCHROLLER_DEBUG"):
            raise
        if type(exc).__module__ == "sqlite3":
            return _fail(describe_sqlite_error(exc))
        return _fail(f"{type(exc).__name__}: {exc} (set TOUCHROLLER_DEBUG=1 for a traceback)")
    return int(result or 0)


if __name__ == "__main__":
    sys.exit(main())
