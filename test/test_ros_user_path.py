"""The README's "With ROS 2" section, done as a user does it, with the real colcon, launch and ros2cli.

A workspace with this package in src/, `colcon build`, `source install/setup.bash`, `ros2 launch
touchroller_bringup scan.launch.py`, the start call (`ros2 service call .../start std_srvs/srv/Trigger`),
`ros2 topic echo` of the contacts, and Ctrl-C (SIGINT to the whole process group, as a terminal sends
it): every process must end cleanly. Then the same with `namespace:=left`. Skipped where the ROS 2 tools
are not available (see the `ros_tools` fixture).
"""
from __future__ import annotations

import os
import re
import shlex
import shutil
import signal
import subprocess
import threading
import time
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import pytest

from touchroller_bringup import names
from touchroller_bringup.ros_domains import reserve_domain_id

pytestmark = [pytest.mark.ros, pytest.mark.slow]
ROOT = Path(__file__).resolve().parents[1]
NOT_PACKAGED = (".git", ".venv", "build", "install", "log", "__pycache__", "*.egg-info", ".pytest_cache",
                ".ruff_cache", ".mypy_cache", ".hypothesis", "scan_output", "out", "results")


def _readme_colcon_build() -> list[str]:
    """The README's `colcon build` in the workspace, as arguments."""
    found = re.search(r"^cd ~/tr_ws && (colcon build.*)$", (ROOT / "README.md").read_text(encoding="utf-8"),
                      re.MULTILINE)
    assert found, "README: no `cd ~/tr_ws && colcon build ...` line"
    return shlex.split(found.group(1).split("#")[0])


@pytest.fixture(scope="module")
def workspace(ros_tools: Path, tmp_path_factory: pytest.TempPathFactory) -> Path:
    """`mkdir -p ws/src && <clone> ws/src/touchroller_bringup && colcon build --base-paths ...` (README):
    touchroller_bringup and touchroller_interfaces."""
    ws = tmp_path_factory.mktemp("tr_ws")
    shutil.copytree(ROOT, ws / "src" / "touchroller_bringup", ignore=shutil.ignore_patterns(*NOT_PACKAGED))
    # the ROS install's environment (`source /opt/ros/<distro>/setup.bash`): here the venv is the install, and
    # rosidl finds its type supports through the ament index
    paths = {name: os.pathsep.join(p for p in (str(ros_tools.parent), os.environ.get(name, "")) if p)
             for name in ("AMENT_PREFIX_PATH", "CMAKE_PREFIX_PATH")}
    env = _env(ros_tools, **paths)
    built = subprocess.run(_readme_colcon_build(), cwd=ws, env=env, capture_output=True, text=True, timeout=900)
    assert built.returncode == 0, built.stdout[-2000:] + built.stderr[-2000:]
    assert (ws / "install" / "setup.bash").is_file()
    assert (ws / "install" / "touchroller_interfaces" / "share" / "touchroller_interfaces" / "action"
            / "Sweep.action").is_file()
    return ws


def _env(ros_tools: Path, **extra: str) -> dict[str, str]:
    env = dict(os.environ, PATH=f"{ros_tools}{os.pathsep}{os.environ.get('PATH', '')}", PYTHONUNBUFFERED="1",
               RCUTILS_LOGGING_BUFFERED_STREAM="0", **extra)
    env.pop("PYTHONPATH", None)   # what the workspace's setup.bash gives, no more
    return env


class Shell:
    """One command in bash after `source install/setup.bash`, in its own process group (a terminal's job),
    its output collected line by line."""

    def __init__(self, ws: Path, command: str, env: dict[str, str]) -> None:
        self.lines: list[str] = []
        self.terminated = False
        self.process = subprocess.Popen(["bash", "-c", f"source install/setup.bash && exec {command}"], cwd=ws,
                                        env=env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True,
                                        start_new_session=True)
        self._reader = threading.Thread(target=self._read, daemon=True)
        self._reader.start()

    def _read(self) -> None:
        assert self.process.stdout is not None
        for line in self.process.stdout:
            self.lines.append(line.rstrip("\n"))

    @property
    def output(self) -> str:
        return "\n".join(self.lines)

    def wait_for(self, pattern: str, count: int = 1, timeout: float = 60.0) -> bool:
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            if len(re.findall(pattern, self.output, re.MULTILINE)) >= count:
                return True
            if self.process.poll() is not None:
                break
            time.sleep(0.1)
        return len(re.findall(pattern, self.output, re.MULTILINE)) >= count

    def ctrl_c(self, timeout: float = 30.0, terminate_after: float | None = None) -> int:
        """SIGINT to the process group, as Ctrl-C in a terminal; the exit code.

        With `terminate_after`, a process still running that long after the SIGINT gets SIGTERM, as a user
        presses Ctrl-C again or closes the terminal; `terminated` says whether it was needed."""
        os.killpg(self.process.pid, signal.SIGINT)
        self.terminated = False
        try:
            if terminate_after is not None:
                try:
                    self.process.wait(terminate_after)
                except subprocess.TimeoutExpired:
                    self.terminated = True
                    os.killpg(self.process.pid, signal.SIGTERM)
            code = self.process.wait(timeout)
        except subprocess.TimeoutExpired:
            os.killpg(self.process.pid, signal.SIGKILL)
            code = self.process.wait(10)
            pytest.fail(f"did not end within {timeout:.0f} s of Ctrl-C:\n{self.output[-3000:]}")
        self._reader.join(5)
        return code

    def kill(self) -> None:
        if self.process.poll() is None:
            os.killpg(self.process.pid, signal.SIGKILL)
            self.process.wait(10)


