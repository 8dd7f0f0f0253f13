"""Taking a topic's messages from one node only: its publishers told apart by the publisher gid of each
message (rclpy's MessageInfo), their node looked up on the ROS graph.

The perception node follows `sweep_progress` to start and finish maps; any other publisher on that
topic (a stray `ros2 topic pub`, a `touchroller replay` of a recording) used to cut a map short. With
`PublisherFilter` it takes progress only from the sweep node of its own namespace. The graph's
publishers of the topic are looked up when a message comes from a gid not seen before (at most every
`refresh_s` for gids still unknown), so a filter costs a dictionary look-up per message.
"""
from __future__ import annotations

import time
from typing import Any

from touchroller_bringup import names


def message_gid(info: Any) -> bytes | None:
    """The publisher gid of a message (rclpy MessageInfo dict), None where the RMW does not give one."""
    gid = info.get("publisher_gid") if isinstance(info, dict) else None
    data = gid.get("data") if isinstance(gid, dict) else None
    return bytes(data) if data else None


class PublisherFilter:
    """`accepts(info)`: the message came from a publisher of the node `source` (a fully qualified name,
    e.g. /touchroller/sweep) on `topic` (absolute). `rejected` counts the others."""

    def __init__(self, node: Any, topic: str, source: str, refresh_s: float = 0.5) -> None:
        self.node, self.topic, self.source = node, topic, source
        self.refresh_s = refresh_s
        self._known: dict[bytes, bool] = {}   # gid -> from the source node
        self._looked_up = -1.0
        self.rejected = 0
        self.last_rejected = ""   # the node of the last message refused

    def accepts(self, info: Any) -> bool:
        gid = message_gid(info)
        if gid is None:   # an RMW without gids: nothing to tell publishers apart by
            return True
        if gid not in self._known and time.monotonic() - self._looked_up >= self.refresh_s:
            self._refresh()
        if self._known.get(gid, self._known.get(gid[:16], False)):
            return True
        self.rejected += 1
        return False

    def _refresh(self) -> None:
        self._looked_up = time.monotonic()
        for endpoint in self.node.get_publishers_info_by_topic(self.topic):
            publisher = names.topic(endpoint.node_name, endpoint.node_namespace.strip("/"))
            gid = bytes(endpoint.endpoint_gid)
            self._known[gid[:16]] = self._known[gid] = publisher == self.source
            if publisher != self.source:
                self.last_rejected = publisher
