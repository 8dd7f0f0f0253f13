"""`touchroller map BAG --out map.png`: the tactile map of a recording (docs/design.md).

When the bag has /tf and /tf_static linking `--world-frame` to touchroller_cylinder, the map is one
mosaic in the world frame (`touchroller_perception.world_map`): `map.png` (grey plus alpha) and
`map.yaml` beside it (nav2 map_server format, `frame_id`); the camera's latency is estimated from the
data unless `--latency` says it, and the passes are registered against each other unless
`--no-register`. Without TF (or with `--strip`) it is the strip map: grey, at camera pixel scale
(rows along the roll), or resampled to millimetres with `--metric`; `--method paper` reproduces the
paper's integer MAE search for comparison. One pass over the bag either way; the flat field (what
does not move with the surface) is applied to the whole map at the end.
"""
from __future__ import annotations

import argparse
import contextlib
import csv
import gc
import math
import os
import queue
import sys
import threading
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any, TypeVar

import yaml

from touchroller_bringup.commands import read_calibration
from touchroller_bringup.errors import UserError
from touchroller_bringup.names import IMAGE_TOPIC
from touchroller_bringup.outputs import Output, check_outputs
from touchroller_perception.files import atomic_write

DEFAULT_MM_PER_PX = 0.1
METRIC_RANGE = (0.001, 10.0)   # mm per pixel: 1 um (a hundred times finer than the camera sees) to 1 cm
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
    parser.add_argument("--world-frame", default="base", help="world map: the frame it lies in (default: %(default)s)")
    parser.add_argument("--cylinder-frame", default="touchroller_cylinder",
                        help="world map: the roller's cylinder frame in the bag's TF (default: %(default)s)")
    parser.add_argument("--resolution", type=float, default=1e-4,
                        help="world map: metres per pixel (default: %(default)s)")
    parser.add_argument("--latency", default="auto", help="world map: the camera's latency in seconds (what the "
                                                          "stamps lag the exposure), or 'auto' to estimate it")
    parser.add_argument("--no-register", action="store_true", help="world map: place by TF only, do not register "
                                                                   "the passes against each other")
    parser.add_argument("--photometric", type=Path, help="world map: also the height map (height.tif beside the "
                        "map, docs/height.md) with this PHOTOMETRIC.npz of 'touchroller calibrate photometric'")
    parser.add_argument("--reference", type=Path, help="world map with --photometric: a no-contact image of the sensor")
    parser.add_argument("--strip", action="store_true", help="the strip map even when the bag has TF")
    parser.add_argument("--workers", type=int, default=None,
                        help="world map: processes decoding a compressed recording's frames (default: one per "
                             "processor; 1: decoded by the process reading the bag)")
    parser.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    # numpy's work here is on 4x4 matrices and short vectors: OpenBLAS's worker thread would only spin
    # on the second core (that the reader uses) after start-up. Read when numpy is first imported.
    os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
    import cv2

    out = Path(args.out)
    check_outputs([Output("--out", out)] + ([Output("--steps", args.steps)] if args.steps else []),
                  {"BAG": args.bag, "--params": args.params})
    if not out.suffix or not cv2.haveImageWriter(str(out)):
        raise UserError(f"--out {out}: unknown image format; use .png, .tif, .jpg or .bmp")
    if args.metric is not None and not (METRIC_RANGE[0] <= args.metric <= METRIC_RANGE[1]):
        raise UserError(f"--metric must be a positive number of millimetres per pixel in [{METRIC_RANGE[0]:g}, "
                        f"{METRIC_RANGE[1]:g}], got {args.metric}")
    if not 8 <= args.band_rows <= 4096:
        raise UserError(f"--band-rows must be in [8, 4096], got {args.band_rows}")
    if args.workers is not None and not 1 <= args.workers <= 64:
        raise UserError(f"--workers must be in [1, 64], got {args.workers}")
    if not 1 <= args.search <= 4096:
        raise UserError(f"--search must be in [1, 4096] pixels, got {args.search}")
    camera = _load_camera(args.params)
    world = not args.strip and _has_tf(args.bag, args.strip)
    if world:
        _check_world_arguments(args, out, camera)
        heights = [Output("the height map", out.parent / "height.tif")] if args.photometric else []
        check_outputs([Output("--out", out), Output("the map's YAML", out.with_suffix(".yaml")),
                       Output("the map's GeoTIFF", out.with_suffix(".tif"))] + heights,
                      {"BAG": args.bag, "--params": args.params})
    # OpenCV's own thread pool costs more than it saves on a 70-row band; the second core reads the bag.
    threads = cv2.getNumThreads()
    cv2.setNumThreads(1)
    try:
        return _world_map(args, out, camera) if world else _stitch_bag(args, out, camera)
    finally:
        cv2.setNumThreads(threads)


