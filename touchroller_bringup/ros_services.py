"""Trigger services for every node, and calls to other nodes' services that cannot wait for ever
(rclpy glue, no algorithms).

The nodes' "do it now" services (sweep `~/start`/`~/stop`, calibration `~/capture`/`~/solve`/`~/reset`,
perception `~/recapture_reference`) are `std_srvs/srv/Trigger`
(`ros2 service call /touchroller/sweep/start std_srvs/srv/Trigger`).
"""
from __future__ import annotations

import threading
from collections.abc import Callable
from typing import Any

from rclpy.node import Node
from std_srvs.srv import Trigger


def create_trigger_service(node: Node, name: str, action: Callable[[], tuple[bool, str]], *,
                           log: bool = True, **kwargs: Any) -> Any:
    """A Trigger service on `node` that answers `action()`'s (success, message); extra keywords
    (e.g. `callback_group`) go to `Node.create_service`."""

    def serve(_request: Any, response: Any) -> Any:
        success, message = action()
        response.success, response.message = bool(success), str(message)
        if log and success:   # two call sites: rclpy fixes a call site's severity on first use
            node.get_logger().info(f"{name}: {message}")
        elif log:
            node.get_logger().warning(f"{name}: {message}")
        return response

    return node.create_service(Trigger, name, serve, **kwargs)


def call_with_deadline(node: Node, client: Any, request: Any, timeout_s: float,
                       on_done: Callable[[Any | None, str], None]) -> Any:
    """Call `client` without blocking; `on_done(response, "")` once answered, or `on_done(None, why)` when
    no answer came within `timeout_s` (a server that died, or an answer DDS dropped and its server did not
    send again: answer_delivery): the request is then forgotten, and a late answer ignored. `on_done` runs
    once, on the node's executor. Returns the call's future."""
    from rclpy.clock import Clock, ClockType

    once = threading.Lock()   # taken by the first of the answer and the deadline, never released
    timer: Any = None

    def finish(response: Any | None, why: str) -> None:
        if not once.acquire(blocking=False):
            return
        if timer is not None:
            timer.cancel()
            node.destroy_timer(timer)
        on_done(response, why)

    def expired() -> None:
        if future.done():
            return
        finish(None, f"no answer from {client.srv_name} within {timeout_s:g} s")
        client.remove_pending_request(future)
        future.cancel()

    future = client.call_async(request)
    # a steady clock: a paused simulated /clock must not make a call wait for ever
    timer = node.create_timer(timeout_s, expired, clock=Clock(clock_type=ClockType.STEADY_TIME))
    future.add_done_callback(lambda done: finish(None if done.cancelled() else done.result(), ""))
    return future
