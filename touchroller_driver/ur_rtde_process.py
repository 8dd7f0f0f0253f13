"""ur_rtde in a child process that the arm thread can abandon.

ur_rtde's constructors, and any of its calls on a robot that stopped answering, block inside C++ while
holding Python's GIL: in the sweep node's process that froze everything, diagnostics, services and
Ctrl-C included, and a host that answers the RTDE greeting and then goes silent passes any probe. So
`UR5Arm` makes every ur_rtde call in a child process (`RtdeChild`), one request at a time over a pipe,
and waits for each answer with a deadline: a call not answered in time (or `abort()` from any thread)
kills the child (SIGKILL) and raises `RtdeGone` (an `ArmError`, one line). The child's sockets to the
robot close with it; the control script's communication watchdog (`setWatchdog`, armed on connect)
then stops the robot, since nothing kicks it any more (docs/ur5.md). The child dies with its parent
(PR_SET_PDEATHSIG), is in a session of its own (a terminal's Ctrl-C goes to the parent, which decides),
and its stdout/stderr (ur_rtde prints there) are not the protocol's pipes.

`LocalRtde` makes the same objects in this process (the child runs one; tests run it with doubles).
"""
from __future__ import annotations

import os
import pickle
import select
import signal
import struct
import subprocess
import sys
import threading
import time
from typing import Any

from touchroller_driver.arm import ArmError

INTERFACES = ("receive", "control", "dashboard")
CALL_TIMEOUT_S = 1.0    # a UR answers an RTDE call in milliseconds
OPEN_TIMEOUT_S = 10.0   # RTDEControlInterface uploads its control script and waits for it to run
STARTUP_TIMEOUT_S = 30.0   # the child's Python and ur_rtde import (a loaded machine is slow)
_HEADER = struct.Struct(">I")


class RtdeGone(ArmError):
    """The ur_rtde child did not answer in time, was aborted, or ended: it is gone, and so is the connection."""


class LocalRtde:
    """The ur_rtde objects of one robot, made and called in this process (no deadline: a hang is final)."""

    def __init__(self) -> None:
        self.objects: dict[str, Any] = {}

    def open(self, interface: str, host: str, frequency: float) -> Any:
        if interface == "receive":
            import rtde_receive

            made = rtde_receive.RTDEReceiveInterface(host, frequency)
        elif interface == "control":
            import rtde_control

            made = rtde_control.RTDEControlInterface(host, frequency)
        elif interface == "dashboard":
            import dashboard_client

            made = dashboard_client.DashboardClient(host)
        else:
            raise ValueError(f"unknown ur_rtde interface {interface!r}; expected one of {', '.join(INTERFACES)}")
        self.objects[interface] = made
        return made

    def call(self, interface: str, method: str, *args: Any) -> Any:
        target = self.objects.get(interface)
        if target is None:
            raise RuntimeError(f"{interface} interface not open")
        return getattr(target, method)(*args)


