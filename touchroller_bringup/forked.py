"""Forked child processes, started and ended in one place: `touchroller map`'s reader (`forked_reader`) and
its decoding workers (`decode_pool`) are both a function run by a child of the process that forks it.

`fork_child(run, close)` forks; the child closes the descriptors `close` names (the parent's ends of its
pipes, other children's), runs `run()` and leaves with `os._exit` (0 when `run` returned, 1 on any exception:
a child that fails tells its parent through its pipes, or the parent sees them end), never running the
parent's clean-up or flushing the parent's buffers twice. The child ends with its parent however the parent
ends (SIGKILL too: PR_SET_PDEATHSIG), gets the default SIGTERM and SIGHUP (the parent's handlers raise), and,
with `interrupt=False`, ignores Ctrl-C (its parent handles it and ends the child). `end_child(pid, wait)`
reaps a child, ending it first when it is still at work and `wait` is False (the parent stopped early).
POSIX only (`fork_available`).
"""
from __future__ import annotations

import os
import pickle
import signal
import sys
from collections.abc import Callable, Iterable

_PR_SET_PDEATHSIG = 1   # linux/prctl.h


def fork_available() -> bool:
    """Whether a child may be forked: Linux (macOS's system libraries are not safe to use after a fork of a
    process that loaded them; Windows has no fork)."""
    return sys.platform.startswith("linux") and hasattr(os, "fork")


def fork_child(run: Callable[[], None], close: Iterable[int] = (), interrupt: bool = True) -> int:
    """Fork a child that runs `run()` (module docstring); returns its pid, in the parent only."""
    close = list(close)
    parent = os.getpid()
    pid = os.fork()
    if pid:
        return pid
    code = 1
    try:
        if not interrupt:
            signal.signal(signal.SIGINT, signal.SIG_IGN)
        _die_with_parent(parent)
        for fd in close:
            try:
                os.close(fd)
            except OSError:
                pass
        run()
        code = 0
    except BaseException:  # noqa: BLE001 - the parent has gone (a broken pipe) or was told the error
        pass
    finally:
        os._exit(code)


def _die_with_parent(parent: int) -> None:
    """The child ends when the parent does, however it ends (SIGKILL too): the kernel sends it SIGKILL
    when the parent thread exits (prctl PR_SET_PDEATHSIG); a parent already gone before that was set
    is seen by the parent pid. SIGTERM and SIGHUP get their default action (the parent's handlers raise)."""
    import ctypes

    signal.signal(signal.SIGTERM, signal.SIG_DFL)
    signal.signal(signal.SIGHUP, signal.SIG_DFL)
    try:
        libc = ctypes.CDLL(None, use_errno=True)
        libc.prctl(_PR_SET_PDEATHSIG, signal.SIGKILL, 0, 0, 0)
    except (OSError, AttributeError):   # no prctl: the broken pipe still ends the child once it writes
        pass
    if os.getppid() != parent:
        os._exit(1)


def end_child(pid: int, wait: bool) -> None:
    """Reap the child; one that is still at work (the parent stopped early, `wait` False) is ended first."""
    if not wait and os.waitpid(pid, os.WNOHANG) == (0, 0):
        try:
            os.kill(pid, signal.SIGKILL)
        except ProcessLookupError:
            pass
    try:
        os.waitpid(pid, 0)
    except ChildProcessError:
        pass


def picklable(exc: BaseException) -> BaseException:
    """`exc` if it survives pickling (to be raised again by the parent), else a RuntimeError of its type and text."""
    try:
        pickle.loads(pickle.dumps(exc))
        return exc
    except Exception:  # noqa: BLE001 - an exception that does not survive pickling: its type and text
        return RuntimeError(f"{type(exc).__name__}: {exc}")
