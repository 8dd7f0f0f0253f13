"""A Universal Robots UR5 (CB3 or e-Series) behind the `Arm` interface, through ur_rtde.

`rtde_receive` streams the robot state (TCP pose, safety mode); `rtde_control` uploads its control
script and executes `moveL`. Limits are checked before a command is sent; a protective or emergency
stop, or a lost connection, becomes `fault()` and refuses further motion until `reset_fault()` (which
unlocks a protective stop through the dashboard server, as the teach pendant's button does, and
reconnects) or `connect()` again.

ur_rtde's constructors connect with no timeout and hold the GIL while they wait: a host that accepts
TCP on the UR ports and never answers would freeze the whole process for good. So `connect()` first
probes the ports with the protocols' own greetings and a timeout (`probe_rtde`: the RTDE protocol
version request on 30004; `probe_dashboard`: the dashboard server's welcome line on 29999, which the
control interface opens too) and only then constructs the interfaces.
A host can pass both probes and then go silent (or a robot can stop answering mid-sweep): so every
ur_rtde call, constructors included, runs in a child process with a deadline (`ur_rtde_process`); one
not answered in time ends the child and becomes a fault, and the robot's own communication watchdog
(armed on connect) stops the control script once nothing kicks it; we also ask the dashboard server to
stop the program, in case it still answers. `abort()` (any thread) gives up at once.
All calls must come from one thread (the sweep node's worker): ur_rtde's interfaces are not shared.
See docs/ur5.md for running against a real robot or URSim.
"""
from __future__ import annotations

import ipaddress
import math
import socket
import struct
import time
from typing import Any

import numpy as np
from numpy.typing import ArrayLike

from touchroller_driver.arm import ArmError, ArmLimits, check_path_start
from touchroller_driver.path import blend_radii, fraction_along_path
from touchroller_driver.ur_rtde_process import CALL_TIMEOUT_S, OPEN_TIMEOUT_S, LocalRtde, RtdeChild, RtdeGone

# Every ur_rtde call this module makes, with the positional arguments it passes (besides self).
# test_ur5.py checks these against the installed module's pybind signatures.
CONTROL_CALLS: dict[str, int] = {
    "moveL": 4,  # pose, speed, acceleration, asynchronous
    "stopL": 1,  # deceleration
    "getAsyncOperationProgress": 0,
    "isSteady": 0,
    "isConnected": 0,
    "isPoseWithinSafetyLimits": 1,
    "stopScript": 0,
    "disconnect": 0,
    "setWatchdog": 1,  # minimum frequency
    "kickWatchdog": 0,
}
# moveL's other overload, a path: moveL([[x, y, z, rx, ry, rz, speed, accel, blend], ...], asynchronous)
PATH_CALLS: dict[str, int] = {"moveL": 2}
RECEIVE_CALLS: dict[str, int] = {
    "getActualTCPPose": 0,
    "isProtectiveStopped": 0,
    "isEmergencyStopped": 0,
    "getSafetyMode": 0,
    "isConnected": 0,
    "disconnect": 0,
}
CONSTRUCTOR_CALLS: dict[str, int] = {"RTDEControlInterface": 2, "RTDEReceiveInterface": 2}  # host, frequency

DASHBOARD_CALLS: dict[str, int] = {"connect": 1, "unlockProtectiveStop": 0, "disconnect": 0}  # connect(timeout ms)

STOP_DECELERATION = 0.5  # m/s^2: stopL's tool deceleration when the sweep is stopped
WATCHDOG_HZ = 10.0  # the controller shuts our control script down if keepalive() stops coming this often
CONNECT_TIMEOUT_S = 2.0  # each port probe's limit: a UR controller answers in milliseconds
RTDE_PORT = 30004
DASHBOARD_PORT = 29999
RTDE_PROTOCOL_VERSION = 2
DASHBOARD_WELCOME = "Connected: Universal Robots Dashboard Server"


