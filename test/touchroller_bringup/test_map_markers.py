"""The world map in place for RViz: the perception node's `map_markers` (textured TRIANGLE_LIST quads in
base, one per tile) and its `map` view within the size budget, on a real rclpy context."""
from __future__ import annotations

import numpy as np
import pytest

pytest.importorskip("rclpy")
pytest.importorskip("visualization_msgs")
pytestmark = pytest.mark.ros

from rclpy.executors import SingleThreadedExecutor  # noqa: E402
from rclpy.parameter import Parameter  # noqa: E402

from touchroller_bringup import names  # noqa: E402
from touchroller_perception.geometry import CameraModel  # noqa: E402

CAMERA = CameraModel(fx=200.0, fy=200.0, cx=159.5, cy=119.5, width=320, height=240)
RES = 1e-4
TILE = 64
BOUNDS = (0.40005, -0.1, 0.43, -0.08)   # the map's corner half a cell off the world grid of cells


def quad(marker):
    """(corner of texel (0, 0)'s top-left, step per texel column, step per texel row) of a textured quad,
    from its points and their texture coordinates (uv (0, 0) the image's top-left, (1, 1) its bottom-right)."""
    points = np.array([[p.x, p.y, p.z] for p in marker.points])
    uv = np.array([[c.u, c.v] for c in marker.uv_coordinates])
    assert len(points) == len(uv) == 6 and marker.type == marker.TRIANGLE_LIST
    top_left = points[np.all(np.isclose(uv, [0, 0]), axis=1)][0]
    top_right = points[np.all(np.isclose(uv, [1, 0]), axis=1)][0]
    bottom_left = points[np.all(np.isclose(uv, [0, 1]), axis=1)][0]
    return top_left, top_right - top_left, bottom_left - top_left


def reassemble(markers, image):
    """The map (image rows from the top, `image.origin` its lower-left corner) rebuilt from the markers'
    textures: each texel's centre, placed by the quad's corners and uv, looked up in the map's cells."""
    from touchroller_bringup.map_markers import texture_of

    rows, cols = image.grey.shape
    grey, alpha = np.full((rows, cols), -1), np.full((rows, cols), -1)
    for marker in markers:
        tex_grey, tex_alpha = texture_of(marker)
        h, w = tex_grey.shape
        corner, along_u, along_v = quad(marker)
        j, i = np.meshgrid((np.arange(w) + 0.5) / w, (np.arange(h) + 0.5) / h)
        xyz = corner + j[..., None] * along_u + i[..., None] * along_v
        col = np.floor((xyz[..., 0] - image.origin[0]) / image.resolution).astype(int)
        row = rows - 1 - np.floor((xyz[..., 1] - image.origin[1]) / image.resolution).astype(int)
        inside = (row >= 0) & (row < rows) & (col >= 0) & (col < cols)
        assert not (tex_alpha[~inside] > 0).any()
        assert (grey[row[inside], col[inside]] == -1).all()   # tiles do not overlap
        grey[row[inside], col[inside]] = tex_grey[inside]
        alpha[row[inside], col[inside]] = tex_alpha[inside]
    return grey, alpha


@pytest.fixture
def mapping(ros_context):
    from rclpy.node import Node
    from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy
    from sensor_msgs.msg import Image
    from visualization_msgs.msg import MarkerArray

    from touchroller_bringup.nodes.perception_node import PerceptionNode
    from touchroller_perception.world_map import WorldMapConfig, WorldMapper

    overrides = [Parameter(name, value=value) for name, value in CAMERA.to_params().items()]
    overrides += [Parameter("map.publish_rate", value=50.0), Parameter("map.tile_px", value=TILE)]
    node = PerceptionNode(context=ros_context, parameter_overrides=overrides)
    helper = Node("markers_test_helper", context=ros_context)
    arrays: list = []
    maps: list = []
    helper.create_subscription(MarkerArray, names.topic(names.MAP_MARKERS), arrays.append, 10)
    latched = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=1, reliability=ReliabilityPolicy.RELIABLE,
                         durability=DurabilityPolicy.TRANSIENT_LOCAL)
    helper.create_subscription(Image, names.topic(names.MAP), maps.append, latched)
    executor = SingleThreadedExecutor(context=ros_context)
    executor.add_node(node)
    executor.add_node(helper)
    # a world map whose canvas the test fills (the node maps frames into it the same way)
    world = WorldMapper(CAMERA, lambda stamps: np.zeros((len(stamps), 4, 4)),
                        WorldMapConfig(resolution=RES, bounds=BOUNDS))

    def land(c0: int, r0: int, rows: int, cols: int, seed: int) -> None:
        band = np.random.default_rng(seed).uniform(10, 240, (rows, cols)).astype(np.float32)
        with node._map_lock:
            world.canvas.add([band, np.ones_like(band), np.ones_like(band)], c0, r0)
            node.world = world
            node._map_dirty = True

    yield node, executor, arrays, maps, world, land
    executor.shutdown()
    node.destroy_node()
    helper.destroy_node()


