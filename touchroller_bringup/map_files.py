"""Map files of a world map, beside each other (each written whole or not at all: a temporary file renamed
into place, so a failed write leaves an existing map as it was):

* `map.tif`: the map itself at full resolution, a tiled pyramidal GeoTIFF (`touchroller_bringup.geotiff`:
  grey plus alpha, the map's own grey levels, overviews at 1/2, 1/4, ..., placed by GeoTIFF tags),
  written streamed from the map's tiles;
* `map.png` + `map.yaml`: nav2 map_server's view of it: the map (downscaled by a power of two until it
  has at most `VIEW_MAX_PIXELS`) contrast-stretched, 8-bit grey plus alpha (0 where nothing was
  mapped); `map.yaml` says image, resolution (the view's), origin (its lower-left corner), `mode: scale`
  with negate 0 and thresholds 0 and 1 (map_server then shows every grey level as an occupancy of
  0..100 and leaves unmapped cells unknown), plus `frame_id`, `view` (the downscale and the stretch) and
  `geotiff` (the full-resolution file: image, resolution, size, origin).

`read_world_map` reads both kinds: a map with `geotiff` in its YAML from the TIFF (full resolution), an
older one (map.png at full resolution, `mode: trinary`) from the PNG.
"""
from __future__ import annotations

import struct
import zlib
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import yaml

from touchroller_bringup.errors import UserError
from touchroller_perception.files import atomic_path
from touchroller_perception.tiles import LayerView, StorageFull, to_alpha, to_grey
from touchroller_perception.world_map import WorldMapImage

try:   # the same deflate format, faster (optional; pinned in requirements.txt)
    from isal import isal_zlib as _deflate
except ImportError:   # pragma: no cover - a ROS install may lack it
    _deflate = zlib  # type: ignore[misc]

TIFF_TILE = 512   # map.tif's tile side
VIEW_MAX_PIXELS = 16_000_000   # map.png (nav2 map_server's view) is downscaled until it has at most this many
STRETCH_PERCENTILES = (0.5, 99.5)   # map.png's grey spans these percentiles of the mapped cells' values


@dataclass(frozen=True)
class MapYaml:
    """map.yaml: nav2 map_server's keys (image, mode, resolution, origin, negate, thresholds) for the view,
    plus frame_id, the view's downscale and stretch, and the full-resolution GeoTIFF."""

    image: str
    resolution: float
    origin: tuple[float, float, float]
    frame_id: str
    negate: int = 0
    occupied_thresh: float = 1.0
    free_thresh: float = 0.0
    latency: dict[str, Any] | None = None   # the camera latency the map was placed with (value_ms, sigma_ms, ...)
    mode: str = "scale"
    view: dict[str, Any] | None = None      # downscale (a power of two), stretch [low, high] of the map's grey
    geotiff: dict[str, Any] | None = None   # image, resolution, size [columns, rows], origin [x, y, 0], levels

    def as_dict(self) -> dict[str, Any]:
        return {"image": self.image, "mode": self.mode, "resolution": float(self.resolution),
                "origin": [float(v) for v in self.origin], "negate": int(self.negate),
                "occupied_thresh": float(self.occupied_thresh), "free_thresh": float(self.free_thresh),
                "frame_id": self.frame_id, **({"view": self.view} if self.view else {}),
                **({"geotiff": self.geotiff} if self.geotiff else {}),
                **({"camera_latency": self.latency} if self.latency else {})}


class ImageView:
    """A `WorldMapImage` (grey, alpha; row 0 the top) as a `tiles.LayerView` (rows growing with y)."""

    mapped_weight = 0.5

    def __init__(self, image: WorldMapImage, tile: int = 512) -> None:
        self.image, self.tile = image, tile
        self.resolution, self.origin = image.resolution, image.origin
        self._value = np.ascontiguousarray(image.grey[::-1], np.float32)
        self._weight = (np.asarray(image.alpha[::-1]) > 0).astype(np.float32)

    def extent(self) -> tuple[int, int, int, int] | None:
        rows, cols = self._value.shape
        return (0, rows, 0, cols) if rows and cols and self._weight.any() else None

    def read(self, r0: int, r1: int, c0: int, c1: int) -> tuple[np.ndarray, np.ndarray]:
        rows, cols = self._value.shape
        value, weight = np.zeros((2, r1 - r0, c1 - c0), np.float32)
        a0, a1, b0, b1 = max(r0, 0), min(r1, rows), max(c0, 0), min(c1, cols)
        if a1 > a0 and b1 > b0:
            value[a0 - r0:a1 - r0, b0 - c0:b1 - c0] = self._value[a0:a1, b0:b1]
            weight[a0 - r0:a1 - r0, b0 - c0:b1 - c0] = self._weight[a0:a1, b0:b1]
        return value, weight


