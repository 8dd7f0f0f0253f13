"""The world height map's per-frame relief and its per-pass levelling (touchroller_perception.world_height)."""
from __future__ import annotations

import numpy as np
import pytest

from touchroller_perception.tiles import TileConfig
from touchroller_perception.world_canvas import WorldCanvas
from touchroller_perception.world_height import HEIGHT_LAYERS, PASS, PASS_W, HeightBand, HeightLayer, WorldHeightConfig


def _canvas(shape=(120, 200), tile=512) -> tuple[WorldCanvas, HeightLayer]:
    canvas = WorldCanvas(1e-4, (0.0, 0.0, shape[1] * 1e-4, shape[0] * 1e-4), TileConfig(tile=tile))
    layer = HeightLayer(WorldHeightConfig(min_overlap=50))
    layer.add_layers(canvas)
    return canvas, layer


def _add_pass(canvas, layer, height, weight, c0, r0):
    canvas.add_named(layer.pass_planes(height * weight, weight), c0, r0)
    layer.end_pass(canvas)


@pytest.mark.parametrize("tile", [512, 32])   # one tile, or passes spanning many (and windows of them)
def test_each_pass_loses_its_plane_and_meets_the_earlier_ones_where_they_overlap(tile):
    canvas, layer = _canvas(tile=tile)
    rng = np.random.default_rng(0)
    relief = rng.normal(0, 20e-6, (120, 200)).astype(np.float32)
    rows, cols = np.mgrid[0:120, 0:200].astype(np.float32)
    weight = np.ones((120, 120), np.float32)
    # pass 1: columns 0..120, pressed 0.5 mm and tilted; pass 2: columns 80..200, 0.45 mm, another tilt
    first = relief[:, :120] + 5e-4 + 1e-6 * cols[:, :120] - 2e-6 * rows[:, :120]
    second = relief[:, 80:] + 4.5e-4 - 3e-6 * cols[:, :120] + 1e-6 * rows[:, :120]
    _add_pass(canvas, layer, first, weight, 0, 0)
    _add_pass(canvas, layer, second, weight, 80, 0)
    value = layer.value(canvas)
    assert np.isfinite(value).all()
    error = value - relief
    A = np.c_[np.ones(error.size), rows.ravel(), cols.ravel()]
    coef, *_ = np.linalg.lstsq(A, error.ravel(), rcond=None)
    residual = error.ravel() - A @ coef
    assert float(np.sqrt(np.mean(residual**2))) < 2e-6   # 20 um of relief, the passes' planes gone
    assert layer.passes == 2 and layer.levelled[1][2] == 120 * 40
    assert abs(layer.levelled[0][0] - (5e-4 + (1e-6 - 2e-6) * 59.5)) < 2e-6   # the first pass's plane at its middle


def test_a_pass_with_nothing_in_contact_adds_nothing_and_clears_the_pass_layers():
    canvas, layer = _canvas()
    _add_pass(canvas, layer, np.ones((10, 10), np.float32), np.zeros((10, 10), np.float32), 5, 5)
    assert layer.passes == 0 and layer.layer(canvas) is None
    for name in HEIGHT_LAYERS:   # nothing kept, and the pass's tiles are gone
        assert not canvas.read(name, (0, 120, 0, 200)).any()
    assert not canvas.store.tiles(PASS) and not canvas.store.tiles(PASS_W)


def test_unmapped_cells_are_nan():
    canvas, layer = _canvas()
    _add_pass(canvas, layer, np.full((30, 40), 1e-4, np.float32), np.ones((30, 40), np.float32), 10, 20)
    result = layer.layer(canvas)
    assert result is not None and result.resolution == 1e-4
    assert np.isfinite(result.height[20:50, 10:50]).all()
    assert np.isnan(result.height[:20]).all() and np.isnan(result.height[:, 60:]).all()
    assert np.allclose(result.height[20:50, 10:50], 0.0, atol=1e-9)   # a constant is the pass's plane


def test_a_held_band_keeps_its_relief_to_half_a_micrometre():
    relief = np.linspace(-3e-4, 9e-4, 640 * 70, dtype=np.float32).reshape(70, 640)
    band = HeightBand(relief, relief > 0).compact()
    assert band.relief.dtype == np.float16
    assert float(np.abs(band.relief.astype(np.float32) - relief).max()) <= 5e-7


