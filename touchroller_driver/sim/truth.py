"""Ground truth files written next to a simulated recording.

BAG/ground_truth.yaml: scene (after variants/overrides), seed, true and "paper" cameras (docs/design.md
parameter names), per-frame truth (stamp, time, roller state and pose, contacts with 3D points in
`touchroller_cylinder` and pixels, board poses), dropped frames, and scene-specific extras.
BAG/camera_truth.yaml and BAG/camera_paper.yaml: ROS 2 params files for `--params`.
BAG/ground_truth_surface.npy (relief, metres, full surface grid), ground_truth_surface.png (the
surface height at camera pixel scale along the roll, `SimulatedSensor.surface_map_truth`) and
ground_truth_tactile.png (the same relief as the sensor's shading renders it, grey) for roll scenes.
"""
from __future__ import annotations

import dataclasses
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import yaml

from touchroller_driver.sim.render import SimulatedSensor
from touchroller_perception.files import atomic_path, atomic_write


def plain(value: Any) -> Any:
    """YAML-safe copy: dataclasses to mappings, numpy scalars/arrays to Python, tuples to lists, NaN kept as .nan."""
    if dataclasses.is_dataclass(value) and not isinstance(value, type):
        return plain(dataclasses.asdict(value))
    if isinstance(value, Mapping):
        return {str(k): plain(v) for k, v in value.items()}
    if isinstance(value, np.ndarray):
        return plain(value.tolist())
    if isinstance(value, Sequence) and not isinstance(value, str | bytes):
        return [plain(v) for v in value]
    if isinstance(value, np.integer | bool | np.bool_):
        return value.item() if hasattr(value, "item") else value
    if isinstance(value, np.floating | float):
        return float(value)
    return value


def write_ground_truth(out_dir: str | Path, sensor: SimulatedSensor, frames: list[dict[str, Any]],
                       dropped: list[float], extra: dict[str, Any] | None = None) -> dict[str, Path]:
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    scene = sensor.scene
    written: dict[str, Path] = {}
    sensor.camera.to_yaml(out / "camera_truth.yaml")
    scene.paper_camera.to_yaml(out / "camera_paper.yaml")
    written["camera_truth"] = out / "camera_truth.yaml"
    written["camera_paper"] = out / "camera_paper.yaml"
    mpp_u, mpp_v = sensor.metres_per_px_at_contact()
    document: dict[str, Any] = {
        "scene": scene.name,
        "variant": scene.data.get("variant"),
        "seed": sensor.seed,
        "scene_data": scene.data,
        "camera_truth": sensor.camera.to_params(),
        "camera_paper": scene.paper_camera.to_params(),
        "calibration_error": scene.data.get("calibration_error"),
        "thickness_variation": float(scene.sensor.get("thickness_variation", 0.0)),
        "contact_row_v": sensor.contact_row(),
        "metres_per_px_at_contact": {"u": mpp_u, "v": mpp_v},
        "effects": list(sensor.effects),
        "surface": {"description": sensor.surface.description, "resolution": sensor.surface.resolution,
                    "x0": sensor.surface.x0, "y0": sensor.surface.y0,
                    "width": sensor.surface.width, "length": sensor.surface.length,
                    "max_height": sensor.surface.max_height},
        "frame_count": len(frames),
        "dropped_frame_times": dropped,
        "frames": frames,
    }
    if scene.motion.get("kind") == "roll":
        with atomic_write(out / "ground_truth_surface.npy", "wb") as stream:
            np.save(stream, sensor.surface.height)
        truth_map = sensor.surface_map_truth()
        for name, image in (("ground_truth_surface.png", truth_map.image),
                            ("ground_truth_tactile.png", truth_map.tactile)):
            with atomic_path(out / name) as temporary:
                if not cv2.imwrite(str(temporary), image):
                    raise OSError(f"cannot write {out / name}")
        written["tactile_png"] = out / "ground_truth_tactile.png"
        written["surface_npy"] = out / "ground_truth_surface.npy"
        written["surface_png"] = out / "ground_truth_surface.png"
        document["surface_map"] = {
            "file": "ground_truth_surface.png", "tactile_file": "ground_truth_tactile.png",
            "rows": "world Y increasing (rolling direction)",
            "mm_per_px_rows": truth_map.mm_per_px_rows, "mm_per_px_cols": truth_map.mm_per_px_cols,
            "y_start": truth_map.y_start, "x_first_column": float(truth_map.x_of_column[0]),
            "x_last_column": float(truth_map.x_of_column[-1]), "grey_255_is_height_m": sensor.surface.max_height,
        }
    if scene.motion.get("kind") == "chessboard":
        board = sensor._board
        document["board"] = {"pattern_size": list(board.pattern_size), "square_size": board.square,
                             "object_points": board.object_points()}
    document.update(extra or {})
    with atomic_write(out / "ground_truth.yaml") as stream:
        yaml.safe_dump(plain(document), stream, sort_keys=False, width=120)
    written["ground_truth"] = out / "ground_truth.yaml"
    return written
