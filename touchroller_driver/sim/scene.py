"""Scenes: YAML files under `config/scenes/` naming the surface, the motion, the camera and the effects.

A scene is a nested mapping. `load_scene(name_or_path, **overrides)` reads it, applies a named
variant (`variant="fast"`) and then dotted overrides (`**{"motion.duration": 5.0}`, or the
keyword-friendly `motion__duration=5.0`), validates it and returns a `Scene`.
"""
from __future__ import annotations

import copy
import math
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import yaml

from touchroller_driver.paths import config_path
from touchroller_perception.geometry import CameraModel

#: Effects a scene may list; the contact geometry and the membrane shading are always rendered.
EFFECTS = ("background", "vignetting", "noise", "blur", "compression", "dropped_frames")
MOTION_KINDS = ("roll", "taps", "hemispheres", "chessboard", "ball_presses")

_DEFAULT_EFFECT_PARAMS: dict[str, dict[str, Any]] = {
    "background": {"illumination": 0.12, "led_falloff": 0.25, "specks": 60, "speck_radius_px": [1.0, 3.0]},
    "vignetting": {"strength": 0.35},
    "noise": {"sigma": 2.0, "shot": 0.0},   # read noise (DN); shot: DN per electron (0 = off)
    "blur": {},
    "compression": {"quality": 85},
    "dropped_frames": {"probability": 0.02},
}

_DEFAULT_SENSOR: dict[str, Any] = {
    "elastomer_thickness": 2.0e-3,   # m (not stated in the paper; a typical GelSight-like gel)
    "lowpass_sigma": "auto",         # m, or "auto" = lowpass_per_thickness * elastomer_thickness
    "lowpass_per_thickness": 0.075,  # empirical: 2 mm of gel -> 0.15 mm Gaussian (see docs/simulator.md)
    "thickness_variation": 0.0,      # m: amplitude of the membrane radius error along x and alpha
    "light_elevation_deg": 25.0,
    # B, G, R lights 120 deg apart in the membrane's tangent plane (0 deg = +x along the axis, 90 deg =
    # +v around it); green, which dominates a grey conversion, lights diagonally so grey images keep
    # slopes in both directions (a symmetric layout would cancel them in grey).
    "light_azimuths_deg": [200.0, 80.0, 320.0],
    # One white directional LED instead (a GelSight-type membrane lit from one side): its azimuth in
    # the membrane's tangent plane (deg, as above; null = the three coloured lights), and how much its
    # irradiance grows per 10 mm of membrane towards it (0 = uniform).
    "directional_light_deg": None,
    "directional_falloff": 0.15,
    "ambient": 0.2,
    "light_gain": 1.2,
    "exposure_scale": 0.72,          # DN = 255 * scale * shading
}


# Where the surface lies in the world frame (`base`) for the simulated arm (touchroller_driver.sim.camera):
# grid point (0, 0) on the contact line of the default sweep.start_pose (tool0 at (0.4, 0, 0.2) pointing
# down, the roller's axis 10 cm below it: mount.xyz) and its rows along world +x (the default sweep
# direction); the surface plane is where that pose touches it (z = 0.2 - 0.1 - r).
_DEFAULT_WORLD: dict[str, Any] = {"surface_origin": [0.4, 0.0, 0.05], "surface_yaw": 0.0}


def _default_camera() -> dict[str, Any]:
    path = config_path("touchroller.yaml")
    return CameraModel.from_yaml(path).to_params() if path.is_file() else CameraModel().to_params()


