"""The console-script entry shared by every node: init, spin, clean shutdown on Ctrl-C.

Bad start-up input (a parameter out of its range or of the wrong type, a params file rcl cannot
parse, a combination the node refuses) is one line on stderr and exit code 2, as in the
`touchroller` command; `TOUCHROLLER_DEBUG=1` shows the traceback instead.
"""
from __future__ import annotations

import os
import re
import sys
from collections.abc import Callable, Sequence
from pathlib import Path

import rclpy
from rclpy.exceptions import NameValidationException, ParameterException
from rclpy.executors import ExternalShutdownException
from rclpy.impl.implementation_singleton import rclpy_implementation as _rclpy
from rclpy.node import Node

from touchroller_bringup.errors import UserError

#: What a node's constructor raises for bad parameters or names: the user's input, not a bug.
START_UP_ERRORS: tuple[type[BaseException], ...] = (ParameterException, NameValidationException, UserError,
                                                     ValueError, TypeError)


def run_node(make_node: Callable[[], Node], args: Sequence[str] | None = None) -> None:
    try:
        rclpy.init(args=args)
    except _rclpy.RCLError as exc:   # e.g. a --params-file that is not YAML
        raise SystemExit(_start_up_failure(exc)) from None
    try:
        node = make_node()
    except START_UP_ERRORS as exc:
        rclpy.try_shutdown()
        raise SystemExit(_start_up_failure(exc)) from None
    try:
        rclpy.spin(node)
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    except _rclpy.RCLError:
        # Ctrl-C shuts the context down from the signal handler; landing between spin's context check
        # and building its wait set, that surfaces as "the given context is not valid". Only then
        # is it a clean exit: with the context still up, an RCLError is a real failure.
        if node.context.ok():
            raise
    finally:
        node.destroy_node()
        rclpy.try_shutdown()


def _start_up_failure(exc: BaseException) -> int:
    """Print `exc` as one line (`camera_node: error: ...`) and return the exit code 2."""
    if os.environ.get("TOUCHROLLER_DEBUG"):
        raise exc
    print(f"{_program()}: error: {one_line(exc)} (bad start-up parameters; TOUCHROLLER_DEBUG=1 for a traceback)",
          file=sys.stderr, flush=True)
    return 2


def one_line(exc: BaseException) -> str:
    """An exception's message on one line, without rcl's source locations (`, at /project/src/x.c:12`)."""
    text = re.sub(r",? at /\S+:\d+", "", str(exc))
    return " ".join(text.split()) or type(exc).__name__


def _program() -> str:
    name = Path(sys.argv[0]).name if sys.argv and sys.argv[0] not in ("", "-c") else ""
    return name or "touchroller node"
