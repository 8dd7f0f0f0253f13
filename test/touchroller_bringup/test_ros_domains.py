"""Domain IDs for tests and benchmarks: never one that another process on this host is using."""
from __future__ import annotations

import socket
import subprocess
import sys

import pytest

from touchroller_bringup.ros_domains import DomainLease, discovery_port, domain_in_use, reserve_domain_id


def free_ids(n: int) -> list[int]:
    ids = [d for d in range(120, 232) if not domain_in_use(d)]
    assert len(ids) >= n
    return ids[:n]


def test_leases_are_exclusive_until_released():
    first, second = free_ids(2)
    with reserve_domain_id([first, second], start=0) as lease:
        assert lease.domain_id == first
        other = reserve_domain_id([first, second], start=0)       # first is leased: the next one
        assert other.domain_id == second
        with pytest.raises(RuntimeError, match="no free ROS domain ID"):
            reserve_domain_id([first, second])
        other.release()
    assert reserve_domain_id([first], start=0).domain_id == first   # released on leaving the block


def test_a_lease_held_by_another_process_is_skipped():
    first, second = free_ids(2)
    code = ("import sys, time\nfrom touchroller_bringup.ros_domains import reserve_domain_id\n"
            f"lease = reserve_domain_id([{first}], start=0)\nprint(lease.domain_id, flush=True)\n"
            "sys.stdin.readline()\n")
    holder = subprocess.Popen([sys.executable, "-c", code], stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True)
    try:
        assert holder.stdout.readline().strip() == str(first)
        assert reserve_domain_id([first, second], start=0).domain_id == second
    finally:
        holder.communicate("\n", timeout=10)
    assert reserve_domain_id([first, second], start=0).domain_id == first   # its lock died with it


def test_a_domain_with_a_participant_is_skipped_even_without_a_lease():
    first, second = free_ids(2)
    squatter = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)   # what a DDS participant 1 binds
    squatter.bind(("0.0.0.0", discovery_port(first, participant=1)))
    try:
        assert domain_in_use(first) and not domain_in_use(second)
        assert reserve_domain_id([first, second], start=0).domain_id == second
    finally:
        squatter.close()


@pytest.mark.ros
def test_a_live_rclpy_participant_marks_its_domain_in_use(monkeypatch):
    rclpy = pytest.importorskip("rclpy")
    lease: DomainLease = reserve_domain_id(free_ids(5))
    monkeypatch.setenv("ROS_AUTOMATIC_DISCOVERY_RANGE", "LOCALHOST")
    context = rclpy.context.Context()
    rclpy.init(context=context, domain_id=lease.domain_id)
    node = rclpy.create_node("domain_probe", context=context)
    try:
        assert domain_in_use(lease.domain_id)
    finally:
        node.destroy_node()
        context.try_shutdown()
        lease.release()


def test_bad_candidates_are_refused():
    with pytest.raises(ValueError):
        reserve_domain_id([])
    with pytest.raises(ValueError):
        reserve_domain_id([233])
