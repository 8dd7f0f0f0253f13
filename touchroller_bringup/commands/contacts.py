"""`touchroller contacts BAG --out contacts.csv`: the contacts in a recording, one CSV row per contact.

Columns: stamp_ns,u,v,x,y,z (docs/design.md; x y z in metres in touchroller_cylinder, `nan` without
`--params`), then the contact's score (peak change in noise std), area (px^2), ellipse (major_axis,
minor_axis in px, angle in rad from +u towards +v), confidence (0..1), and the covariance diagonal
var_x, var_y, var_z (m^2, from `--pixel-sigma` through the camera model). The no-contact reference
is the mean of the first `--reference-frames` frames (or `--reference-bag`); they produce no rows.
"""
from __future__ import annotations

import argparse
import csv
import math
from pathlib import Path

from touchroller_bringup.commands import read_calibration
from touchroller_bringup.errors import UserError
from touchroller_bringup.names import IMAGE_TOPIC
from touchroller_bringup.outputs import Output, check_outputs
from touchroller_perception.files import atomic_write

POINT_COLUMNS = ("stamp_ns", "u", "v", "x", "y", "z")          # docs/design.md, first
CONTACT_COLUMNS = ("score", "area", "major_axis", "minor_axis", "angle", "confidence")
COLUMNS = POINT_COLUMNS + CONTACT_COLUMNS + ("var_x", "var_y", "var_z")
MAX_REFERENCE_FRAMES = 1000   # as the perception node's reference.frames
MAX_PIXEL_SIGMA = 1e3         # a centre's std beyond the image itself means nothing (and 1e300 overflows)


def register(subparsers: argparse._SubParsersAction) -> None:
    parser = subparsers.add_parser(
        "contacts", help="detect contacts in a recording and write them as CSV",
        description="Detect contacts in the images of a rosbag2 recording (sqlite3 or MCAP) and write "
                    "one CSV row per contact: " + ",".join(COLUMNS) + ".")
    parser.add_argument("bag", help="rosbag2 folder")
    parser.add_argument("--out", required=True, help="CSV file to write")
    parser.add_argument("--params", help="calibration YAML (ROS 2 params file); without it x, y, z are nan")
    parser.add_argument("--topic", default=IMAGE_TOPIC, help="image topic (default: %(default)s)")
    parser.add_argument("--reference-frames", type=int, default=5,
                        help="no-contact frames at the start that form the reference (default: %(default)s)")
    parser.add_argument("--reference-bag", metavar="BAG",
                        help="take the reference from the first --reference-frames frames of this recording "
                             "(made without contact, e.g. just before the run) instead of from BAG's start")
    parser.add_argument("--method", choices=("colour", "paper"), default="colour",
                        help="colour-aware detector, or the paper's grey/threshold/moments pipeline")
    parser.add_argument("--threshold-sigma", type=float, default=None,
                        help="threshold in multiples of the reference noise (default: the detector's)")
    parser.add_argument("--pixel-sigma", type=float, default=0.3,
                        help="std of a detected centre in pixels, for the covariance (default: %(default)s)")
    parser.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from touchroller_bringup.bags import read_images
    from touchroller_perception.contacts import ContactDetector, DetectorConfig
    from touchroller_perception.localisation import localise

    if not 1 <= args.reference_frames <= MAX_REFERENCE_FRAMES:   # the frames are held in memory
        raise UserError(f"--reference-frames must be in [1, {MAX_REFERENCE_FRAMES}], got {args.reference_frames}")
    if not (args.pixel_sigma >= 0 and math.isfinite(args.pixel_sigma) and args.pixel_sigma <= MAX_PIXEL_SIGMA):
        raise UserError(f"--pixel-sigma must be a number of pixels in [0, {MAX_PIXEL_SIGMA:g}], got {args.pixel_sigma}")
    check_outputs([Output("--out", args.out)],
                  {"BAG": args.bag, "--params": args.params, "--reference-bag": args.reference_bag})
    camera = read_calibration(args.params) if args.params else None
    changes = {"method": args.method}
    if args.threshold_sigma is not None:
        changes["threshold_sigma"] = args.threshold_sigma
    try:
        config = DetectorConfig(**changes)
    except ValueError as exc:
        raise UserError(str(exc)) from None
    detector = ContactDetector(config, reference_frames=args.reference_frames)
    skipped = args.reference_frames
    if args.reference_bag:
        detector.set_reference(_reference_frames(args.reference_bag, args.topic, args.reference_frames, read_images))
        skipped = 0
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    frames = rows = 0
    # written whole or not at all: a run that fails part-way leaves an existing CSV as it was
    with atomic_write(out, newline="") as stream:
        writer = csv.writer(stream)
        writer.writerow(COLUMNS)
        for record in read_images(args.bag, args.topic):
            frames += 1
            if camera is not None and frames == 1:
                _check_size(camera, record.image, args.params, args.bag)
            try:
                contacts = detector.process(record.image)
            except ValueError as exc:
                raise UserError(f"frame at stamp {record.stamp_ns}: {exc}") from None
            for row in _rows(record.stamp_ns, contacts or [], camera, args.pixel_sigma, localise):
                writer.writerow(row)
                rows += 1
        if frames < skipped:
            raise UserError(f"{args.bag} has {frames} image(s) on {args.topic}; the reference needs "
                            f"{args.reference_frames} (--reference-frames)")
    where = "pixels and cylinder points" if camera else "pixels only (no --params: x y z are nan)"
    source = f"{args.reference_bag}" if args.reference_bag else "the recording's start"
    print(f"{rows} contacts in {frames - skipped} frames, reference of {args.reference_frames} frame(s) from "
          f"{source} -> {out} ({where})")
    return 0