@dataclass
class Run:
    namespace: str
    call: str      # `ros2 service call` output
    echo: str      # `ros2 topic echo` output
    echo_code: int
    echo_terminated: bool   # the upstream echo needed SIGTERM after the Ctrl-C
    launch: str    # `ros2 launch` output
    launch_code: int


@pytest.fixture(scope="module", params=["", "left"], ids=["default_namespace", "namespace_left"])
def quick_start(request: pytest.FixtureRequest, workspace: Path, ros_tools: Path) -> Iterator[Run]:
    """The README's steps once per namespace: launch, start call, echo until 3 contacts, Ctrl-C both."""
    namespace = request.param
    ns = namespace or names.DEFAULT_NAMESPACE
    with reserve_domain_id() as lease:   # other test runs and benches publish /touchroller/* too
        env = _env(ros_tools, ROS_DOMAIN_ID=str(lease.domain_id), ROS_AUTOMATIC_DISCOVERY_RANGE="LOCALHOST")
        arguments = f" namespace:={namespace}" if namespace else ""
        launch = Shell(workspace, f"ros2 launch touchroller_bringup scan.launch.py{arguments}", env)
        echo = call = None
        try:
            assert launch.wait_for(r"\[sweep_node-\d+\]: process started", timeout=60), launch.output
            contacts = names.topic(names.CONTACTS, ns)
            echo = Shell(workspace, f"ros2 topic echo {contacts} geometry_msgs/msg/PointStamped", env)
            start = names.service(names.SWEEP_NODE, names.START, ns)
            call = Shell(workspace, f"ros2 service call {start} std_srvs/srv/Trigger", env)
            assert call.process.wait(60) == 0, call.output
            echo.wait_for(r"^point:", count=3, timeout=60)
            # upstream `ros2 topic echo` (not ours) now and then hangs in its own shutdown after Ctrl-C; what
            # this checks is that our graph's topics reach a user, so the echo gets a SIGTERM fallback (the
            # launch below does not: our nodes must end on the Ctrl-C itself)
            echo_code = echo.ctrl_c(terminate_after=15)
            launch_code = launch.ctrl_c()   # mid-sweep, as a user stops a roll
        finally:
            for shell in (echo, call, launch):
                if shell is not None:
                    shell.kill()
            # the echo started the ros2 daemon of this domain, as it does for a user: stop it
            subprocess.run(["ros2", "daemon", "stop"], env=env, capture_output=True, timeout=30)
    yield Run(ns, call.output, echo.output, echo_code, echo.terminated, launch.output, launch_code)


@pytest.mark.timeout(300)
def test_launch_start_call_and_contacts_as_the_readme_shows(quick_start: Run) -> None:
    run = quick_start
    assert "success=True" in run.call and "sweep started" in run.call, run.call
    assert len(re.findall(r"^point:", run.echo, re.MULTILINE)) >= 3, (run.echo[-2000:], run.launch[-3000:])
    assert f"frame_id: {names.frame_prefix(run.namespace)}{names.CYLINDER_FRAME}" in run.echo
    # ros2cli's exit codes for Ctrl-C: SIGINT when it sees KeyboardInterrupt, SIGTERM when rclpy's own handler
    # shut the context down first (ExternalShutdownException); which one depends on where the signal lands
    echo_codes = {signal.SIGINT, signal.SIGTERM} | ({-signal.SIGTERM} if run.echo_terminated else set())
    assert run.echo_code in echo_codes, (run.echo_code, run.echo[-2000:])
    assert run.echo_terminated or "Traceback" not in run.echo, run.echo[-2000:]
    assert f"[{run.namespace}.sweep]: start: sweep started" in run.launch   # the node logs in its namespace


@pytest.mark.timeout(300)
def test_ctrl_c_stops_every_node_without_escalation(quick_start: Run) -> None:
    """Every node process ends on the Ctrl-C itself: launch never has to escalate to SIGTERM or SIGKILL."""
    run = quick_start
    for node in ("camera_node", "perception_node", "sweep_node"):
        assert re.search(rf"\[{node}-\d+\]: process (has finished cleanly|has died .*exit code -2)", run.launch), \
            run.launch[-4000:]
    assert "SIGTERM" not in run.launch and "SIGKILL" not in run.launch, run.launch[-4000:]


