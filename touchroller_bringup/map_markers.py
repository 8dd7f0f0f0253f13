"""The world map's live views as ROS messages: `map` (sensor_msgs/Image mono8) and `map_metadata`
(nav_msgs/MapMetaData) at the level of detail that fits `map.view_max_pixels`, and `map_markers`
(visualization_msgs/MarkerArray): the map in place in RViz, one `TRIANGLE_LIST` quad per tile in the
map's frame with the tile's image as an embedded PNG texture (grey and alpha; `texture_resource`
`embedded://...`, `uv_coordinates`), sent again only when its pixels changed. The tiles and levels are
`touchroller_perception.map_tiles`, kept from the tiles bands touched by `touchroller_perception.live_view`;
this module only builds and publishes messages.

Marker ids are stable per tile: namespace `touchroller_map/level_K`, id from the tile's (column, row).
A change of level, a new map or a new subscriber (RViz started after the scan) sends a `DELETEALL` and
then every tile of the current view.
"""
from __future__ import annotations

from typing import Any

import cv2
import numpy as np
from geometry_msgs.msg import Point
from nav_msgs.msg import MapMetaData
from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy
from visualization_msgs.msg import Marker, MarkerArray, UVCoordinate

from touchroller_bringup import names
from touchroller_bringup.image_conversion import array_to_image
from touchroller_perception.live_view import LiveMapView, LiveUpdate
from touchroller_perception.map_tiles import MapTile, TileConfig

MARKER_NAMESPACE = "touchroller_map"
#: reliable and volatile, a few arrays deep: a subscriber that joins later is sent the whole view
MARKERS_QOS = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=4, reliability=ReliabilityPolicy.RELIABLE,
                         durability=DurabilityPolicy.VOLATILE)
#: texture coordinates of a quad's corners (lower-left, lower-right, upper-right, upper-left): image row 0,
#: v = 0, is the tile's top edge (largest y)
_UV = ((0.0, 1.0), (1.0, 1.0), (1.0, 0.0), (0.0, 0.0))
_TRIANGLES = (0, 1, 2, 0, 2, 3)


def marker_id(tile: MapTile) -> int:
    """A tile's marker id (int32), unique per (column, row) within +-16384 tiles of the frame's origin."""
    return ((tile.row & 0x7FFF) << 15) | (tile.column & 0x7FFF)


def texture_png(tile: MapTile) -> bytes:
    """The tile's image as PNG: grey in all three colour channels and the alpha (0 outside the map); zlib
    level 1 (a tile of mapped texture compresses about as well at 1 as at 3, in half the time)."""
    bgra = cv2.merge([tile.grey, tile.grey, tile.grey, tile.alpha])
    ok, data = cv2.imencode(".png", bgra, [cv2.IMWRITE_PNG_COMPRESSION, 1])
    if not ok:
        raise ValueError("PNG encoding of a map tile failed")
    return data.tobytes()


def _stamp(msg: Any, stamp_ns: int) -> None:
    msg.stamp.sec, msg.stamp.nanosec = divmod(int(stamp_ns), 1_000_000_000)


def tile_marker(tile: MapTile, frame_id: str, stamp_ns: int) -> Marker:
    """One tile as a textured quad (two triangles) in `frame_id`."""
    marker = Marker()
    marker.header.frame_id = frame_id
    _stamp(marker.header, stamp_ns)
    marker.ns = f"{MARKER_NAMESPACE}/level_{tile.level}"
    marker.id = marker_id(tile)
    marker.type = Marker.TRIANGLE_LIST
    marker.action = Marker.ADD
    marker.pose.orientation.w = 1.0
    marker.scale.x = marker.scale.y = marker.scale.z = 1.0
    marker.color.r = marker.color.g = marker.color.b = marker.color.a = 1.0
    points, uvs = [], []
    for k in _TRIANGLES:
        point = Point()
        point.x, point.y, point.z = (float(v) for v in tile.corners[k])
        points.append(point)
        uvs.append(UVCoordinate(u=_UV[k][0], v=_UV[k][1]))
    marker.points, marker.uv_coordinates = points, uvs
    marker.texture_resource = f"embedded://{MARKER_NAMESPACE}_{tile.level}_{tile.column}_{tile.row}.png"
    marker.texture.header = marker.header
    marker.texture.format = "png"
    marker.texture.data = texture_png(tile)
    return marker


