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
