"""`touchroller height` and `touchroller calibrate photometric`: the membrane's relief in metres.

    touchroller calibrate photometric PRESSES --labels labels.csv --reference ref.png --ball-radius 0.002 \\
        --pixel-size 2.95e-5 --out photometric.npz
    touchroller height FRAMES --photometric photometric.npz --reference ref.png --pixel-size 2.95e-5 --out heights/

INPUT is an image folder (png/jpg/bmp/tif, sorted by name), one image file or a rosbag2 recording
(topic `/touchroller/image_raw` unless `--topic`). LABELS.csv has the header `image,u,v,radius_px`:
an image's file name (in a recording: its index on the topic, from 0), the contact circle's centre and
radius in pixels. `--pixel-size` (m per pixel) serves a flat sensor; `--params CAL.yaml` the roller:
the pixel size comes from the camera model (at each press for the calibration, at the contact line
for the height), and `touchroller height` estimates only the contact band (`--band-depth`), NaN
elsewhere. Each output is `DIR/<image stem>.tiff` (a recording: `<stamp_ns>.tiff`): float32 metres of
indentation, positive into the gel, the image's size.
"""
from __future__ import annotations

import argparse
import csv
import math
from pathlib import Path
from typing import Any

import numpy as np

from touchroller_bringup.commands.calibrate import _load_camera
from touchroller_bringup.commands.inputs import read_image, read_input_images
from touchroller_bringup.errors import UserError
from touchroller_bringup.names import IMAGE_TOPIC

LABEL_COLUMNS = ("image", "u", "v", "radius_px")


def register(subparsers: argparse._SubParsersAction) -> None:
    parser = subparsers.add_parser(
        "height", help="the membrane's indentation in metres, per image (photometric stereo)",
        description="Slopes from each image's colour change against the no-contact reference (the model of "
                    "'touchroller calibrate photometric'), integrated exactly to metres of indentation; one "
                    "float32 TIFF per image, NaN where nothing is estimated.")
    parser.add_argument("input", type=Path, help="image folder, image file or rosbag2 recording")
    parser.add_argument("--photometric", type=Path, required=True, help="PHOTOMETRIC.npz from calibrate photometric")
    parser.add_argument("--reference", type=Path, required=True, help="a no-contact image of the same sensor")
    _pixel_arguments(parser)
    parser.add_argument("--band-depth", type=float, default=1.0e-3,
                        help="with --params: the band is the rows a press this deep reaches, m (default 0.001)")
    parser.add_argument("--still-slope", type=float, default=None,
                        help="the zero-slope prior's threshold: slopes shorter than it (in the model's ellipse) read "
                             "0, longer than twice it as they are "
                             "(default: the model's own, what its calibration presses' undeformed gel read; 0: off)")
    parser.add_argument("--out", type=Path, required=True, help="folder for the <image stem>.tiff files")
    parser.add_argument("--topic", default=IMAGE_TOPIC, help="image topic in a recording (default: %(default)s)")
    parser.set_defaults(func=run_height)


def register_calibration(steps: argparse._SubParsersAction) -> None:
    """`touchroller calibrate photometric` (added to calibrate's steps)."""
    parser = steps.add_parser(
        "photometric", help="colour -> membrane slope, from presses of a ball of known radius",
        description="Learns the map from colour change (and image position) to the membrane's slope from "
                    "presses of a ball of known radius: the labelled circles are refined from the images, the "
                    "ball's slopes inside them are the targets. Writes one .npz.")
    parser.add_argument("input", type=Path, help="image folder, image file or rosbag2 recording of the presses")
    parser.add_argument("--labels", type=Path, required=True, help="CSV with the header image,u,v,radius_px")
    parser.add_argument("--reference", type=Path, required=True, help="a no-contact image of the same sensor")
    parser.add_argument("--ball-radius", type=float, required=True, help="the ball's radius, m")
    _pixel_arguments(parser)
    parser.add_argument("--no-refine", action="store_true", help="use the labelled circles as they are")
    parser.add_argument("--reference-from", choices=("given", "presses", "auto"), default="given",
                        help="the reference the model reads colour changes against: the given no-contact image, one "
                             "built from the presses' far fields (per pixel the median of the presses beyond 3 label "
                             "radii), or the one of the two the presses' far fields match better (default: "
                             "%(default)s); give the one used (--reference-out) to `touchroller height`")
    parser.add_argument("--reference-out", type=Path,
                        help="PNG to write the reference the model was calibrated against (needed with "
                             "--reference-from presses or auto)")
    parser.add_argument("--position-colour-degrees", default="",
                        help="comma-separated candidate degrees (0..3) of the colour terms that get image-position "
                             "factors; the one whose held-out presses read their normals best is used (e.g. 1,2,3; "
                             "default: none, the model's own 2)")
    parser.add_argument("--still-quantile", type=float, default=None,
                        help="the zero-slope prior's threshold stored in the model: this quantile of the slope the "
                             "model reads on the presses beyond 3 label radii (default: "
                             "PressCalibrationConfig's; 0: none)")
    parser.add_argument("--out", type=Path, required=True, help="PHOTOMETRIC.npz to write")
    parser.add_argument("--topic", default=IMAGE_TOPIC, help="image topic in a recording (default: %(default)s)")
    parser.set_defaults(func=run_calibrate)


