"""The ur_rtde arm against the installed ur_rtde module (no robot: loopback only).

- every call ur5.py makes exists in the installed pybind module with an overload that takes the
  number of positional arguments we pass;
- connecting to a loopback address where nothing listens fails fast with one clear line and a fault;
- the fault/limit logic runs on autospecced doubles of the real classes (a misspelt call fails).
"""
from __future__ import annotations

import math
import re
from unittest import mock

import numpy as np
import pytest

from touchroller_driver import ur5
from touchroller_driver.arm import Arm, ArmError, ArmLimitError, ArmLimits

rtde_control = pytest.importorskip("rtde_control")
rtde_receive = pytest.importorskip("rtde_receive")
dashboard_client = pytest.importorskip("dashboard_client")

# A loopback address nothing listens on (all of 127/8 is loopback on Linux): connection refused.
REFUSED_HOST = "127.0.0.213"
POSE = [0.4, 0.0, 0.2, math.pi, 0.0, 0.0]


def _split_top_level(text: str) -> list[str]:
    parts, depth, current = [], 0, []
    for char in text:
        if char in "[(":
            depth += 1
        elif char in "])":
            depth -= 1
        if char == "," and depth == 0:
            parts.append("".join(current).strip())
            current = []
        else:
            current.append(char)
    if "".join(current).strip():
        parts.append("".join(current).strip())
    return parts


def overload_arities(function, name: str) -> list[tuple[int, int]]:
    """(required, total) positional parameters (without self) of each pybind overload of `function`."""
    arities = []
    for match in re.finditer(rf"^(?:\d+\. )?{name}\((.*)\) -> ", function.__doc__ or "", flags=re.MULTILINE):
        params = [p for p in _split_top_level(match.group(1)) if not p.startswith("self")]
        required = sum("=" not in p for p in params)
        arities.append((required, len(params)))
    return arities


@pytest.mark.parametrize(("cls", "calls"), [
    (rtde_control.RTDEControlInterface, ur5.CONTROL_CALLS),
    (rtde_control.RTDEControlInterface, ur5.PATH_CALLS),
    (rtde_receive.RTDEReceiveInterface, ur5.RECEIVE_CALLS),
    (dashboard_client.DashboardClient, ur5.DASHBOARD_CALLS),
])
def test_every_call_exists_with_the_arity_we_use(cls, calls):
    for name, n_args in calls.items():
        assert hasattr(cls, name), f"{cls.__name__}.{name} does not exist in ur_rtde"
        arities = overload_arities(getattr(cls, name), name)
        assert arities, f"could not read the signature of {cls.__name__}.{name}"
        assert any(lo <= n_args <= hi for lo, hi in arities), (name, n_args, arities)


def test_constructors_take_host_and_frequency():
    for cls_name, n_args in ur5.CONSTRUCTOR_CALLS.items():
        cls = getattr(rtde_control if "Control" in cls_name else rtde_receive, cls_name)
        arities = overload_arities(cls.__init__, "__init__")
        assert any(lo <= n_args <= hi for lo, hi in arities), (cls_name, arities)


def test_the_path_overload_of_moveL_takes_waypoints_with_speed_accel_and_blend():
    doc = rtde_control.RTDEControlInterface.moveL.__doc__ or ""
    assert re.search(r"moveL\(self[^,]*, path: list\[list\[float\]\], asynchronous: bool = False\) -> bool", doc)
    assert "acceleration, speed and blend" in doc


def test_signature_parser_rejects_a_wrong_arity():
    # moveL(pose, speed, accel, async) exists; moveL with 6 positional arguments does not.
    arities = overload_arities(rtde_control.RTDEControlInterface.moveL, "moveL")
    assert not any(lo <= 6 <= hi for lo, hi in arities)


def test_refused_connection_is_one_clear_line_and_a_fault():
    arm = ur5.UR5Arm(REFUSED_HOST)
    assert isinstance(arm, Arm)
    with pytest.raises(ArmError) as info:
        arm.connect()
    message = str(info.value)
    assert REFUSED_HOST in message and "\n" not in message and "cannot connect" in message
    assert arm.fault() == message
    with pytest.raises(ArmError):
        arm.tcp_pose()
    with pytest.raises(ArmError):
        arm.move_linear(POSE, 0.01, 0.1)
    arm.stop()  # harmless when not connected
    arm.disconnect()


