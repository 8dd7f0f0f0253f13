"""ROS domain IDs that no other process on this host is using, for tests and benchmarks.

`ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST` keeps a graph off the network but not away from other
processes on the same host: two test runs, or a test and a benchmark, that pick the same domain ID
see each other's `/touchroller/*` topics (an extra contact, a foreign 640x480 image) and fail in ways
that look like lost messages. `reserve_domain_id()` hands out an ID that is

* not leased by another process using this module (a lock file per ID, held until `release()` or
  the process ends; the kernel drops the lock of a process that dies), and
* not in use by any other DDS participant on this host: Fast DDS participant `i` of domain `d` binds
  UDP port 7410 + 250 d + 2 i for its discovery traffic (the RTPS well-known ports, used by the
  shared-memory profile too), so a port that cannot be bound means the domain is taken.

Pure Python (no rclpy): usable from conftest fixtures and benchmark scripts before `rclpy.init`.
"""
from __future__ import annotations

import errno
import fcntl
import itertools
import os
import socket
import tempfile
from collections.abc import Iterable
from pathlib import Path
from typing import IO

LOCK_DIR = Path(tempfile.gettempdir()) / "touchroller_ros_domains"
# 0 is everyone's default domain (robots, other users); above 232 the RTPS ports pass 65535.
DOMAIN_IDS = range(1, 233)
PROBED_PARTICIPANTS = 4   # participants 0..3 of a domain: several processes or contexts


def discovery_port(domain_id: int, participant: int = 0) -> int:
    """RTPS metatraffic unicast port: PB 7400 + DG 250 * domain + d1 10 + PG 2 * participant."""
    return 7400 + 250 * domain_id + 10 + 2 * participant


class DomainLease:
    """A reserved domain ID; `release()` (or leaving the `with` block) gives it back."""

    def __init__(self, domain_id: int, lock: IO[str]) -> None:
        self.domain_id = domain_id
        self._lock: IO[str] | None = lock

    def release(self) -> None:
        if self._lock is not None:
            fcntl.flock(self._lock, fcntl.LOCK_UN)
            self._lock.close()
            self._lock = None

    def __enter__(self) -> DomainLease:
        return self

    def __exit__(self, *_exc: object) -> None:
        self.release()

    def __repr__(self) -> str:
        return f"DomainLease({self.domain_id}{'' if self._lock else ', released'})"


def domain_in_use(domain_id: int) -> bool:
    """True if some DDS participant on this host holds one of the domain's discovery ports."""
    for participant in range(PROBED_PARTICIPANTS):
        with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as probe:
            try:
                probe.bind(("0.0.0.0", discovery_port(domain_id, participant)))
            except OSError as exc:
                if exc.errno in (errno.EADDRINUSE, errno.EACCES):
                    return True
                raise
    return False


_LEASES = itertools.count()


def reserve_domain_id(candidates: Iterable[int] | None = None, *, start: int | None = None) -> DomainLease:
    """The first free domain of `candidates` (default 1..232), tried from `start` (default: spread by
    pid, so concurrent processes rarely contend for the same lock); RuntimeError if none is free."""
    ids = list(candidates if candidates is not None else DOMAIN_IDS)
    if not ids:
        raise ValueError("no candidate domain IDs")
    if any(not 0 <= d <= 232 for d in ids):
        raise ValueError(f"ROS domain IDs must be in 0..232, got {ids}")
    # spread by pid, and moved on at each lease of this process: a graph just shut down in this process can
    # linger in discovery for a moment, and the next lease must not hand its domain straight back
    first = (os.getpid() * 7 + 13 * next(_LEASES) if start is None else start) % len(ids)
    LOCK_DIR.mkdir(parents=True, exist_ok=True)
    for domain_id in ids[first:] + ids[:first]:
        lock = open(LOCK_DIR / f"{domain_id}.lock", "a+", encoding="utf-8")  # noqa: SIM115 - held by the lease
        try:
            fcntl.flock(lock, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except OSError:
            lock.close()
            continue
        if domain_in_use(domain_id):
            fcntl.flock(lock, fcntl.LOCK_UN)
            lock.close()
            continue
        return DomainLease(domain_id, lock)
    raise RuntimeError(f"no free ROS domain ID among {len(ids)} candidates (all leased or in use on this host)")