def _has_tf(bag: str, strip: bool = False) -> bool:
    """Whether the bag has both TF topics (a world map). One of them alone: a note on stderr saying which is
    missing and that the world map was skipped, not a strip map without a word."""
    import sys

    from touchroller_bringup.bags import tf_topics

    found = set(tf_topics(bag))
    if found == {"/tf", "/tf_static"}:
        return True
    if found and not strip:
        missing = ({"/tf", "/tf_static"} - found).pop()
        what = ("the fixed transforms (the roller's mount, tool0 -> touchroller_cylinder)" if missing == "/tf_static"
                else "the moving transforms (the arm's pose, base -> tool0)")
        print(f"touchroller map: note: {bag} has {found.pop()} but no {missing}, which holds {what}: the world map "
              "was skipped; this is the strip map (record both TF topics for a world map, or give --strip to "
              "ask for the strip map)", file=sys.stderr)
    return False


def _check_world_arguments(args: argparse.Namespace, out: Path, camera) -> None:
    if out.suffix.lower() != ".png":
        raise UserError(f"--out {out}: a world map is a PNG (grey and alpha) with map.yaml beside it")
    if camera is None:
        raise UserError("a world map needs a camera model for these images (--params CAL.yaml)")
    if args.method != "default" or args.metric is not None or args.steps:
        raise UserError("--method paper, --metric and --steps are for the strip map (add --strip)")
    from touchroller_bringup.names import InvalidName, check_frame_id

    for flag, value in (("--world-frame", args.world_frame), ("--cylinder-frame", args.cylinder_frame)):
        try:
            check_frame_id(value, flag)
        except InvalidName as exc:
            raise UserError(str(exc)) from None
    if not (math.isfinite(args.resolution) and 1e-6 <= args.resolution <= 0.01):
        raise UserError(f"--resolution must be in [1e-6, 0.01] m per pixel, got {args.resolution}")
    if (args.photometric is None) != (args.reference is None):
        raise UserError("--photometric and --reference go together (the height map needs both)")
    if args.latency != "auto":
        try:
            value = float(args.latency)
        except ValueError:
            value = math.nan
        if not (math.isfinite(value) and 0 <= value <= 1.0):
            raise UserError(f"--latency must be 'auto' or seconds in [0, 1], got {args.latency}")


