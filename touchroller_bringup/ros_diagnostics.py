"""A small shared diagnostics helper: measured rates and lags, published on `/diagnostics`.

`RateMeter` and `LagWindow` are plain Python (thread-safe, no rclpy) so node code can feed them
from any thread. `DiagnosticsPublisher` (rclpy) calls a callback once a period and publishes the
returned `DiagnosticStatus` values as a `diagnostic_msgs/DiagnosticArray`, like diagnostic_updater.

    diagnostics = DiagnosticsPublisher(node, "touchroller camera", hardware_id=source.info)
    diagnostics.add(lambda: Status(OK, "streaming", {"frame_rate_hz": meter.rate(), ...}))
"""
from __future__ import annotations

import threading
import time
from collections import deque
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from typing import Any

import numpy as np

OK, WARN, ERROR, STALE = 0, 1, 2, 3
DIAGNOSTICS_TOPIC = "/diagnostics"


@dataclass
class Status:
    """One DiagnosticStatus: level (OK/WARN/ERROR/STALE), a message and key/value pairs."""

    level: int
    message: str
    values: Mapping[str, Any] = field(default_factory=dict)
    name: str | None = None  # defaults to the publisher's name


class RateMeter:
    """Events per second over a sliding time window (monotonic clock)."""

    def __init__(self, window_s: float = 2.0, clock: Callable[[], float] = time.monotonic) -> None:
        self.window_s = window_s
        self._clock = clock
        self._times: deque[float] = deque()
        self._lock = threading.Lock()
        self.total = 0

    def tick(self) -> None:
        now = self._clock()
        with self._lock:
            self._times.append(now)
            self.total += 1
            self._trim(now)

    def rate(self) -> float:
        """Measured rate in Hz; 0.0 with fewer than two events in the window."""
        now = self._clock()
        with self._lock:
            self._trim(now)
            if len(self._times) < 2:
                return 0.0
            span = self._times[-1] - self._times[0]
            return (len(self._times) - 1) / span if span > 0 else 0.0

    def _trim(self, now: float) -> None:
        while self._times and now - self._times[0] > self.window_s:
            self._times.popleft()


class LagWindow:
    """The last `size` lag samples (seconds) with their median and maximum; NaN when empty."""

    def __init__(self, size: int = 100) -> None:
        self._values: deque[float] = deque(maxlen=size)
        self._lock = threading.Lock()

    def add(self, seconds: float) -> None:
        with self._lock:
            self._values.append(float(seconds))

    def summary(self) -> tuple[float, float]:
        with self._lock:
            values = np.fromiter(self._values, float)
        if values.size == 0:
            return float("nan"), float("nan")
        return float(np.median(values)), float(values.max())


def format_value(value: Any) -> str:
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, float):
        return "nan" if not np.isfinite(value) else f"{value:.6g}"
    return str(value)


def make_status(status: Status, default_name: str, hardware_id: str = "") -> Any:
    from diagnostic_msgs.msg import DiagnosticStatus, KeyValue

    message = DiagnosticStatus()
    message.level = bytes([int(status.level)])
    message.name = status.name or default_name
    message.message = status.message
    message.hardware_id = hardware_id
    message.values = [KeyValue(key=str(k), value=format_value(v)) for k, v in status.values.items()]
    return message


class DiagnosticsPublisher:
    """Publishes the statuses returned by registered callbacks on `/diagnostics` every `period_s`."""

    def __init__(self, node: Any, name: str, hardware_id: str = "", period_s: float = 1.0) -> None:
        from diagnostic_msgs.msg import DiagnosticArray

        self._array_type = DiagnosticArray
        self.node = node
        self.name = name
        self.hardware_id = hardware_id
        self._callbacks: list[Callable[[], Status]] = []
        self._publisher = node.create_publisher(DiagnosticArray, DIAGNOSTICS_TOPIC, 10)
        self._timer = node.create_timer(period_s, self.publish) if period_s > 0 else None

    def add(self, callback: Callable[[], Status]) -> None:
        self._callbacks.append(callback)

    def publish(self) -> None:
        array = self._array_type()
        array.header.stamp = self.node.get_clock().now().to_msg()
        for callback in self._callbacks:
            try:
                status = callback()
            except Exception as exc:  # noqa: BLE001 - a broken probe must show up, not kill the timer
                status = Status(ERROR, f"diagnostic failed: {type(exc).__name__}: {exc}")
            array.status.append(make_status(status, self.name, self.hardware_id))
        self._publisher.publish(array)

    def destroy(self) -> None:
        if self._timer is not None:
            self.node.destroy_timer(self._timer)
        self.node.destroy_publisher(self._publisher)


def status_values(status_msg: Any) -> dict[str, str]:
    """A DiagnosticStatus message's values as a dict (for tests and tools)."""
    return {kv.key: kv.value for kv in status_msg.values}
