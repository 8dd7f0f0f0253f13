"""The tile store: layers of fixed tiles, a bounded cache in memory, the rest on disk; its pyramid views."""
from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from touchroller_perception.tiles import (
    StorageFull,
    TileConfig,
    TileStore,
    levels_for,
    pyramid_tile,
    reduce2,
    render_tile,
)

T = 32
TILE_BYTES = T * T * 4


def test_memory_holds_no_more_tiles_than_the_cache_and_the_rest_reads_back_from_disk():
    store = TileStore(TileConfig(tile=T, cache_bytes=5 * TILE_BYTES))
    store.add_layer("sum", np.float32)
    store.add_layer("count", np.uint16)
    rng = np.random.default_rng(1)
    full = np.zeros((10 * T, 10 * T), np.float32)
    most = 0
    for _ in range(60):   # patches all over an 8 x 8 tile area, negative cells too
        r, c = (int(v) for v in rng.integers(-4 * T, 3 * T, 2))
        patch = rng.uniform(0, 1, (int(rng.integers(1, 2 * T)), int(rng.integers(1, 2 * T)))).astype(np.float32)
        store.add("sum", patch, r, c)
        full[r + 4 * T:r + 4 * T + patch.shape[0], c + 4 * T:c + 4 * T + patch.shape[1]] += patch
        most = max(most, store.resident())
    store.write("count", np.full((3, 3), 7, np.uint16), -1, -1)
    assert most <= 5 and store.resident_bytes <= 5 * TILE_BYTES
    assert store.spilled > 0 and len(store.tiles("sum")) > 5
    np.testing.assert_array_equal(store.read("sum", -4 * T, 6 * T, -4 * T, 6 * T), full)
    assert store.loaded > 0
    assert store.read("count", -2, 3, -2, 3).tolist() == [[0] * 5] + [[0, 7, 7, 7, 0]] * 3 + [[0] * 5]
    assert store.read("count", 0, 1, 0, 1).dtype == np.uint16
    folder = store.folder
    assert any(folder.iterdir())
    store.close()
    assert not folder.exists()


def test_a_new_tile_that_would_fill_the_disk_is_refused_and_what_is_there_stays(tmp_path):
    store = TileStore(TileConfig(tile=T, folder=str(tmp_path)))
    store.add_layer("sum")
    store.add("sum", np.ones((4, 4), np.float32), 0, 0)
    store.config = TileConfig(tile=T, folder=str(tmp_path), min_free_bytes=2 ** 62)   # "the disk is full"
    store.add("sum", np.ones((4, 4), np.float32), 1, 1)   # an existing tile: no new bytes
    with pytest.raises(StorageFull, match="MB free"):
        store.add("sum", np.ones((4, 4), np.float32), 10 * T, 0)
    assert store.tiles("sum") == {(0, 0)}
    assert store.read("sum", 0, 2, 0, 2).tolist() == [[1, 1], [1, 2]]


def test_touched_says_the_tiles_written_since_the_last_call():
    store = TileStore(TileConfig(tile=T))
    store.add_layer("sum")
    store.add("sum", np.ones((2, 2), np.float32), T - 1, -1)   # four tiles
    assert store.touched() == {(-1, 0), (0, 0), (-1, 1), (0, 1)}
    assert store.touched() == set()
    store.read("sum", 0, 3 * T, 0, 3 * T)   # reading is not touching
    store.add("sum", np.ones((1, 1), np.float32), 2 * T, 2 * T)
    assert store.touched() == {(2, 2)}


def test_layers_are_checked():
    store = TileStore(TileConfig(tile=T))
    store.add_layer("a", np.float32)
    with pytest.raises(ValueError, match="exists"):
        store.add_layer("a", np.uint8)
    with pytest.raises(ValueError, match="name"):
        store.add_layer("a/b")
    with pytest.raises(ValueError, match="multiple of 16"):
        TileConfig(tile=20)


class _ArrayView:
    """A whole array as a LayerView (the reference the tiled pyramid is checked against)."""

    mapped_weight = 0.05

    def __init__(self, value, weight, tile):   # value 0 where nothing is known, as the canvas gives it
        self.value, self.weight, self.tile = np.where(weight > 0, value, 0).astype(np.float32), weight, tile
        self.resolution, self.origin = 1e-4, (0.0, 0.0)

    def extent(self):
        return 0, self.value.shape[0], 0, self.value.shape[1]

    def read(self, r0, r1, c0, c1):
        out = np.zeros((2, r1 - r0, c1 - c0), np.float32)
        rows, cols = self.value.shape
        a0, a1, b0, b1 = max(r0, 0), min(r1, rows), max(c0, 0), min(c1, cols)
        if a1 > a0 and b1 > b0:
            out[0, a0 - r0:a1 - r0, b0 - c0:b1 - c0] = self.value[a0:a1, b0:b1]
            out[1, a0 - r0:a1 - r0, b0 - c0:b1 - c0] = self.weight[a0:a1, b0:b1]
        return out[0], out[1]