def test_bad_robot_ip_is_rejected_up_front():
    with pytest.raises(ValueError):
        ur5.UR5Arm("")
    with pytest.raises(ValueError):
        ur5.UR5Arm("192.168.1.2 ; rm")


@pytest.fixture()
def connected_arm(monkeypatch):
    """A UR5Arm whose ur_rtde interfaces are autospecced doubles of the installed classes."""
    control = mock.create_autospec(rtde_control.RTDEControlInterface, instance=True)
    receive = mock.create_autospec(rtde_receive.RTDEReceiveInterface, instance=True)
    control.isConnected.return_value = True
    control.isPoseWithinSafetyLimits.return_value = True
    control.moveL.return_value = True
    control.getAsyncOperationProgress.return_value = 0
    control.isSteady.return_value = False
    receive.isConnected.return_value = True
    receive.isProtectiveStopped.return_value = False
    receive.isEmergencyStopped.return_value = False
    receive.getSafetyMode.return_value = 1
    receive.getActualTCPPose.return_value = list(POSE)
    control.setWatchdog.return_value = True
    monkeypatch.setattr(rtde_control, "RTDEControlInterface", lambda host, freq: control)
    monkeypatch.setattr(rtde_receive, "RTDEReceiveInterface", lambda host, freq: receive)
    monkeypatch.setattr(ur5, "probe_rtde", lambda host, timeout: None)   # no controller behind the doubles
    monkeypatch.setattr(ur5, "probe_dashboard", lambda host, timeout: None)
    arm = ur5.UR5Arm("127.0.0.1", limits=ArmLimits(max_speed=0.05, max_accel=0.5), isolated=False)
    arm.connect()
    return arm, control, receive


def test_watchdog_is_armed_on_connect_and_kicked_by_keepalive(connected_arm):
    arm, control, _ = connected_arm
    control.setWatchdog.assert_called_once_with(ur5.WATCHDOG_HZ)
    arm.keepalive()
    arm.keepalive()
    assert control.kickWatchdog.call_count == 2


def test_limits_are_checked_before_moveL_is_sent(connected_arm):
    arm, control, _ = connected_arm
    with pytest.raises(ArmLimitError):
        arm.move_linear(np.add(POSE, [0.1, 0, 0, 0, 0, 0]), 0.5, 0.1)
    control.moveL.assert_not_called()
    arm.move_linear(np.add(POSE, [0.1, 0, 0, 0, 0, 0]), 0.02, 0.1)
    args = control.moveL.call_args.args
    assert args[1:] == (0.02, 0.1, True) and args[0][0] == pytest.approx(0.5)


def test_unreachable_target_is_refused(connected_arm):
    arm, control, _ = connected_arm
    control.isPoseWithinSafetyLimits.return_value = False
    with pytest.raises(ArmError, match="safety limits"):
        arm.move_linear(POSE, 0.02, 0.1)
    control.moveL.assert_not_called()


def test_protective_stop_becomes_a_fault_that_refuses_motion(connected_arm):
    arm, control, receive = connected_arm
    assert arm.fault() is None
    receive.isProtectiveStopped.return_value = True
    assert "protective stop" in arm.fault()
    with pytest.raises(ArmError, match="protective stop"):
        arm.move_linear(POSE, 0.02, 0.1)
    control.moveL.assert_not_called()


def test_lost_connection_is_a_fault(connected_arm):
    arm, control, _ = connected_arm
    control.isConnected.return_value = False
    assert "lost the RTDE connection" in arm.fault()


def test_progress_follows_the_measured_tcp(connected_arm):
    arm, control, receive = connected_arm
    arm.move_linear(np.add(POSE, [0.1, 0, 0, 0, 0, 0]), 0.02, 0.1)
    receive.getActualTCPPose.return_value = list(np.add(POSE, [0.025, 0, 0, 0, 0, 0]))
    assert arm.progress() == pytest.approx(0.25)
    assert arm.is_moving()
    arm.stop()
    control.stopL.assert_called_once_with(ur5.STOP_DECELERATION)
    assert arm.progress() == pytest.approx(0.25)
    arm.disconnect()
    control.stopScript.assert_called_once_with()
    receive.disconnect.assert_called_once_with()


