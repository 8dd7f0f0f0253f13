"""The recorder's queue between the subscriptions (which must take messages off the wire at once) and the
writer thread (which encodes PNG and writes chunks, and may fall behind on a loaded machine or a slow disk).

Bounded in bytes, never silent: a message that would take the queued bytes past `max_bytes` is refused,
counted per topic (`QueueStats.overflowed`) and the caller says so (the recorder's log, /diagnostics and the
scan's report). Unbounded, a writer slower than the camera would hold every frame it has not written yet
in memory until the process runs out of it; bounded, a recording of a camera that cannot wait loses the
frames past the bound, and says how many. Thread-safe; plain Python (no rclpy).
"""
from __future__ import annotations

import threading
import time
from collections import deque
from dataclasses import dataclass, field
from typing import Any


@dataclass(frozen=True)
class QueueStats:
    """What the queue holds and has held: the bytes now, the most it held, and what it refused."""

    queued: int                       # items waiting for the writer
    queued_bytes: int
    peak_bytes: int                   # the most bytes queued at once
    max_bytes: int                    # the bound
    overflowed: dict[str, int] = field(default_factory=dict)   # topic -> messages refused at the bound

    @property
    def overflowed_total(self) -> int:
        return sum(self.overflowed.values())


class BoundedQueue:
    """FIFO of (item, size, topic); `put` refuses an item that would take the queued bytes past `max_bytes`
    (always accepts into an empty queue, so one message larger than the bound is still written); `put_always`
    (control items: new topics, the end) never refuses."""

    def __init__(self, max_bytes: int) -> None:
        if max_bytes <= 0:
            raise ValueError(f"the recorder's queue bound must be > 0 bytes, got {max_bytes}")
        self._max_bytes = int(max_bytes)
        self._items: deque[tuple[Any, int]] = deque()
        self._bytes = 0
        self._peak = 0
        self._overflowed: dict[str, int] = {}
        self._changed = threading.Condition()

    @property
    def max_bytes(self) -> int:
        return self._max_bytes

    @max_bytes.setter
    def max_bytes(self, value: int) -> None:
        if value <= 0:
            raise ValueError(f"the recorder's queue bound must be > 0 bytes, got {value}")
        with self._changed:
            self._max_bytes = int(value)

    def put(self, item: Any, size: int, topic: str) -> bool:
        """Queue `item` of `size` bytes; False (counted for `topic`) when it does not fit under the bound."""
        with self._changed:
            if self._items and self._bytes + size > self._max_bytes:
                self._overflowed[topic] = self._overflowed.get(topic, 0) + 1
                return False
            self._append(item, size)
            return True

    def put_always(self, item: Any, size: int = 0) -> None:
        with self._changed:
            self._append(item, size)

    def _append(self, item: Any, size: int) -> None:
        self._items.append((item, size))
        self._bytes += size
        self._peak = max(self._peak, self._bytes)
        self._changed.notify()

    def get(self, timeout: float | None = None) -> Any:
        """The oldest item; raises `queue.Empty`-like `TimeoutError` when none came within `timeout` s."""
        deadline = None if timeout is None else time.monotonic() + max(0.0, timeout)
        with self._changed:
            while not self._items:
                remaining = None if deadline is None else deadline - time.monotonic()
                if remaining is not None and remaining <= 0:
                    raise TimeoutError
                self._changed.wait(remaining)
            item, size = self._items.popleft()
            self._bytes -= size
            return item

    def stats(self) -> QueueStats:
        with self._changed:
            return QueueStats(len(self._items), self._bytes, self._peak, self._max_bytes, dict(self._overflowed))
