"""Hostile probes of the arm (issue #29): a UR that greets and then goes silent, oversized rasters, a start
its caller was told failed, a start whose answer never reaches its caller, and foreign publishers on a
scan's topics.

Each probe runs what a user runs (the `sweep_node` and `touchroller` console scripts, as processes, on a
ROS domain of its own, loopback only) and returns None when the expectation held, else one line. The
one exception is the refused start: its planning has to be made slow, which only an in-process node
allows (the bounds make real planning instantaneous).
"""
from __future__ import annotations

import os
import signal
import subprocess
import sys
import tempfile
import threading
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from pathlib import Path

from bench._common import ROOT
from bench.hostile.fake_ur import half_alive_ur_host
from bench.hostile.probe import Probe

BIN = Path(sys.executable).parent
SIGINT_LIMIT_S = 2.0   # a node must be gone this soon after Ctrl-C


@contextmanager
def _domain() -> Iterator[dict[str, str]]:
    """The environment of a process on a ROS domain no one else on this host uses, localhost discovery."""
    from touchroller_bringup.ros_domains import reserve_domain_id

    with reserve_domain_id() as lease:
        code = os.environ.get("HOSTILE_CODE", str(ROOT))
        env = dict(os.environ, ROS_DOMAIN_ID=str(lease.domain_id), ROS_AUTOMATIC_DISCOVERY_RANGE="LOCALHOST",
                   PYTHONPATH=os.pathsep.join(filter(None, [code, os.environ.get("PYTHONPATH")])))
        env.pop("TOUCHROLLER_DEBUG", None)
        yield env


def _one_line(done: subprocess.CompletedProcess, *words: str) -> str | None:
    lines = [line for line in done.stderr.splitlines() if line.strip() and not line.startswith("[")]
    if done.returncode == -999:
        return lines[0] if lines else "still running after its time"
    if "Traceback" in done.stderr:
        return f"a traceback (exit {done.returncode})"
    if done.returncode != 2:
        return f"exit {done.returncode}, expected 2: {' / '.join(lines[-2:])}"
    if len(lines) != 1:
        return f"{len(lines)} stderr lines: {' / '.join(lines[:3])}"
    missing = [w for w in words if w not in lines[0]]
    return f"the line does not say {missing}: {lines[0]}" if missing else None


def _run(command: list[str], env: dict[str, str], timeout: float = 120.0) -> subprocess.CompletedProcess:
    """The command's result; one still running after `timeout` s is killed and has returncode -999."""
    try:
        return subprocess.run(command, capture_output=True, text=True, timeout=timeout, env=env,
                              cwd=tempfile.gettempdir())
    except subprocess.TimeoutExpired as exc:
        return subprocess.CompletedProcess(command, -999, "", f"still running after {timeout:g} s\n"
                                           f"{exc.stderr.decode(errors='replace') if exc.stderr else ''}")


# -- a UR that greets and then goes silent ------------------------------------------------------------