def stretch_of(value: np.ndarray, mapped: np.ndarray) -> tuple[float, float]:
    """(low, high): `STRETCH_PERCENTILES` of the mapped cells' values (at least one grey level apart)."""
    values = value[mapped]
    values = values[::max(1, values.size // 2_000_000)]   # a display stretch: 2 million values are plenty
    if values.size == 0:
        return 0.0, 255.0
    low, high = (float(v) for v in np.percentile(values, STRETCH_PERCENTILES))
    if high - low < 1.0:
        low, high = low - 0.5, low + 0.5
    return round(low, 3), round(high, 3)


def _replace(path: Path, write: Any) -> None:
    """Write through a temporary file in the same folder, then rename it over `path`."""
    path.parent.mkdir(parents=True, exist_ok=True)
    with atomic_path(path) as temporary:
        write(temporary)


def png_grey_alpha(grey: np.ndarray, alpha: np.ndarray) -> bytes:
    """An 8-bit grey-plus-alpha PNG (colour type 4) of two (rows, columns) uint8 images: every row unfiltered,
    deflate level 1 (ISA-L's when `isal` is installed: three times as fast as zlib's for a few per cent more
    bytes; the same pixels either way). These maps are noise-like: filtering and harder compression save
    10-20 % of the bytes for twice the time (and PIL's import); any PNG reader reads it."""
    if grey.shape != alpha.shape or grey.ndim != 2 or grey.size == 0:
        raise ValueError(f"grey and alpha must be the same non-empty 2-D shape, got {grey.shape} and {alpha.shape}")
    rows, cols = grey.shape
    raw = np.zeros((rows, 1 + 2 * cols), np.uint8)   # each row: filter type 0, then grey, alpha, grey, alpha...
    raw[:, 1::2] = grey
    raw[:, 2::2] = alpha

    def chunk(kind: bytes, data: bytes) -> bytes:
        return struct.pack(">I", len(data)) + kind + data + struct.pack(">I", zlib.crc32(kind + data))

    header = struct.pack(">IIBBBBB", cols, rows, 8, 4, 0, 0, 0)   # 8 bits, grey + alpha, deflate, no interlace
    return (b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", header) + chunk(b"IDAT", _deflate.compress(raw, 1))
            + chunk(b"IEND", b""))


def _view_png(value: np.ndarray, weight: np.ndarray, mapped_weight: float) -> tuple[bytes, tuple[float, float], int]:
    """(map.png's bytes, its stretch, its rows) of a view level's value and weight (image rows, row 0 the top)."""
    low, high = stretch_of(value, weight > mapped_weight)
    grey = to_grey(value, low, high, flip=False)
    alpha = to_alpha(weight, mapped_weight, flip=False)
    return png_grey_alpha(grey, alpha), (low, high), grey.shape[0]


class _HeldView:
    """A view's (value, weight) over `box`, read once a tile's rows at a time (never three whole layers in
    memory at once) and held as a `tiles.LayerView` of the same cells: the GeoTIFF writer reads its tiles
    from here while map.png is made from the same arrays, so the map's tiles (and the flat field's
    division) are read once for both files. Held over the whole file tiles the GeoTIFF's full resolution
    reads (`tile`-sized, from the box's top-left corner: its right and bottom ones reach past the box),
    so its tiles, padding included, are what the view itself gives."""

    def __init__(self, view: LayerView, box: tuple[int, int, int, int], tile: int) -> None:
        r0, r1, c0, c1 = box
        self.box, self.tile, self.mapped_weight = box, view.tile, view.mapped_weight
        self.resolution, self.origin = view.resolution, view.origin
        self.cover = (r1 - -(-(r1 - r0) // tile) * tile, r1, c0, c0 + -(-(c1 - c0) // tile) * tile)
        q0, q1, p0, p1 = self.cover
        self.value, self.weight = np.empty((2, q1 - q0, p1 - p0), np.float32)
        t = view.tile
        for a0 in [q0, *range((q0 // t + 1) * t, q1, t)]:   # along the map's own tile rows
            a1 = min((a0 // t + 1) * t, q1)
            self.value[a0 - q0:a1 - q0], self.weight[a0 - q0:a1 - q0] = view.read(a0, a1, p0, p1)

    def rows_down(self) -> tuple[np.ndarray, np.ndarray]:
        """(value, weight) over the box as image rows (row 0 the top): views, not copies."""
        r0, r1, c0, c1 = self.box
        q0, _, p0, _ = self.cover
        inside = slice(r1 - q0 - 1, r0 - q0 - 1 if r0 > q0 else None, -1), slice(c0 - p0, c1 - p0)
        return self.value[inside], self.weight[inside]

    def extent(self) -> tuple[int, int, int, int]:
        return self.box

    def read(self, r0: int, r1: int, c0: int, c1: int) -> tuple[np.ndarray, np.ndarray]:
        q0, q1, p0, p1 = self.cover
        if q0 <= r0 and r1 <= q1 and p0 <= c0 and c1 <= p1:   # what the GeoTIFF writer reads
            return (self.value[r0 - q0:r1 - q0, c0 - p0:c1 - p0].copy(),
                    self.weight[r0 - q0:r1 - q0, c0 - p0:c1 - p0].copy())
        raise ValueError(f"rows {r0}..{r1}, columns {c0}..{c1} lie outside the held cells {self.cover}")


class _Background:
    """`function(*args)` run by a thread of its own; `result()` waits for it (and raises what it raised)."""

    def __init__(self, function: Any, *args: Any) -> None:
        import threading

        self._result: Any = None
        self._error: BaseException | None = None

        def run() -> None:
            try:
                self._result = function(*args)
            except BaseException as exc:  # noqa: BLE001 - raised again by result(), in the caller's thread
                self._error = exc

        self._thread = threading.Thread(target=run, name="map-png", daemon=True)
        self._thread.start()

    def result(self) -> Any:
        self._thread.join()
        if self._error is not None:
            raise self._error
        return self._result


def write_png_grey_alpha(path: Path, grey: np.ndarray, alpha: np.ndarray) -> None:
    data = png_grey_alpha(np.asarray(grey, np.uint8), np.asarray(alpha, np.uint8))
    _replace(path, lambda temporary: Path(temporary).write_bytes(data))


def write_world_map(png: str | Path, source: WorldMapImage | LayerView, frame_id: str,
                    latency: dict[str, Any] | None = None) -> tuple[Path, Path]:
    """map.tif, map.png + map.yaml (same stem: module docstring) of a world map, streamed from a tiled
    `source` (`WorldMapper.view()`) or from a `WorldMapImage`; returns the PNG's and the YAML's paths.
    UserError on a bad path, an empty map or a full disk. `latency`: the camera latency it was placed
    with (`world_map.latency_summary`), as `camera_latency`."""
    from touchroller_bringup.geotiff import view_level, write_geotiff

    png = Path(png)
    if png.suffix.lower() != ".png":
        raise UserError(f"a world map is written as PNG with a YAML beside it; got {png}")
    view = ImageView(source) if isinstance(source, WorldMapImage) else source
    box = view.extent()
    if box is None:
        raise UserError("the world map is empty: no frame was mapped (was the roller ever pressed and rolled?)")
    shape = (box[1] - box[0], box[3] - box[2])
    level = view_level(shape, VIEW_MAX_PIXELS)
    tif_path, yaml_path = png.with_suffix(".tif"), png.with_suffix(".yaml")
    try:
        png.parent.mkdir(parents=True, exist_ok=True)
        # all three to temporaries, renamed over the old ones only once all three are written
        with atomic_path(tif_path) as tif_file, atomic_path(png) as png_file, atomic_path(yaml_path) as yaml_file:
            view_png = None
            if level == 0:
                # the full resolution is the view: read once here, its PNG made by a second thread (zlib
                # and numpy's big loops let go of the GIL) while this one writes the GeoTIFF from the same
                # arrays
                held = _HeldView(view, box, TIFF_TILE)
                view_png = _Background(_view_png, *held.rows_down(), view.mapped_weight)
                view = held
            tif = write_geotiff(tif_path, view, "intensity", frame_id, tile=TIFF_TILE,
                                keep_level=None if level == 0 else level, into=tif_file)
            if view_png is None:
                assert tif.kept is not None
                data, (low, high), rows = _view_png(*tif.kept, view.mapped_weight)
            else:
                data, (low, high), rows = view_png.result()
            view_res = tif.resolution * 2 ** level
            origin = (tif.top_left[0], tif.top_left[1] - rows * view_res, 0.0)
            meta = MapYaml(png.name, view_res, origin, frame_id, latency=latency,
                           view={"downscale": 2 ** level, "stretch": [low, high],
                                 "grey": "255 (value - low) / (high - low), clipped; geotiff: the map's grey levels"},
                           geotiff={"image": tif_path.name, "resolution": float(tif.resolution),
                                    "size": [tif.shape[1], tif.shape[0]],
                                    "origin": [float(tif.origin[0]), float(tif.origin[1]), 0.0],
                                    "levels": tif.levels, "bigtiff": tif.bigtiff})
            Path(png_file).write_bytes(data)
            Path(yaml_file).write_text(yaml.safe_dump(meta.as_dict(), sort_keys=False), encoding="utf-8")
    except StorageFull as exc:
        raise UserError(f"cannot write the map to {png}: {exc}") from None
    except OSError as exc:
        raise UserError(f"cannot write the map to {png}: {exc.strerror or exc}") from None
    return png, yaml_path


def read_world_map(yaml_path: str | Path) -> tuple[np.ndarray, np.ndarray, dict[str, Any]]:
    """(grey, alpha, the YAML) of a map written by `write_world_map`, at full resolution: from its GeoTIFF
    when the YAML names one (the YAML returned with that image's `resolution` and `origin`), else from
    its PNG (older maps)."""
    from PIL import Image

    yaml_path = Path(yaml_path)
    meta = yaml.safe_load(yaml_path.read_text(encoding="utf-8"))
    geotiff = meta.get("geotiff") if isinstance(meta, dict) else None
    if geotiff:
        import tifffile

        data = tifffile.imread(yaml_path.parent / geotiff["image"], level=0)
        meta = {**meta, "resolution": geotiff["resolution"], "origin": geotiff["origin"]}
        return np.ascontiguousarray(data[..., 0]), np.ascontiguousarray(data[..., 1]), meta
    with Image.open(yaml_path.parent / meta["image"]) as picture:
        la = np.asarray(picture.convert("LA"))
    return la[..., 0].copy(), la[..., 1].copy(), meta


# GeoTIFF tags (GeoTIFF 1.1) read_height_tif places the height map by (written by `geotiff.write_geotiff`)
_MODEL_PIXEL_SCALE, _MODEL_TIEPOINT = 33550, 33922


def write_height_tif(path: str | Path, height: LayerView, frame_id: str) -> Path:
    """`height.tif`: a world height map (`WorldMapper.height_view()`: float32 metres, NaN where unmapped)
    streamed from the tiles as a tiled pyramidal float32 GeoTIFF (`geotiff.write_geotiff(view, "float")`:
    the full resolution first, row 0 the top (largest y) as map.png, over the cells map.tif spans, placed by
    ModelPixelScale and ModelTiepoint in `frame_id`; overviews the weighted means). Written whole or not at
    all; UserError on a bad path, a full disk or an empty map."""
    from touchroller_bringup.geotiff import write_geotiff

    path = Path(path)
    try:
        write_geotiff(path, height, "float", frame_id)
    except ValueError:
        raise UserError("the height map is empty: no pass was mapped with a height") from None
    except StorageFull as exc:
        raise UserError(f"cannot write the height map to {path}: {exc}") from None
    except OSError as exc:
        raise UserError(f"cannot write the height map to {path}: {exc.strerror or exc}") from None
    return path


def read_height_tif(path: str | Path) -> tuple[np.ndarray, tuple[float, float], float]:
    """(float32 metres with row 0 the top, the top-left corner's world (x, y), resolution) of a height.tif."""
    import tifffile

    with tifffile.TiffFile(path) as tif:
        page = tif.pages[0]
        values = page.asarray()
        scale = page.tags[_MODEL_PIXEL_SCALE].value
        tie = page.tags[_MODEL_TIEPOINT].value
    return values, (float(tie[3]), float(tie[4])), float(scale[0])
