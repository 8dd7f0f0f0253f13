"""A second raster generator, deliberately different from the simulator, for the world map's benches.

The world map's figures must not rest on the simulator's assumptions alone (issue 22). This package
films rasters its own way and imports nothing of `touchroller_driver.sim`:

* `surfaces`: height fields synthesised here (band-limited noise with grooves and pits, a smooth painted
  panel with micrometre relief, cracks and dents, glass, a periodic weave), placed in `base`;
* `motion`: a boustrophedon raster under a motion profile (ramp, blend, constant, pauses + jitter),
  integrated at 1 kHz under an acceleration limit, at any raster yaw;
* `render`: the camera on the roller's axis (the project's camera contract, docs/design.md) seeing the
  membrane pressed against the surface: its own contact model, LEDs, flat field and sensor noise;
* `generate`: the rosbag2 recording (/touchroller/image_raw, /tf at a chosen rate with jitter,
  /tf_static of the mount and camera) with a chosen true camera latency, and the truth beside it;
* `truth`: `truth.json` + `surface.npy`, and `load_truth` to score a map against them.

`python -m bench.raster_generator OUT [--profile blend] [--latency 0.035] ...` films one raster.
Only evaluation code uses this package (the product never does), hence it lives in `bench/`.
"""
from bench.raster_generator.generate import generate, sensor
from bench.raster_generator.motion import PROFILES, MotionConfig
from bench.raster_generator.render import Camera, Look, load_camera
from bench.raster_generator.surfaces import KINDS
from bench.raster_generator.truth import RasterSpec, RasterTruth, load_truth

__all__ = ["KINDS", "PROFILES", "Camera", "Look", "MotionConfig", "RasterSpec", "RasterTruth", "generate",
           "load_camera", "load_truth", "sensor"]
