"""The console-script entry shared by every node: init, spin, clean shutdown on Ctrl-C."""
from __future__ import annotations

from collections.abc import Callable, Sequence

import rclpy
from rclpy.executors import ExternalShutdownException
from rclpy.impl.implementation_singleton import rclpy_implementation as _rclpy
from rclpy.node import Node


def run_node(make_node: Callable[[], Node], args: Sequence[str] | None = None) -> None:
    rclpy.init(args=args)
    node = make_node()
    try:
        rclpy.spin(node)
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    except _rclpy.RCLError:
        # Ctrl-C shuts the context down from the signal handler; landing between spin's context check
        # and building its wait set, that surfaces as "the given context is not valid". Only then
        # is it a clean exit: with the context still up, an RCLError is a real failure.
        if node.context.ok():
            raise
    finally:
        node.destroy_node()
        rclpy.try_shutdown()