def test_markers_are_the_map_in_place_and_only_changed_tiles_are_sent_again(mapping, spin_until):
    from touchroller_bringup.image_conversion import image_to_array

    node, executor, arrays, maps, world, land = mapping
    assert spin_until(executor, lambda: node.map_views.markers_pub.get_subscription_count() > 0, timeout=10.0)
    land(20, 10, 120, 200, seed=1)
    assert spin_until(executor, lambda: len(arrays) >= 1 and len(maps) >= 1, timeout=20.0)
    image = world.map_image()
    first = arrays[0].markers
    assert first[0].action == first[0].DELETEALL   # a new map replaces whatever was shown
    tiles = first[1:]
    assert len(tiles) >= 4 and len({(m.ns, m.id) for m in tiles}) == len(tiles)
    for marker in tiles:
        assert marker.header.frame_id == names.BASE_FRAME and marker.action == marker.ADD
        assert marker.texture_resource.startswith("embedded://") and marker.texture.format == "png"
        corner, along_u, along_v = quad(marker)
        # squares of TILE map cells in the plane z = 0 (the pressed height is not known here)
        assert np.linalg.norm(along_u) == pytest.approx(TILE * RES)
        assert np.linalg.norm(along_v) == pytest.approx(TILE * RES)
        assert along_u[0] > 0 and along_v[1] < 0 and corner[2] == 0.0
    grey, alpha = reassemble(tiles, image)
    mapped = image.alpha > 0
    assert mapped.sum() == 120 * 200
    assert np.array_equal(alpha == 255, mapped) and np.array_equal(grey[mapped], image.grey[mapped])
    # the map view: within the budget the map itself, with its placement on map_metadata
    assert np.array_equal(image_to_array(maps[-1]), image.grey) and maps[-1].header.frame_id == names.BASE_FRAME

    # frames land in one corner: only the tiles there are sent again, with the same ids
    before = len(arrays)
    land(40, 15, 10, 10, seed=2)   # world grid columns 4040-4050, rows -985..-975: inside one 64-cell tile
    assert spin_until(executor, lambda: len(arrays) > before, timeout=20.0)
    again = arrays[-1].markers
    assert len(again) == 1 and again[0].action == again[0].ADD
    assert (again[0].ns, again[0].id) in {(m.ns, m.id) for m in tiles}
    image = world.map_image()
    grey, alpha = reassemble(again, image)
    shown = alpha == 255
    assert np.array_equal(grey[shown], image.grey[shown])
    # nothing new mapped: nothing sent
    before = len(arrays)
    with node._map_lock:
        node._map_dirty = True
    executor.spin_once(timeout_sec=0.2)
    assert not spin_until(executor, lambda: len(arrays) > before, timeout=1.0)


def test_a_map_past_the_budget_is_published_coarser_and_its_tiles_replaced(mapping, spin_until):
    from nav_msgs.msg import MapMetaData
    from rclpy.node import Node
    from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy

    from touchroller_bringup.image_conversion import image_to_array
    from touchroller_perception.map_tiles import view_at, world_map_raster
    from touchroller_perception.world_map import WorldMapConfig, WorldMapper

    node, executor, arrays, maps, world, land = mapping
    metadata: list = []
    listener = Node("metadata_test_helper", context=node.context)
    listener.create_subscription(MapMetaData, names.topic(names.MAP_METADATA), metadata.append, QoSProfile(
        depth=1, reliability=ReliabilityPolicy.RELIABLE, durability=DurabilityPolicy.TRANSIENT_LOCAL))
    executor.add_node(listener)
    try:
        assert spin_until(executor, lambda: node.map_views.markers_pub.get_subscription_count() > 0, timeout=10.0)
        land(0, 0, 100, 100, seed=3)
        assert spin_until(executor, lambda: len(arrays) >= 1, timeout=20.0)
        assert {m.ns for m in arrays[-1].markers[1:]} == {"touchroller_map/level_0"}
        assert not node.set_parameters([Parameter("map.view_max_pixels", value=1000)])[0].successful
        assert node.set_parameters([Parameter("map.view_max_pixels", value=262_144)])[0].successful
        big = WorldMapper(CAMERA, world.poses, WorldMapConfig(resolution=RES, bounds=(0.4, -0.1, 0.46, -0.04)))
        band = np.random.default_rng(4).uniform(10, 240, (600, 600)).astype(np.float32)
        before = len(arrays)
        with node._map_lock:   # 600 x 600 cells: past 512 x 512, so every other cell (level 1)
            big.canvas.add([band, np.ones_like(band), np.ones_like(band)], 0, 0)
            node.world = big
            node._map_dirty = True
        # map, map_metadata and map_markers are separate topics, delivered independently: wait for all three
        assert spin_until(executor, lambda: len(arrays) > before and metadata and maps
                          and metadata[-1].resolution == pytest.approx(2 * RES)
                          and (maps[-1].height, maps[-1].width) == (300, 300)
                          and {m.ns for m in arrays[-1].markers[1:]} == {"touchroller_map/level_1"}, timeout=20.0)
        # the view is read from the tile store's pyramid at level 1 (a tile at a time), not from the map
        # built whole: the weighted mean of each 2 x 2 block, within a grey level of the view of the whole map
        raster = world_map_raster(big, 262_144)
        assert raster.level == 1 and raster.grey.shape == (300, 300)
        expected = view_at(raster, 0)
        assert expected.level == 1 and expected.resolution == pytest.approx(2 * RES)
        assert np.array_equal(image_to_array(maps[-1]), expected.grey) and expected.grey.shape == (300, 300)
        whole = view_at(world_map_raster(big), 1)
        assert whole.origin == pytest.approx(expected.origin)
        assert int(np.abs(whole.grey.astype(int) - expected.grey).max()) <= 1
        assert (metadata[-1].width, metadata[-1].height) == (300, 300)
        assert (metadata[-1].origin.position.x, metadata[-1].origin.position.y) == pytest.approx(expected.origin)
        replaced = arrays[-1].markers
        assert replaced[0].action == replaced[0].DELETEALL
        assert {m.ns for m in replaced[1:]} == {"touchroller_map/level_1"}
        for marker in replaced[1:]:   # a tile of TILE level cells is 2 TILE map cells wide
            _, along_u, _ = quad(marker)
            assert np.linalg.norm(along_u) == pytest.approx(2 * TILE * RES)
    finally:
        executor.remove_node(listener)
        listener.destroy_node()