def _receive_exactly(sock: socket.socket, count: int, deadline: float) -> bytes:
    data = b""
    while len(data) < count:
        sock.settimeout(max(deadline - time.monotonic(), 1e-3))
        chunk = sock.recv(count - len(data))
        if not chunk:
            raise ConnectionError("the connection closed")
        data += chunk
    return data


def _probe(host: str, port: int, timeout: float, what: str, exchange: Any) -> None:
    """Open (host, port) and run `exchange(sock, deadline)` within `timeout` s; ArmError (one line) if
    the port is closed, silent, or answers something else."""
    deadline = time.monotonic() + timeout
    try:
        with socket.create_connection((host, port), timeout=timeout) as sock:
            exchange(sock, deadline)
    except TimeoutError:
        raise ArmError(f"cannot connect to the UR at {host}: no {what} answer on port {port} within "
                       f"{timeout:g} s") from None
    except (OSError, ConnectionError) as exc:
        raise ArmError(f"cannot connect to the UR at {host}: {what} on port {port}: {_one_line(exc)}") from None


def probe_rtde(host: str, timeout: float = CONNECT_TIMEOUT_S) -> None:
    """The RTDE handshake's first step: request protocol version 2 and read the controller's accept."""
    def exchange(sock: socket.socket, deadline: float) -> None:
        sock.sendall(struct.pack(">HBH", 5, ord("V"), RTDE_PROTOCOL_VERSION))
        size, kind = struct.unpack(">HB", _receive_exactly(sock, 3, deadline))
        payload = _receive_exactly(sock, max(size - 3, 0), deadline)
        if kind != ord("V") or not payload:
            raise ConnectionError(f"not an RTDE answer (package type {kind})")
        if payload[0] != 1:
            raise ConnectionError(f"the controller refused RTDE protocol version {RTDE_PROTOCOL_VERSION}")

    _probe(host, RTDE_PORT, timeout, "RTDE", exchange)


def dashboard_stop(host: str, timeout: float = CONNECT_TIMEOUT_S) -> bool:
    """Ask the dashboard server to stop the running program (the control script): True if it said so.
    A plain socket with a deadline, no ur_rtde: used when the ur_rtde process was given up mid-motion."""
    answer = b""

    def exchange(sock: socket.socket, deadline: float) -> None:
        nonlocal answer
        line = b""
        while not line.endswith(b"\n") and len(line) < 256:
            line += _receive_exactly(sock, 1, deadline)
        sock.sendall(b"stop\n")
        while not answer.endswith(b"\n") and len(answer) < 256:
            answer += _receive_exactly(sock, 1, deadline)

    try:
        _probe(host, DASHBOARD_PORT, timeout, "dashboard", exchange)
    except ArmError:
        return False
    return answer.lower().startswith(b"stopped")


def probe_dashboard(host: str, timeout: float = CONNECT_TIMEOUT_S) -> None:
    """The dashboard server greets every client with one line; read it."""
    def exchange(sock: socket.socket, deadline: float) -> None:
        line = b""
        while not line.endswith(b"\n") and len(line) < 256:
            line += _receive_exactly(sock, 1, deadline)
        if not line.decode(errors="replace").startswith(DASHBOARD_WELCOME):
            raise ConnectionError(f"not a UR dashboard server (it said {line[:60]!r})")

    _probe(host, DASHBOARD_PORT, timeout, "dashboard", exchange)


