"""`touchroller map BAG --out map.png`: the stitched tactile map of a recording (docs/design.md).

The map is grey, at camera pixel scale (rows along the roll), or resampled to millimetres with
`--metric`. `--method paper` reproduces the paper's integer MAE search for comparison. One pass over
the bag; the flat field (what does not move with the surface) is applied to the whole map at the end.
"""
from __future__ import annotations

import argparse
import csv
import math
import queue
import threading
from collections.abc import Iterator
from pathlib import Path
from typing import TypeVar

from touchroller_bringup.errors import UserError
from touchroller_bringup.names import IMAGE_TOPIC

DEFAULT_MM_PER_PX = 0.1
T = TypeVar("T")


def register(subparsers: argparse._SubParsersAction) -> None:
    parser = subparsers.add_parser(
        "map", help="stitch the tactile map of a recording into a PNG",
        description="Stitch the images of a rosbag2 recording (sqlite3 or MCAP) into one tactile map: "
                    "grey, rows along the rolling direction, at camera pixel scale unless --metric.")
    parser.add_argument("bag", help="rosbag2 folder")
    parser.add_argument("--out", required=True, help="image file to write (.png, .tif, ...)")
    parser.add_argument("--method", choices=("default", "paper"), default="default",
                        help="subpixel keyframe registration (default) or the paper's integer MAE search")
    parser.add_argument("--topic", default=IMAGE_TOPIC, help="image topic (default: %(default)s)")
    parser.add_argument("--params", help="calibration YAML (ROS 2 params file): rectifies the band through the "
                                         "camera model and gives the metric scale (default: config/touchroller.yaml)")
    parser.add_argument("--metric", nargs="?", type=float, const=DEFAULT_MM_PER_PX, default=None,
                        metavar="MM_PER_PX",
                        help="resample the map to square pixels of MM_PER_PX millimetres "
                             f"(default {DEFAULT_MM_PER_PX})")
    parser.add_argument("--band-rows", type=int, default=70,
                        help="rows of the contact band used per frame (default: %(default)s, as the paper)")
    parser.add_argument("--search", type=int, default=25,
                        help="largest shift per frame searched, pixels (default: %(default)s, as the paper)")
    parser.add_argument("--steps", help="also write the per-frame registration as CSV "
                                        "(stamp_ns,shift_px,lateral_px,position_px,confidence,used_prior)")
    parser.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    import cv2

    out = Path(args.out)
    if out.is_dir():
        raise UserError(f"--out {out} is a directory; give an image file name such as map.png")
    if not out.suffix or not cv2.haveImageWriter(str(out)):
        raise UserError(f"--out {out}: unknown image format; use .png, .tif, .jpg or .bmp")
    if args.metric is not None and not (args.metric > 0 and math.isfinite(args.metric)):
        raise UserError(f"--metric must be a positive number of millimetres per pixel, got {args.metric}")
    if args.band_rows < 8:
        raise UserError(f"--band-rows must be at least 8, got {args.band_rows}")
    if args.search < 1:
        raise UserError(f"--search must be at least 1 pixel, got {args.search}")
    camera = _load_camera(args.params)
    # OpenCV's own thread pool costs more than it saves on a 70-row band; the second core reads the bag.
    threads = cv2.getNumThreads()
    cv2.setNumThreads(1)
    try:
        return _stitch_bag(args, out, camera)
    finally:
        cv2.setNumThreads(threads)