def _half_alive_robot(scratch: Path) -> str | None:
    import rclpy
    from diagnostic_msgs.msg import DiagnosticArray
    from rclpy.executors import SingleThreadedExecutor
    from rclpy.node import Node
    from std_srvs.srv import Trigger

    from touchroller_bringup import names

    with _domain() as env, half_alive_ur_host(subnet=3) as host:
        process = subprocess.Popen([str(BIN / "sweep_node"), "--ros-args", "-p", "use_sim:=false", "-p",
                                    f"robot_ip:={host}", "-p", "robot_timeout:=2.0"], env=env,
                                   stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
        context = rclpy.context.Context()
        rclpy.init(context=context, args=[], domain_id=int(env["ROS_DOMAIN_ID"]))
        probe = Node("hostile_arm_probe", context=context)
        executor = SingleThreadedExecutor(context=context)
        executor.add_node(probe)
        errors: list[str] = []
        probe.create_subscription(DiagnosticArray, "/diagnostics", lambda m: errors.extend(
            s.message for s in m.status if s.name.endswith(names.SWEEP_NODE) and s.level == b"\x02"), 10)

        def spin_until(predicate: Callable[[], bool], timeout: float) -> bool:
            deadline = time.monotonic() + timeout
            while not predicate() and time.monotonic() < deadline:
                executor.spin_once(timeout_sec=0.05)
            return predicate()

        try:
            if not spin_until(lambda: bool(errors), 60.0):
                return "no ERROR on /diagnostics within 60 s (the node froze?)"
            if host not in errors[0]:
                return f"the ERROR does not name the robot: {errors[0]}"
            for service in (names.RESET_FAULT, names.START):
                client = probe.create_client(Trigger, names.service(names.SWEEP_NODE, service))
                if not spin_until(client.service_is_ready, 30.0):
                    return f"~/{service} not available"
                future = client.call_async(Trigger.Request())
                if not spin_until(future.done, 30.0):
                    return f"~/{service} did not answer within 30 s"
                if future.result().success:
                    return f"~/{service} answered success with a silent robot"
            client.call_async(Trigger.Request())   # a start retrying the connection, and Ctrl-C meanwhile
            spin_until(lambda: False, 0.5)
            process.send_signal(signal.SIGINT)
            sent = time.monotonic()
            try:
                process.wait(timeout=30.0)
            except subprocess.TimeoutExpired:
                return "still running 30 s after SIGINT"
            took = time.monotonic() - sent
            if took > SIGINT_LIMIT_S:
                return f"ended {took:.1f} s after SIGINT (limit {SIGINT_LIMIT_S:g} s)"
            return "a traceback on exit" if "Traceback" in (process.stderr.read() if process.stderr else "") else None
        finally:
            if process.poll() is None:
                process.kill()
                process.wait(timeout=10)
            executor.shutdown()
            probe.destroy_node()
            context.try_shutdown()


# -- oversized rasters ---------------------------------------------------------------------------------

def _refused_at_start_up(argument: str, *words: str) -> Callable[[Path], str | None]:
    def check(scratch: Path) -> str | None:
        with _domain() as env:
            done = _run([str(BIN / "sweep_node"), "--ros-args", "-p", argument], env, timeout=60.0)
        return _one_line(done, *words)
    return check


def _scan_refused(argument: str, *words: str) -> Callable[[Path], str | None]:
    """`touchroller scan ARGUMENT` is refused: exit 2, one line holding `words`, no output folder left."""
    def check(scratch: Path) -> str | None:
        out = scratch / "out"
        with _domain() as env:
            done = _run([str(BIN / "touchroller"), "scan", argument, "--quiet", "--out", str(out)], env)
        return _one_line(done, *words) or (f"left {out} behind" if out.exists() else None)
    return check


def _huge_area_at_set_time(scratch: Path) -> str | None:
    """`ros2 param set` of a 5 km area on a running node: refused at once (it blocked the parameter
    service for 7.8 s while planning 110 000 passes)."""
    import rclpy
    from rclpy.parameter import Parameter

    from touchroller_bringup.nodes.sweep_node import SweepNode
    from touchroller_driver.arm import DEFAULT_START_POSE, SimulatedArm

    with _domain() as env:
        context = rclpy.context.Context()
        rclpy.init(context=context, args=[], domain_id=int(env["ROS_DOMAIN_ID"]))
        node = SweepNode(arm=SimulatedArm(DEFAULT_START_POSE), context=context)
        try:
            started = time.monotonic()
            result = node.set_parameters([Parameter("sweep.area", value=[0.4, -0.03, 5000.0, 5000.0])])[0]
            took = time.monotonic() - started
        finally:
            node.destroy_node()
            context.try_shutdown()
    if result.successful:
        return "a 5 km area was accepted"
    if took > 0.5:
        return f"refused, but after {took:.1f} s (the parameter service was blocked)"
    return None if "reach" in result.reason else f"refused for another reason: {result.reason}"


# -- a start its caller was told failed ---------------------------------------------------------------

def _failed_start_never_moves(scratch: Path) -> str | None:
    import rclpy

    from touchroller_bringup.nodes import sweep_node
    from touchroller_driver.arm import DEFAULT_START_POSE, SimulatedArm

    slow = threading.Event()
    original, original_timeout = sweep_node.plan_sweep, sweep_node.COMMAND_TIMEOUT_S

    def slow_plan(*args: object, **kwargs: object) -> object:
        if slow.is_set():
            time.sleep(1.5)   # planning outlasts the service's wait
        return original(*args, **kwargs)

    with _domain() as env:
        context = rclpy.context.Context()
        rclpy.init(context=context, args=[], domain_id=int(env["ROS_DOMAIN_ID"]))
        sweep_node.plan_sweep, sweep_node.COMMAND_TIMEOUT_S = slow_plan, 0.3
        arm = SimulatedArm(DEFAULT_START_POSE)
        node = sweep_node.SweepNode(arm=arm, context=context)
        try:
            deadline = time.monotonic() + 20.0
            while node.status.phase.value != "idle" and time.monotonic() < deadline:
                time.sleep(0.02)
            rest = arm.tcp_pose()
            slow.set()
            success, message = node.request_start()
            if success:
                return "the slow start answered success (the probe did not make it outlast the wait)"
            time.sleep(3.0)   # planning done long ago; the arm thread has run many loops
            moved = float(abs(arm.tcp_pose() - rest).max())
            return f"answered failure ({message}), then the arm moved {moved * 1e3:.2f} mm" if moved > 0 or \
                arm.is_moving() else None
        finally:
            sweep_node.plan_sweep, sweep_node.COMMAND_TIMEOUT_S = original, original_timeout
            node.destroy_node()
            context.try_shutdown()


# -- a start whose answer never reaches its caller -------------------------------------------------------

def _unheard_start_stops(scratch: Path) -> str | None:
    """A caller in another process whose reply reader can never match (a transient-local durability the
    service does not offer) is served by `~/start`, but DDS drops every answer to it: the sweep node
    must stop the sweep that start began once it gives the answer up."""
    import rclpy
    from geometry_msgs.msg import PoseStamped
    from rclpy.executors import SingleThreadedExecutor
    from rclpy.node import Node
    from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy
    from std_srvs.srv import Trigger

    from touchroller_bringup import names

    deaf_qos = QoSProfile(depth=10, reliability=ReliabilityPolicy.RELIABLE, durability=DurabilityPolicy.TRANSIENT_LOCAL)
    log = scratch / "sweep_node.log"
    with _domain() as env, log.open("w") as out:
        # a 10 cm roll at 5 mm/s: 20 s, far longer than the 3 s after which an unheard answer is given up
        process = subprocess.Popen([str(BIN / "sweep_node"), "--ros-args", "-p", "use_sim:=true",
                                    "-p", "sweep.length:=0.1", "-p", "sweep.speed:=0.005"], env=env,
                                   stdout=out, stderr=subprocess.STDOUT, text=True)
        context = rclpy.context.Context()
        rclpy.init(context=context, args=[], domain_id=int(env["ROS_DOMAIN_ID"]))
        probe = Node("hostile_deaf_caller", context=context)
        executor = SingleThreadedExecutor(context=context)
        executor.add_node(probe)
        poses: list[tuple[float, list[float]]] = []
        probe.create_subscription(PoseStamped, names.topic(names.TCP_POSE), lambda m: poses.append(
            (time.monotonic(), [m.pose.position.x, m.pose.position.y, m.pose.position.z])), 50)
        deaf = probe.create_client(Trigger, names.service(names.SWEEP_NODE, names.START), qos_profile=deaf_qos)

        def spin_for(seconds: float) -> None:
            deadline = time.monotonic() + seconds
            while time.monotonic() < deadline:
                executor.spin_once(timeout_sec=0.05)

        def moving_since(since: float) -> bool:
            after = [xyz for t, xyz in poses if t >= since]
            return len(after) >= 2 and max(abs(a - b) for a, b in zip(after[0], after[-1], strict=True)) > 1e-6

        try:
            deadline = time.monotonic() + 60.0
            while not poses and time.monotonic() < deadline:   # the node is up and publishes its pose
                spin_for(0.2)
            if not poses:
                return "no tcp_pose from the sweep node within 60 s"
            called = time.monotonic()
            while not moving_since(called) and time.monotonic() < called + 30.0:
                deaf.call_async(Trigger.Request())   # until its request writer is matched and a start taken
                spin_for(0.5)
            if not moving_since(called):
                return "the deaf caller's start never moved the arm (the probe did not start a sweep)"
            spin_for(6.0)   # the answer is given up after 3 s; the stop follows at once
            still = time.monotonic()
            spin_for(1.5)
            if moving_since(still):
                return "the arm still moves 6 s after a start whose answer never reached its caller"
        finally:
            executor.shutdown()
            probe.destroy_node()
            context.try_shutdown()
            process.send_signal(signal.SIGINT)
            try:
                process.wait(timeout=30.0)
            except subprocess.TimeoutExpired:
                process.kill()
                process.wait(timeout=10)
    text = log.read_text()
    if "never reached its caller" not in text or "is stopped" not in text:
        return f"stopped, but the log does not say why: {text.strip().splitlines()[-1:]}"
    return None


# -- foreign publishers on a scan's topics -------------------------------------------------------------

def _scan_with(stray: Callable[[Path, dict[str, str]], subprocess.Popen], *words: str) -> Callable[[Path], str | None]:
    def check(scratch: Path) -> str | None:
        out = scratch / "out"
        with _domain() as env:
            other = stray(scratch, env)
            try:
                time.sleep(2.0)   # it is up and discoverable
                done = _run([str(BIN / "touchroller"), "scan", "sweep_length:=0.01", "sweep_speed:=0.02", "--quiet",
                             "--out", str(out)], env)
            finally:
                other.kill()
                other.wait(timeout=10)
        return _one_line(done, "another node publishes on this scan's topics", *words) or \
            (f"left {out} behind" if out.exists() else None)
    return check


def _progress_publisher(scratch: Path, env: dict[str, str]) -> subprocess.Popen:
    code = ("import rclpy, time\nfrom std_msgs.msg import Float32\nrclpy.init()\n"
            "node = rclpy.create_node('stray_progress')\n"
            "pub = node.create_publisher(Float32, '/touchroller/sweep_progress', 10)\n"
            "while True:\n    pub.publish(Float32(data=1.0)); time.sleep(0.1)\n")
    return subprocess.Popen([sys.executable, "-c", code], env=env, stdout=subprocess.DEVNULL,
                            stderr=subprocess.DEVNULL)


def _replay(scratch: Path, env: dict[str, str]) -> subprocess.Popen:
    import numpy as np

    from touchroller_bringup.bags import write_images

    write_images(scratch / "bag", [(k * 33_000_000, np.zeros((24, 32, 3), np.uint8)) for k in range(30)])
    return subprocess.Popen([str(BIN / "touchroller"), "replay", str(scratch / "bag"), "--loop"], env=env,
                            stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)


def probes() -> list[Probe]:
    return [
        Probe("a UR that greets, then goes silent", "arm",
              "the sweep node shows ERROR naming the robot, ~/reset_fault and ~/start answer failure, and it exits "
              f"within {SIGINT_LIMIT_S:g} s of SIGINT (a start retrying meanwhile)", _half_alive_robot),
        Probe("sweep_node sweep.area:=5 km", "arm", "exit 2, one line: beyond the arm's reach",
              _refused_at_start_up("sweep.area:=[0.4,-0.03,5000.0,5000.0]", "sweep parameters refused", "reach")),
        Probe("sweep_node sweep.area 3000 m wide (66 667 passes)", "arm", "exit 2, one line, before planning",
              _refused_at_start_up("sweep.area:=[0.40,-0.03,0.04,3000.0]", "sweep parameters refused", "reach")),
        Probe("sweep_node sweep.area 1 km away (78 h approach)", "arm", "exit 2, one line: beyond the arm's reach",
              _refused_at_start_up("sweep.area:=[1000.0,1000.0,0.05,0.05]", "sweep parameters refused", "reach")),
        Probe("sweep_node sweep.speed:=0.5 (over arm.max_speed)", "arm", "exit 2, one line at start-up",
              _refused_at_start_up("sweep.speed:=0.5", "sweep parameters refused", "speed 0.5")),
        Probe("sweep_node NaN sweep.direction", "arm", "exit 2, one line at start-up",
              _refused_at_start_up("sweep.direction:=[.nan,0.0,0.0]", "sweep.direction", "finite")),
        Probe("touchroller scan area:=0.40,-0.03,0.04,3000", "arm", "exit 2, one line, no output folder left",
              _scan_refused("area:=0.40,-0.03,0.04,3000", "reach")),
        Probe("ros2 param set sweep.area 5 km", "arm", "refused at once (within 0.5 s): beyond the reach",
              _huge_area_at_set_time),
        Probe("~/start whose planning outlasts the service's wait", "arm",
              "answered failure, and the arm never moves for it", _failed_start_never_moves),
        Probe("~/start from a caller DDS never delivers the answer to", "arm",
              "the sweep it started is stopped once the answer is given up, and the log says why",
              _unheard_start_stops),
        Probe("a stray sweep_progress publisher before touchroller scan", "arm",
              "exit 2, one line naming /stray_progress, no output folder left",
              _scan_with(_progress_publisher, "/stray_progress")),
        Probe("touchroller replay started before touchroller scan", "arm",
              "exit 2, one line naming the replayer, no output folder left",
              _scan_with(_replay, "/touchroller_replayer")),
    ]
