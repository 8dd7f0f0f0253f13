"""Shared fixtures: an isolated rclpy Context per test, a spin helper, and rosbag2 bags made in the test."""
from __future__ import annotations

import itertools
import os
import time
from collections.abc import Callable, Iterator
from pathlib import Path

import numpy as np
import pytest
from hypothesis import settings

# CI replays a fixed set of examples so `main` stays reproducibly green; local runs keep exploring.
settings.register_profile("ci", derandomize=True, deadline=None, print_blob=True)
settings.register_profile("dev", deadline=None, print_blob=True)
settings.load_profile("ci" if os.environ.get("CI") else "dev")

ROOT = Path(__file__).resolve().parents[1]
# The real ROS 2 command-line and launch tools for a pip-built venv (launch, launch_ros, ros2cli; tests only):
# `shared/ros-extras` beside the checkout (`../shared/ros-extras`), or beside a folder above it (a worktree).
ROS_EXTRAS_INSTALL = next((parent / "shared" / "ros-extras" / "install" for parent in ROOT.parents
                           if (parent / "shared" / "ros-extras" / "install").is_file()), None)


def _ros_tools_import() -> bool:
    import importlib.util

    importlib.invalidate_caches()
    return all(importlib.util.find_spec(name) is not None for name in ("launch", "launch_ros", "ros2cli"))


def pytest_collection_modifyitems(items: list[pytest.Item]) -> None:
    """The files holding a test marked `longest` first, each file's tests kept together and in order.
    `make test` hands whole files to two workers in collection order (`--dist loadfile
    --no-loadscope-reorder`): the longest test handed out last would leave the other worker idle meanwhile."""
    first = {item.path for item in items if item.get_closest_marker("longest")}
    items.sort(key=lambda item: item.path not in first)   # stable


@pytest.fixture(scope="session")
def ros_tools() -> Path:
    """The folder of the `ros2` and `colcon` executables, with `launch`/`launch_ros` importable: a ROS 2
    install's, or this venv's once `ROS_EXTRAS_INSTALL` has added them (idempotent: about a second when
    done before). Skips where neither is available, as in a user's clone without a ROS 2 install."""
    import fcntl
    import shutil
    import subprocess
    import sys

    bin_dir = Path(sys.executable).parent
    if not _ros_tools_import() or not (bin_dir / "ros2").exists():
        if ROS_EXTRAS_INSTALL is None or sys.prefix == sys.base_prefix:
            ros2 = shutil.which("ros2")
            if ros2 and _ros_tools_import():
                return Path(ros2).parent
            pytest.skip("no ROS 2 command-line tools: neither a ROS 2 install nor shared/ros-extras beside the "
                        "checkout")
        venv = Path(sys.prefix)
        with open(venv / ".ros-extras.lock", "w") as lock:   # one installer at a time per venv
            fcntl.flock(lock, fcntl.LOCK_EX)
            # ros-extras/install rewrites the message wheels' /opt/python include paths in the venv's CMake
            # files; after `make setup` has done that (interfaces/build_missing.sh) its `grep | while` finds
            # nothing and fails under pipefail. A file it can rewrite keeps it going; removed afterwards.
            marker = venv / "share" / "touchroller_ros_extras" / "include_paths.cmake"
            marker.parent.mkdir(parents=True, exist_ok=True)
            marker.write_text("# /opt/python/cp311-cp311/include/python3.11\n")
            try:
                done = subprocess.run([str(ROS_EXTRAS_INSTALL), str(venv)], capture_output=True, text=True,
                                      timeout=900)
            finally:
                shutil.rmtree(marker.parent, ignore_errors=True)
        if done.returncode != 0 or not _ros_tools_import():
            pytest.fail(f"{ROS_EXTRAS_INSTALL} {venv} failed: {(done.stderr or done.stdout).strip()[-500:]}")
    return bin_dir