def _check_size(camera, image, params: str, bag: str) -> None:
    """A calibration is for one image size: pixels of another size back-project to wrong points."""
    height, width = image.shape[:2]
    if (camera.width, camera.height) != (width, height):
        raise UserError(f"calibration {params} is for {camera.width}x{camera.height} images but {bag} has "
                        f"{width}x{height}; give the calibration of this camera (or no --params for pixels only)")


def _reference_frames(bag: str, topic: str, count: int, read_images) -> list:
    """The first `count` images of `bag` on `topic`, all of one format."""
    from touchroller_perception.contacts import NoContactReference

    frames = []
    for record in read_images(bag, topic):
        frames.append(record.image)
        if len(frames) == count:
            break
    if len(frames) < count:
        raise UserError(f"--reference-bag {bag} has {len(frames)} image(s) on {topic}; the reference needs {count}")
    try:
        NoContactReference(frames)
    except ValueError as exc:
        raise UserError(f"--reference-bag {bag}: {exc}") from None
    return frames


def _rows(stamp_ns: int, contacts, camera, pixel_sigma: float, localise):
    if camera is None:
        for c in contacts:
            yield (stamp_ns, _f(c.u), _f(c.v), "nan", "nan", "nan", *_details(c), "nan", "nan", "nan")
        return
    for loc in localise(camera, contacts, pixel_sigma=pixel_sigma):
        c = loc.contact
        var = [loc.covariance[i, i] for i in range(3)]
        yield (stamp_ns, _f(c.u), _f(c.v), *(_f(p, "%.9g") for p in loc.point), *_details(c),
               *(_f(v, "%.6g") for v in var))


def _details(c) -> tuple[str, ...]:
    """The CONTACT_COLUMNS of one contact."""
    return (_f(c.score, "%.2f"), _f(c.area, "%.1f"), _f(c.major_axis, "%.2f"), _f(c.minor_axis, "%.2f"),
            _f(c.angle), _f(c.confidence))


def _f(value: float, fmt: str = "%.4f") -> str:
    value = float(value)
    return fmt % value if math.isfinite(value) else "nan"
