"""map.tif (tiled pyramidal GeoTIFF) and map.png + map.yaml (nav2 map_server's view) of a tiled map."""
from __future__ import annotations

import math
import shutil
import subprocess

import numpy as np
import pytest
import tifffile
import yaml

from touchroller_bringup.geotiff import read_window, write_geotiff
from touchroller_bringup.map_files import read_world_map, write_world_map
from touchroller_perception.tiles import TileConfig
from touchroller_perception.world_canvas import WorldCanvas

RES = 1e-4


def _canvas(rows=1300, cols=2100, tile=256, seed=0, span=(60, 200)):
    """A growing canvas with a textured rectangle mapped (a hole in it), spilled to disk on small tiles."""
    rng = np.random.default_rng(seed)
    canvas = WorldCanvas(RES, None, TileConfig(tile=tile, cache_bytes=12 * tile * tile * 4))
    canvas.ensure(0, 0, cols, rows)
    for r in range(0, rows, 100):   # in bands, as frames land
        h = min(100, rows - r)
        weight = np.ones((h, cols), np.float32)
        if r == (rows // 200) * 100:
            weight[:, 100:300] = 0   # a hole: nothing mapped there
        grey = rng.uniform(*span, (h, cols)).astype(np.float32)
        canvas.add([grey * weight, weight, weight], 0, r)   # flat field 1 at level 1: value = grey
    return canvas


def _nav2_scale(png_grey, png_alpha, meta):
    """nav2 map_server's loadMapFromFile for `mode: scale` (map_io.cpp), per pixel: shade = grey / 255 (the
    mean of R, G, B of a grey image), occ = 1 - shade (negate 0) or shade; alpha not opaque -> unknown
    (-1); occ > occupied_thresh -> 100; occ < free_thresh -> 0; else rint((occ - free) / (occupied - free) 100)."""
    assert meta["mode"] == "scale"
    shade = png_grey.astype(np.float64) / 255.0
    occ = shade if meta["negate"] else 1.0 - shade
    free, occupied = meta["free_thresh"], meta["occupied_thresh"]
    cells = np.rint((occ - free) / (occupied - free) * 100.0)
    cells = np.where(occ > occupied, 100, np.where(occ < free, 0, cells))
    return np.where(png_alpha == 255, cells, -1).astype(np.int8)


def test_the_map_files_open_in_tifffile_with_size_overviews_and_placement(tmp_path):
    canvas = _canvas()
    view = canvas.view(1.0)
    png, yaml_path = write_world_map(tmp_path / "map.png", view, "base")
    meta = yaml.safe_load(yaml_path.read_text())
    image = canvas.value_in(1.0, (0, 1300, 0, 2100))
    with tifffile.TiffFile(tmp_path / "map.tif") as tif:
        series = tif.series[0]
        assert series.shape == (1300, 2100, 2) and series.dtype == np.uint8
        assert [level.shape[:2] for level in series.levels] == [(1300, 2100), (650, 1050), (325, 525), (163, 263)]
        page = tif.pages[0]
        assert page.is_tiled and (page.tilelength, page.tilewidth) == (512, 512)
        geo = page.geotiff_tags
        assert geo["ModelPixelScale"][:2] == [RES, RES]
        x0, y0 = canvas.origin
        assert geo["ModelTiepoint"][3:5] == pytest.approx([x0, y0 + 1300 * RES])   # the upper-left corner
        assert int(geo["GTModelTypeGeoKey"]) == 32767 and int(geo["ProjLinearUnitsGeoKey"]) == 9001
        full = series.asarray()
    grey = np.clip(np.floor(image[0] + 0.5), 0, 255).astype(np.uint8)[::-1]
    np.testing.assert_array_equal(full[..., 0], grey)
    assert (full[..., 1] == 255).sum() == 1300 * 2100 - 100 * 200 and not full[600:700, 100:300, 1].any()
    # the YAML: the GeoTIFF at full resolution; map.png the view (under 16 MP: not downscaled) stretched
    assert meta["geotiff"]["size"] == [2100, 1300] and meta["geotiff"]["levels"] == 4
    assert meta["geotiff"]["origin"][:2] == pytest.approx(list(canvas.origin))
    assert meta["view"]["downscale"] == 1 and meta["origin"][:2] == pytest.approx(list(canvas.origin))
    back, alpha, back_meta = read_world_map(yaml_path)
    np.testing.assert_array_equal(back, grey)
    assert back_meta["resolution"] == RES


def test_any_window_of_any_level_reads_back_as_the_level(tmp_path):
    canvas = _canvas(seed=1)
    write_geotiff(tmp_path / "m.tif", canvas.view(1.0), tile=256)
    with tifffile.TiffFile(tmp_path / "m.tif") as tif:
        levels = [level.asarray() for level in tif.series[0].levels]
    for level, data in enumerate(levels):
        for r0, c0 in [(0, 0), (100, 300), (data.shape[0] - 50, data.shape[1] - 70)]:
            window = read_window(tmp_path / "m.tif", level, r0, c0, 512, 512)
            np.testing.assert_array_equal(window, data[r0:r0 + 512, c0:c0 + 512])
    with pytest.raises(ValueError, match="levels"):
        read_window(tmp_path / "m.tif", len(levels), 0, 0, 10, 10)


def test_an_overview_is_the_weighted_mean_of_the_full_resolution(tmp_path):
    canvas = _canvas(seed=2, rows=700, cols=900)
    write_geotiff(tmp_path / "m.tif", canvas.view(1.0), tile=256)
    value, weight = canvas.value_in(1.0, (0, 700, 0, 900))
    value, weight = value[::-1], weight[::-1]
    with tifffile.TiffFile(tmp_path / "m.tif") as tif:
        half = tif.series[0].levels[1].asarray()
    sums = (value * weight).reshape(350, 2, 450, 2).sum(axis=(1, 3))
    totals = weight.reshape(350, 2, 450, 2).sum(axis=(1, 3))
    mean = np.divide(sums, totals, out=np.zeros_like(sums), where=totals > 0)
    assert np.abs(half[..., 0].astype(float) - mean).max() <= 0.5 + 1e-3
    np.testing.assert_array_equal(half[..., 1] == 255, totals / 4 > 0.05)


def test_a_float_layer_is_written_as_float32_with_nan_where_nothing_is_known(tmp_path):
    """The writer other layers use (a height in metres kept as sum(w height) beside sum(w): the canvas's
    `ratio_view`): float32, NaN unmapped, GDAL_NODATA nan."""
    canvas = _canvas(seed=3, rows=300, cols=400)
    canvas.add_layer("height_sum")
    rng = np.random.default_rng(3)
    weight = canvas.read("weight", (0, 300, 0, 400))
    heights = rng.normal(0, 20e-6, (300, 400)).astype(np.float32)
    canvas.add_named({"height_sum": heights * weight}, 0, 0)
    result = write_geotiff(tmp_path / "height.tif", canvas.ratio_view("height_sum"), "float", tile=256)
    with tifffile.TiffFile(tmp_path / "height.tif") as tif:
        data = tif.series[0].asarray()
        assert data.dtype == np.float32 and tif.pages[0].tags["GDAL_NODATA"].value == "nan"
    assert result.shape == (300, 400) and data.shape == (300, 400)
    known = np.isfinite(data)
    assert (~known).sum() == 100 * 200
    np.testing.assert_allclose(data[known], heights[::-1][known], rtol=1e-5, atol=1e-12)


def test_map_png_in_nav2_map_servers_scale_mode_shows_the_texture(tmp_path):
    """map_server's own rule (scale mode) over map.png: every mapped cell a value in 0..100 that follows the
    map's grey (darker: more occupied), unmapped cells unknown; under the old `trinary` with 0.65 / 0.25
    the same map read as (nearly) all unknown."""
    canvas = _canvas(seed=4, rows=400, cols=500, span=(107, 132))   # flat-looking grey, as the issue saw it
    png, yaml_path = write_world_map(tmp_path / "map.png", canvas.view(1.0), "base")
    meta = yaml.safe_load(yaml_path.read_text())
    import cv2

    picture = cv2.imread(str(png), cv2.IMREAD_UNCHANGED)
    grey, alpha = picture[..., 0], picture[..., 3]
    cells = _nav2_scale(grey, alpha, meta)
    known = cells >= 0
    assert known.sum() == 400 * 500 - 100 * 200
    assert len(np.unique(cells[known])) > 80   # the texture, not three levels
    with tifffile.TiffFile(tmp_path / "map.tif") as tif:
        data = tif.series[0].asarray()[..., 0]
    assert np.corrcoef(cells[known].astype(float), -data[known].astype(float))[0, 1] > 0.99
    assert data[known].max() - data[known].min() < 30   # the data itself spans few grey levels
    low, high = meta["view"]["stretch"]
    assert 107 <= low < high <= 132
    trinary = 1.0 - data[known] / 255.0
    assert ((trinary > 0.25) & (trinary < 0.65)).mean() > 0.99   # trinary: unknown


def test_a_map_over_16_megapixels_has_a_downscaled_view(tmp_path, monkeypatch):
    """The view is halved until it has at most VIEW_MAX_PIXELS (here lowered to keep the test small):
    resolution and origin in the YAML are the view's; the TIFF keeps full resolution."""
    import touchroller_bringup.map_files as map_files

    monkeypatch.setattr(map_files, "VIEW_MAX_PIXELS", 100_000)
    canvas = _canvas(seed=5, rows=700, cols=900)
    png, yaml_path = write_world_map(tmp_path / "map.png", canvas.view(1.0), "base")
    meta = yaml.safe_load(yaml_path.read_text())
    assert meta["view"]["downscale"] == 4 and meta["resolution"] == pytest.approx(4 * RES)
    import cv2

    picture = cv2.imread(str(png), cv2.IMREAD_UNCHANGED)
    assert picture.shape[:2] == (math.ceil(700 / 4), math.ceil(900 / 4))
    top = canvas.origin[1] + 700 * RES
    assert meta["origin"][1] + picture.shape[0] * meta["resolution"] == pytest.approx(top)
    assert meta["geotiff"]["size"] == [900, 700]


@pytest.mark.skipif(shutil.which("gdalinfo") is None, reason="gdalinfo (Debian's gdal-bin) is not installed")
def test_gdal_opens_the_map_with_its_size_overviews_and_placement(tmp_path):
    canvas = _canvas(seed=6, rows=1300, cols=2100)
    write_world_map(tmp_path / "map.png", canvas.view(1.0), "base")
    info = subprocess.run(["gdalinfo", "-json", str(tmp_path / "map.tif")], capture_output=True, text=True,
                          check=True)
    import json

    described = json.loads(info.stdout)
    assert described["size"] == [2100, 1300]
    x0, y0 = canvas.origin
    transform = described["geoTransform"]
    assert transform == pytest.approx([x0, RES, 0.0, y0 + 1300 * RES, 0.0, -RES])
    bands = described["bands"]
    assert len(bands) == 2 and bands[1]["colorInterpretation"] == "Alpha"
    assert [o["size"] for o in bands[0]["overviews"]] == [[1050, 650], [525, 325], [263, 163]]
    assert "ENGCRS" in described["coordinateSystem"]["wkt"] and "metre" in described["coordinateSystem"]["wkt"]


def test_the_files_hold_what_map_image_holds_pixel_for_pixel(tmp_path):
    """Streamed from the tiles (map.tif) or built whole in memory (`WorldMapper.map_image`, the live topic):
    the same grey, alpha and origin, for a growing map cropped to what was mapped."""
    from touchroller_perception.world_map import WorldMapConfig, WorldMapper

    rng = np.random.default_rng(9)
    mapper = WorldMapper.__new__(WorldMapper)   # the canvas and the map's level only
    mapper.config = WorldMapConfig()
    mapper.canvas = WorldCanvas(RES, None, TileConfig(tile=64, cache_bytes=8 * 64 * 64 * 4))
    mapper._level = 117.0
    for c, r in [(0, 0), (150, -90), (-200, 260), (333, 41)]:
        dc, dr = mapper.canvas.ensure(c, r, c + 120, r + 70)
        weight = rng.uniform(0, 1, (70, 120)).astype(np.float32)
        flat = weight * rng.uniform(80, 120, (70, 120)).astype(np.float32)
        mapper.canvas.add([flat * rng.uniform(0.5, 1.5, (70, 120)).astype(np.float32), flat, weight],
                          c + dc, r + dr)
    image = mapper.map_image()
    write_world_map(tmp_path / "map.png", mapper.view(), "base")
    grey, alpha, meta = read_world_map(tmp_path / "map.yaml")
    np.testing.assert_array_equal(grey, image.grey)
    np.testing.assert_array_equal(alpha, image.alpha)
    assert meta["origin"][:2] == pytest.approx(list(image.origin), abs=1e-12)


def test_a_map_that_would_not_fit_on_the_disk_is_refused_before_writing(tmp_path, monkeypatch):
    """The file's size is known before it is written: too little room is one line, the old map kept."""
    from collections import namedtuple

    import touchroller_bringup.geotiff as geotiff
    from touchroller_bringup.errors import UserError

    canvas = _canvas(seed=7, rows=300, cols=400)
    write_world_map(tmp_path / "map.png", canvas.view(1.0), "base")
    before = {p.name: p.read_bytes() for p in tmp_path.iterdir()}
    usage = namedtuple("usage", "total used free")
    monkeypatch.setattr(geotiff.shutil, "disk_usage", lambda _path: usage(10**9, 10**9 - 100_000, 100_000))
    with pytest.raises(UserError, match="needs 0 MB and .* has 0 MB free"):
        write_world_map(tmp_path / "map.png", canvas.view(2.0), "base")
    assert {p.name: p.read_bytes() for p in tmp_path.iterdir()} == before


def test_bigtiff_when_asked_or_large_and_the_same_image_either_way(tmp_path):
    canvas = _canvas(seed=8, rows=300, cols=400)
    small = write_geotiff(tmp_path / "small.tif", canvas.view(1.0), tile=256)
    big = write_geotiff(tmp_path / "big.tif", canvas.view(1.0), tile=256, bigtiff=True)
    assert not small.bigtiff and big.bigtiff
    with tifffile.TiffFile(tmp_path / "small.tif") as a, tifffile.TiffFile(tmp_path / "big.tif") as b:
        assert not a.is_bigtiff and b.is_bigtiff
        assert len(b.series[0].levels) == len(a.series[0].levels) == 2
        np.testing.assert_array_equal(a.series[0].asarray(), b.series[0].asarray())
        assert b.pages[0].geotiff_tags["ModelTiepoint"] == a.pages[0].geotiff_tags["ModelTiepoint"]


def test_map_png_made_beside_the_geotiff_is_the_full_resolution_view_and_its_errors_surface(tmp_path, monkeypatch):
    """At full resolution map.png is made by a second thread while map.tif is written: the same picture as
    the GeoTIFF's full resolution (stretched), and an error there is the command's one line, nothing written."""
    import touchroller_bringup.map_files as map_files
    from touchroller_bringup.errors import UserError

    canvas = _canvas(seed=11, rows=500, cols=700)
    png, yaml_path = write_world_map(tmp_path / "map.png", canvas.view(1.0), "base")
    meta = yaml.safe_load(yaml_path.read_text())
    assert meta["view"]["downscale"] == 1
    from PIL import Image

    with Image.open(png) as image:
        picture = np.asarray(image.convert("LA"))
    full = tifffile.imread(tmp_path / "map.tif", level=0)
    np.testing.assert_array_equal(picture[..., 1], full[..., 1])
    low, high = meta["view"]["stretch"]
    expected = np.clip(np.floor((full[..., 0].astype(np.float64) - low) * 255.0 / (high - low) + 0.5), 0, 255)
    assert np.abs(picture[..., 0].astype(np.float64) - expected)[full[..., 1] == 255].max() <= 1.0

    def full_disk(grey, alpha):
        raise OSError(28, "No space left on device")

    monkeypatch.setattr(map_files, "png_grey_alpha", full_disk)
    with pytest.raises(UserError, match="No space left on device"):
        write_world_map(tmp_path / "other" / "map.png", canvas.view(1.0), "base")
    assert not list((tmp_path / "other").glob("map.*"))


def test_at_full_resolution_the_maps_tiles_are_read_once_for_both_files_and_the_tif_is_unchanged(tmp_path):
    """map.tif and map.png are made from one read of the map's cells (the flat field's division done once):
    map.tif byte for byte the file `write_geotiff` streams from the map itself (its edge tiles' padding too),
    map.png the stretched full resolution."""
    from touchroller_bringup.map_files import TIFF_TILE

    canvas = _canvas(seed=5, rows=700, cols=1100)
    view = canvas.view(1.0)
    cells = []

    class Counting:
        tile, resolution, origin, mapped_weight = view.tile, view.resolution, view.origin, view.mapped_weight

        def extent(self):
            return view.extent()

        def read(self, r0, r1, c0, c1):
            cells.append((r1 - r0) * (c1 - c0))
            return view.read(r0, r1, c0, c1)

    write_world_map(tmp_path / "map.png", Counting(), "base")
    r0, r1, c0, c1 = view.extent()
    covered = math.ceil((r1 - r0) / TIFF_TILE) * math.ceil((c1 - c0) / TIFF_TILE) * TIFF_TILE ** 2
    assert sum(cells) <= covered   # each cell of the GeoTIFF's full-resolution tiles read once
    write_geotiff(tmp_path / "direct.tif", view, "intensity", "base", tile=TIFF_TILE)
    assert (tmp_path / "map.tif").read_bytes() == (tmp_path / "direct.tif").read_bytes()