def _world_map(args: argparse.Namespace, out: Path, camera) -> int:
    import numpy as np

    from touchroller_bringup.bags import (
        CompressedRecord,
        ImageRecord,
        TransformRecord,
        decode_compressed,
        read_images_and_tf,
    )
    from touchroller_bringup.map_files import write_height_tif, write_world_map
    from touchroller_perception.contact_timing import SUMMARY_SHAPE
    from touchroller_perception.stitching import StitcherConfig
    from touchroller_perception.tiles import TileConfig
    from touchroller_perception.transforms import Transform, TransformBuffer
    from touchroller_perception.world_map import WorldMapConfig, WorldMapper, buffer_lookup, latency_summary

    buffer = TransformBuffer(cache_ns=None)
    # the map's tiles beyond the memory cache are spilled beside the output (removed at the end)
    config = WorldMapConfig(resolution=args.resolution, latency=None if args.latency == "auto" else float(args.latency),
                            register=not args.no_register, tiles=TileConfig(folder=str(out.parent)))
    # the world mapper's strip stitcher only measures the roll (no lateral tracking, coarser columns)
    stitcher = StitcherConfig(band_rows=args.band_rows, search=args.search, lateral=False, column_bin=8)
    mapper = WorldMapper(camera, buffer_lookup(buffer, args.world_frame, args.cylinder_frame), config, stitcher,
                         height=_height_source(args))

    rows = mapper.source_rows((camera.height, camera.width))
    try:
        height_rows = mapper.height_rows((camera.height, camera.width))
    except ValueError as exc:   # the model, the reference and the camera disagree
        raise UserError(f"--photometric/--reference: {exc}") from None
    if height_rows is not None:
        rows = (min(rows[0], height_rows[0]), max(rows[1], height_rows[1]))

    def cut(record: ImageRecord | CompressedRecord) -> tuple[tuple[int, bytes | None], Any]:
        # ((stamp, the band's contact summary), band) of a frame (decoded first when compressed: only the
        # rows up to the band's end). The summary depends on the band alone: made here, by the reader (or
        # a decoding worker), not by the mapping process, as float32 bytes (a few hundred: cheap to pickle)
        if isinstance(record, CompressedRecord):
            try:
                record = decode_compressed(record, rows)
            except ValueError as exc:   # ImageFormatError too
                raise UserError(f"bag {args.bag}: malformed message: {exc}") from None
        height, width = record.frame_shape
        if (camera.width, camera.height) != (width, height):
            raise UserError(f"the camera model is for {camera.width}x{camera.height} images but the bag "
                            f"has {width}x{height}")
        band = mapper.band(record.image, record.row0, height)
        relief = mapper.height_band(record.image, record.row0, height)
        summary = mapper.contact_summary(band)
        return (record.stamp_ns, None if summary is None else summary.tobytes()), (
            band if relief is None else (band, relief))

    def records() -> Iterator[tuple[object, Any]]:
        # The reader reads the bag (only the band's rows where it can) and cuts the bands: ((stamp,
        # summary), band) for a frame, ((record, transform), None) for a transform. Compressed frames are
        # decoded and cut by a pool of processes (`decode_pool`), in order: one per processor (decoding is the
        # heaviest stage; the reader and the mapping between them take less than a processor).
        from touchroller_bringup.decode_pool import ordered, pool_workers

        stream = read_images_and_tf(args.bag, args.topic, rows=rows, decode=False)
        for record in ordered(stream, cut, _compressed, args.workers or pool_workers()):
            if isinstance(record, ImageRecord):
                yield cut(record)
            elif isinstance(record, TransformRecord):
                try:
                    transform = Transform(record.translation, record.rotation)
                except ValueError:   # a malformed transform: skipped, as a TF listener would
                    continue
                yield (record, transform), None
            else:   # a compressed frame, decoded and cut
                yield record

    frames = 0
    first_stamp: list = [None]
    with _set_up_objects_frozen():
        # bands with their relief go through a thread (the forked reader passes bands alone)
        read = _read_ahead(records(), batch=8) if mapper.height_source is not None else _reader(
            records, mapper.band_shape, meanwhile=_import_writers)
        for item, band in read:
            if band is None:
                record, transform = item
                try:
                    buffer.set_transform(record.parent, record.child, record.stamp_ns, transform,
                                         static=record.static)
                except ValueError:   # a malformed transform (a frame its own parent, an empty name): skipped
                    continue
            else:
                stamp, summary = item
                if first_stamp[0] is None:
                    first_stamp[0] = stamp
                contact = None if summary is None else np.frombuffer(summary, np.float32).reshape(SUMMARY_SHAPE)
                try:
                    if isinstance(band, tuple):
                        mapper.push_band(band[0], stamp, band[1], contact)
                    else:
                        mapper.push_band(band, stamp, summary=contact)
                except MemoryError as exc:   # one band would span too many cells at this resolution
                    raise _too_fine(args, exc) from None
                frames += 1
    if frames == 0:
        raise UserError(f"{args.bag} has no images on {args.topic}")
    if args.world_frame not in buffer.frames or args.cylinder_frame not in buffer.frames:
        raise UserError(f"the bag's TF has no {args.world_frame} -> {args.cylinder_frame} (frames: "
                        f"{', '.join(sorted(buffer.frames)) or 'none'}); give --world-frame/--cylinder-frame "
                        "or --strip")
    try:
        mapper.finalise()
    except MemoryError as exc:
        raise _too_fine(args, exc) from None
    if stats_warning := mapper.stats.storage_warning:
        print(f"WARN: the map's tiles: {stats_warning}", file=sys.stderr)
    view = mapper.view()
    if view.extent() is None:
        raise UserError(_nothing_placed(buffer, args, first_stamp[0]))
    stats = mapper.stats
    latency, latency_yaml = latency_summary(stats)
    height_note = ""
    try:
        png, yaml_path = write_world_map(out, view, args.world_frame, latency_yaml)
        if mapper.height_source is not None:
            height_view = mapper.height_view()
            if height_view is None or height_view.extent() is None:
                print("WARN: no pass was mapped with a height: height.tif not written", file=sys.stderr)
            else:
                tif_path = write_height_tif(out.parent / "height.tif", height_view, args.world_frame)
                height_note = f"height map -> {tif_path} (float32 metres, NaN where unmapped)"
    finally:
        mapper.close()   # the tiles spilled to disk
    meta = yaml.safe_load(yaml_path.read_text(encoding="utf-8"))
    tif = meta["geotiff"]
    print(f"{frames} frames -> {png} + {yaml_path.name} + {tif['image']} ({tif['size'][0]}x{tif['size'][1]} px at "
          f"{tif['resolution'] * 1e3:g} mm, origin ({tif['origin'][0]:.4f}, {tif['origin'][1]:.4f}) m in "
          f"{args.world_frame}; {png.name} 1/{meta['view']['downscale']}, grey {meta['view']['stretch'][0]:g}.."
          f"{meta['view']['stretch'][1]:g} stretched); {stats.mapped} frames mapped in {stats.passes} pass(es), "
          f"camera latency {latency}")
    if height_note:
        print(height_note)
    if stats.left_out_storage_full:
        print(f"WARN: {stats.left_out_storage_full} frames not mapped (the disk is full)", file=sys.stderr)
    if stats.latency_warning:
        print(f"WARN: {stats.latency_warning}; give --latency SECONDS if it is known", file=sys.stderr)
    return 0


