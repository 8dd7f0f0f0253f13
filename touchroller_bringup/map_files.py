"""Map files: `map.png` (8-bit grey plus alpha, alpha 0 where nothing was mapped) and `map.yaml` beside it
in the nav2 map_server format (image, resolution, origin of the lower-left pixel's corner, negate,
occupied_thresh, free_thresh) plus `frame_id`. Both are written whole or not at all (a temporary file
renamed into place), so a failed write leaves an existing map as it was.
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
from touchroller_perception.world_map import WorldMapImage


@dataclass(frozen=True)
class MapYaml:
    image: str
    resolution: float
    origin: tuple[float, float, float]
    frame_id: str
    negate: int = 0
    occupied_thresh: float = 0.65
    free_thresh: float = 0.25
    latency: dict[str, Any] | None = None   # the camera latency the map was placed with (value_ms, sigma_ms, ...)

    def as_dict(self) -> dict[str, Any]:
        return {"image": self.image, "mode": "trinary", "resolution": float(self.resolution),
                "origin": [float(v) for v in self.origin], "negate": int(self.negate),
                "occupied_thresh": float(self.occupied_thresh), "free_thresh": float(self.free_thresh),
                "frame_id": self.frame_id, **({"camera_latency": self.latency} if self.latency else {})}


def _replace(path: Path, write: Any) -> None:
    """Write through a temporary file in the same folder, then rename it over `path`."""
    path.parent.mkdir(parents=True, exist_ok=True)
    with atomic_path(path) as temporary:
        write(temporary)


def png_grey_alpha(grey: np.ndarray, alpha: np.ndarray) -> bytes:
    """An 8-bit grey-plus-alpha PNG (colour type 4) of two (rows, columns) uint8 images: every row unfiltered,
    zlib level 1. These maps are noise-like: filtering and harder compression save 10-20 % of the bytes
    for twice the time (and PIL's import); any PNG reader reads it."""
    if grey.shape != alpha.shape or grey.ndim != 2 or grey.size == 0:
        raise ValueError(f"grey and alpha must be the same non-empty 2-D shape, got {grey.shape} and {alpha.shape}")
    rows, cols = grey.shape
    raw = np.zeros((rows, 1 + 2 * cols), np.uint8)   # each row: filter type 0, then grey, alpha, grey, alpha...
    raw[:, 1::2] = grey
    raw[:, 2::2] = alpha

    def chunk(kind: bytes, data: bytes) -> bytes:
        return struct.pack(">I", len(data)) + kind + data + struct.pack(">I", zlib.crc32(kind + data))

    header = struct.pack(">IIBBBBB", cols, rows, 8, 4, 0, 0, 0)   # 8 bits, grey + alpha, deflate, no interlace
    return (b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", header) + chunk(b"IDAT", zlib.compress(raw.tobytes(), 1))
            + chunk(b"IEND", b""))


def write_png_grey_alpha(path: Path, grey: np.ndarray, alpha: np.ndarray) -> None:
    data = png_grey_alpha(np.asarray(grey, np.uint8), np.asarray(alpha, np.uint8))
    _replace(path, lambda temporary: Path(temporary).write_bytes(data))


def write_world_map(png: str | Path, image: WorldMapImage, frame_id: str,
                    latency: dict[str, Any] | None = None) -> tuple[Path, Path]:
    """map.png + map.yaml (same stem) for a world map; returns both paths. UserError on a bad path.
    `latency`: the camera latency it was placed with (`world_map.latency_summary`), as `camera_latency`."""
    png = Path(png)
    if png.suffix.lower() != ".png":
        raise UserError(f"a world map is written as PNG with a YAML beside it; got {png}")
    if image.grey.size == 0:
        raise UserError("the world map is empty: no frame was mapped (was the roller ever pressed and rolled?)")
    meta = MapYaml(png.name, image.resolution, (image.origin[0], image.origin[1], 0.0), frame_id, latency=latency)
    yaml_path = png.with_suffix(".yaml")
    try:
        write_png_grey_alpha(png, image.grey, image.alpha)
        _replace(yaml_path, lambda temporary: temporary.write_text(yaml.safe_dump(meta.as_dict(), sort_keys=False),
                                                                   encoding="utf-8"))
    except OSError as exc:
        raise UserError(f"cannot write the map to {png}: {exc.strerror or exc}") from None
    return png, yaml_path


def read_world_map(yaml_path: str | Path) -> tuple[np.ndarray, np.ndarray, dict[str, Any]]:
    """(grey, alpha, the YAML) of a map written by `write_world_map`."""
    from PIL import Image

    yaml_path = Path(yaml_path)
    meta = yaml.safe_load(yaml_path.read_text(encoding="utf-8"))
    with Image.open(yaml_path.parent / meta["image"]) as picture:
        la = np.asarray(picture.convert("LA"))
    return la[..., 0].copy(), la[..., 1].copy(), meta


# GeoTIFF tags (GeoTIFF 1.1): the height map's placement in the map's frame
_MODEL_PIXEL_SCALE, _MODEL_TIEPOINT, _GEO_KEY_DIRECTORY = 33550, 33922, 34735
#: GTModelTypeGeoKey user-defined (the robot's frame, no Earth CRS); GTRasterTypeGeoKey PixelIsArea
_GEO_KEYS = (1, 1, 0, 2, 1024, 0, 1, 32767, 1025, 0, 1, 1)


def write_height_tif(path: str | Path, height: Any, frame_id: str) -> Path:
    """`height.tif`: a world height map (`world_height.HeightMapLayer`: float32 metres, rows growing with y,
    NaN where unmapped) as a float32 GeoTIFF, row 0 the top (largest y) as map.png, placed by
    ModelPixelScale (resolution) and ModelTiepoint (raster (0, 0) -> the top-left corner's world x, y in
    `frame_id`, also in the image description). Written whole or not at all; UserError on a bad path."""
    import tifffile

    path = Path(path)
    values = np.ascontiguousarray(np.asarray(height.height, np.float32)[::-1])
    if values.ndim != 2 or values.size == 0:
        raise UserError("the height map is empty: no pass was mapped with a height")
    res = float(height.resolution)
    x0, y_top = float(height.origin[0]), float(height.origin[1]) + values.shape[0] * res
    tags = [(_MODEL_PIXEL_SCALE, "d", 3, (res, res, 0.0), True),
            (_MODEL_TIEPOINT, "d", 6, (0.0, 0.0, 0.0, x0, y_top, 0.0), True),
            (_GEO_KEY_DIRECTORY, "H", len(_GEO_KEYS), _GEO_KEYS, True)]
    description = (f"height above the surface's base plane under the roller, metres, NaN unmapped; frame_id "
                   f"{frame_id}; top-left corner ({x0:.6f}, {y_top:.6f}) m; resolution {res:g} m")

    def write(temporary: Path) -> None:
        tifffile.imwrite(temporary, values, photometric="minisblack", description=description, extratags=tags,
                         metadata=None)

    try:
        _replace(path, write)
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