@pytest.mark.timeout(300)
def test_ctrl_c_ends_every_node_cleanly(quick_start: Run) -> None:
    """A terminal's Ctrl-C reaches each node twice (from the terminal and from launch), at any moment of
    its shutdown: every node stops in order (ros_main.StopSignals) and exits 0, without a traceback."""
    run = quick_start
    assert "Traceback" not in run.launch and "process has died" not in run.launch, run.launch[-4000:]
    for node in ("camera_node", "perception_node", "sweep_node"):
        assert re.search(rf"\[{node}-\d+\]: process has finished cleanly", run.launch), run.launch[-4000:]
    assert run.launch_code == 0, run.launch[-4000:]


def test_show_args_lists_the_launch_arguments(workspace: Path, ros_tools: Path) -> None:
    from touchroller_bringup.graph import LAUNCH_ARGUMENTS

    shown = subprocess.run(["bash", "-c", "source install/setup.bash && "
                            "ros2 launch touchroller_bringup scan.launch.py --show-args"],
                           cwd=workspace, env=_env(ros_tools), capture_output=True, text=True, timeout=60)
    assert shown.returncode == 0, shown.stderr
    for argument in LAUNCH_ARGUMENTS["scan"]:
        assert f"'{argument.name}':" in shown.stdout


@pytest.mark.timeout(600)
def test_the_sweep_action_of_the_launched_graph(workspace: Path, ros_tools: Path,
                                                monkeypatch: pytest.MonkeyPatch) -> None:
    """The README's `ros2 action send_goal` for the launched graph. ros2cli's `ros2 action` is not among the
    tools installable here (shared/ros-extras), so the README's action name, type and goal YAML are turned
    into the goal as ros2action does (rosidl_runtime_py's get_action and set_message_fields) and sent with
    rclpy's ActionClient: accepted, feedback, SUCCEEDED with the pass and the distance, from the sweep node of
    the workspace built as the README says."""
    import yaml

    rclpy = pytest.importorskip("rclpy")
    pytest.importorskip("touchroller_interfaces.action", reason="touchroller_interfaces is not built")
    from rclpy.action import ActionClient
    from rosidl_runtime_py.set_message import set_message_fields
    from rosidl_runtime_py.utilities import get_action

    line = re.search(r"^ros2 action send_goal --feedback (\S+) (\S+) \"(.*)\"$",
                     (ROOT / "README.md").read_text(encoding="utf-8"), re.MULTILINE)
    assert line, "README: no `ros2 action send_goal --feedback NAME TYPE \"GOAL\"` line"
    action_name, action_type, goal_yaml = line.groups()
    assert action_name == names.topic(names.SWEEP_ACTION)
    sweep = get_action(action_type)
    goal = sweep.Goal()
    set_message_fields(goal, yaml.safe_load(goal_yaml))
    from rclpy.executors import SingleThreadedExecutor
    from rclpy.node import Node

    with reserve_domain_id() as lease:
        env = _env(ros_tools, ROS_DOMAIN_ID=str(lease.domain_id), ROS_AUTOMATIC_DISCOVERY_RANGE="LOCALHOST")
        monkeypatch.setenv("ROS_DOMAIN_ID", str(lease.domain_id))
        monkeypatch.setenv("ROS_AUTOMATIC_DISCOVERY_RANGE", "LOCALHOST")
        launch = Shell(workspace, "ros2 launch touchroller_bringup scan.launch.py", env)
        context = rclpy.context.Context()
        rclpy.init(context=context, domain_id=lease.domain_id)
        node = Node("readme_sweep_goal", context=context)
        executor = SingleThreadedExecutor(context=context)
        executor.add_node(node)
        feedback: list = []

        def spin_until(predicate, timeout: float) -> bool:
            deadline = time.monotonic() + timeout
            while not predicate() and time.monotonic() < deadline:
                executor.spin_once(timeout_sec=0.05)
            return bool(predicate())

        try:
            assert launch.wait_for(r"\[sweep_node-\d+\]: process started", timeout=60), launch.output
            client = ActionClient(node, sweep, action_name)
            assert spin_until(client.server_is_ready, 60.0), launch.output[-3000:]
            for _ in range(6):   # a request sent before the server has discovered this client is lost: again
                sent = client.send_goal_async(goal, feedback_callback=lambda m: feedback.append(m.feedback))
                if spin_until(sent.done, 10.0):
                    break
            assert sent.done() and sent.result().accepted, launch.output[-3000:]
            result = sent.result().get_result_async()
            assert spin_until(result.done, 300.0), launch.output[-3000:]
            assert result.result().result.outcome == sweep.Result.SUCCEEDED, result.result().result.message
            assert (result.result().result.passes_done, result.result().result.pass_count) == (1, 1)
            # the README's goal leaves the length to the parameter: config/scan.yaml's
            length = yaml.safe_load((ROOT / "config" / "scan.yaml").read_text())["/**"]["ros__parameters"][
                "sweep.length"]
            assert result.result().result.distance == pytest.approx(length)
            assert feedback and all(0.0 <= f.distance <= length + 1e-9 for f in feedback)
            assert launch.ctrl_c() == 0, launch.output[-3000:]
        finally:
            launch.kill()
            executor.shutdown()
            node.destroy_node()
            context.try_shutdown()