@dataclass
class Scene:
    """A validated scene. `data` is the full nested mapping (after variants and overrides)."""

    name: str
    data: dict[str, Any]
    path: Path | None = None

    @property
    def fps(self) -> float:
        return float(self.data["fps"])

    @property
    def exposure(self) -> float:
        return float(self.data["exposure"])

    @property
    def effects(self) -> tuple[str, ...]:
        return tuple(self.data["effects"])

    @property
    def motion(self) -> dict[str, Any]:
        return self.data["motion"]

    @property
    def surface(self) -> dict[str, Any]:
        return self.data.get("surface") or {"kind": "flat"}

    @property
    def world(self) -> dict[str, Any]:
        """The surface's placement in the world frame: `surface_origin` [x, y, z] (m) of the surface grid's
        point (0, 0), `surface_yaw` (rad) of its rows (the rolling direction) from world x."""
        return self.data["world"]

    @property
    def sensor(self) -> dict[str, Any]:
        return self.data["sensor"]

    @property
    def camera(self) -> CameraModel:
        """The true camera of the simulated sensor."""
        return CameraModel.from_params(self.data["camera"])

    @property
    def paper_camera(self) -> CameraModel:
        """The camera as a flawed calibration would report it (truth + `calibration_error`)."""
        err = self.data.get("calibration_error") or {}
        cam = self.camera
        return cam.replace(theta=cam.theta + float(err.get("theta", 0.0)), d=cam.d + float(err.get("d", 0.0)))

    def effect_params(self, effect: str) -> dict[str, Any]:
        params = dict(_DEFAULT_EFFECT_PARAMS.get(effect, {}))
        params.update((self.data.get("effect_params") or {}).get(effect) or {})
        return params

    @property
    def duration(self) -> float:
        """Seconds of the scene's own motion (frames are captured over [0, duration])."""
        from touchroller_driver.sim.scenarios import scene_duration

        return scene_duration(self)


def load_scene(name_or_path: str | Path, variant: str | None = None, **overrides: Any) -> Scene:
    """A scene by name (a file in `config/scenes/`) or by path, with a variant and dotted overrides.
    `NAME:VARIANT` names a variant too (`calibration_hemispheres:by_hand`), so one string can carry it."""
    if variant is None and isinstance(name_or_path, str) and ":" in name_or_path and not Path(name_or_path).is_file():
        name_or_path, _, variant = name_or_path.rpartition(":")
    path = _resolve(name_or_path)
    try:
        with open(path, encoding="utf-8") as stream:
            data = yaml.safe_load(stream)
    except yaml.YAMLError as exc:
        raise ValueError(f"scene {path}: not valid YAML ({str(exc).splitlines()[0]})") from None
    if not isinstance(data, dict):
        raise ValueError(f"scene {path}: expected a mapping at the top level")
    data = copy.deepcopy(data)
    variant = variant if variant is not None else overrides.pop("variant", None) or data.get("variant")
    if variant is not None:
        variants = data.get("variants") or {}
        if variant not in variants:
            raise ValueError(f"scene {path.stem}: unknown variant {variant!r} (has: {', '.join(variants) or 'none'})")
        for key, value in (variants[variant] or {}).items():
            set_dotted(data, key, value)
        data["variant"] = variant
    for key, value in overrides.items():
        set_dotted(data, key.replace("__", "."), value)
    data = _with_defaults(data)
    scene = Scene(name=str(data.get("name") or path.stem), data=data, path=path)
    validate(scene)
    return scene


def available_scenes() -> list[str]:
    return sorted(p.stem for p in config_path("scenes").glob("*.yaml"))


def set_dotted(data: dict[str, Any], key: str, value: Any) -> None:
    """`set_dotted(d, "motion.duration", 5)` sets d["motion"]["duration"], creating mappings on the way."""
    parts = key.split(".")
    node = data
    for part in parts[:-1]:
        child = node.get(part)
        if not isinstance(child, dict):
            child = {}
            node[part] = child
        node = child
    node[parts[-1]] = value


def _resolve(name_or_path: str | Path) -> Path:
    candidate = Path(name_or_path)
    if candidate.suffix in (".yaml", ".yml") and candidate.is_file():
        return candidate
    named = config_path("scenes", f"{name_or_path}.yaml")
    if named.is_file():
        return named
    raise ValueError(f"no scene {str(name_or_path)!r} (known: {', '.join(available_scenes()) or 'none'})")


def _with_defaults(data: dict[str, Any]) -> dict[str, Any]:
    camera = _default_camera()
    given = _flatten_camera(data.get("camera") or {})
    for block in ("extrinsics", "cylinder"):     # `--set extrinsics.theta=...` lands at the top level
        if isinstance(data.get(block), Mapping):
            given.update({f"{block}.{k}": v for k, v in data.pop(block).items()})
    camera.update(_camera_names(given))
    data["camera"] = camera
    sensor = dict(_DEFAULT_SENSOR)
    sensor.update(data.get("sensor") or {})
    data["sensor"] = sensor
    data.setdefault("fps", 30.0)
    data.setdefault("exposure", 0.02)
    data.setdefault("effects", [])
    data.setdefault("effect_params", {})
    data.setdefault("calibration_error", {"theta": 0.0, "d": 0.0})
    data.setdefault("start_stamp_ns", 1_700_000_000_000_000_000)
    world = dict(_DEFAULT_WORLD)
    world.update(data.get("world") or {})
    data["world"] = world
    return data


