"""The console-script entry shared by every node: init, spin, and an orderly shutdown on Ctrl-C.

A terminal's Ctrl-C reaches a node twice under `ros2 launch` (from the terminal and from launch), at
any moment: while the modules load, while the node is built, while it spins or while it is being
destroyed. rclpy's own handler shuts the context down from the signal and raises KeyboardInterrupt
wherever the main thread is, which left a traceback ("process has died") or a node cut off half-way
through its cleanup (a sweep worker's arm stop). Here SIGINT and SIGTERM only ask to stop (`StopSignals`,
installed before the node's module is imported): the node is built to the end, spinning ends between
callbacks, the node's own stop path runs first (the sweep node stops the arm), then the node is
destroyed and the context shut down, and the process exits 0. A stop signal while the node's modules
load (seconds on a loaded machine) ends the process there, at the next module it imports, exit 0: nothing
is built yet that a stop must wait for, so it does not wait for the imports to finish either. The handler
itself never raises: an exception from a signal handler lands wherever the main thread is, which may be
the import machinery's weakref callback (only printed, "Exception ignored"), or C code that imports a
module and replaces whatever failed with an ImportError of its own (an extension module's
initialisation, such as numpy's). Further signals during that cleanup
change nothing however many arrive (a user's second Ctrl-C under launch is the third and fourth
signal); a process that must go at once is ended with SIGKILL (launch escalates to it by itself). A
signal before the console script has run this module's entry (the interpreter's own start and its site
imports, the first tens of milliseconds) meets Python's default handling, KeyboardInterrupt: no code of
ours has run yet.

Bad start-up input (a parameter out of its range or of the wrong type, a params file rcl cannot
parse, a combination the node refuses) is one line on stderr and exit code 2, as in the
`touchroller` command; `TOUCHROLLER_DEBUG=1` shows the traceback instead.
"""
from __future__ import annotations

import importlib
import os
import re
import signal
import sys
import threading
from collections.abc import Callable, Iterator, Sequence
from contextlib import contextmanager
from pathlib import Path
from typing import Any

STOP_SIGNALS = (signal.SIGINT, signal.SIGTERM)


class StartUpInterrupted(BaseException):
    """A stop signal while a node's modules loaded (see `StopSignals.interrupting`). A BaseException, as
    KeyboardInterrupt is: the modules' own `except Exception` must not swallow it."""


class StopSignals:
    """Stop signals (SIGINT, SIGTERM by default) set a flag instead of raising; `install()` once per
    process (or per `touchroller` command), early, from the main thread."""

    _installed: StopSignals | None = None

    def __init__(self) -> None:
        self.requested = threading.Event()
        self.count = 0
        self.last_signal: int | None = None
        self._previous: dict[int, Any] = {}

    @classmethod
    def install(cls, signals: Sequence[int] = STOP_SIGNALS) -> StopSignals:
        """The process's handler (idempotent: the one installed first stays)."""
        if cls._installed is None:
            stop = cls()
            for signum in signals:
                stop._previous[signum] = signal.signal(signum, stop._on_signal)
            cls._installed = stop
        return cls._installed

    @classmethod
    def installed(cls) -> StopSignals | None:
        return cls._installed

    @classmethod
    def uninstall(cls) -> None:
        """Put the handlers back that `install()` replaced."""
        stop, cls._installed = cls._installed, None
        if stop is not None:
            for signum, handler in stop._previous.items():
                signal.signal(signum, handler)

    @property
    def name(self) -> str:
        return signal.Signals(self.last_signal).name if self.last_signal is not None else "a stop request"

    @contextmanager
    def interrupting(self) -> Iterator[None]:
        """For the imports of a node's modules (nothing is built yet that must be stopped in order): once a
        stop is requested, the next module this thread imports raises StartUpInterrupted instead of loading,
        and so does every one after it; a stop requested before raises at once. Whatever leaves the block
        after a stop was requested leaves it as StartUpInterrupted: code between the raise and here may
        have caught it and raised something else (C code that imports a module replaces the exception with
        an ImportError of its own), or swallowed it and finished."""
        if self.requested.is_set():
            raise StartUpInterrupted(self.name)
        gate = _StopAtImport(self, threading.get_ident())
        sys.meta_path.insert(0, gate)
        try:
            yield
        except BaseException as exc:
            if self.requested.is_set():
                raise StartUpInterrupted(self.name) from exc
            raise
        finally:
            if gate in sys.meta_path:
                sys.meta_path.remove(gate)
        if self.requested.is_set():
            raise StartUpInterrupted(self.name)

    def _on_signal(self, signum: int, _frame: Any) -> None:
        # never raises: it runs wherever the main thread is (see the module's docstring)
        self.count += 1
        self.last_signal = signum
        self.requested.set()