@pytest.mark.parametrize("field, value", [("band_depth", 0.0), ("outer_fraction", 0.5), ("min_indentation", -1.0),
                                          ("min_weight", 0.0), ("min_overlap", 1), ("axis_sigma", -1.0),
                                          ("row_frames", -1), ("smoothing", -0.5), ("smoothing", float("nan"))])
def test_config_is_checked(field, value):
    with pytest.raises(ValueError):
        WorldHeightConfig(**{field: value})


def test_a_pass_is_levelled_on_the_window_of_its_tiles_not_the_whole_map():
    """On a map of many 32-cell tiles, ending a pass reads and writes only the tiles the pass reached (the
    earlier passes' tiles elsewhere are never read), and the pass's own tiles are dropped after."""
    canvas, layer = _canvas(shape=(256, 512), tile=32)
    weight = np.ones((40, 60), np.float32)
    _add_pass(canvas, layer, np.full((40, 60), 2e-4, np.float32), weight, 400, 200)   # far corner
    reads: list[tuple[str, int, int, int, int]] = []
    read = canvas.store.read

    def logged(name, r0, r1, c0, c1):
        reads.append((name, r0, r1, c0, c1))
        return read(name, r0, r1, c0, c1)

    canvas.store.read = logged
    _add_pass(canvas, layer, np.full((50, 70), 1e-4, np.float32), np.ones((50, 70), np.float32), 10, 20)
    assert {name for name, *_ in reads} == set(HEIGHT_LAYERS)
    for _, r0, r1, c0, c1 in reads:   # rows 20..70, columns 10..80: tiles rows 0..96, columns 0..96
        assert (r0, r1, c0, c1) == (0, 96, 0, 96)
    assert layer.passes == 2 and not canvas.store.tiles(PASS) and not canvas.store.tiles(PASS_W)
    value = layer.value(canvas)
    assert np.isfinite(value[20:70, 10:80]).all() and np.isfinite(value[200:240, 400:460]).all()
    assert np.isnan(value[100:180, 100:380]).all()


def test_the_height_map_at_a_level_is_read_from_the_tiles_in_place():
    """`WorldMapper.height_level(k)` (what map_height publishes within the view's budget): level 0 is
    `height_layer()` cell for cell; level 1 each cell the weighted mean of the 2 x 2 cells it covers, at
    twice the resolution, its corner on the same extent; NaN where nothing has a height."""
    from touchroller_perception.geometry import CameraModel
    from touchroller_perception.world_height import DONE, DONE_W, HeightSource
    from touchroller_perception.world_map import WorldMapConfig, WorldMapper

    camera = CameraModel(fx=200.0, fy=200.0, cx=159.5, cy=119.5, width=320, height=240)
    res = 2.0 ** -13
    mapper = WorldMapper(camera, lambda stamps: np.zeros((len(stamps), 4, 4)),
                         WorldMapConfig(resolution=res, bounds=(0.25, -0.125, 0.25 + 200 * res, -0.125 + 120 * res),
                                        tiles=TileConfig(tile=32)),
                         height=HeightSource(None, None, WorldHeightConfig()))   # type: ignore[arg-type]
    assert mapper.height_level(0) is None   # no pass yet
    rng = np.random.default_rng(7)
    relief = rng.normal(0, 2e-5, (60, 100)).astype(np.float32)
    weight = rng.uniform(0.5, 2.0, (60, 100)).astype(np.float32)
    mapper.canvas.add([np.ones_like(weight), np.ones_like(weight), np.ones_like(weight)], 40, 20)
    mapper.canvas.add_named({DONE: relief * weight, DONE_W: weight}, 40, 20)
    mapper._height_layer.passes = 1
    whole, level0, level1 = mapper.height_layer(), mapper.height_level(0), mapper.height_level(1)
    assert whole is not None and level0 is not None and level1 is not None
    np.testing.assert_array_equal(level0.height, whole.height)
    assert level0.origin == whole.origin and level0.resolution == whole.resolution == res
    assert level1.resolution == 2 * res and level1.height.shape == (60, 100)   # a fixed map: all its cells
    assert level1.origin == pytest.approx(whole.origin)
    mean = ((relief * weight).reshape(30, 2, 50, 2).sum(axis=(1, 3)) / weight.reshape(30, 2, 50, 2).sum(axis=(1, 3)))
    np.testing.assert_allclose(level1.height[10:40, 20:70], mean, atol=1e-9)
    known = np.isfinite(level1.height)
    assert known[10:40, 20:70].all() and known.sum() == 30 * 50