def _pixel_arguments(parser: argparse.ArgumentParser) -> None:
    group = parser.add_mutually_exclusive_group(required=True)
    group.add_argument("--pixel-size", type=float, help="metres per pixel (a flat sensor)")
    group.add_argument("--params", type=Path, help="calibration YAML of the roller (pixel size from its camera model)")


def named_images(path: Path, topic: str) -> list[tuple[str, str, np.ndarray]]:
    """(label key, output stem, image) of an image folder, image file or recording."""
    found = read_input_images(path, topic)
    return [(item.key, item.stem, _colour(np.asarray(item.image),
                                          path if found.from_recording or path.is_file() else path / item.key))
            for item in found.images]


def _colour(image: np.ndarray, where: Path) -> np.ndarray:
    if image.ndim != 3 or image.shape[2] != 3 or image.dtype != np.uint8:
        raise UserError(f"{where}: needs 8-bit colour images (three lights, three channels); one channel "
                        "cannot give slopes")
    return image


def _reference(path: Path) -> np.ndarray:
    import cv2

    if not path.is_file():
        raise UserError(f"no such reference image: {path}")
    return _colour(read_image(path, cv2), path)


def read_labels(path: Path) -> list[tuple[str, float, float, float]]:
    if not path.is_file():
        raise UserError(f"no such labels file: {path}")
    try:
        with path.open(newline="") as stream:
            reader = csv.DictReader(stream)
            if tuple(name.strip() for name in (reader.fieldnames or ())) != LABEL_COLUMNS:
                raise UserError(f"{path}: the header must be {','.join(LABEL_COLUMNS)}, got "
                                f"{','.join(reader.fieldnames or [])}")
            rows = []
            for line, row in enumerate(reader, start=2):
                try:
                    u, v, r = float(row["u"]), float(row["v"]), float(row["radius_px"])
                except (TypeError, ValueError):
                    raise UserError(f"{path}:{line}: u, v and radius_px must be numbers") from None
                if not (math.isfinite(u) and math.isfinite(v) and math.isfinite(r) and r > 0):
                    raise UserError(f"{path}:{line}: u, v must be finite and radius_px positive")
                rows.append((str(row["image"]).strip(), u, v, r))
    except (OSError, UnicodeDecodeError, csv.Error) as exc:
        raise UserError(f"cannot read {path}: {exc}") from None
    if not rows:
        raise UserError(f"{path}: no labelled presses")
    return rows


def _degrees(text: str) -> tuple[int, ...]:
    """--position-colour-degrees: comma-separated degrees 0..3 (the model's colour degree), or none."""
    try:
        degrees = tuple(int(part) for part in text.split(",") if part.strip())
    except ValueError:
        raise UserError(f"--position-colour-degrees must be comma-separated integers, got {text!r}") from None
    if not all(0 <= d <= 3 for d in degrees):
        raise UserError(f"--position-colour-degrees must each be 0..3, got {text!r}")
    return degrees


def _positive(value: float | None, what: str) -> None:
    if value is not None and not (math.isfinite(value) and value > 0):
        raise UserError(f"{what} must be a positive number of metres, got {value}")