@pytest.fixture
def ros_context(monkeypatch: pytest.MonkeyPatch) -> Iterator[object]:
    """An initialised rclpy Context on a ROS domain no other process on this host uses, localhost discovery
    (LOCALHOST discovery alone does not keep concurrent test runs and benchmarks on one domain apart)."""
    rclpy = pytest.importorskip("rclpy")
    from touchroller_bringup.ros_domains import reserve_domain_id

    with reserve_domain_id() as lease:
        monkeypatch.setenv("ROS_DOMAIN_ID", str(lease.domain_id))
        monkeypatch.setenv("ROS_AUTOMATIC_DISCOVERY_RANGE", "LOCALHOST")
        context = rclpy.context.Context()
        rclpy.init(context=context, domain_id=lease.domain_id)
        try:
            yield context
        finally:
            context.try_shutdown()


@pytest.fixture
def other_participant(ros_context: object) -> Iterator[object]:
    """A second initialised Context on ros_context's domain: a DDS participant of its own, as a caller in
    another process has (discovery between the two is not immediate, and QoS is matched across it)."""
    import os

    import rclpy

    context = rclpy.context.Context()
    rclpy.init(context=context, domain_id=int(os.environ["ROS_DOMAIN_ID"]))
    try:
        yield context
    finally:
        context.try_shutdown()


@pytest.fixture
def never_answered_qos() -> object:
    """A client with this QoS is served (its request writer matches a service's volatile request reader)
    but its reply reader never matches the service's volatile reply writer: rmw_fastrtps drops every
    answer to it, as it drops one to a caller it has not discovered yet."""
    from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy

    return QoSProfile(depth=10, reliability=ReliabilityPolicy.RELIABLE, durability=DurabilityPolicy.TRANSIENT_LOCAL)


def _spin_until(executor_or_node: object, predicate: Callable[[], bool], timeout: float = 20.0) -> bool:
    """Spin until `predicate()` is true or `timeout` s pass; returns the predicate's last value.

    Returns as soon as the predicate holds, so a generous timeout costs nothing on a quiet machine and
    keeps a loaded CI machine (slow discovery, starved threads) from failing at random."""
    from rclpy.executors import Executor, SingleThreadedExecutor

    if isinstance(executor_or_node, Executor):
        executor, owned = executor_or_node, False
    else:
        executor = SingleThreadedExecutor(context=executor_or_node.context)
        executor.add_node(executor_or_node)
        owned = True
    try:
        deadline = time.monotonic() + timeout
        while not predicate():
            if time.monotonic() > deadline:
                return bool(predicate())
            executor.spin_once(timeout_sec=0.02)
        return True
    finally:
        if owned:
            executor.remove_node(executor_or_node)
            executor.shutdown()


class NodeInitFailure(Exception):
    """Raised by `fail_after_node_init` right after rclpy's Node.__init__ has returned."""


@pytest.fixture
def fail_after_node_init(monkeypatch: pytest.MonkeyPatch) -> Callable[[type], type[Exception]]:
    """`fail_after_node_init(cls)`: the constructor of `cls` raises NodeInitFailure (returned) as soon as
    rclpy's Node.__init__ returns. That is the worst place to fail part-way: from there on the context
    tracks the node and destroys it at shutdown, before the subclass has set anything of its own."""
    from rclpy.node import Node

    original = Node.__init__

    def arm(cls: type) -> type[Exception]:
        def init(self: Node, *args: object, **kwargs: object) -> None:
            original(self, *args, **kwargs)
            if type(self) is cls:
                raise NodeInitFailure(f"{cls.__name__} failed part-way")

        monkeypatch.setattr(Node, "__init__", init)
        return NodeInitFailure

    return arm


@pytest.fixture
def spin_until() -> Callable[..., bool]:
    return _spin_until


@pytest.fixture
def bag_factory(tmp_path: Path) -> Callable[..., Path]:
    """`bag_factory(records, storage="sqlite3", topic=...)` writes a rosbag2 folder and returns its path.

    `records` are (stamp_ns, image) pairs or ImageRecords; bags are written inside the test rather
    than committed as binaries.
    """
    from touchroller_bringup.bags import IMAGE_TOPIC, write_images

    counter = itertools.count()

    def make(records, storage: str = "sqlite3", topic: str = IMAGE_TOPIC) -> Path:
        path = tmp_path / f"bag_{next(counter)}_{storage}"
        write_images(path, records, topic=topic, storage=storage)
        return path

    return make


