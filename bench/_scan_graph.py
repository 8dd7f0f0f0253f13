"""What the benches that run `touchroller scan`'s graph in their own process share (bench.scan_soak,
bench.scan_square_metre, bench.inspection_scan): a ROS domain of the scan's own, and the process's memory
and the world map's, read while the scan runs.
"""
from __future__ import annotations

import gc
import os
from collections.abc import Iterator
from contextlib import contextmanager
from typing import Any

_ENVIRONMENT = ("ROS_DOMAIN_ID", "ROS_AUTOMATIC_DISCOVERY_RANGE")


@contextmanager
def own_domain() -> Iterator[int]:
    """A ROS domain no other process here uses (another graph in the namespace would stop the scan),
    discovery on this host only, for a graph run inside; the environment as it was afterwards."""
    from touchroller_bringup.ros_domains import reserve_domain_id

    saved = {name: os.environ.get(name) for name in _ENVIRONMENT}
    try:
        with reserve_domain_id() as lease:
            os.environ["ROS_DOMAIN_ID"] = str(lease.domain_id)
            os.environ["ROS_AUTOMATIC_DISCOVERY_RANGE"] = "LOCALHOST"
            yield lease.domain_id
    finally:
        for name, value in saved.items():
            if value is None:
                os.environ.pop(name, None)
            else:
                os.environ[name] = value


def status_mb(field: str = "VmRSS") -> float:
    """A memory field of this process's /proc/self/status (VmRSS: resident now, VmHWM: its peak), MB."""
    with open("/proc/self/status") as stream:
        for line in stream:
            if line.startswith(field + ":"):
                return int(line.split()[1]) / 1024
    return float("nan")


def perception_node() -> Any | None:
    """The perception node the scan made in this process (None before it exists)."""
    from touchroller_bringup.nodes.perception_node import PerceptionNode

    return next((o for o in gc.get_objects() if isinstance(o, PerceptionNode)), None)


def map_tiles_mb(perception: Any | None) -> float:
    """The world map's own memory: the bytes of its tiles in memory (the layers' and the copies a pass
    registers against; the tile store's cache bounds them, the rest is on disk)."""
    store = getattr(getattr(getattr(perception, "world", None), "canvas", None), "store", None)
    return store.resident_bytes / 2**20 if store is not None else 0.0