def _compressed(record: object) -> bool:
    from touchroller_bringup.bags import CompressedRecord

    return isinstance(record, CompressedRecord)


def _height_source(args: argparse.Namespace) -> Any:
    """The world mapper's HeightSource from --photometric and --reference; None without them."""
    if args.photometric is None:
        return None
    from touchroller_bringup.commands.height import _reference
    from touchroller_perception.height import PhotometricModel
    from touchroller_perception.world_height import HeightSource

    if not args.photometric.is_file():
        raise UserError(f"no such photometric model: {args.photometric}")
    try:
        model = PhotometricModel.load(args.photometric)
    except (OSError, ValueError, KeyError) as exc:
        raise UserError(f"--photometric {args.photometric}: not a photometric model ({exc})") from None
    return HeightSource(model, _reference(args.reference))


def _too_fine(args: argparse.Namespace, exc: MemoryError) -> UserError:
    return UserError(f"--resolution {args.resolution:g} m per pixel: {exc}; give a coarser --resolution (the "
                     "default is 1e-4)")


def _nothing_placed(buffer, args: argparse.Namespace, first_stamp: int | None) -> str:
    """Why no frame could be placed in the world frame, in one sentence (TF at other times, a loop, ...)."""
    from touchroller_perception.transforms import TransformError

    reason = "TF never placed the roller while it rolled"
    if first_stamp is not None:
        try:
            buffer.lookup(args.world_frame, args.cylinder_frame, first_stamp)
        except TransformError as exc:
            reason = f"at the first image ({first_stamp / 1e9:.3f} s) {' '.join(str(exc).split())}"
        span = buffer.time_range(args.cylinder_frame) or buffer.time_range(args.world_frame)
        if span is not None and span[0] != span[1]:
            reason += f"; the bag's TF runs from {span[0] / 1e9:.3f} to {span[1] / 1e9:.3f} s"
    return (f"no frame of {args.bag} could be placed in {args.world_frame}: {reason}. Check the recording's TF "
            "(frames, clock) or give --strip for the strip map")


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
    try:
        image = stitcher.map_image(args.metric)
    except ValueError as exc:   # e.g. a metric map too large to allocate
        raise UserError(f"--metric {args.metric}: {exc}") from None
    out.parent.mkdir(parents=True, exist_ok=True)
    # encoded in memory, then written: a full disk is then an OSError of ours, not libpng's own stderr line
    encoded, data = cv2.imencode(out.suffix, image)
    if not encoded:
        raise UserError(f"--out {out}: OpenCV cannot encode the map as {out.suffix}")
    try:
        with atomic_write(out, "wb") as stream:
            stream.write(data.tobytes())
    except OSError as exc:
        raise UserError(f"cannot write --out {out}: {exc.strerror or exc}; nothing was written "
                        "(free some space or choose another path)") from None
    if args.steps:
        _write_steps(Path(args.steps), stitcher)
    flagged = stitcher.prior_frames
    travel = abs(stitcher.position_px)
    scale = f", {travel * stitcher.mm_per_px:.1f} mm" if stitcher.mm_per_px else ""
    note = f"; {flagged} frame(s) without texture took the motion prior" if flagged else ""
    print(f"{frames} frames -> {out} ({image.shape[1]}x{image.shape[0]} px, travel {travel:.1f} px{scale}, "
          f"method {args.method}{note})")
    return 0