def delete_all(frame_id: str, stamp_ns: int) -> Marker:
    marker = Marker()
    marker.header.frame_id = frame_id
    _stamp(marker.header, stamp_ns)
    marker.action = Marker.DELETEALL
    return marker


def map_metadata(resolution: float, shape: tuple[int, int], origin: tuple[float, float],
                 stamp_ns: int) -> MapMetaData:
    """nav_msgs/MapMetaData of a map image (origin: the lower-left pixel's corner, as nav2 publishes)."""
    meta = MapMetaData()
    meta.map_load_time.sec, meta.map_load_time.nanosec = divmod(int(stamp_ns), 1_000_000_000)
    meta.resolution = float(resolution)
    meta.height, meta.width = (int(n) for n in shape)
    meta.origin.position.x, meta.origin.position.y = (float(v) for v in origin)
    meta.origin.orientation.w = 1.0
    return meta


class MapViewPublisher:
    """Publishes a world map's views (see the module docstring) with the node's `map` and `map_metadata`
    publishers and a `map_markers` publisher of its own."""

    def __init__(self, node: Any, map_pub: Any, metadata_pub: Any, config: TileConfig) -> None:
        self.map_pub, self.metadata_pub = map_pub, metadata_pub
        self.markers_pub = node.create_publisher(MarkerArray, names.MAP_MARKERS, MARKERS_QOS)
        self.live = LiveMapView(config)
        self._subscribers = 0
        self.markers_sent = 0   # tile markers published (all arrays)

    @property
    def config(self) -> TileConfig:
        return self.live.config

    def configure(self, config: TileConfig) -> None:
        """A new budget or tile size: the next view is built again and replaces every tile."""
        self.live = LiveMapView(config)

    def reset(self) -> None:
        """A new map: the next view replaces every tile."""
        self.live.reset()

    def publish(self, world: Any, touched: set[tuple[int, int]], frame_id: str, stamp_ns: int) -> LiveUpdate | None:
        """The view of the world map (a `WorldMapper`) on `map` + `map_metadata`, the changed tiles on
        `map_markers`, after the store's tiles `touched` changed (`WorldMapper.touched_tiles()`: only they are
        rendered again); None if nothing is mapped."""
        subscribers = self.markers_pub.get_subscription_count()
        if subscribers > self._subscribers:   # someone new (RViz started late): the whole view again
            self.live.resend()
        self._subscribers = subscribers
        live = self.live.update(world, touched)
        if live is None:
            return None
        view, update = live.view, live.tiles
        self.map_pub.publish(array_to_image(view.grey, stamp_ns, frame_id=frame_id))
        self.metadata_pub.publish(map_metadata(view.resolution, view.grey.shape, view.origin, stamp_ns))
        if update.tiles or update.replaced:
            markers = [delete_all(frame_id, stamp_ns)] if update.replaced else []
            markers += [tile_marker(tile, frame_id, stamp_ns) for tile in update.tiles]
            self.markers_pub.publish(MarkerArray(markers=markers))
            self.markers_sent += len(update.tiles)
        return live


def texture_of(marker: Marker) -> tuple[np.ndarray, np.ndarray]:
    """(grey, alpha) of a tile marker's embedded texture (for tests and tools)."""
    data = np.frombuffer(bytes(marker.texture.data), np.uint8)
    image = cv2.imdecode(data, cv2.IMREAD_UNCHANGED)
    if image is None or image.ndim != 3 or image.shape[2] != 4:
        raise ValueError("the marker's texture is not a 4-channel PNG")
    return image[:, :, 0], image[:, :, 3]