def run_calibrate(args: argparse.Namespace) -> int:
    from touchroller_perception import height as ht
    from touchroller_perception.calibration import CalibrationError
    from touchroller_perception.files import atomic_write

    _positive(args.ball_radius, "--ball-radius")
    _positive(args.pixel_size, "--pixel-size")
    if args.reference_from != "given" and args.reference_out is None:
        raise UserError(f"--reference-from {args.reference_from} needs --reference-out (the reference to give "
                        "`touchroller height`)")
    camera = _load_camera(args.params) if args.params is not None else None
    labels = read_labels(args.labels)
    reference = _reference(args.reference)
    images = {key: image for key, _stem, image in named_images(args.input, args.topic)}
    presses = []
    for name, u, v, r in labels:
        if name not in images:
            raise UserError(f"{args.labels}: image {name!r} is not in {args.input}")
        try:
            size = (args.pixel_size, args.pixel_size) if camera is None else ht.pixel_size_at(camera, u, v)
        except ValueError as exc:
            raise UserError(f"{args.labels}: {name}: {exc}") from None
        presses.append(ht.BallPress(images[name], u, v, r, size, name,
                                    math.inf if camera is None else float(camera.radius)))
    quantile = ht.PressCalibrationConfig().still_quantile if args.still_quantile is None else args.still_quantile
    if not (math.isfinite(quantile) and 0.0 <= quantile < 1.0):
        raise UserError(f"--still-quantile must be in [0, 1) (0: none), got {quantile}")
    config = ht.PressCalibrationConfig(refine=not args.no_refine, reference=args.reference_from,
                                       position_colour_degrees=_degrees(args.position_colour_degrees),
                                       still_quantile=quantile)
    try:
        result = ht.calibrate_photometric(presses, reference, args.ball_radius, config)
    except CalibrationError as exc:
        raise UserError(f"calibrate photometric: {exc}") from None
    try:
        args.out.parent.mkdir(parents=True, exist_ok=True)
        with atomic_write(args.out, "wb") as stream:
            result.model.save_to(stream)
        if args.reference_out is not None:
            _write_reference(args.reference_out, reference if result.reference is None else result.reference)
    except OSError as exc:
        raise UserError(f"cannot write {exc.filename or args.out}: {exc.strerror}") from None
    print(result.summary())
    for fit in result.presses:
        c = fit.circle
        print(f"  {fit.name}: normal residual median {fit.normal_error_deg:.2f} deg "
              f"(p90 {fit.normal_error_p90_deg:.2f}); circle ({c.u:.1f}, {c.v:.1f}) r {c.radius_px:.1f} px"
              + ("" if c.refined else " (label kept)"))
    print(f"wrote {args.out}" + (f" and {args.reference_out}" if args.reference_out is not None else ""))
    return 0


def _write_reference(path: Path, reference: np.ndarray) -> None:
    """The reference as an 8-bit PNG (the channel order the images were read in), written whole or not at all."""
    import cv2

    from touchroller_perception.files import atomic_write

    ok, data = cv2.imencode(".png", np.clip(np.rint(reference), 0, 255).astype(np.uint8))
    if not ok:
        raise OSError(0, "PNG encoding failed", str(path))
    path.parent.mkdir(parents=True, exist_ok=True)
    with atomic_write(path, "wb") as stream:
        stream.write(data.tobytes())


def run_height(args: argparse.Namespace) -> int:
    from touchroller_perception import height as ht
    from touchroller_perception.files import atomic_write

    _positive(args.pixel_size, "--pixel-size")
    try:
        model = ht.PhotometricModel.load(args.photometric)
    except ValueError as exc:
        raise UserError(str(exc)) from None
    reference = _reference(args.reference)
    rows = None
    size: Any = args.pixel_size
    if args.params is not None:
        camera = _load_camera(args.params)
        try:
            band = ht.contact_band(camera, args.band_depth)
        except ValueError as exc:
            raise UserError(f"--band-depth / {args.params}: {exc}") from None
        rows, size = band.rows, band.pixel_size
    if args.still_slope is not None and not (math.isfinite(args.still_slope) and 0.0 <= args.still_slope <= 1.0):
        raise UserError(f"--still-slope must be a slope in [0, 1] (0: off), got {args.still_slope}")
    try:
        estimator = ht.HeightEstimator(model, reference, size, rows=rows,
                                       config=ht.HeightConfig(still_slope=args.still_slope))
    except ValueError as exc:
        raise UserError(f"{args.reference}: {exc}") from None
    images = named_images(args.input, args.topic)
    import tifffile

    try:
        args.out.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise UserError(f"cannot create {args.out}: {exc.strerror}") from None
    for _key, stem, image in images:
        if image.shape != reference.shape:
            raise UserError(f"{stem}: image {image.shape[1]}x{image.shape[0]} does not match the reference "
                            f"{reference.shape[1]}x{reference.shape[0]}")
        z = estimator.height(image)
        target = args.out / f"{stem}.tiff"
        try:
            with atomic_write(target, "wb") as stream:
                tifffile.imwrite(stream, z.astype(np.float32), photometric="minisblack",
                                 metadata={"unit": "m", "quantity": "indentation"})
        except OSError as exc:
            raise UserError(f"cannot write {target}: {exc.strerror}") from None
    band_note = "" if rows is None else f" (rows {rows[0]}-{rows[1] - 1}, NaN elsewhere)"
    print(f"wrote {len(images)} height images to {args.out}{band_note}")
    return 0