class UR5Arm:
    """ur_rtde implementation of `touchroller_driver.arm.Arm`."""

    def __init__(self, robot_ip: str, *, limits: ArmLimits | None = None, frequency: float = -1.0,
                 check_reachability: bool = True, watchdog_hz: float = WATCHDOG_HZ,
                 connect_timeout: float = CONNECT_TIMEOUT_S, isolated: bool = True,
                 call_timeout: float = CALL_TIMEOUT_S, open_timeout: float = OPEN_TIMEOUT_S) -> None:
        """`isolated` (the default): ur_rtde runs in a child process with deadlines (`call_timeout` for a
        call, `open_timeout` for a constructor); False makes the objects in this process (tests with doubles)."""
        try:
            ipaddress.ip_address(robot_ip)
        except ValueError:
            if not robot_ip or any(c.isspace() for c in robot_ip):
                raise ValueError(f"robot_ip {robot_ip!r} is not an IP address or host name") from None
        self.robot_ip = robot_ip
        self.limits = limits or ArmLimits()
        self.frequency = float(frequency)
        self.check_reachability = check_reachability
        self.watchdog_hz = float(watchdog_hz)  # 0 disables the watchdog
        if not (math.isfinite(connect_timeout) and connect_timeout > 0):
            raise ValueError(f"connect_timeout must be a number of seconds > 0, got {connect_timeout}")
        self.connect_timeout = float(connect_timeout)
        for name, value in (("call_timeout", call_timeout), ("open_timeout", open_timeout)):
            if not (math.isfinite(value) and value > 0):
                raise ValueError(f"{name} must be a number of seconds > 0, got {value}")
        self.isolated = isolated
        self.call_timeout, self.open_timeout = float(call_timeout), float(open_timeout)
        self._child: RtdeChild | None = None
        self._local: LocalRtde | None = None
        self._control: Any = None
        self._receive: Any = None
        self._fault: str | None = None
        self._move_start: np.ndarray | None = None
        self._move_target: np.ndarray | None = None
        self._move_path: np.ndarray | None = None   # the waypoints (N, 6) of a path under way
        self._halted_fraction = 1.0

    # -- connection ----------------------------------------------------------------------------
    def _open(self, interface: str) -> Any:
        """A ur_rtde object: a proxy of one in the child process (isolated), or the object itself."""
        if not self.isolated:
            self._local = self._local or LocalRtde()
            return self._local.open(interface, self.robot_ip, self.frequency)
        if self._child is None or not self._child.alive:
            self._child = RtdeChild(self.robot_ip, call_timeout=self.call_timeout, open_timeout=self.open_timeout)
        return self._child.open(interface, self.frequency)

    def abort(self) -> None:
        """From any thread: give up the ur_rtde call under way (and every later one until `connect()`)."""
        child = self._child
        if child is not None:
            child.abort()

    def connect(self) -> None:
        """Open the receive stream, then the control interface (which uploads the control script), each
        after probing its ports (a silent host fails here in `connect_timeout`, not in ur_rtde for ever),
        each within `open_timeout` (a host that greets and then goes silent fails here too)."""
        self.disconnect()
        try:
            probe_rtde(self.robot_ip, self.connect_timeout)
            self._receive = self._open("receive")
            probe_dashboard(self.robot_ip, self.connect_timeout)
            self._control = self._open("control")
        except RtdeGone as exc:
            self.disconnect()
            self._fault = f"cannot connect to the UR at {self.robot_ip}: {exc}"
            raise ArmError(self._fault) from None
        except ArmError as exc:
            self.disconnect()
            self._fault = str(exc)
            raise
        except RuntimeError as exc:
            self.disconnect()
            message = f"cannot connect to the UR at {self.robot_ip}: {_one_line(exc)}"
            self._fault = message
            raise ArmError(message) from exc
        if self.watchdog_hz > 0 and not self._control.setWatchdog(self.watchdog_hz):
            self.disconnect()
            self._fault = "the robot refused the communication watchdog"
            raise ArmError(self._fault)
        self._fault = None

    def reset_fault(self) -> None:
        """Clear a fault as the UR's dashboard does: a protective stop is unlocked through the dashboard
        server (the controller allows it 5 s after the stop), then the interfaces reconnect (a protective
        stop ends the control script). An emergency stop must be released on the teach pendant first;
        ArmError (one line) when the fault remains."""
        receive = self._receive
        emergency = protective = False
        if receive is not None:
            try:
                if receive.isConnected():
                    emergency, protective = receive.isEmergencyStopped(), receive.isProtectiveStopped()
            except (RuntimeError, ArmError):
                pass   # the stream (or the ur_rtde process) is gone: reconnecting tells
        if emergency:
            raise ArmError("emergency stop: release it on the teach pendant, then reset")
        if protective:
            self._unlock_protective_stop()
        self._fault = None
        self.connect()
        fault = self.fault()
        if fault is not None:
            raise ArmError(f"the fault remains after the reset: {fault}")

    def _unlock_protective_stop(self) -> None:
        probe_dashboard(self.robot_ip, self.connect_timeout)
        dashboard = self._open("dashboard")
        try:
            dashboard.connect(round(self.connect_timeout * 1000))
            dashboard.unlockProtectiveStop()
        except RuntimeError as exc:
            raise ArmError(f"unlocking the protective stop failed: {_one_line(exc)}") from exc
        finally:
            try:
                dashboard.disconnect()
            except (RuntimeError, ArmError):
                pass

    def keepalive(self) -> None:
        """Kick the controller-side watchdog: if this process hangs or dies, the robot stops."""
        if self._control is not None and self.watchdog_hz > 0:
            self._control.kickWatchdog()

    def disconnect(self) -> None:
        control, receive = self._control, self._receive
        self._control = self._receive = None
        child, self._child = self._child, None
        self._local = None
        for interface, calls in ((control, ("stopScript", "disconnect")), (receive, ("disconnect",))):
            if interface is None:
                continue
            for call in calls:
                try:
                    getattr(interface, call)()
                except (RuntimeError, ArmError):
                    pass  # already gone: nothing left to release
        if child is not None:
            child.close()

    # -- state ---------------------------------------------------------------------------------
    def tcp_pose(self) -> np.ndarray:
        receive = self._require_receive()
        pose = np.asarray(receive.getActualTCPPose(), dtype=np.float64)
        if pose.shape != (6,):
            raise ArmError(f"robot returned a TCP pose with {pose.size} values")
        return pose

    def fault(self) -> str | None:
        """A protective/emergency stop, a lost connection or a robot that stopped answering (the ur_rtde
        process given up), as one line; None when healthy."""
        if self._fault is not None:
            return self._fault
        if self._child is not None and self._child.failure is not None:
            return self._gone(self._child.failure)
        if self._receive is None or self._control is None:
            return None
        try:
            return self._read_fault()
        except RtdeGone as exc:
            return self._gone(str(exc))

    def _gone(self, why: str) -> str:
        """The ur_rtde process was given up: latch the fault, drop the interfaces, and ask the dashboard
        server to stop the program too (the controller's watchdog stops it regardless)."""
        self._control = self._receive = None
        stopped = dashboard_stop(self.robot_ip, min(self.connect_timeout, 0.5))
        self._fault = (f"the UR at {self.robot_ip} stopped answering ({why}): the ur_rtde connection was given up, "
                       "the robot's communication watchdog stops the control script"
                       f"{'; the dashboard server stopped the program' if stopped else ''}")
        return self._fault

    def _read_fault(self) -> str | None:
        if not self._receive.isConnected() or not self._control.isConnected():
            self._fault = "lost the RTDE connection to the robot"
        elif self._receive.isEmergencyStopped():
            self._fault = "emergency stop"
        elif self._receive.isProtectiveStopped():
            self._fault = f"protective stop (safety mode {self._receive.getSafetyMode()})"
        return self._fault

    def is_moving(self) -> bool:
        control = self._require_control()
        return control.getAsyncOperationProgress() >= 0 or not control.isSteady()

    def progress(self) -> float:
        """Fraction (0..1) of the current or last move (of a path: of its length), from the measured TCP."""
        if self._move_path is not None:
            return fraction_along_path(self._move_path, self.tcp_pose())
        if self._move_start is None or self._move_target is None:
            return self._halted_fraction
        return _fraction_along(self._move_start, self._move_target, self.tcp_pose())

    # -- motion --------------------------------------------------------------------------------
    def move_linear(self, target_pose: ArrayLike, speed: float, accel: float,
                    asynchronous: bool = True) -> None:
        target = self.limits.check(target_pose, speed, accel)
        control = self._require_control()
        if self.fault() is not None:
            raise ArmError(f"arm faulted: {self._fault}")
        if self.check_reachability and not control.isPoseWithinSafetyLimits(target.tolist()):
            raise ArmError(f"target {np.round(target, 4).tolist()} is outside the robot's safety limits")
        self._move_start, self._move_target, self._move_path = self.tcp_pose(), target, None
        if not control.moveL(target.tolist(), float(speed), float(accel), bool(asynchronous)):
            raise ArmError(self.fault() or "the robot refused moveL")

    def move_path(self, waypoints: ArrayLike, speed: float, accel: float, blend: float,
                  asynchronous: bool = True) -> None:
        """One ur_rtde moveL of a path: every waypoint [x, y, z, rx, ry, rz, speed, accel, blend] (its
        `blend_radii` radius: 0 at both ends, so it stops only at the last), after every waypoint and corner
        passed `ArmLimits.check_path`, the controller's safety limits and the tool is at the first one.
        Asynchronous (the default), the control script runs it while the sweep node keeps kicking the
        watchdog; `stop()` (stopL) ends it where it is."""
        points = self.limits.check_path(waypoints, speed, accel, blend)
        control = self._require_control()
        if self.fault() is not None:
            raise ArmError(f"arm faulted: {self._fault}")
        if self.check_reachability:
            for k, pose in enumerate(points):
                if not control.isPoseWithinSafetyLimits(pose.tolist()):
                    raise ArmError(f"path waypoint {k + 1} of {len(points)} {np.round(pose, 4).tolist()} is "
                                   "outside the robot's safety limits")
        start = self.tcp_pose()
        check_path_start(start, points)
        path = [[*pose.tolist(), float(speed), float(accel), float(radius)]
                for pose, radius in zip(points, blend_radii(points, blend), strict=True)]
        self._move_start, self._move_target, self._move_path = start, points[-1], points
        if not control.moveL(path, bool(asynchronous)):
            raise ArmError(self.fault() or "the robot refused the moveL path")

    def stop(self) -> None:
        if self._control is None:
            return
        try:
            if self._move_path is not None and self._receive is not None:
                self._halted_fraction = fraction_along_path(self._move_path, self.tcp_pose())
            elif self._move_start is not None and self._move_target is not None and self._receive is not None:
                self._halted_fraction = _fraction_along(self._move_start, self._move_target, self.tcp_pose())
            self._move_start = self._move_target = self._move_path = None
            self._control.stopL(STOP_DECELERATION)
        except RtdeGone as exc:   # the robot stopped answering: given up, its watchdog stops it
            self._gone(str(exc))
        except RuntimeError as exc:  # e.g. the script already ended on a protective stop: nothing moves
            self._fault = self._fault or f"stopL failed: {_one_line(exc)}"


    # -- internals -----------------------------------------------------------------------------
    def _require_control(self) -> Any:
        if self._control is None:
            raise ArmError(self._fault or "arm not connected")
        return self._control

    def _require_receive(self) -> Any:
        if self._receive is None:
            raise ArmError(self._fault or "arm not connected")
        return self._receive


def _fraction_along(start: np.ndarray, target: np.ndarray, pose: np.ndarray) -> float:
    delta = target[:3] - start[:3]
    length_sq = float(delta @ delta)
    if length_sq == 0.0:
        return 1.0
    fraction = float((pose[:3] - start[:3]) @ delta) / length_sq
    return min(max(fraction, 0.0), 1.0) if math.isfinite(fraction) else float("nan")


def _one_line(exc: BaseException) -> str:
    return " ".join(str(exc).split()) or type(exc).__name__


__all__ = ["CONSTRUCTOR_CALLS", "CONTROL_CALLS", "DASHBOARD_CALLS", "PATH_CALLS", "RECEIVE_CALLS", "UR5Arm",
           "probe_dashboard", "probe_rtde"]