@pytest.fixture
def rng() -> np.random.Generator:
    return np.random.default_rng(12345)


@pytest.fixture(scope="session")
def real_presses() -> Callable[..., object]:
    """`real_presses(sensor="gelsight_mini")`: real GelSight presses with labelled centres (bench.real_presses),
    loaded once per sensor from the pinned `taxim` wheel; the test is skipped where the wheel is absent."""
    from bench import real_presses as module

    if not module.available():
        pytest.skip("the taxim wheel (real GelSight presses) is not installed")
    cache: dict[str, object] = {}

    def load(sensor: str = module.TUNING_SENSOR) -> object:
        if sensor not in cache:
            cache[sensor] = module.load_presses(sensor)
        return cache[sensor]

    return load


SILENT_SERVER = r'''
import socket, sys, threading
host, ports = sys.argv[1], [int(p) for p in sys.argv[2:]]
held = []
def accept(server):
    while True:
        held.append(server.accept()[0])   # accepted, never answered
servers = []
for port in ports:
    server = socket.socket(); server.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
    server.bind((host, port)); server.listen(8); servers.append(server)
    threading.Thread(target=accept, args=(server,), daemon=True).start()
print("listening", flush=True)
threading.Event().wait()
'''


@pytest.fixture
def silent_ur_host() -> Iterator[str]:
    """A free 127.0.1.x whose UR ports (RTDE, dashboard, script) accept TCP connections and never answer:
    ur_rtde's constructors would wait there for ever with the GIL held."""
    import subprocess
    import sys

    for attempt in range(10):
        host = f"127.0.1.{(os.getpid() + 23 * attempt) % 250 + 1}"
        server = subprocess.Popen([sys.executable, "-u", "-c", SILENT_SERVER, host, "30004", "29999", "30003",
                                   "30002"], stdout=subprocess.PIPE, stderr=subprocess.DEVNULL, text=True)
        if server.stdout.readline().strip() == "listening":
            break
        server.wait(timeout=5)
    else:
        pytest.skip("no free loopback address for the silent server")
    try:
        yield host
    finally:
        server.kill()
        server.wait(timeout=5)


@pytest.fixture
def half_alive_ur_host() -> Iterator[str]:
    """A free 127.0.2.x that answers the RTDE protocol-version request and the dashboard's welcome line, then
    nothing (bench.hostile.fake_ur): every start-up probe passes and ur_rtde's constructors wait for ever."""
    from bench.hostile.fake_ur import half_alive_ur_host as serve

    try:
        with serve() as host:
            yield host
    except RuntimeError as exc:
        pytest.skip(str(exc))


@pytest.fixture
def mount_tmpfs(tmp_path: Path) -> Iterator[Callable[..., Path]]:
    """`mount_tmpfs(size="64k", read_only=False, free_bytes=None)`: a real tmpfs mounted for the test (root
    with the mount capability; the test is skipped elsewhere), unmounted afterwards; `free_bytes`: filled
    (by a hidden file) until about that much is left."""
    import subprocess

    mounted: list[Path] = []

    def mount(size: str = "64k", read_only: bool = False, free_bytes: int | None = None) -> Path:
        point = tmp_path / f"tmpfs{len(mounted)}"
        point.mkdir()
        options = f"size={size}" + (",ro" if read_only else "")
        made = subprocess.run(["mount", "-t", "tmpfs", "-o", options, "tmpfs", str(point)],
                              capture_output=True, text=True, check=False)
        if made.returncode != 0:
            pytest.skip(f"cannot mount a tmpfs here: {made.stderr.strip() or made.returncode}")
        mounted.append(point)
        if free_bytes is not None:
            stats = os.statvfs(point)
            left = stats.f_bavail * stats.f_frsize - free_bytes
            with open(point / ".filler", "wb") as stream:
                try:
                    stream.write(b"\0" * max(left, 0))
                    stream.flush()
                except OSError:
                    pass
        return point

    yield mount
    for point in mounted:
        subprocess.run(["umount", "-l", str(point)], check=False)