# -- the real rtde_receive against a minimal RTDE server on loopback --------------------------------
# The server runs in a subprocess: ur_rtde's pybind constructors hold the GIL while connecting, so a
# server thread in this interpreter could never answer. It speaks RTDE v2 on 30004 to any number of
# clients (UR5Arm probes first): protocol version, controller version, output recipe setup (answering
# each requested variable with its RTDE type), start, then data packages at 100 Hz carrying a TCP pose
# and safety status bits that stdin commands change; and the dashboard server on 29999, whose "unlock
# protective stop" clears the protective stop.
FAKE_RTDE_SERVER = r'''
import socket, struct, sys, threading, time
HOST = sys.argv[1]
FORMATS = {"DOUBLE": "d", "UINT64": "Q", "INT32": "i", "UINT32": "I", "VECTOR6D": "6d", "VECTOR3D": "3d",
           "VECTOR6INT32": "6i"}
NAMED = {"timestamp": "DOUBLE", "actual_digital_input_bits": "UINT64", "actual_digital_output_bits": "UINT64",
         "robot_mode": "INT32", "safety_mode": "INT32", "joint_mode": "VECTOR6INT32", "runtime_state": "UINT32",
         "robot_status_bits": "UINT32", "safety_status_bits": "UINT32", "actual_tool_accelerometer": "VECTOR3D",
         "payload_cog": "VECTOR3D", "actual_execution_time": "DOUBLE", "speed_scaling": "DOUBLE",
         "target_speed_fraction": "DOUBLE", "actual_momentum": "DOUBLE", "actual_main_voltage": "DOUBLE",
         "actual_robot_voltage": "DOUBLE", "actual_robot_current": "DOUBLE", "payload": "DOUBLE"}
def kind(name):
    if name in NAMED: return NAMED[name]
    if name.startswith("output_int_register"): return "INT32"
    if name.startswith(("output_double_register", "standard_analog")): return "DOUBLE"
    return "VECTOR6D"
state = {"pose": [0.0] * 6, "safety_bits": 1, "unlocks": 0}
def commands():
    for line in sys.stdin:
        words = line.split()
        if words[:1] == ["protective"]: state["safety_bits"] = 1 | 4
        if words[:1] == ["pose"]: state["pose"] = [float(x) for x in words[1:7]]
threading.Thread(target=commands, daemon=True).start()
def listen(port):
    server = socket.socket(); server.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
    server.bind((HOST, port)); server.listen(8)
    return server
def rtde(conn):
    # one RTDE client: protocol version, controller version, output recipe, start, data at 100 Hz
    lock = threading.Lock()
    def send(t, payload):
        with lock: conn.sendall(struct.pack(">HB", len(payload) + 3, ord(t)) + payload)
    def exact(n):
        data = b""
        while len(data) < n:
            chunk = conn.recv(n - len(data))
            if not chunk: raise EOFError
            data += chunk
        return data
    names = []
    def stream():
        while True:
            package = b"\x01"
            for name in names:
                fmt = FORMATS[kind(name)]
                count = int(fmt[:-1] or 1)
                values = {"actual_TCP_pose": state["pose"], "safety_status_bits": [state["safety_bits"]],
                          "timestamp": [time.monotonic()]}.get(name, [0] * count)
                package += struct.pack(">" + fmt, *values)
            try: send("U", package)
            except OSError: return
            time.sleep(0.01)
    try:
        while True:
            size, kind_byte = struct.unpack(">HB", exact(3))
            payload, command = exact(size - 3), chr(kind_byte)
            if command == "V": send("V", b"\x01")
            elif command == "v": send("v", struct.pack(">IIII", 5, 15, 0, 0))
            elif command == "O":
                names = [n for n in payload[8:].decode().split(",") if n]
                send("O", b"\x01" + ",".join(kind(n) for n in names).encode())
            elif command == "S":
                send("S", b"\x01"); threading.Thread(target=stream, daemon=True).start()
            elif command == "P": send("P", b"\x01")
    except (EOFError, OSError):
        pass
def dashboard(conn):
    # the dashboard server: a welcome line, then one answer per command line
    try:
        conn.sendall(b"Connected: Universal Robots Dashboard Server\n")
        for line in conn.makefile("rb"):
            if line.strip() == b"unlock protective stop":
                state["safety_bits"], state["unlocks"] = 1, state["unlocks"] + 1
                conn.sendall(b"Protective stop releasing\n")
            else:
                conn.sendall(b"could not understand: '" + line.strip() + b"'\n")
    except OSError:
        pass
def serve(server, handler):
    while True:
        conn, _ = server.accept()
        threading.Thread(target=handler, args=(conn,), daemon=True).start()
servers = [(listen(30004), rtde), (listen(29999), dashboard)]
for server, handler in servers:
    threading.Thread(target=serve, args=(server, handler), daemon=True).start()
print("listening", flush=True)
threading.Event().wait()
'''


