"""`touchroller simulate SCENE --out BAG`: render a scene to a rosbag2 recording plus its ground truth."""
from __future__ import annotations

import argparse
import dataclasses
import sqlite3
import time
from pathlib import Path
from typing import Any

from touchroller_bringup import bag_format
from touchroller_bringup.errors import UserError
from touchroller_bringup.names import IMAGE_TOPIC
from touchroller_bringup.outputs import Output, check_outputs
from touchroller_perception.files import new_directory


def register(subparsers: argparse._SubParsersAction) -> None:
    parser = subparsers.add_parser(
        "simulate", help="render a simulated scene to a bag (+ ground truth)",
        description="Render a scene from config/scenes (or a scene YAML path) to a rosbag2 recording of "
                    "/touchroller/image_raw, with BAG/ground_truth.yaml, BAG/camera_truth.yaml and "
                    "BAG/camera_paper.yaml. Deterministic for a seed.")
    parser.add_argument("scene", help="scene name (e.g. surface_mapping) or path to a scene YAML")
    parser.add_argument("--out", required=True, type=Path, help="output bag folder (must not exist)")
    parser.add_argument("--seed", type=int, default=0, help="random seed (default 0)")
    parser.add_argument("--storage", choices=("sqlite3", "mcap"), default="sqlite3")
    parser.add_argument("--bag-format", choices=bag_format.CHOICES, default="auto", help=bag_format.HELP)
    parser.add_argument("--variant", help="a variant the scene defines (e.g. slow, medium, fast, paper)")
    parser.add_argument("--set", dest="overrides", action="append", default=[], metavar="KEY=VALUE",
                        help="override a scene value, dotted keys, YAML values (e.g. motion.duration=5)")
    parser.add_argument("--topic", default=IMAGE_TOPIC, help="image topic (default: %(default)s)")
    parser.set_defaults(func=run)


def parse_overrides(items: list[str]) -> dict[str, Any]:
    import yaml

    overrides: dict[str, Any] = {}
    for item in items:
        key, sep, value = item.partition("=")
        if not sep or not key.strip():
            raise UserError(f"--set expects KEY=VALUE, got {item!r}")
        try:
            overrides[key.strip()] = yaml.safe_load(value)
        except yaml.YAMLError:
            raise UserError(f"--set {key}: value {value!r} is not valid YAML") from None
    return overrides


def run(args: argparse.Namespace) -> int:
    from touchroller_bringup.bags import write_images
    from touchroller_driver.sim import SimulatedSensor, load_scene
    from touchroller_driver.sim.flat_sensor import compare
    from touchroller_driver.sim.truth import write_ground_truth

    if args.out.exists() or args.out.is_symlink():
        raise UserError(f"output {args.out} already exists; give a new bag folder")
    scene_file = Path(args.scene) if Path(args.scene).suffix in (".yaml", ".yml") else None
    check_outputs([Output("--out", args.out, folder=True)], {"SCENE": scene_file})
    _check_parent_writable(args.out)
    overrides = parse_overrides(args.overrides)
    try:
        scene = load_scene(args.scene, variant=args.variant, **overrides)
        sensor = SimulatedSensor(scene, seed=args.seed)
    except (ValueError, TypeError, KeyError) as exc:
        raise UserError(f"scene {args.scene}: {exc}") from None
    truths: list[dict[str, Any]] = []
    started = time.perf_counter()

    def records():
        for frame in sensor.frames():
            truths.append(frame.truth)
            yield frame.stamp_ns, frame.image

    try:
        count, dropped = _render(args, scene, sensor, records, truths, write_images, compare, write_ground_truth)
    except (OSError, sqlite3.Error) as exc:
        why = getattr(exc, "strerror", None) or str(exc)
        raise UserError(f"cannot write the bag --out {args.out}: {why}; nothing was written (free some space or "
                        "choose another place)") from None
    elapsed = time.perf_counter() - started
    print(f"simulate: {scene.name}{'/' + scene.data['variant'] if scene.data.get('variant') else ''}: "
          f"{count} frames ({len(dropped)} dropped) in {elapsed:.1f} s -> {args.out} "
          f"(+ ground_truth.yaml, camera_truth.yaml, camera_paper.yaml)")
    return 0


def _render(args, scene, sensor, records, truths, write_images, compare, write_ground_truth):
    """The bag and its side files, whole or not at all; (frames written, times dropped)."""
    with new_directory(args.out) as folder:   # the bag and its side files appear whole or not at all
        count = write_images(folder, records(), topic=args.topic, storage=args.storage, distro=args.bag_format)
        all_times = _all_times(scene)
        kept = {round(t["t"], 9) for t in truths}
        dropped = [t for t in all_times if round(t, 9) not in kept]
        extra = {}
        if "comparison" in scene.data:
            import cv2

            from touchroller_driver.sim.flat_sensor import flat_press_mosaic

            comparison = compare(scene.data["comparison"], scene.motion)
            if not cv2.imwrite(str(folder / "flat_sensor_presses.png"),
                               flat_press_mosaic(sensor, scene.data["comparison"])):
                raise UserError(f"cannot write {args.out / 'flat_sensor_presses.png'}")
            # the ground-truth file carries the timing, its speed-up and the presses' image
            extra["comparison"] = {**dataclasses.asdict(comparison), "speedup": comparison.speedup,
                                   "presses_image": "flat_sensor_presses.png"}
        write_ground_truth(folder, sensor, truths, dropped, extra)
    return count, dropped


def _check_parent_writable(out: Path) -> None:
    """A bag folder is made beside its final place: a folder that cannot take it is refused before the render."""
    import os

    parent = out.parent
    while not parent.exists() and parent != parent.parent:
        parent = parent.parent
    if not parent.is_dir():
        raise UserError(f"--out {out}: {parent} is not a folder")
    if not os.access(parent, os.W_OK | os.X_OK):
        raise UserError(f"--out {out}: the folder {parent} is not writable; choose another place for the bag")


def _all_times(scene) -> list[float]:
    from touchroller_driver.sim.scenarios import frame_count

    return [k / scene.fps for k in range(frame_count(scene))]
