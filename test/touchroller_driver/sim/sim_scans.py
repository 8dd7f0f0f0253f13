"""Simulated raster scans for the world-map tests (test_world_map, test_map_windows, test_cmd_map_world,
test_cmd_inspect): the arm's default mount and start pose, the raster they roll, the scan's events, a world
mapper fed by them, and the events as a recording's records.

Loaded by file path as sweep_arms.py is (the test folders are not packages, and `test` is the standard
library's name). A test that makes a scan is skipped where the simulator cannot be imported.
"""
from __future__ import annotations

from collections.abc import Iterable, Iterator, Sequence
from typing import Any

import numpy as np
import pytest

from touchroller_driver.arm import (
    DEFAULT_MOUNT_RPY,
    DEFAULT_MOUNT_XYZ,
    DEFAULT_START_POSE,
    mount_transform,
    plan_raster,
)
from touchroller_perception.transforms import TransformBuffer
from touchroller_perception.world_map import WorldMapConfig, WorldMapper, buffer_lookup

MOUNT = mount_transform(DEFAULT_MOUNT_XYZ, DEFAULT_MOUNT_RPY)


def large_surface(seed: int = 0, variant: str | None = None, **overrides: Any) -> Any:
    """The simulated sensor over the `large_surface` scene (a variant, scene overrides)."""
    sim = pytest.importorskip("touchroller_driver.sim")
    return sim.SimulatedSensor(sim.load_scene("large_surface", variant, **overrides), seed=seed)


def raster(area: Sequence[float], start: Any = DEFAULT_START_POSE, **options: Any) -> Any:
    """The raster over `area` (x, y, length, width; m) from `start`, with the tests' motion: 20 mm/s,
    0.1 m/s^2, 0.5 mm deep, 2 mm clearance, approached at 5 mm/s (`options` change them or add to them)."""
    motion = {"speed": 0.02, "accel": 0.1, "depth": 5e-4, "clearance": 0.002, "approach_speed": 0.005}
    return plan_raster(start, area=area, mount=MOUNT, **{**motion, **options})


def sweep(sensor: Any, plan: Any, latency_s: float, **options: Any) -> Iterator[tuple[Any, ...]]:
    """The scan's events in time order, ("tf", stamp, tool pose) and ("image", stamp, image, seq), from
    above the first pass, the camera `latency_s` late (`options`: simulate_sweep's)."""
    simulate_sweep = pytest.importorskip("touchroller_driver.sim.sweep").simulate_sweep
    return simulate_sweep(sensor, plan, np.array(plan.segments[0].target), MOUNT, latency_s=latency_s, **options)


def world_mapper(camera: Any, config: WorldMapConfig) -> tuple[WorldMapper, TransformBuffer]:
    """A world mapper placing frames by TF from a buffer holding the static mount; feed it with `feed`."""
    buffer = TransformBuffer(cache_ns=None)
    buffer.set_transform("tool0", "touchroller_cylinder", 0, MOUNT, static=True)
    return WorldMapper(camera, buffer_lookup(buffer, "base", "touchroller_cylinder"), config), buffer


def feed(mapper: WorldMapper, buffer: TransformBuffer, event: tuple[Any, ...]) -> bool:
    """One event: a tool pose into the buffer (False), an image into the mapper (True)."""
    if event[0] == "tf":
        buffer.set_transform("base", "tool0", event[1], event[2])
        return False
    mapper.push(event[2], event[1])
    return True


def bag_records(events: Iterable[tuple[Any, ...]]) -> Iterator[Any]:
    """The events as a scan recording's records (`bags.write_scan`): the static mount, then /tf and images."""
    from touchroller_bringup.bags import ImageRecord, TransformRecord

    yield TransformRecord("tool0", "touchroller_cylinder", 0, MOUNT.translation, MOUNT.rotation, True)
    for event in events:
        if event[0] == "tf":
            yield TransformRecord("base", "tool0", event[1], event[2].translation, event[2].rotation, False)
        else:
            yield ImageRecord(event[1], event[2])