@pytest.fixture
def fake_rtde_server():
    """(host, send_command) of a fake RTDE server on a free 127.0.0.x:30004."""
    import os
    import subprocess
    import sys

    for attempt in range(10):
        host = f"127.0.0.{100 + (os.getpid() + 17 * attempt) % 150}"
        server = subprocess.Popen([sys.executable, "-u", "-c", FAKE_RTDE_SERVER, host], stdin=subprocess.PIPE,
                                  stdout=subprocess.PIPE, stderr=subprocess.DEVNULL, text=True)
        if server.stdout.readline().strip() == "listening":
            break
        server.wait(timeout=5)
    else:
        pytest.skip("no free loopback address for the fake RTDE server")

    def command(line: str) -> None:
        server.stdin.write(line + "\n")
        server.stdin.flush()

    try:
        yield host, command
    finally:
        server.kill()
        server.wait(timeout=5)


def _wait_for(predicate, timeout: float = 20.0) -> bool:
    import time

    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if predicate():
            return True
        time.sleep(0.02)
    return predicate()


@pytest.mark.timeout(30)
def test_real_rtde_receive_reads_pose_and_protective_stop(fake_rtde_server, monkeypatch):
    host, command = fake_rtde_server
    control = mock.create_autospec(rtde_control.RTDEControlInterface, instance=True)
    control.isConnected.return_value = True
    control.isPoseWithinSafetyLimits.return_value = True
    control.moveL.return_value = True
    control.setWatchdog.return_value = True
    monkeypatch.setattr(rtde_control, "RTDEControlInterface", lambda h, f: control)  # receive stays real
    arm = ur5.UR5Arm(host, isolated=False)   # the control double lives in this process
    arm.connect()
    try:
        assert isinstance(arm._receive, rtde_receive.RTDEReceiveInterface)
        command("pose 0.41 -0.02 0.205 3.1 0.05 -0.01")
        assert _wait_for(lambda: arm.tcp_pose()[0] == pytest.approx(0.41))
        np.testing.assert_allclose(arm.tcp_pose(), [0.41, -0.02, 0.205, 3.1, 0.05, -0.01])
        assert arm.fault() is None
        arm.move_linear([0.45, -0.02, 0.205, 3.1, 0.05, -0.01], 0.01, 0.1)
        command("protective")
        assert _wait_for(lambda: arm.fault() is not None)
        assert "protective stop" in arm.fault()
        control.moveL.reset_mock()
        with pytest.raises(ArmError, match="protective stop"):
            arm.move_linear(POSE, 0.01, 0.1)
        control.moveL.assert_not_called()
    finally:
        arm.disconnect()


def test_reset_fault_unlocks_a_protective_stop_and_reconnects(connected_arm, monkeypatch):
    arm, control, receive = connected_arm
    dashboard = mock.create_autospec(dashboard_client.DashboardClient, instance=True)
    monkeypatch.setattr(dashboard_client, "DashboardClient", lambda host: dashboard)
    receive.isProtectiveStopped.return_value = True
    assert "protective stop" in arm.fault()
    dashboard.unlockProtectiveStop.side_effect = lambda: setattr(receive.isProtectiveStopped, "return_value", False)
    control.setWatchdog.reset_mock()
    arm.reset_fault()
    dashboard.unlockProtectiveStop.assert_called_once_with()
    control.setWatchdog.assert_called_once_with(ur5.WATCHDOG_HZ)   # reconnected: the control script again
    assert arm.fault() is None
    arm.move_linear(POSE, 0.02, 0.1)
    control.moveL.assert_called_once()