def test_a_pass_whose_height_does_not_fit_on_the_disk_leaves_the_finished_passes_as_they_were(monkeypatch):
    from touchroller_perception.tiles import StorageFull
    from touchroller_perception.world_height import DONE, DONE_W

    canvas, layer = _canvas(tile=32)
    _add_pass(canvas, layer, np.full((40, 60), 1e-4, np.float32), np.ones((40, 60), np.float32), 0, 0)
    before = {name: canvas.read(name, (0, 120, 0, 200)) for name in (DONE, DONE_W)}
    reserve = canvas.store.reserve

    def full(keys):
        if any(k[0] == DONE_W for k in keys):   # the weights' new tiles do not fit
            raise StorageFull("the disk is full")
        reserve(keys)

    monkeypatch.setattr(canvas.store, "reserve", full)
    with pytest.raises(StorageFull):   # a second pass partly on new tiles
        _add_pass(canvas, layer, np.full((40, 100), 2e-4, np.float32), np.ones((40, 100), np.float32), 40, 30)
    assert layer.passes == 1 and not canvas.store.tiles(PASS) and not canvas.store.tiles(PASS_W)
    for name, values in before.items():   # neither sum changed (not one without the other)
        np.testing.assert_array_equal(canvas.read(name, (0, 120, 0, 200)), values)


def test_the_finished_passes_get_tiles_only_where_a_pass_reached():
    """A pass along the diagonal of its window: its levelled height is added on its own tiles, not on the
    window's others (they would hold zeros, in memory or on disk, for nothing)."""
    from touchroller_perception.world_height import DONE, DONE_W

    canvas, layer = _canvas(shape=(256, 256), tile=32)
    for k in range(0, 200, 20):   # 20 x 20 squares down the diagonal: one pass
        canvas.add_named(layer.pass_planes(np.full((20, 20), 1e-4, np.float32), np.ones((20, 20), np.float32)), k, k)
    reached = canvas.store.tiles(PASS_W)
    layer.end_pass(canvas)
    assert layer.passes == 1
    assert canvas.store.tiles(DONE) == reached and canvas.store.tiles(DONE_W) == reached
    assert len(reached) < 7 * 7 / 2
    value = layer.value(canvas)
    assert np.isfinite(value[np.arange(200), np.arange(200)]).all() and np.isnan(value[0, 100])


@pytest.mark.parametrize("follow_arm", [True, False])
def test_a_press_that_eases_along_a_pass_is_not_read_as_relief_when_the_arm_is_followed(follow_arm):
    """A pass whose roller lifts by up to 0.15 mm towards its end (touching down and lifting off at speed): each
    frame is pressed that much less, so its band reads the relief less that much; given the arm's lift the
    pass gives back the relief, taken as a constant press depth it bends by what its plane cannot take out."""
    canvas = WorldCanvas(1e-4, (0.0, 0.0, 0.03, 0.012), TileConfig(tile=512))
    layer = HeightLayer(WorldHeightConfig(follow_arm=follow_arm))
    layer.add_layers(canvas)
    rng = np.random.default_rng(1)
    relief = rng.normal(0, 10e-6, (120, 300)).astype(np.float32)
    weights = np.ones((120, 20), np.float32)
    for c0 in range(0, 281, 4):                       # a band 20 cells along the pass, every 4 cells
        lift = 1.5e-4 * max(0.0, (c0 - 200) / 80) ** 2
        band = HeightBand(relief[:, c0:c0 + 20] - np.float32(lift), np.ones((120, 20), bool))
        weighted, w = layer.planes(weights, band, lift)
        canvas.add_named(layer.pass_planes(weighted, w), c0, 0)
    layer.end_pass(canvas)
    value = layer.value(canvas)
    error = (value - relief)[:, 10:-10]
    rows, cols = np.mgrid[0:error.shape[0], 0:error.shape[1]]
    A = np.c_[np.ones(error.size), rows.ravel(), cols.ravel()]
    coef, *_ = np.linalg.lstsq(A, error.ravel(), rcond=None)
    rms = float(np.sqrt(np.mean((error.ravel() - A @ coef) ** 2)))
    if follow_arm:
        assert rms < 1e-6
    else:
        assert rms > 20e-6


