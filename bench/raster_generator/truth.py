"""What a generated raster really was, written beside its bag: `truth.json` + `surface.npy`.

`truth.json` holds the spec it was made from, the true camera latency, the rates, where the surface lies
in `base` (corner, yaw, resolution, its kind and planted features), the raster (corner, yaw, length,
width) and each pass as rolled (its line in `base`, direction, when the membrane touched). `surface.npy`
is the height field (float32, m). `load_truth(folder)` gives it back as `RasterTruth`, which also renders
what an ideal map of it looks like in place (`appearance`).
"""
from __future__ import annotations

import dataclasses
import json
import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from bench.raster_generator.motion import MotionConfig, PassTruth
from bench.raster_generator.render import Camera, Look, appearance
from bench.raster_generator.surfaces import Feature, Surface

FORMAT = "touchroller-raster-truth/1"


@dataclass(frozen=True)
class RasterSpec:
    """How to make one raster. `corner`: the raster rectangle's corner (x, y) in base; `yaw` (deg): the
    pass direction from base x; `length` (m) along the passes, `width` (m) across; `passes` pass lines
    flush with the width's edges. Latency (s): how late the images are stamped after their exposure."""

    surface: str = "grained"
    corner: tuple[float, float] = (0.40, -0.09)
    length: float = 0.24
    width: float = 0.18
    passes: int = 3
    yaw_deg: float = 0.0
    surface_yaw_deg: float = 0.0
    surface_z: float = 0.02
    latency: float = 0.035
    tf_rate: float = 125.0
    tf_jitter: float = 0.2           # of the TF period, uniform +-
    fps: float = 30.0
    frame_jitter_s: float = 3e-4
    motion: MotionConfig = MotionConfig()
    surface_resolution: float = 5e-5
    weave_period: float = 1.2e-3
    features: int = 8                # planted cracks / dents (grooves / pits on the grained surface)
    seed: int = 0
    storage: str = "sqlite3"

    @property
    def roll(self) -> np.ndarray:
        """The pass direction (u, and the cylinder frame's y) in base."""
        yaw = math.radians(self.yaw_deg)
        return np.array([math.cos(yaw), math.sin(yaw)])

    @property
    def across(self) -> np.ndarray:
        """The across direction (w, and the roller's axis, cylinder x) in base."""
        yaw = math.radians(self.yaw_deg)
        return np.array([-math.sin(yaw), math.cos(yaw)])

    def to_base(self, u: np.ndarray | float, w: np.ndarray | float) -> np.ndarray:
        """Raster-frame (u, w) -> base (x, y), (..., 2)."""
        u, w = np.asarray(u, dtype=np.float64), np.asarray(w, dtype=np.float64)
        return np.asarray(self.corner) + u[..., None] * self.roll + w[..., None] * self.across

    def area_polygon(self) -> np.ndarray:
        """The raster rectangle's corners (4, 2) in base."""
        return self.to_base(np.array([0.0, self.length, self.length, 0.0]),
                            np.array([0.0, 0.0, self.width, self.width]))


@dataclass(frozen=True)
class RasterTruth:
    spec: RasterSpec
    camera: Camera
    look: Look
    surface: Surface
    passes: tuple[PassTruth, ...]
    epoch_ns: int                      # base time of the trajectory's t = 0
    frames: int

    def pass_line(self, k: int) -> tuple[np.ndarray, np.ndarray]:
        """Pass k's start and end (x, y) in base, in the order it was rolled."""
        p = self.passes[k]
        return self.spec.to_base(p.u_start, p.w), self.spec.to_base(p.u_end, p.w)

    def appearance(self, origin: tuple[float, float], shape: tuple[int, int], resolution: float) -> np.ndarray:
        """What an ideal map shows on a base grid (see `BandRenderer.appearance`)."""
        return appearance(self.surface, self.camera, self.look, origin, shape, resolution, self.spec.roll)


def _plain(value: Any) -> Any:
    if dataclasses.is_dataclass(value) and not isinstance(value, type):
        return {f.name: _plain(getattr(value, f.name)) for f in dataclasses.fields(value)}
    if isinstance(value, (tuple, list)):
        return [_plain(v) for v in value]
    if isinstance(value, np.ndarray):
        return value.tolist()
    if isinstance(value, np.generic):
        return value.item()
    return value


def write_truth(folder: Path, truth: RasterTruth) -> None:
    """truth.json + surface.npy in `folder` (each written to a temporary name and renamed)."""
    folder.mkdir(parents=True, exist_ok=True)
    surface = truth.surface
    document = {
        "format": FORMAT,
        "spec": _plain(truth.spec),
        "camera": _plain(truth.camera),
        "look": _plain(truth.look),
        "latency_s": truth.spec.latency,
        "epoch_ns": truth.epoch_ns,
        "frames": truth.frames,
        "surface": {"kind": surface.kind, "file": "surface.npy", "resolution": surface.resolution,
                    "origin": list(surface.origin), "yaw": surface.yaw, "shape": list(surface.height.shape),
                    "weave_period": surface.weave_period, "features": _plain(surface.features)},
        "area_polygon": truth.spec.area_polygon().tolist(),
        "passes": [dict(_plain(p), start_xy=truth.pass_line(k)[0].tolist(), end_xy=truth.pass_line(k)[1].tolist())
                   for k, p in enumerate(truth.passes)],
    }
    temporary = folder / ".surface.npy.part"
    with open(temporary, "wb") as handle:
        np.save(handle, surface.height)
    temporary.replace(folder / "surface.npy")
    text = folder / ".truth.json.part"
    text.write_text(json.dumps(document, indent=1) + "\n", encoding="utf-8")
    text.replace(folder / "truth.json")


def _tuples(value: Any) -> Any:
    return tuple(_tuples(v) for v in value) if isinstance(value, list) else value


def load_truth(folder: str | Path) -> RasterTruth:
    """The truth written by `write_truth` (ValueError if `truth.json` is not one)."""
    folder = Path(folder)
    document = json.loads((folder / "truth.json").read_text(encoding="utf-8"))
    if document.get("format") != FORMAT:
        raise ValueError(f"{folder / 'truth.json'} is not a {FORMAT} file")
    spec_fields = dict(document["spec"])
    spec_fields["motion"] = MotionConfig(**spec_fields["motion"])
    spec = RasterSpec(**{k: _tuples(v) for k, v in spec_fields.items()})
    camera = Camera(**{k: _tuples(v) for k, v in document["camera"].items()})
    look = Look(**{k: _tuples(v) for k, v in document["look"].items()})
    s = document["surface"]
    height = np.load(folder / s["file"])
    if list(height.shape) != list(s["shape"]):
        raise ValueError(f"{folder / s['file']} has shape {height.shape}, truth.json says {s['shape']}")
    features = tuple(Feature(f["kind"], tuple(f["start"]), tuple(f["end"]), f["width"], f["depth"])
                     for f in s["features"])
    surface = Surface(s["kind"], height, float(s["resolution"]), tuple(s["origin"]), float(s["yaw"]),
                      features, s["weave_period"])
    passes = tuple(PassTruth(**{k: v for k, v in p.items() if k not in ("start_xy", "end_xy")})
                   for p in document["passes"])
    return RasterTruth(spec, camera, look, surface, passes, int(document["epoch_ns"]), int(document["frames"]))