def test_reset_fault_refuses_an_emergency_stop_and_keeps_the_fault(connected_arm, monkeypatch):
    arm, control, receive = connected_arm
    dashboard = mock.create_autospec(dashboard_client.DashboardClient, instance=True)
    monkeypatch.setattr(dashboard_client, "DashboardClient", lambda host: dashboard)
    receive.isEmergencyStopped.return_value = True
    assert arm.fault() == "emergency stop"
    with pytest.raises(ArmError, match="teach pendant"):
        arm.reset_fault()
    dashboard.unlockProtectiveStop.assert_not_called()
    assert arm.fault() == "emergency stop"
    with pytest.raises(ArmError):
        arm.move_linear(POSE, 0.02, 0.1)


def test_a_failed_unlock_is_one_line_and_the_fault_stays(connected_arm, monkeypatch):
    arm, control, receive = connected_arm
    dashboard = mock.create_autospec(dashboard_client.DashboardClient, instance=True)
    dashboard.unlockProtectiveStop.side_effect = RuntimeError("Cannot unlock protective stop until 5s after\n"
                                                              "occurrence")
    monkeypatch.setattr(dashboard_client, "DashboardClient", lambda host: dashboard)
    receive.isProtectiveStopped.return_value = True
    with pytest.raises(ArmError) as info:
        arm.reset_fault()
    assert "5s after occurrence" in str(info.value) and "\n" not in str(info.value)
    assert "protective stop" in arm.fault()


@pytest.mark.timeout(60)
def test_real_clients_reset_a_protective_stop_on_the_fake_controller(fake_rtde_server, monkeypatch):
    """The real rtde_receive and the real dashboard client against the fake controller: the protective stop
    shows, `reset_fault` unlocks it through the dashboard server and reconnects, and the fault is gone."""
    host, command = fake_rtde_server
    control = mock.create_autospec(rtde_control.RTDEControlInterface, instance=True)
    control.isConnected.return_value = True
    control.setWatchdog.return_value = True
    monkeypatch.setattr(rtde_control, "RTDEControlInterface", lambda h, f: control)  # receive stays real
    arm = ur5.UR5Arm(host, isolated=False)   # the control double lives in this process
    arm.connect()
    try:
        command("protective")
        assert _wait_for(lambda: arm.fault() is not None)
        assert "protective stop" in arm.fault()
        arm.reset_fault()
        assert arm.fault() is None
        assert isinstance(arm._receive, rtde_receive.RTDEReceiveInterface)
    finally:
        arm.disconnect()


@pytest.mark.timeout(120)
def test_a_silent_host_is_a_one_line_error_not_a_frozen_process(silent_ur_host):
    """ur_rtde's constructors would wait for ever with the GIL held; the probe gives up first. Run in a
    child process: a frozen interpreter cannot even be interrupted, so the parent is the judge."""
    import subprocess
    import sys

    code = ("import sys\nfrom touchroller_driver.ur5 import UR5Arm\nfrom touchroller_driver.arm import ArmError\n"
            "arm = UR5Arm(sys.argv[1], connect_timeout=0.5)\n"
            "try:\n    arm.connect()\nexcept ArmError as exc:\n"
            "    print('ERROR', exc)\n    print('FAULT', arm.fault())\n")
    try:
        done = subprocess.run([sys.executable, "-c", code, silent_ur_host], capture_output=True, text=True,
                              timeout=60)
    except subprocess.TimeoutExpired:
        pytest.fail("connecting to a silent host froze the process")
    lines = done.stdout.splitlines()
    assert lines[0].startswith("ERROR cannot connect to the UR at " + silent_ur_host), done.stdout + done.stderr
    assert "no RTDE answer" in lines[0]
    assert lines[1] == "FAULT " + lines[0][len("ERROR "):]


def test_probes_tell_a_controller_from_something_else(fake_rtde_server, silent_ur_host):
    host, _ = fake_rtde_server
    ur5.probe_rtde(host, 5.0)
    ur5.probe_dashboard(host, 5.0)
    with pytest.raises(ArmError, match="no RTDE answer on port 30004 within 0.2 s"):
        ur5.probe_rtde(silent_ur_host, 0.2)
    with pytest.raises(ArmError, match="no dashboard answer on port 29999"):
        ur5.probe_dashboard(silent_ur_host, 0.2)
    with pytest.raises(ArmError, match="cannot connect to the UR at 127.0.0.213: RTDE on port 30004"):
        ur5.probe_rtde(REFUSED_HOST, 1.0)