def _placed_gain(resampling: str, wavelength: float, along: str, phase: float, scale: float = 1.0) -> float:
    """A sinusoidal relief (`wavelength` map cells, along the roller's `axis` or its `roll`) given exactly at every
    band pixel of 40 frames rolled along a pass, placed by a `WorldMapper` at the band's own scale (`scale` 1: the
    axis-aligned placement, the pass `phase` cells off the map's grid across the roll) or at another (the affine
    warp): the map's in-phase gain against the relief on its cells, a plane removed."""
    import cv2

    from touchroller_perception.geometry import CameraModel
    from touchroller_perception.stitching import BandSampler
    from touchroller_perception.world_height import HeightSource
    from touchroller_perception.world_map import WorldMapConfig, WorldMapper

    camera = CameraModel(fx=200.0, fy=200.0, cx=159.5, cy=119.5, width=320, height=240)
    sampler = BandSampler((camera.height, camera.width), 64, camera, None, True)
    res = sampler.mm_per_px_cols * 1e-3 * scale
    k = 2 * np.pi / (wavelength * res)
    kx, ky = (k, 0.0) if along == "axis" else (0.0, k)

    def relief(x: np.ndarray, y: np.ndarray) -> np.ndarray:
        return 2e-5 * np.sin(kx * x + ky * y + 0.3)

    def poses(stamps: np.ndarray) -> np.ndarray:   # the roller's axis along x, rolled along y at 20 mm/s
        out = np.zeros((len(stamps), 4, 4))
        out[:, 0, 0], out[:, 1, 1], out[:, 2, 2], out[:, 3, 3] = 1.0, -1.0, -1.0, 1.0
        out[:, 0, 3], out[:, 1, 3], out[:, 2, 3] = phase * res, 0.02 * np.asarray(stamps) * 1e-9, 0.1
        return out

    config = WorldMapConfig(resolution=res, bounds=(-0.03, -0.01, 0.03, 0.04), latency=0.0, register=False)
    mapper = WorldMapper(camera, poses, config, height=HeightSource(None, None,   # type: ignore[arg-type]
                                                                    WorldHeightConfig(resampling=resampling)))
    mapper.source_rows((camera.height, camera.width))
    rows, cols = mapper.band_shape
    jj, ii = np.meshgrid(np.arange(cols), np.arange(rows))
    bx = (jj - sampler.centre_u) * sampler.mm_per_px_cols * 1e-3
    by = (ii - (rows - 1) / 2.0) * sampler.mm_per_px * 1e-3
    rng = np.random.default_rng(0)
    for n in range(40):
        stamp = round((n / 30.0 + 0.1) * 1e9)
        pose = poses(np.array([stamp]))[0]
        x = pose[0, 0] * bx + pose[0, 1] * by + pose[0, 2] * camera.radius + pose[0, 3]
        y = pose[1, 0] * bx + pose[1, 1] * by + pose[1, 2] * camera.radius + pose[1, 3]
        band = (128 + 20 * rng.standard_normal((rows, cols))).astype(np.float32)
        mapper.push_band(band, stamp, HeightBand(relief(x, y).astype(np.float32), np.ones((rows, cols), bool)))
    mapper.finalise()
    layer = mapper.height_layer(crop=False)
    assert layer is not None and mapper.stats.mapped == 40
    assert (mapper._placements[0].axes is not None) == (scale == 1.0)   # the blend, or the affine warp
    inside = cv2.erode(np.isfinite(layer.height).astype(np.uint8), np.ones((21, 21), np.uint8)) > 0
    r, c = np.nonzero(inside)
    x, y = layer.origin[0] + (c + 0.5) * res, layer.origin[1] + (r + 0.5) * res
    A = np.c_[np.sin(kx * x + ky * y + 0.3), np.cos(kx * x + ky * y + 0.3), np.ones(len(r)), r, c] * 2e-5
    coef, *_ = np.linalg.lstsq(A, layer.height[inside].astype(np.float64), rcond=None)
    return float(coef[0])


