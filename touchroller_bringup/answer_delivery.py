"""Service answers that DDS dropped, sent again; and told when they never reach their caller.

rmw_fastrtps gives a service 100 ms after it took a request to discover the caller's reply reader, and
drops the answer otherwise: rclpy then only prints `RuntimeWarning: failed to send response (timeout)`
on stderr, and the caller waits for ever. A caller that calls the moment the service appears, on a
loaded machine, meets it now and then; one whose reply reader can never match (a QoS the service does
not offer) meets it every time. The request was served all the same: a `~/start` that nobody heard
answered success has started the arm.

`AnswerDelivery` replaces a service's `send_response` with one that sends the answer, and when rmw
dropped it sends it again every `resend_every_s` (the reader is usually discovered a moment later;
a caller takes the first answer of its request and ignores the rest) until `give_up_after_s`. An
answer that still has not gone then is logged as an ERROR and handed to the service's `on_lost`
(the sweep node stops the arm a start nobody heard started).

How a drop is seen: rclpy issues the warning with `PyErr_WarnFormat` and ignores its result, so a
warning filter "error" for this module's calls makes CPython raise `SystemError` from the call, with
the `RuntimeWarning` as its cause (or the `RuntimeWarning` itself from a binding that checks). The
filter is limited to warnings issued from this module and to that message: every other warning, and
the same warning of any service not handled here, is left as it was.
"""
from __future__ import annotations

import re
import threading
import time
import warnings
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

DROPPED_ANSWER = r"failed to send response \(timeout\)"   # rclpy's text for rmw's RMW_RET_TIMEOUT
_FILTER_ARGS = dict(action="error", message=DROPPED_ANSWER, category=RuntimeWarning,
                    module=re.escape(__name__) + "$")
# the entry warnings.filterwarnings makes of them (it compiles the message ignoring case)
_FILTER_ITEM = ("error", re.compile(DROPPED_ANSWER, re.I), RuntimeWarning, re.compile(re.escape(__name__) + "$"), 0)

OnLost = Callable[[Any], None]   # called with the response nobody heard


@dataclass(frozen=True)
class AnswerDeliveryConfig:
    """How long a dropped answer is sent again. The defaults cover discovery on a loaded machine (the
    reader shows up within a second or two) and keep a start nobody heard from moving the arm for
    longer than a few seconds."""

    resend_every_s: float = 0.25
    give_up_after_s: float = 3.0

    def __post_init__(self) -> None:
        if not 0.0 < self.resend_every_s <= self.give_up_after_s:
            raise ValueError(f"need 0 < resend_every_s <= give_up_after_s, got {self.resend_every_s}, "
                             f"{self.give_up_after_s}")


@dataclass
class _Pending:
    service: Any
    response: Any
    header: Any
    on_lost: OnLost | None
    deadline: float
    attempts: int = 1


@dataclass
class DeliveryCounts:
    """Answers sent at the first attempt, after resending, and never."""

    first: int = 0
    resent: int = 0
    lost: int = 0
    lost_services: list[str] = field(default_factory=list)


def _ensure_filter() -> None:
    """Install the module's "error" filter if it is not there (again): a `warnings.catch_warnings`
    block (pytest runs each test in one) restores the filters it found, dropping one added inside it."""
    if _FILTER_ITEM not in warnings.filters:
        warnings.filterwarnings(**_FILTER_ARGS)   # an identical one is moved to the front, never doubled


def _is_dropped(exc: BaseException) -> bool:
    warning = exc if isinstance(exc, RuntimeWarning) else exc.__cause__ or exc.__context__
    return isinstance(warning, RuntimeWarning) and re.search(DROPPED_ANSWER, str(warning)) is not None


def service_name(service: Any) -> str:
    """The service's full name, or the name it was created with once it is destroyed."""
    try:
        return str(service.service_name)
    except Exception:   # InvalidHandle: destroyed meanwhile
        return str(getattr(service, "srv_name", "a service"))