# -- issue #29: every ur_rtde call in a child process the arm thread can give up -----------------------

@pytest.mark.timeout(120)
def test_a_host_that_greets_then_stalls_is_given_up_without_freezing_the_process(half_alive_ur_host):
    """The probes pass (the host answers the RTDE greeting and the dashboard's welcome line), then ur_rtde's
    constructor waits for ever with the GIL held: it runs in the child, which is given up after open_timeout;
    meanwhile this process runs (a thread counts). Judged from a parent: a frozen interpreter cannot judge."""
    import subprocess
    import sys

    code = ("import sys, threading, time\nfrom touchroller_driver.ur5 import UR5Arm\n"
            "from touchroller_driver.arm import ArmError\n"
            "ticks = []\nthreading.Thread(target=lambda: [ticks.append(time.sleep(0.01)) for _ in iter(int, 1)],"
            " daemon=True).start()\n"
            "arm = UR5Arm(sys.argv[1], open_timeout=1.0)\n"
            "try:\n    arm.connect()\nexcept ArmError as exc:\n"
            "    print('ERROR', exc)\n    print('FAULT', arm.fault())\n    print('TICKS', len(ticks))\n")
    try:
        done = subprocess.run([sys.executable, "-c", code, half_alive_ur_host], capture_output=True, text=True,
                              timeout=60)
    except subprocess.TimeoutExpired:
        pytest.fail("connecting to a host that greets and then stalls froze the process")
    lines = done.stdout.splitlines()
    assert lines and lines[0] == f"ERROR cannot connect to the UR at {half_alive_ur_host}: no answer to " \
        f"RTDEReceiveInterface('{half_alive_ur_host}') (connecting) within 1 s", done.stdout + done.stderr
    assert lines[1] == "FAULT " + lines[0][len("ERROR "):]
    assert int(lines[2].split()[1]) > 10   # the other thread ran while ur_rtde waited in the child


@pytest.mark.timeout(60)
def test_abort_from_another_thread_gives_up_a_call_at_once(half_alive_ur_host):
    import threading

    arm = ur5.UR5Arm(half_alive_ur_host, open_timeout=600.0)
    failed: list[str] = []

    def connect() -> None:
        try:
            arm.connect()
        except ArmError as exc:
            failed.append(str(exc))

    thread = threading.Thread(target=connect)
    thread.start()
    assert _wait_for(lambda: arm._child is not None and arm._child._process is not None)
    arm.abort()
    thread.join(timeout=30.0)
    assert not thread.is_alive() and failed and "aborted" in failed[0]
    assert arm.fault() == failed[0]


@pytest.mark.timeout(60)
def test_the_real_receive_interface_answers_from_the_child_and_a_hung_child_is_a_fault(fake_rtde_server):
    """The real rtde_receive in the child reads the fake controller's stream; then the child hangs (SIGSTOP
    stands in for ur_rtde blocked on a robot gone silent mid-run): the next call is given up after
    call_timeout, the child is killed, and UR5Arm reports the fault in one line and refuses motion."""
    import os
    import signal

    from touchroller_driver.ur_rtde_process import RtdeChild, RtdeGone

    host, command = fake_rtde_server
    child = RtdeChild(host, call_timeout=0.5)
    receive = child.open("receive", -1.0)
    command("pose 0.41 -0.02 0.205 3.1 0.05 -0.01")
    assert _wait_for(lambda: receive.getActualTCPPose()[0] == pytest.approx(0.41))
    assert receive.isConnected() is True
    arm = ur5.UR5Arm(host)
    arm._child, arm._receive, arm._control = child, receive, receive   # connected (control: any proxy will do)
    assert arm.fault() is None
    pid = child._process.pid
    os.kill(pid, signal.SIGSTOP)
    fault = arm.fault()
    assert fault.startswith(f"the UR at {host} stopped answering (no answer to isConnected() within 0.5 s)")
    assert "\n" not in fault and child.failure is not None
    with pytest.raises(ProcessLookupError):   # killed, and reaped
        os.kill(pid, 0)
    with pytest.raises(ArmError, match="stopped answering"):
        arm.move_linear(POSE, 0.01, 0.1)
    with pytest.raises(RtdeGone):
        receive.getActualTCPPose()
    arm.disconnect()