class _StopAtImport:
    """A meta-path finder first in line: after a stop request, an import of a module not loaded yet (in the
    thread that started the imports) raises StartUpInterrupted. A finder that raises is a way out of an
    import that importlib expects: it holds no lock of its own then, and half-loaded modules are undone."""

    def __init__(self, stop: StopSignals, thread: int) -> None:
        self._stop = stop
        self._thread = thread

    def find_spec(self, name: str, path: Any = None, target: Any = None) -> None:   # importlib's signature
        if self._stop.requested.is_set() and threading.get_ident() == self._thread:
            raise StartUpInterrupted(self._stop.name)
        return None


def run_node(make_node: Callable[[], Any], args: Sequence[str] | None = None) -> None:
    """Build the node, spin it until SIGINT/SIGTERM (or the context is shut down), then stop it in order."""
    ours = StopSignals.installed() is None   # the console scripts install it before the imports
    stop = StopSignals.install()
    from touchroller_bringup.heap import bound_heap_growth

    bound_heap_growth()   # a node runs for hours: its frames must not creep up the C heap
    import rclpy
    from rclpy.executors import ExternalShutdownException, SingleThreadedExecutor
    from rclpy.impl.implementation_singleton import rclpy_implementation as _rclpy
    from rclpy.signals import SignalHandlerOptions

    from touchroller_bringup.errors import UserError

    try:
        _check_params_files(sys.argv if args is None else args)   # before rcl, which logs a line of its own
        rclpy.init(args=args, signal_handler_options=SignalHandlerOptions.NO)
    except (_rclpy.RCLError, UserError) as exc:   # e.g. a --params-file that is not a params file
        if ours:
            StopSignals.uninstall()
        raise SystemExit(_start_up_failure(exc)) from None
    node = None
    executor = None
    try:
        if not stop.requested.is_set():   # Ctrl-C while the modules loaded: nothing to build
            try:
                node = make_node()
            except start_up_errors() as exc:
                raise SystemExit(_start_up_failure(exc)) from None
        executor = SingleThreadedExecutor()
        if node is not None:
            _deliver_answers(node)
            executor.add_node(node)
        while not stop.requested.is_set() and rclpy.ok():
            executor.spin_once(timeout_sec=0.1)   # a signal is seen within this, between callbacks
    except ExternalShutdownException:
        pass
    except _rclpy.RCLError:
        # the context shut down by someone else while spin built its wait set ("the given context is
        # not valid"): a clean exit; with the context still up, an RCLError is a real failure
        if rclpy.ok():
            raise
    finally:
        try:
            if executor is not None:
                executor.shutdown(timeout_sec=1.0)
            if node is not None:
                stop_node(node)
                node.destroy_node()
        finally:
            rclpy.try_shutdown()
            if ours:   # called in-process (tests): the caller's handlers again
                StopSignals.uninstall()


def _deliver_answers(node: Any) -> None:
    """Answers DDS dropped are sent again for every service of a node in a process of its own, where
    callers from other processes meet that (answer_delivery); a node that handles some itself keeps its own."""
    from touchroller_bringup.answer_delivery import AnswerDelivery

    delivery = getattr(node, "answers", None)
    if not isinstance(delivery, AnswerDelivery):
        delivery = AnswerDelivery(node)
    delivery.handle_all()


