"""Trigger-style services for every node (rclpy glue, no algorithms).

The nodes' "do it now" services (sweep `~/start`/`~/stop`, calibration `~/capture`/`~/solve`/`~/reset`,
perception `~/recapture_reference`) are `std_srvs/srv/Trigger`, which every ROS 2 install has and
`ros-std-srvs` provides in our venv. Where std_srvs is missing they fall back to
`diagnostic_msgs/srv/AddDiagnostics`: its response has the same `success` and `message` fields and
its request string is ignored, so callers written against either type work unchanged
(`ros2 service call /touchroller_sweep/start diagnostic_msgs/srv/AddDiagnostics {}`).
"""
from __future__ import annotations

from collections.abc import Callable
from typing import Any

from rclpy.node import Node


def trigger_service_type() -> tuple[type, bool]:
    """(service type, is std_srvs/Trigger): Trigger when std_srvs imports, else AddDiagnostics."""
    try:
        from std_srvs.srv import Trigger
    except ImportError:
        from diagnostic_msgs.srv import AddDiagnostics

        return AddDiagnostics, False
    return Trigger, True


def create_trigger_service(node: Node, name: str, action: Callable[[], tuple[bool, str]], *,
                           log: bool = True, **kwargs: Any) -> Any:
    """A Trigger service on `node` that answers `action()`'s (success, message); extra keywords
    (e.g. `callback_group`) go to `Node.create_service`."""
    service_type, _ = trigger_service_type()

    def serve(_request: Any, response: Any) -> Any:
        success, message = action()
        response.success, response.message = bool(success), str(message)
        if log and success:   # two call sites: rclpy fixes a call site's severity on first use
            node.get_logger().info(f"{name}: {message}")
        elif log:
            node.get_logger().warning(f"{name}: {message}")
        return response

    return node.create_service(service_type, name, serve, **kwargs)