@contextlib.contextmanager
def _set_up_objects_frozen() -> Iterator[None]:
    """The objects made so far (the imports' modules, the mapper) live as long as the command: the garbage
    collector leaves them alone while the mapping makes and drops its small per-frame objects (and does not
    write to their pages, which a forked reader shares)."""
    gc.freeze()
    try:
        yield
    finally:
        gc.unfreeze()


def _reader(records: Callable[[], Iterator[T]], band_shape: tuple[int, int],
            meanwhile: Callable[[], None] | None = None) -> Iterator[T]:
    """`records()` run by a second process where the system can fork (its own GIL: reading and mapping
    really overlap, see `touchroller_bringup.forked_reader`), else by a second thread. `meanwhile()`: run
    once the reader has started, while it opens the bag (by the forked reader's parent; before the thread)."""
    from touchroller_bringup.forked_reader import fork_available, read_forked

    if fork_available():
        return read_forked(records, band_shape, meanwhile=meanwhile)  # type: ignore[arg-type]
    if meanwhile is not None:
        meanwhile()
    return _read_ahead(records(), batch=8)


def _import_writers() -> None:
    """Import what writing the map's files needs (tifffile: tens of milliseconds, numpy.ma with it): done
    while the reader opens the bag, when the command would otherwise wait for its first frames."""
    import tifffile  # noqa: F401

    import touchroller_bringup.geotiff  # noqa: F401


def _read_ahead(records: Iterator[T], depth: int = 8, batch: int = 1) -> Iterator[T]:
    """`records`, produced by a second thread a few items ahead: SQLite reads and OpenCV both release
    the GIL, so reading the bag overlaps with stitching instead of adding to it. Errors surface in order.
    `batch` items go through the queue together (fewer hand-overs between the threads)."""
    items: queue.Queue = queue.Queue(maxsize=depth)
    stop = threading.Event()
    done = object()

    def put(chunk: list) -> bool:
        while not stop.is_set():
            try:
                items.put((chunk, None), timeout=0.1)
                return True
            except queue.Full:
                continue
        return False

    def produce() -> None:
        chunk: list = []
        try:
            for item in records:
                chunk.append(item)
                if len(chunk) >= batch:
                    if not put(chunk):
                        return
                    chunk = []
            if chunk and not put(chunk):
                return
            items.put((done, None))
        except BaseException as exc:  # noqa: BLE001 - re-raised in the consumer's thread
            if chunk:
                put(chunk)
            items.put((done, exc))

    reader = threading.Thread(target=produce, name="bag-reader", daemon=True)
    reader.start()
    try:
        while True:
            chunk, error = items.get()
            if chunk is done:
                if error is not None:
                    raise error
                return
            yield from chunk
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
        # Per-frame records only when --steps wants them: memory then does not grow with the bag. The
        # recording is mapped whole (no rolling window: that bounds a live node fed frames for hours).
        config = StitcherConfig(method=args.method, band_rows=args.band_rows, search=args.search, live_map=False,
                                history=None if args.steps else 1, max_rows=None)
        return Stitcher(config, camera=camera)
    except ValueError as exc:
        raise UserError(str(exc)) from None


def _load_camera(path: str | None):
    """The `--params` calibration, else the default config's camera if there is one."""
    from touchroller_driver.paths import config_path

    if path is not None:
        return read_calibration(path)
    default = config_path("touchroller.yaml")
    return read_calibration(default) if default.is_file() else None


def _write_steps(path: Path, stitcher) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    stamps = stitcher.stamps
    with atomic_write(path, newline="") as stream:
        writer = csv.writer(stream)
        writer.writerow(("stamp_ns", "shift_px", "lateral_px", "position_px", "confidence", "used_prior"))
        for stamp, s in zip(stamps, stitcher.steps, strict=True):
            writer.writerow((stamp, f"{s.shift_px:.4f}", f"{s.lateral_px:.4f}", f"{s.position_px:.4f}",
                             f"{s.confidence:.3f}", int(s.used_prior)))