def send_once(service: Any, response: Any, header: Any) -> bool:
    """Send `response` to the caller of `header`: True when rmw took it, False when it dropped it because
    the caller's reply reader is not (yet) discovered. Any other failure raises as rclpy raises it."""
    request_id = getattr(header, "request_id", header)   # rmw_service_info_t or rmw_request_id_t
    if not isinstance(response, service.srv_type.Response):
        raise TypeError(f"an answer of {service.srv_type.__name__} expected, got {type(response).__name__}")
    _ensure_filter()
    with service.handle:
        try:
            service.handle.service_send_response(response, request_id)
        except (SystemError, RuntimeWarning) as exc:
            if _is_dropped(exc):
                return False
            raise
    return True


class AnswerDelivery:
    """Sends the answers of a node's services again while DDS drops them (module docstring)."""

    def __init__(self, node: Any, config: AnswerDeliveryConfig | None = None) -> None:
        from rclpy.clock import Clock, ClockType

        self.node = node
        self.config = config or AnswerDeliveryConfig()
        self.counts = DeliveryCounts()
        self._lock = threading.Lock()
        self._pending: list[_Pending] = []
        self._handled: set[int] = set()
        # a steady clock: a simulated /clock that pauses must not hold an answer (or a stop) back
        self._timer = node.create_timer(self.config.resend_every_s, self._resend, autostart=False,
                                        clock=Clock(clock_type=ClockType.STEADY_TIME))

    def handle(self, service: Any, on_lost: OnLost | None = None) -> None:
        """Deliver `service`'s answers through this (again for a service handled already: the new `on_lost`)."""
        self._handled.add(id(service))

        def send_response(response: Any, header: Any) -> None:
            self._send(service, response, header, on_lost)

        service.send_response = send_response   # the executor calls srv.send_response(response, header)

    def handle_all(self) -> None:
        """Every service of the node not handled yet (its parameter services among them)."""
        for service in self.node.services:
            if id(service) not in self._handled:
                self.handle(service)

    @property
    def pending(self) -> int:
        with self._lock:
            return len(self._pending)

    def _send(self, service: Any, response: Any, header: Any, on_lost: OnLost | None) -> None:
        sent = send_once(service, response, header)
        with self._lock:
            if sent:
                self.counts.first += 1
                return
            self._pending.append(_Pending(service, response, header, on_lost,
                                          time.monotonic() + self.config.give_up_after_s))
        self._timer.reset()   # (re)starts the resend timer

    def _resend(self) -> None:
        with self._lock:
            pending, self._pending = self._pending, []
        kept, lost = [], []
        for item in pending:
            item.attempts += 1
            try:
                sent = send_once(item.service, item.response, item.header)
            except Exception as exc:   # the service went away meanwhile: nothing will reach its caller
                self.node.get_logger().warning(f"{service_name(item.service)}: answer not resent: {exc}")
                lost.append(item)
                continue
            if sent:
                with self._lock:
                    self.counts.resent += 1
                self.node.get_logger().info(f"{service_name(item.service)}: answer delivered on attempt "
                                            f"{item.attempts} (the caller's reply reader was discovered late)")
            elif time.monotonic() >= item.deadline:
                lost.append(item)
            else:
                kept.append(item)
        with self._lock:
            self._pending[:0] = kept
            if not self._pending:
                self._timer.cancel()
        for item in lost:
            self._lose(item)

    def _lose(self, item: _Pending) -> None:
        with self._lock:
            self.counts.lost += 1
            self.counts.lost_services.append(service_name(item.service))
        success = getattr(item.response, "success", "?")
        self.node.get_logger().error(
            f"{service_name(item.service)}: the answer (success={success}) never reached its caller: DDS did not "
            f"match the caller's reply reader within {self.config.give_up_after_s:g} s ({item.attempts} attempts)")
        if item.on_lost is not None:
            item.on_lost(item.response)
