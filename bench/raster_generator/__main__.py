"""`python -m bench.raster_generator OUT ...`: film one raster of the second generator into OUT/."""
from __future__ import annotations

import argparse
import dataclasses
import sys
from pathlib import Path

from bench.raster_generator import KINDS, PROFILES, MotionConfig, RasterSpec, generate, load_camera


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m bench.raster_generator", description=__doc__.splitlines()[0])
    parser.add_argument("out", type=Path, help="folder to write (bag/, truth.json, surface.npy); must not hold a bag")
    parser.add_argument("--surface", choices=KINDS, default="grained")
    parser.add_argument("--profile", choices=PROFILES, default="blend")
    parser.add_argument("--area", default="0.40,-0.09,0.24,0.18", help="x,y,length,width (m) of the raster in base")
    parser.add_argument("--passes", type=int, default=3)
    parser.add_argument("--yaw", type=float, default=0.0, help="pass direction from base x (deg)")
    parser.add_argument("--latency", type=float, default=0.035, help="true camera latency (s)")
    parser.add_argument("--tf-rate", type=float, default=125.0, help="/tf rate (Hz)")
    parser.add_argument("--speed", type=float, default=0.02, help="m/s along a pass")
    parser.add_argument("--jitter", type=float, default=0.03, help="pauses profile: RMS relative speed jitter")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--storage", choices=("sqlite3", "mcap"), default="sqlite3")
    parser.add_argument("--params", default=str(Path(__file__).resolve().parents[2] / "config" / "touchroller.yaml"),
                        help="params file giving the camera and mount (default: config/touchroller.yaml)")
    args = parser.parse_args(argv)
    try:
        x, y, length, width = (float(v) for v in args.area.split(","))
    except ValueError:
        print(f"error: --area must be x,y,length,width, got {args.area!r}", file=sys.stderr)
        return 2
    if (args.out / "bag").exists():
        print(f"error: {args.out / 'bag'} already exists", file=sys.stderr)
        return 2
    motion = dataclasses.replace(MotionConfig(), profile=args.profile, speed=args.speed, jitter=args.jitter,
                                 seed=args.seed)
    spec = RasterSpec(surface=args.surface, corner=(x, y), length=length, width=width, passes=args.passes,
                      yaw_deg=args.yaw, latency=args.latency, tf_rate=args.tf_rate, motion=motion, seed=args.seed,
                      storage=args.storage)
    truth = generate(spec, args.out, camera=load_camera(args.params))
    print(f"{truth.frames} frames -> {args.out / 'bag'}; truth: {args.out / 'truth.json'} + surface.npy "
          f"(latency {spec.latency * 1e3:g} ms, {len(truth.passes)} passes, {args.profile}, yaw {args.yaw:g} deg)")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