class RtdeChild:
    """A child process serving `LocalRtde` calls; `open(...)` returns a proxy whose methods are calls in
    the child with a deadline. Call from one thread; `abort()` from any."""

    def __init__(self, host: str, *, call_timeout: float = CALL_TIMEOUT_S,
                 open_timeout: float = OPEN_TIMEOUT_S) -> None:
        self.host = host
        self.call_timeout = float(call_timeout)
        self.open_timeout = float(open_timeout)
        self.failure: str | None = None   # why the child is gone (one line), None while it serves
        self._aborted = threading.Event()
        self._process: subprocess.Popen[bytes] | None = None
        self._requests = self._answers = -1

    # -- life cycle --------------------------------------------------------------------------------
    def _start(self) -> None:
        to_child_r, to_child_w = os.pipe()
        from_child_r, from_child_w = os.pipe()
        try:
            self._process = subprocess.Popen(
                [sys.executable, "-m", "touchroller_driver.ur_rtde_process", str(to_child_r), str(from_child_w)],
                pass_fds=(to_child_r, from_child_w), stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL,
                stderr=subprocess.DEVNULL, start_new_session=True)
        finally:
            os.close(to_child_r)
            os.close(from_child_w)
        self._requests, self._answers = to_child_w, from_child_r
        self._exchange(("ping",), STARTUP_TIMEOUT_S, "starting the ur_rtde process")

    def abort(self) -> None:
        """Give up at once: a call under way (on another thread) kills the child and raises RtdeGone."""
        self._aborted.set()

    def close(self) -> None:
        """End the child (SIGKILL: a child blocked in ur_rtde does not read a polite request)."""
        process, self._process = self._process, None
        for fd in (self._requests, self._answers):
            if fd >= 0:
                os.close(fd)
        self._requests = self._answers = -1
        if process is not None and process.poll() is None:
            process.kill()
        if process is not None:
            try:
                process.wait(timeout=5.0)
            except subprocess.TimeoutExpired:
                pass

    @property
    def alive(self) -> bool:
        return self._process is not None and self.failure is None

    # -- calls -------------------------------------------------------------------------------------
    def open(self, interface: str, frequency: float) -> RemoteInterface:
        if self._process is None and self.failure is None:
            self._start()
        self._exchange(("open", interface, self.host, float(frequency)), self.open_timeout,
                       f"{_CLASS_NAMES.get(interface, interface)}({self.host!r}) (connecting)")
        return RemoteInterface(self, interface)

    def call(self, interface: str, method: str, *args: Any, timeout: float | None = None) -> Any:
        return self._exchange(("call", interface, method, args), self.call_timeout if timeout is None else timeout,
                              f"{method}()")

    def _exchange(self, request: tuple[Any, ...], timeout: float, what: str) -> Any:
        if self.failure is not None:
            raise RtdeGone(self.failure)
        if self._aborted.is_set():
            self._fail(f"the ur_rtde process was aborted ({what} not sent)")
        data = pickle.dumps(request)
        try:
            os.write(self._requests, _HEADER.pack(len(data)) + data)
            answer = pickle.loads(self._read_message(timeout, what))
        except (OSError, EOFError, pickle.UnpicklingError) as exc:
            self._fail(f"the ur_rtde process ended during {what}: {type(exc).__name__}: {exc}")
        if answer[0] == "ok":
            return answer[1]
        raise RuntimeError(answer[1])   # what ur_rtde raised in the child (RuntimeError there too)

    def _read_message(self, timeout: float, what: str) -> bytes:
        deadline = time.monotonic() + timeout
        header = self._read_exactly(_HEADER.size, deadline, timeout, what)
        return self._read_exactly(_HEADER.unpack(header)[0], deadline, timeout, what)

    def _read_exactly(self, count: int, deadline: float, timeout: float, what: str) -> bytes:
        data = b""
        while len(data) < count:
            if self._aborted.is_set():
                self._fail(f"the ur_rtde process was aborted during {what}")
            remaining = deadline - time.monotonic()
            if remaining <= 0:
                self._fail(f"no answer to {what} within {timeout:g} s")
            ready, _, _ = select.select([self._answers], [], [], min(remaining, 0.05))
            if ready:
                chunk = os.read(self._answers, count - len(data))
                if not chunk:
                    raise EOFError("the pipe closed")
                data += chunk
        return data

    def _fail(self, message: str) -> None:
        self.failure = message
        self.close()
        raise RtdeGone(message)


_CLASS_NAMES = {"receive": "RTDEReceiveInterface", "control": "RTDEControlInterface", "dashboard": "DashboardClient"}
# calls that take longer than an RTDE round trip by design
_SLOW_CALLS = {"stopL": 3.0, "stopScript": 3.0, "disconnect": 3.0, "connect": 5.0, "unlockProtectiveStop": 5.0}


class RemoteInterface:
    """One ur_rtde object in the child: `proxy.moveL(...)` is `child.call("control", "moveL", ...)`."""

    def __init__(self, child: RtdeChild, interface: str) -> None:
        self._child, self._interface = child, interface

    def __getattr__(self, method: str) -> Any:
        if method.startswith("_"):
            raise AttributeError(method)

        def call(*args: Any) -> Any:
            return self._child.call(self._interface, method, *args, timeout=_SLOW_CALLS.get(method))

        return call


# -- the child --------------------------------------------------------------------------------------

def _die_with_parent() -> None:
    try:
        import ctypes

        libc = ctypes.CDLL(None, use_errno=True)
        libc.prctl(1, signal.SIGKILL)   # PR_SET_PDEATHSIG
    except (OSError, AttributeError):
        pass
    if os.getppid() == 1:   # the parent died before prctl
        os._exit(1)


def _serve(requests: int, answers: int) -> None:
    local = LocalRtde()

    def read_exactly(count: int) -> bytes:
        data = b""
        while len(data) < count:
            chunk = os.read(requests, count - len(data))
            if not chunk:
                raise EOFError
            data += chunk
        return data

    while True:
        try:
            request = pickle.loads(read_exactly(_HEADER.unpack(read_exactly(_HEADER.size))[0]))
        except EOFError:
            return
        try:
            if request[0] == "ping":
                answer: tuple[Any, ...] = ("ok", None)
            elif request[0] == "open":
                local.open(request[1], request[2], request[3])
                answer = ("ok", None)
            else:
                answer = ("ok", local.call(request[1], request[2], *request[3]))
            data = pickle.dumps(answer)
        except Exception as exc:  # noqa: BLE001 - every failure goes back to the parent as one line
            data = pickle.dumps(("error", " ".join(str(exc).split()) or type(exc).__name__))
        os.write(answers, _HEADER.pack(len(data)) + data)


if __name__ == "__main__":
    _die_with_parent()
    signal.signal(signal.SIGINT, signal.SIG_IGN)   # the parent ends it
    _serve(int(sys.argv[1]), int(sys.argv[2]))
