"""Trigger services for every node (rclpy glue, no algorithms).

The nodes' "do it now" services (sweep `~/start`/`~/stop`, calibration `~/capture`/`~/solve`/`~/reset`,
perception `~/recapture_reference`) are `std_srvs/srv/Trigger`
(`ros2 service call /touchroller/sweep/start std_srvs/srv/Trigger`).
"""
from __future__ import annotations

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