@pytest.mark.timeout(60)
def test_a_reset_after_the_ur_rtde_process_was_given_up_reconnects(fake_rtde_server, monkeypatch):
    """`Arm.abort` (a stop or a shutdown the arm thread did not answer) gives the ur_rtde process up; the
    robot itself may be fine. `reset_fault` must then reconnect (a new process), not fail on the old one's
    interfaces: reading their stop bits raises RtdeGone, which the reset passes over."""
    from touchroller_driver.ur_rtde_process import RtdeChild, RtdeGone

    host, _ = fake_rtde_server
    child = RtdeChild(host, call_timeout=0.5)
    receive = child.open("receive", -1.0)
    arm = ur5.UR5Arm(host)
    arm._child, arm._receive, arm._control = child, receive, receive   # connected (control: any proxy will do)
    arm.abort()
    with pytest.raises(RtdeGone):
        receive.isConnected()
    opened = []

    def reconnect() -> None:   # what connect does with a healthy robot: new interfaces, in a new process
        arm.disconnect()
        opened.append(True)

    monkeypatch.setattr(arm, "connect", reconnect)
    arm.reset_fault()
    assert opened == [True] and arm.fault() is None and arm._child is None


def test_the_isolated_connect_reports_the_control_interfaces_own_error(fake_rtde_server):
    """The fake controller has no script interface: the real RTDEControlInterface fails in the child, and
    its message comes back as one line (the receive interface before it connected, in the child too)."""
    host, _ = fake_rtde_server
    arm = ur5.UR5Arm(host, open_timeout=20.0)
    with pytest.raises(ArmError) as info:
        arm.connect()
    assert str(info.value).startswith(f"cannot connect to the UR at {host}: ") and "\n" not in str(info.value)
    assert arm._child is None   # ended with the failed connection


# -- sweep.profile blend/constant: a pass as one moveL path ---------------------------------------------

@pytest.fixture()
def robot_arm(connected_arm):
    """connected_arm whose doubles move a simulated robot (on a fake clock): moveL of a pose or a path,
    stopL, the TCP pose and the async progress, as the real control script does."""
    from touchroller_driver.arm import SimulatedArm

    arm, control, receive = connected_arm
    clock = [100.0]
    robot = SimulatedArm(POSE, limits=ArmLimits(max_speed=1.0, max_accel=5.0), clock=lambda: clock[0])
    robot.connect()
    sent = []

    def move_l(*args):
        sent.append(args)
        if isinstance(args[0][0], list):   # a path: [x, y, z, rx, ry, rz, v, a, r] each
            path = np.array(args[0])
            robot.move_path(path[:, :6], float(path[1, 6]), float(path[1, 7]), float(path[:, 8].max()))
        else:
            robot.move_linear(args[0], args[1], args[2])
        return True

    control.moveL.side_effect = move_l
    control.stopL.side_effect = lambda *a: robot.stop()
    control.getAsyncOperationProgress.side_effect = lambda: 0 if robot.is_moving() else -1
    control.isSteady.side_effect = lambda: not robot.is_moving()
    receive.getActualTCPPose.side_effect = lambda: robot.tcp_pose().tolist()
    return arm, control, robot, clock, sent


def _ur_raster(profile):
    from touchroller_driver.arm import DEFAULT_MOUNT_RPY, DEFAULT_MOUNT_XYZ, mount_transform, plan_raster

    return plan_raster(POSE, area=(0.42, -0.045, 0.05, 0.09), mount=mount_transform(DEFAULT_MOUNT_XYZ,
                       DEFAULT_MOUNT_RPY), speed=0.02, accel=0.1, depth=5e-4, clearance=0.002, profile=profile)


def _run(arm, clock, plan, until=lambda status: False):
    from touchroller_driver.arm import SweepSequencer

    sequencer = SweepSequencer(arm)
    sequencer.start(plan)
    rows = []
    while sequencer.active:
        clock[0] += 0.005
        status = sequencer.poll()
        rows.append((clock[0], *arm.tcp_pose()[:3]))
        if until(status):
            break
    return sequencer, np.array(rows)