def _stitch_bag(args: argparse.Namespace, out: Path, camera) -> int:
    import cv2

    from touchroller_bringup.bags import read_images

    made: list = []  # the stitcher, made by the reader thread from the first frame's size

    def bands() -> Iterator[tuple[int, object]]:
        # Runs in the reader thread: reading, grey conversion and the rectifying remap release the GIL,
        # so they overlap with registration in the main thread. Band cutting is stateless.
        for record in read_images(args.bag, args.topic):
            if not made:
                made.append(_make_stitcher(args, camera, record.image.shape))
            try:
                band = made[0].band(record.image)
            except ValueError as exc:
                raise UserError(f"frame at stamp {record.stamp_ns}: {exc}") from None
            yield record.stamp_ns, band

    frames = 0
    for stamp_ns, band in _read_ahead(bands()):
        try:
            made[0].push_band(band, stamp_ns)
        except ValueError as exc:
            raise UserError(f"frame at stamp {stamp_ns}: {exc}") from None
        frames += 1
    stitcher = made[0] if made else None
    if stitcher is None:
        raise UserError(f"{args.bag} has no images on {args.topic}")
    stitcher.finalise()
    image = stitcher.map_image(args.metric)
    out.parent.mkdir(parents=True, exist_ok=True)
    if not cv2.imwrite(str(out), image):
        raise UserError(f"cannot write {out}")
    if args.steps:
        _write_steps(Path(args.steps), stitcher)
    flagged = stitcher.prior_frames
    travel = abs(stitcher.position_px)
    scale = f", {travel * stitcher.mm_per_px:.1f} mm" if stitcher.mm_per_px else ""
    note = f"; {flagged} frame(s) without texture took the motion prior" if flagged else ""
    print(f"{frames} frames -> {out} ({image.shape[1]}x{image.shape[0]} px, travel {travel:.1f} px{scale}, "
          f"method {args.method}{note})")
    return 0


def _read_ahead(records: Iterator[T], depth: int = 8) -> Iterator[T]:
    """`records`, produced by a second thread a few items ahead: SQLite reads and OpenCV both release
    the GIL, so reading the bag overlaps with stitching instead of adding to it. Errors surface in order."""
    items: queue.Queue = queue.Queue(maxsize=depth)
    stop = threading.Event()
    done = object()

    def produce() -> None:
        try:
            for item in records:
                while not stop.is_set():
                    try:
                        items.put((item, None), timeout=0.1)
                        break
                    except queue.Full:
                        continue
                if stop.is_set():
                    return
            items.put((done, None))
        except BaseException as exc:  # noqa: BLE001 - re-raised in the consumer's thread
            items.put((done, exc))

    reader = threading.Thread(target=produce, name="bag-reader", daemon=True)
    reader.start()
    try:
        while True:
            item, error = items.get()
            if item is done:
                if error is not None:
                    raise error
                return
            yield item
    finally:
        stop.set()
        reader.join(timeout=5.0)


def _make_stitcher(args: argparse.Namespace, camera, shape):
    from touchroller_perception.stitching import Stitcher, StitcherConfig

    height, width = shape[:2]
    if camera is not None and (camera.width, camera.height) != (width, height):
        if args.params:
            raise UserError(f"calibration {args.params} is for {camera.width}x{camera.height} images but the "
                            f"bag has {width}x{height}")
        camera = None  # the default geometry does not fit this camera: plain crop, no metric scale
    if args.metric is not None and camera is None:
        raise UserError("--metric needs a camera model for these images (--params CAL.yaml)")
    try:
        # Per-frame records only when --steps wants them: memory then does not grow with the bag.
        config = StitcherConfig(method=args.method, band_rows=args.band_rows, search=args.search, live_map=False,
                                history=None if args.steps else 1)
        return Stitcher(config, camera=camera)
    except ValueError as exc:
        raise UserError(str(exc)) from None


def _load_camera(path: str | None):
    from touchroller_driver.paths import config_path
    from touchroller_perception.geometry import CameraModel

    explicit = path is not None
    path = Path(path) if explicit else config_path("touchroller.yaml")
    if not path.is_file():
        if explicit:
            raise UserError(f"no such calibration file: {path}")
        return None
    try:
        return CameraModel.from_yaml(path)
    except Exception as exc:  # noqa: BLE001 - YAML, type and range errors all mean a bad file
        raise UserError(f"cannot read calibration {path}: {type(exc).__name__}: {exc}") from None


def _write_steps(path: Path, stitcher) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    stamps = stitcher.stamps
    with open(path, "w", newline="", encoding="utf-8") as stream:
        writer = csv.writer(stream)
        writer.writerow(("stamp_ns", "shift_px", "lateral_px", "position_px", "confidence", "used_prior"))
        for stamp, s in zip(stamps, stitcher.steps, strict=True):
            writer.writerow((stamp, f"{s.shift_px:.4f}", f"{s.lateral_px:.4f}", f"{s.position_px:.4f}",
                             f"{s.confidence:.3f}", int(s.used_prior)))
