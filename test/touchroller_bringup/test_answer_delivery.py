"""Answers DDS dropped are sent again, and one that never reaches its caller is told (answer_delivery).

A real drop is made on purpose by a client with conftest's `never_answered_qos`.
"""
from __future__ import annotations

import time
import warnings

import pytest

pytest.importorskip("rclpy")

from rclpy.executors import SingleThreadedExecutor  # noqa: E402
from rclpy.node import Node  # noqa: E402
from std_srvs.srv import Trigger  # noqa: E402

from touchroller_bringup.answer_delivery import (  # noqa: E402
    AnswerDelivery,
    AnswerDeliveryConfig,
    _ensure_filter,
    send_once,
)

pytestmark = [pytest.mark.ros, pytest.mark.timeout(90)]

QUICK = AnswerDeliveryConfig(resend_every_s=0.1, give_up_after_s=1.0)


class FakeHandle:
    """rclpy's service handle as seen by send_once: drops the first `drops` answers the way rclpy reports
    rmw's timeout (a RuntimeWarning issued from the caller's frame)."""

    def __init__(self, drops: int) -> None:
        self.drops, self.sent = drops, []

    def __enter__(self):
        return self

    def __exit__(self, *exc) -> None:
        return None

    def service_send_response(self, response, request_id) -> None:
        if self.drops > 0:
            self.drops -= 1
            warnings.warn("failed to send response (timeout): client will not receive response", RuntimeWarning,
                          stacklevel=2)
            return
        self.sent.append((response, request_id))


class FakeService:
    srv_type = Trigger
    srv_name = service_name = "/fake/start"

    def __init__(self, drops: int) -> None:
        self.handle = FakeHandle(drops)


def _answer(success: bool = True) -> Trigger.Response:
    return Trigger.Response(success=success, message="sweep started")


def test_an_answer_dropped_a_few_times_is_delivered_once_the_reader_is_found(ros_context, spin_until):
    node = Node("answer_delivery_fake", context=ros_context)
    delivery = AnswerDelivery(node, QUICK)
    service, lost = FakeService(drops=3), []
    try:
        delivery.handle(service, on_lost=lost.append)
        service.send_response(_answer(), "request 1")
        assert delivery.pending == 1 and not service.handle.sent
        assert spin_until(node, lambda: service.handle.sent, timeout=10.0)
        assert service.handle.sent == [(_answer(), "request 1")]
        assert (delivery.counts.first, delivery.counts.resent, delivery.counts.lost) == (0, 1, 0)
        assert not lost and delivery.pending == 0
        service.send_response(_answer(), "request 2")   # a reader already found: sent at once
        assert service.handle.sent[-1] == (_answer(), "request 2") and delivery.counts.first == 1
    finally:
        node.destroy_node()


def test_an_answer_never_delivered_is_given_up_and_handed_to_on_lost(ros_context, spin_until):
    node = Node("answer_delivery_lost", context=ros_context)
    delivery = AnswerDelivery(node, QUICK)
    service, lost = FakeService(drops=10**6), []
    try:
        delivery.handle(service, on_lost=lost.append)
        sent_at = time.monotonic()
        service.send_response(_answer(), "request")
        assert spin_until(node, lambda: lost, timeout=10.0)
        assert time.monotonic() - sent_at >= QUICK.give_up_after_s
        assert lost == [_answer()] and delivery.counts.lost == 1 and delivery.counts.lost_services == ["/fake/start"]
        assert not service.handle.sent and delivery.pending == 0
    finally:
        node.destroy_node()


def test_other_warnings_and_errors_of_a_send_are_left_as_they_are():
    class Failing(FakeService):
        def __init__(self) -> None:
            super().__init__(drops=0)
            self.handle.service_send_response = self.fail

        def fail(self, response, request_id) -> None:
            raise RuntimeError("failed to send response")   # rclpy's RCLError for anything but a timeout

    with pytest.raises(RuntimeError, match="failed to send response"):
        send_once(Failing(), _answer(), "request")
    with pytest.raises(TypeError):
        send_once(FakeService(drops=0), "not a response", "request")
    with warnings.catch_warnings(record=True) as caught:   # the same text from elsewhere is only a warning
        _ensure_filter()
        warnings.warn("failed to send response (timeout): elsewhere", RuntimeWarning, stacklevel=1)
    assert len(caught) == 1


def test_a_real_drop_is_resent_then_given_up_and_a_matched_caller_is_answered(ros_context, other_participant,
                                                                              never_answered_qos, spin_until):
    server = Node("answer_delivery_server", context=ros_context)
    served = []
    service = server.create_service(Trigger, "/answer_delivery/start",
                                    lambda request, response: served.append(1) or _answer())
    delivery = AnswerDelivery(server, QUICK)
    lost = []
    delivery.handle(service, on_lost=lost.append)
    other = other_participant
    caller = Node("answer_delivery_caller", context=other)
    deaf = caller.create_client(Trigger, "/answer_delivery/start", qos_profile=never_answered_qos)
    client = caller.create_client(Trigger, "/answer_delivery/start")
    executor = SingleThreadedExecutor(context=ros_context)
    executor.add_node(server)
    callers = SingleThreadedExecutor(context=other)
    callers.add_node(caller)
    try:
        # the deaf caller's request writer matches the service's reader: it is served, and never answered
        deadline = time.monotonic() + 30.0
        while not served and time.monotonic() < deadline:
            deaf.call_async(Trigger.Request())
            spin_until(executor, lambda: bool(served), timeout=0.5)
        assert served, "the service never took the deaf caller's request"
        assert spin_until(executor, lambda: lost, timeout=10.0)
        assert lost[0] == _answer() and delivery.counts.lost >= 1 and delivery.counts.first == 0
        # a caller whose reader matches is answered at once, through the same delivery
        assert spin_until(callers, client.service_is_ready, timeout=20.0)
        future = client.call_async(Trigger.Request())
        deadline = time.monotonic() + 20.0
        while not future.done() and time.monotonic() < deadline:
            executor.spin_once(timeout_sec=0.02)
            callers.spin_once(timeout_sec=0.02)
        assert future.done() and future.result() == _answer()
        assert delivery.counts.first + delivery.counts.resent >= 1
    finally:
        executor.shutdown()
        callers.shutdown()
        caller.destroy_node()
        server.destroy_node()
