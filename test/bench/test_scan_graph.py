"""bench/_scan_graph.py: the scan's own ROS domain, and the memory figures the scan benches sample."""
from __future__ import annotations

import math
import os
from types import SimpleNamespace

import pytest

from bench import _scan_graph as graph


def test_the_scan_gets_a_domain_of_its_own_on_this_host_and_the_environment_is_restored(monkeypatch):
    monkeypatch.setenv("ROS_DOMAIN_ID", "7")
    monkeypatch.delenv("ROS_AUTOMATIC_DISCOVERY_RANGE", raising=False)
    with graph.own_domain() as domain_id:
        assert os.environ["ROS_DOMAIN_ID"] == str(domain_id) and 0 < domain_id <= 232
        assert os.environ["ROS_AUTOMATIC_DISCOVERY_RANGE"] == "LOCALHOST"
    assert os.environ["ROS_DOMAIN_ID"] == "7" and "ROS_AUTOMATIC_DISCOVERY_RANGE" not in os.environ
    with pytest.raises(RuntimeError), graph.own_domain():   # a scan that fails restores it too
        raise RuntimeError("the scan failed")
    assert os.environ["ROS_DOMAIN_ID"] == "7" and "ROS_AUTOMATIC_DISCOVERY_RANGE" not in os.environ


def test_memory_is_read_from_the_process_status_and_the_map_tiles_from_the_store():
    assert 0 < graph.status_mb() <= graph.status_mb("VmHWM")
    assert math.isnan(graph.status_mb("NoSuchField"))
    assert graph.map_tiles_mb(None) == 0.0 and graph.perception_node() is None
    perception = SimpleNamespace(world=SimpleNamespace(canvas=SimpleNamespace(store=SimpleNamespace(
        resident_bytes=3 * 2**20))))
    assert graph.map_tiles_mb(perception) == 3.0