def _touchdown_speeds(trace, pressed_z):
    speed = np.hypot(*np.diff(trace[:, 1:3], axis=0).T) / np.diff(trace[:, 0])
    pressed = np.abs(trace[:-1, 3] - pressed_z) < 1e-5
    return speed[np.flatnonzero(np.diff(pressed.astype(int)))]


@pytest.mark.parametrize("profile", ["ramp", "blend"])
def test_a_blended_pass_is_one_moveL_path_and_touches_down_at_speed(robot_arm, profile):
    arm, control, robot, clock, sent = robot_arm
    plan = _ur_raster(profile)
    arm.move_linear(plan.segments[0].target, 0.05, 0.5, True)   # the rest pose above the first pass
    clock[0] += 10.0
    sent.clear()
    sequencer, trace = _run(arm, clock, plan)
    assert sequencer.status.phase.value == "done"
    speeds = _touchdown_speeds(trace, plan.segments[plan.rolls[0]].target[2])
    assert len(speeds) == 4
    if profile == "ramp":
        assert speeds.max() < 0.002 and all(len(args) == 4 for args in sent)   # as before: one pose a moveL
        return
    assert speeds.min() > 0.019
    paths = [args for args in sent if len(args) == 2]
    assert len(paths) == 2 and all(args[1] is True for args in paths)   # asynchronous: stopL can end it
    for (path, _), index in zip(paths, plan.motion()[1], strict=True):
        move = plan.motion()[0][index]
        assert [len(w) for w in path] == [9] * 4
        np.testing.assert_allclose(np.array(path)[:, :6], move.waypoints)
        assert [w[6:8] for w in path] == [[0.02, 0.1]] * 4
        assert path[0][8] == 0.0 and path[-1][8] == 0.0 and path[1][8] == path[2][8] == pytest.approx(move.blend)


def test_stop_mid_path_sends_stopL_and_the_robot_stays(robot_arm):
    arm, control, robot, clock, _ = robot_arm
    plan = _ur_raster("blend")
    arm.move_linear(plan.segments[0].target, 0.05, 0.5, True)
    clock[0] += 10.0
    sequencer, _ = _run(arm, clock, plan, until=lambda status: status.roll_progress > 0.2)
    assert sequencer.status.segment == "pass" and arm.is_moving()
    sequencer.stop()
    control.stopL.assert_called_with(ur5.STOP_DECELERATION)
    here = arm.tcp_pose()
    clock[0] += 5.0
    np.testing.assert_array_equal(arm.tcp_pose(), here)
    assert not arm.is_moving() and sequencer.status.phase.value == "stopped"
    assert 0.0 < arm.progress() < 1.0


def test_a_path_waypoint_out_of_limits_or_unsafe_refuses_before_any_moveL(robot_arm):
    arm, control, robot, clock, sent = robot_arm
    plan = _ur_raster("blend")
    arm.move_linear(plan.segments[0].target, 0.05, 0.5, True)
    clock[0] += 10.0
    sent.clear()
    path = plan.motion()[0][1]
    before = robot.tcp_pose()
    with pytest.raises(ArmLimitError, match="path waypoint 4 of 4"):   # the lead-out beyond the workspace
        arm.limits = ArmLimits(max_speed=0.05, workspace_max=(float(path.waypoints[2][0]) + 1e-4, 1.0, 1.0))
        arm.move_path(path.waypoints, path.speed, path.accel, path.blend)
    arm.limits = ArmLimits(max_speed=0.05)
    control.isPoseWithinSafetyLimits.side_effect = lambda pose: pose[2] > path.waypoints[1][2] + 1e-6
    with pytest.raises(ArmError, match="safety limits"):   # the controller refuses the pressed waypoints
        arm.move_path(path.waypoints, path.speed, path.accel, path.blend)
    control.isPoseWithinSafetyLimits.side_effect = None
    with pytest.raises(ArmError, match="first waypoint"):   # not where the tool is
        arm.move_path(plan.motion()[0][3].waypoints, path.speed, path.accel, path.blend)
    assert sent == []
    clock[0] += 1.0
    np.testing.assert_array_equal(robot.tcp_pose(), before)