def _flatten_camera(camera: Mapping[str, Any]) -> dict[str, Any]:
    """Accept docs/design.md names (`camera.fx`, `extrinsics.theta`) or nested mappings."""
    flat: dict[str, Any] = {}
    for key, value in camera.items():
        if isinstance(value, Mapping):
            for inner, v in _flatten_camera(value).items():
                flat[f"{key}.{inner}"] = v
        else:
            flat[key] = value
    return flat


def _camera_names(given: Mapping[str, Any]) -> dict[str, Any]:
    """docs/design.md parameter names for a camera block; bare field names (fx, theta, ...) are accepted."""
    from touchroller_perception.geometry import PARAMETER_NAMES

    by_field = {name.split(".")[-1]: name for name in PARAMETER_NAMES}
    out = {}
    for key, value in given.items():
        name = key if key in PARAMETER_NAMES else by_field.get(key) if "." not in key else None
        if name is None:
            raise ValueError(f"unknown camera parameter {key!r} (expected one of {', '.join(PARAMETER_NAMES)})")
        out[name] = value
    return out


def validate(scene: Scene) -> None:
    d = scene.data
    where = f"scene {scene.name}"
    unknown = [e for e in d["effects"] if e not in EFFECTS]
    if unknown:
        raise ValueError(f"{where}: unknown effects {unknown} (known: {', '.join(EFFECTS)})")
    for key in ("fps", "exposure"):
        value = d[key]
        if not isinstance(value, int | float) or not math.isfinite(value) or value < 0:
            raise ValueError(f"{where}: {key} must be a finite number >= 0, got {value!r}")
    if d["fps"] <= 0:
        raise ValueError(f"{where}: fps must be > 0")
    if d["exposure"] * d["fps"] > 1.0 + 1e-9:
        raise ValueError(f"{where}: exposure {d['exposure']} s is longer than a frame at {d['fps']} fps")
    kind = (d.get("motion") or {}).get("kind")
    if kind not in MOTION_KINDS:
        raise ValueError(f"{where}: motion.kind must be one of {', '.join(MOTION_KINDS)}, got {kind!r}")
    scene.camera  # noqa: B018 - raises ValueError on a bad camera block
    if kind == "roll":
        from touchroller_driver.sim.scenarios import roll_profile

        roll_profile(scene.motion)   # raises ValueError if the move is infeasible
    origin, yaw = d["world"].get("surface_origin"), d["world"].get("surface_yaw")
    origin_ok = isinstance(origin, list | tuple) and len(origin) == 3 and all(_finite(v) for v in origin)
    if not origin_ok or not _finite(yaw):
        raise ValueError(f"{where}: world.surface_origin must be 3 finite numbers and world.surface_yaw a finite "
                         f"angle, got {origin!r} and {yaw!r}")
    if (d.get("surface") or {}).get("defects"):
        from touchroller_driver.sim.defects import surface_defects

        try:
            surface_defects(d["surface"])
        except ValueError as exc:
            raise ValueError(f"{where}: {exc}") from None
    p = scene.effect_params("dropped_frames")["probability"]
    if not 0.0 <= float(p) < 1.0:
        raise ValueError(f"{where}: dropped_frames.probability must be in [0, 1), got {p}")
    if not 1 <= int(scene.effect_params("compression")["quality"]) <= 100:
        raise ValueError(f"{where}: compression.quality must be in 1..100")
    if float(scene.effect_params("noise")["sigma"]) < 0 or float(scene.effect_params("noise")["shot"]) < 0:
        raise ValueError(f"{where}: noise.sigma and noise.shot must be >= 0")


def _finite(value: Any) -> bool:
    return isinstance(value, int | float) and not isinstance(value, bool) and math.isfinite(value)