@settings(max_examples=20, deadline=None)
@given(seed=st.integers(0, 1000), level=st.integers(0, 3))
def test_property_a_pyramid_tile_is_the_weighted_mean_of_its_cells(seed, level):
    """Tile (level, ix, iy) built a tile at a time equals the weighted mean over 2^level x 2^level blocks
    of the whole array; weights 0 (nothing known) leave their cells out."""
    rng = np.random.default_rng(seed)
    size = 4 * 16 * 2 ** 3
    value = rng.uniform(0, 255, (size, size)).astype(np.float32)
    weight = rng.uniform(0, 1, (size, size)).astype(np.float32) * (rng.uniform(size=(size, size)) > 0.3)
    view = _ArrayView(value, weight, 16)
    block = 2 ** level
    sums = (value * weight).reshape(size // block, block, size // block, block).sum(axis=(1, 3))
    totals = weight.reshape(size // block, block, size // block, block).sum(axis=(1, 3))
    for ix, iy in [(0, 0), (1, 2), (size // (16 * block) - 1, 0)]:
        v, w = pyramid_tile(view, level, ix, iy)
        want_w = totals[iy * 16:(iy + 1) * 16, ix * 16:(ix + 1) * 16]
        want_v = np.divide(sums[iy * 16:(iy + 1) * 16, ix * 16:(ix + 1) * 16], want_w, where=want_w > 0,
                           out=np.zeros_like(want_w))
        np.testing.assert_allclose(w, want_w / block ** 2, rtol=1e-4, atol=1e-6)
        np.testing.assert_allclose(v, want_v, rtol=1e-3, atol=1e-2)
    grey, alpha = render_tile(view, level, 1, 0)
    v, w = pyramid_tile(view, level, 1, 0)
    assert grey.dtype == np.uint8 and grey.shape == (16, 16)
    np.testing.assert_array_equal(grey, np.clip(np.floor(v + 0.5), 0, 255).astype(np.uint8)[::-1])
    np.testing.assert_array_equal(alpha, np.where(w > 0.05, 255, 0)[::-1])


def test_reduce2_pads_an_odd_side_with_nothing_and_levels_halve_until_one_tile():
    value = np.array([[1, 3, 5]], np.float32)
    weight = np.array([[1, 1, 1]], np.float32)
    mean, w = reduce2(value, weight)
    assert mean.tolist() == [[2, 5]] and w.tolist() == [[0.5, 0.25]]
    assert levels_for((512, 512), 512) == 1 and levels_for((513, 100), 512) == 2
    assert levels_for((10_000, 10_000), 512) == 6   # 10000, 5000, 2500, 1250, 625, 313


def test_adding_over_windows_found_once_is_adding_layer_by_layer():
    """`windows` + `add_windows` (the tiles a window falls in found once for every layer it adds to) sum
    what `add` sums, across tile borders and negative cells, and track the largest sum alike."""
    rng = np.random.default_rng(3)
    one, many = TileStore(TileConfig(tile=T)), TileStore(TileConfig(tile=T))
    for store in (one, many):
        store.add_layer("a")
        store.add_layer("b")
    for r0, c0, h, w in [(-5, -7, 40, 70), (10, 30, 5, 5), (-40, 60, 33, 9)]:
        a, b = rng.uniform(0, 1, (2, h, w)).astype(np.float32)
        largest = one.add("a", a, r0, c0, track_max=True), one.add("b", b, r0, c0)
        windows = many.windows(r0, r0 + h, c0, c0 + w)
        many.reserve([(name, ix, iy) for name in "ab" for ix, iy, *_ in windows])
        assert (many.add_windows("a", a, windows, track_max=True), many.add_windows("b", b, windows)) == largest
        assert {(ix, iy) for ix, iy, *_ in windows} == set(one.spans(r0, r0 + h, c0, c0 + w))
    for name in "ab":
        assert many.tiles(name) == one.tiles(name)
        np.testing.assert_array_equal(many.read(name, -50, 60, -10, 90), one.read(name, -50, 60, -10, 90))
    assert many.windows(3, 3, 0, 10) == []
