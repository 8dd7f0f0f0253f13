"""The diagnostics helper: measured rate, lag window, and the DiagnosticArray it publishes."""
from __future__ import annotations

import math

import pytest

from touchroller_bringup.ros_diagnostics import ERROR, OK, LagWindow, RateMeter, Status, format_value


class FakeClock:
    def __init__(self):
        self.t = 100.0

    def __call__(self):
        return self.t


def test_rate_meter_measures_events_per_second_over_its_window():
    clock = FakeClock()
    meter = RateMeter(window_s=1.0, clock=clock)
    assert meter.rate() == 0.0
    for _ in range(11):
        meter.tick()
        clock.t += 0.05
    assert meter.rate() == pytest.approx(20.0)
    clock.t += 5.0  # silence: the window empties
    assert meter.rate() == 0.0 and meter.total == 11


def test_lag_window_summary_and_empty_is_nan():
    window = LagWindow(size=3)
    assert all(math.isnan(x) for x in window.summary())
    for lag in (0.5, 0.001, 0.002, 0.003):  # the oldest falls out
        window.add(lag)
    assert window.summary() == pytest.approx((0.002, 0.003))


def test_format_value_is_explicit_about_nan_and_bools():
    assert format_value(float("nan")) == "nan"
    assert format_value(True) == "true"
    assert format_value(0.1234567891) == "0.123457"
    assert format_value(3) == "3"


@pytest.mark.ros
def test_publisher_sends_statuses_and_reports_a_failing_probe(ros_context, spin_until):
    pytest.importorskip("rclpy")
    from diagnostic_msgs.msg import DiagnosticArray
    from rclpy.node import Node

    from touchroller_bringup.ros_diagnostics import DiagnosticsPublisher, status_values

    node = Node("diag_test", context=ros_context)
    received = []
    node.create_subscription(DiagnosticArray, "/diagnostics", received.append, 10)
    diagnostics = DiagnosticsPublisher(node, "probe", hardware_id="hw0", period_s=0.05)
    diagnostics.add(lambda: Status(OK, "fine", {"rate_hz": 29.97, "dropped": 0}))
    diagnostics.add(lambda: 1 / 0)
    try:
        assert spin_until(node, lambda: bool(received), timeout=20)
        good, bad = received[0].status
        assert (good.name, good.hardware_id, good.message) == ("probe", "hw0", "fine")
        assert status_values(good) == {"rate_hz": "29.97", "dropped": "0"}
        assert bad.level == bytes([ERROR]) and "ZeroDivisionError" in bad.message
    finally:
        diagnostics.destroy()
        node.destroy_node()