def start_up_errors() -> tuple[type[BaseException], ...]:
    """What a node's constructor raises for bad parameters or names: the user's input, not a bug."""
    from rclpy.exceptions import NameValidationException, ParameterException

    from touchroller_bringup.errors import UserError

    return (ParameterException, NameValidationException, UserError, ValueError, TypeError)


def _check_params_files(argv: Sequence[str]) -> None:
    """A `--params-file` that is missing or not YAML, as one UserError line."""
    import yaml

    from touchroller_bringup.errors import UserError

    for flag, value in zip(argv, argv[1:], strict=False):
        if flag != "--params-file":
            continue
        try:
            with open(value, encoding="utf-8") as stream:
                document = yaml.safe_load(stream)
        except OSError as exc:
            raise UserError(f"--params-file {value}: {exc.strerror or exc}") from None
        except (yaml.YAMLError, UnicodeDecodeError) as exc:
            mark = getattr(exc, "problem_mark", None)
            where = f" at line {mark.line + 1}, column {mark.column + 1}" if mark is not None else ""
            raise UserError(f"--params-file {value} is not YAML ({getattr(exc, 'problem', None) or exc}{where})") \
                from None
        problem = params_file_problem(document)
        if problem:
            raise UserError(f"--params-file {value} is not a ROS 2 parameters file: {problem}")


def params_file_problem(document: Any) -> str:
    """Why a parsed YAML document is not a ROS 2 parameters file ("" when it is one): node names (or
    `/**`), possibly under namespaces, each with a `ros__parameters` mapping."""
    from collections.abc import Mapping

    if not isinstance(document, Mapping) or not document:
        return ("expected node names (or /**) with ros__parameters: mappings, got "
                f"{type(document).__name__ if document is not None else 'an empty file'}")

    def check(level: Mapping, path: str) -> str:
        for key, value in level.items():
            where = f"{path}{key}"
            if key == "ros__parameters":
                if not isinstance(value, Mapping):
                    return f"{where} must be a mapping of parameter names to values"
                continue
            if not isinstance(value, Mapping):
                return f"{where}: expected a node name with ros__parameters: under it"
            problem = check(value, where + "/")
            if problem:
                return problem
        return ""
    return check(document, "")


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


def stop_node(node: Any) -> None:
    """The node's own stop path before it is destroyed: the sweep node stops the arm."""
    request_stop = getattr(node, "request_stop", None)
    if request_stop is None:
        return
    try:
        request_stop()
    except Exception as exc:  # noqa: BLE001 - destroying the node still releases the arm
        node.get_logger().warning(f"stopping before shutdown: {type(exc).__name__}: {exc}")


def _entry(module: str) -> Callable[[], None]:
    def main() -> None:
        stop = StopSignals.install()   # before the node's module (rclpy, OpenCV, ...) loads: seconds on a slow machine
        try:
            with stop.interrupting():   # a Ctrl-C meanwhile ends the process at the next import, not once all loaded
                node_module = importlib.import_module(module)
        except StartUpInterrupted:
            return   # exit 0, as a stop of a running node: nothing was built
        node_module.main()

    main.__name__ = main.__qualname__ = module.rsplit(".", 1)[-1]
    main.module = module  # type: ignore[attr-defined]
    return main


# console scripts (setup.py): the handlers are up before the heavy imports
camera_node = _entry("touchroller_bringup.nodes.camera_node")
perception_node = _entry("touchroller_bringup.nodes.perception_node")
sweep_node = _entry("touchroller_bringup.nodes.sweep_node")
calibration_node = _entry("touchroller_bringup.nodes.calibration_node")


if __name__ == "__main__":
    sys.exit("usage: a node's console script (camera_node, perception_node, sweep_node, calibration_node)")