@pytest.mark.parametrize(("along", "phase"), [("roll", 0.0), ("axis", 0.5), ("axis", 0.25)])
def test_a_fine_relief_keeps_its_depth_when_placed_on_the_map(along, phase):
    """A relief 4.5 map cells across (the grained surface's finest that matters) keeps its depth through the
    placement: interpolated (the default, Lanczos) it reads within 3 %; splatted bilinearly with the weights
    ("linear", the intensity's way) it loses sinc^2 of it along the roll (the frames' phases average) and up to
    cos(pi / 4.5) along the axis, where a pass's phase stays put."""
    assert WorldHeightConfig().resampling == "lanczos4"
    assert _placed_gain("lanczos4", 4.5, along, phase) == pytest.approx(1.0, abs=0.03)
    assert _placed_gain("cubic", 4.5, along, phase) == pytest.approx(1.0, abs=0.05)
    linear = _placed_gain("linear", 4.5, along, phase)
    assert linear < 0.9
    assert linear == pytest.approx({"roll": 0.85, "axis": 0.83 if phase == 0.25 else np.cos(np.pi / 4.5)}[along],
                                   abs=0.03)


def test_a_fine_relief_placed_at_another_scale_than_the_bands_keeps_its_depth():
    """The same through the affine warp (a map 1.3x coarser than the band: not the axis-aligned blend)."""
    assert _placed_gain("lanczos4", 4.5, "roll", 0.0, scale=1.3) == pytest.approx(1.0, abs=0.03)
    assert _placed_gain("linear", 4.5, "roll", 0.0, scale=1.3) < 0.92


def test_resampling_is_one_of_the_known_ways():
    with pytest.raises(ValueError, match="resampling"):
        WorldHeightConfig(resampling="nearest")


def _pressed_bands(count: int, rows: int = 70, cols: int = 200, seed: int = 0):
    """(static row error (rows, 1), bands): each band a fresh relief (the surface moving under the band) plus the
    same error per band row (a press shape read slightly wrong: a bowl and a tilt across the rows), all in contact."""
    rng = np.random.default_rng(seed)
    y = np.linspace(-1.0, 1.0, rows)[:, None]
    error = (5e-6 * y ** 2 + 3e-6 * y).astype(np.float32)
    bands = [HeightBand((error + 480e-6 + 1e-5 * rng.standard_normal((rows, cols))).astype(np.float32),
                        np.ones((rows, cols), bool)) for _ in range(count)]
    return error, bands


def _row_error_left(layer: HeightLayer, band: HeightBand, error: np.ndarray) -> float:
    """RMS over the rows of what the layer's relief still holds of the rows' static error, m."""
    read = layer.relief(band).mean(axis=1, keepdims=True) - band.relief.mean(axis=1, keepdims=True) + error
    return float(np.sqrt(np.mean((read - read.mean()) ** 2)))


def test_the_band_rows_static_error_is_learnt_from_the_frames_and_taken_out_of_later_ones():
    error, bands = _pressed_bands(31)
    layer = HeightLayer(WorldHeightConfig(row_frames=30))
    for band in bands[:29]:
        layer.observe(band)
    assert layer.row_error() is None                       # not yet: the frames placed as read
    assert _row_error_left(layer, bands[-1], error) == pytest.approx(float(np.std(error)), rel=1e-3)
    layer.observe(bands[29])
    assert layer.row_error() is not None
    assert _row_error_left(layer, bands[-1], error) < 0.1 * float(np.std(error))
    # a relief constant over the rows (the surface, not the press) is left as it was
    flat = HeightBand(np.full_like(bands[0].relief, 1e-5), bands[0].contact)
    assert float(np.ptp(layer.relief(flat) + layer.row_error())) == pytest.approx(0.0, abs=1e-9)


def test_frames_barely_in_contact_teach_nothing_and_row_frames_0_leaves_the_relief_as_read():
    error, bands = _pressed_bands(40)
    layer = HeightLayer(WorldHeightConfig(row_frames=30))
    for band in bands:
        contact = np.zeros_like(band.contact)
        contact[:20] = True                                # lifting off: a few rows pressed
        layer.observe(HeightBand(band.relief, contact))
    assert layer.row_error() is None and layer.row_frames == 0
    off = HeightLayer(WorldHeightConfig(row_frames=0))
    for band in bands:
        off.observe(band)
    assert off.row_error() is None
    np.testing.assert_array_equal(off.relief(bands[0]), bands[0].relief)


def test_frames_are_integrated_as_footprint_slopes_by_default_and_the_way_is_checked():
    assert WorldHeightConfig().slopes == "footprint"
    with pytest.raises(ValueError, match="slopes"):
        WorldHeightConfig(slopes="corner")
