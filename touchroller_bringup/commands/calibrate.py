"""`touchroller calibrate intrinsics|extrinsics INPUT --out CAL.yaml`: the paper's two-step calibration.

INPUT is a rosbag2 recording (topic `/touchroller/image_raw` unless `--topic`), an image folder
(png/jpg/bmp/tif, sorted by name) or one image file. The output is a docs/design.md parameters file
(`/**: ros__parameters:`) that `touchroller contacts --params` and the nodes read.

    touchroller calibrate intrinsics chessboard_bag --out cal.yaml
    touchroller calibrate extrinsics hemispheres_bag --params cal.yaml --out cal.yaml
    touchroller calibrate compare hemispheres_bag/camera_truth.yaml cal.yaml

`calibrate photometric` (colour -> membrane slope from ball presses, a .npz) lives in commands/height.py.
"""
from __future__ import annotations

import argparse
import math
from pathlib import Path
from typing import Any

from touchroller_bringup.camera_info_files import DEFAULT_CAMERA_NAME
from touchroller_bringup.commands.inputs import read_image, read_input_images
from touchroller_bringup.errors import UserError
from touchroller_bringup.names import IMAGE_TOPIC
from touchroller_bringup.outputs import Output, check_outputs
from touchroller_perception.files import atomic_write


def register(subparsers: argparse._SubParsersAction) -> None:
    parser = subparsers.add_parser(
        "calibrate", help="calibrate intrinsics (chessboard) or theta and d (hemisphere frame)",
        description="The paper's calibration, scripted: intrinsics and distortion from chessboard views "
                    "(Zhang), then theta and d from the roller pressed on the 2x5 hemisphere frame.")
    steps = parser.add_subparsers(dest="step", metavar="STEP", parser_class=type(parser))
    steps.required = True

    intr = steps.add_parser("intrinsics", help="fx, fy, cx, cy and the lens distortion",
                            description="Zhang's method on chessboard views, with per-view errors, "
                                        "rejection of bad or blurred views, a distortion model chosen by "
                                        "held-out views, and what the views cover (X / Y / size / skew bars "
                                        "and the image corners).")
    _common(intr)
    intr.add_argument("--board", default="7x7", metavar="COLSxROWS",
                      help="inner corners of the chessboard (default 7x7)")
    intr.add_argument("--square", type=float, default=0.012, help="square side in m (default 0.012)")
    intr.add_argument("--params", type=Path,
                      help="parameters file whose cylinder and extrinsics values are kept (default: built-in)")
    intr.add_argument("--max-view-rms", type=float, default=1.0,
                      help="reject views whose reprojection RMS exceeds this (px) and 3x the median")
    intr.add_argument("--distortion", choices=("auto", "k1", "k1k2", "radial", "k1k2p", "full"), default="auto",
                      help="auto (default): k1, k2, p1, p2, plus k3 only when views held out of the fit need "
                           "it; or a fixed model: k1, k1k2, radial (k1, k2, k3), k1k2p, full (k1, k2, p1, p2, k3)")
    intr.add_argument("--corners", choices=("fronto_parallel", "image"), default="fronto_parallel",
                      help="fronto_parallel (default): the corners refined on the board's plane with the lens of a "
                           "first fit; image: the corners as found in the image (the previous path, for comparison)")
    intr.add_argument("--camera-info", type=Path, metavar="YAML",
                      help="also the intrinsics as camera_calibration_parsers' YAML, for a camera driver's "
                           "camera_info_url (default: beside --out, CAL.camera_info.yaml)")
    intr.add_argument("--camera-name", default=DEFAULT_CAMERA_NAME,
                      help="camera_name in that YAML (letters, digits, _; default %(default)s)")
    intr.set_defaults(func=run_intrinsics)

    extr = steps.add_parser("extrinsics", help="theta and d from hemisphere-frame presses",
                            description="theta and d from images of the roller pressed on the hemisphere "
                                        "frame: imprint centres, a per-image pose solve, mean and spread, "
                                        "outlier rejection, and the terms the paper's model neglects.")
    _common(extr)
    extr.add_argument("--params", type=Path, required=True,
                      help="parameters file with the intrinsics (from 'touchroller calibrate intrinsics')")
    extr.add_argument("--frame", default="2x5", metavar="ROWSxCOLS",
                      help="hemisphere rows (across the axis) x columns (along it), default 2x5")
    extr.add_argument("--pitch", type=float, nargs=2, default=(0.010, 0.008), metavar=("X", "Y"),
                      help="centre distances along the axis and across it, m (default 0.010 0.008)")
    extr.add_argument("--hemisphere-radius", type=float, default=0.001, help="m (default 0.001)")
    extr.add_argument("--press-depth", type=float, default=0.0005, help="m, at the contact line (default 0.0005)")
    extr.add_argument("--reference-frames", type=int, default=None,
                      help="no-contact frames at the start of the input used as reference "
                           "(default 5 for a bag, 0 for images)")
    extr.add_argument("--reference", type=Path, help="a no-contact reference image instead")
    extr.add_argument("--dark", type=Path,
                      help="a no-contact image with the sensor's lights off: imprint strengths are then measured "
                           "against the light alone (an uneven gel or ambient light no longer biases theta)")
    extr.add_argument("--no-row-balance", action="store_true",
                      help="plain mean of theta (the paper) without the frame-shift correction")
    extr.add_argument("--max-view-rms", type=float, default=math.inf,
                      help="an optional hard limit on a view's RMS (px); by default views are judged against "
                           "each other (median + 4 robust standard deviations), not by a fixed number of pixels")
    extr.add_argument("--imprint-centre", choices=("symmetric", "shading", "centroid"), default="symmetric",
                      help="symmetric (default): centres corrected for light from one side; shading: also for the "
                           "slopes a low light leaves in shadow; centroid: the change-weighted centroid")
    extr.add_argument("--imprint-strength", choices=("auto", "relative", "size", "absolute"), default="auto",
                      help="what the row balance compares between the rows: auto (default): relative with "
                           "--dark, else size; relative: energy relative to the light; size: the imprints' extent, "
                           "which no light level changes; absolute: grey levels")
    extr.set_defaults(func=run_extrinsics)

    from touchroller_bringup.commands.height import register_calibration

    register_calibration(steps)   # photometric: colour -> slope from ball presses (docs/height.md)

    compare = steps.add_parser("compare", help="how far apart two calibrations put contacts",
                               description="Parameter differences (B - A) and the distance between the "
                                           "two models' back-projections of the same pixels on the membrane; "
                                           "e.g. a calibration against the simulator's BAG/camera_truth.yaml.")
    compare.add_argument("a", type=Path, help="parameters file A (e.g. the reference or truth)")
    compare.add_argument("b", type=Path, help="parameters file B (e.g. the new calibration)")
    compare.set_defaults(func=run_compare)


def _common(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("input", type=Path, help="rosbag2 folder, image folder or image file")
    parser.add_argument("--out", required=True, type=Path, help="calibration YAML to write")
    parser.add_argument("--topic", default=IMAGE_TOPIC, help="image topic in a bag (default: %(default)s)")
    parser.add_argument("--report", type=Path, help="also write the full report (per view) as YAML")


def load_images(path: Path, topic: str) -> tuple[list[Any], bool]:
    """The images of a bag, a folder or a file; and whether it was a bag."""
    found = read_input_images(path, topic)
    return [item.image for item in found.images], found.from_recording


def _load_camera(path: Path | None):
    from touchroller_perception.geometry import CameraModel

    if path is None:
        return CameraModel()
    if not path.exists():
        raise UserError(f"no such parameters file: {path}")
    try:
        return CameraModel.from_yaml(path)
    except (ValueError, TypeError, OSError) as exc:
        raise UserError(f"{path}: {exc}") from None


def _grid(text: str, what: str) -> tuple[int, int]:
    a, sep, b = text.lower().partition("x")
    try:
        if not sep:
            raise ValueError
        return int(a), int(b)
    except ValueError:
        raise UserError(f"{what} must look like 7x7, got {text!r}") from None


def run_intrinsics(args: argparse.Namespace) -> int:
    from touchroller_bringup.camera_info_files import camera_info_path_for, camera_name_problem
    from touchroller_perception import calibration as cal

    columns, rows = _grid(args.board, "--board")
    if camera_name_problem(args.camera_name):
        raise UserError(camera_name_problem(args.camera_name).replace("camera_name", "--camera-name", 1))
    if args.camera_info is None:
        args.camera_info = camera_info_path_for(args.out)
    check_calibrate_outputs(args)
    prior = _load_camera(args.params)
    images, _ = load_images(args.input, args.topic)
    try:
        config = cal.IntrinsicsConfig(board=cal.Chessboard(columns=columns, rows=rows, square=args.square),
                                      max_view_rms=args.max_view_rms, distortion=args.distortion,
                                      corners=args.corners)
        result = cal.calibrate_intrinsics(images, config, prior=prior, on_view=_view_progress(len(images)))
    except cal.CalibrationError as exc:
        raise UserError(f"calibrate intrinsics: {exc}") from None
    _write(args, result.camera, intrinsics=result)
    _write_camera_info(args, result.camera)
    print(result.summary())
    for index, reason in sorted(result.rejected.items()):
        print(f"  rejected image {index}: {reason}")
    if math.isfinite(result.tangential_chi2) or result.model_scores:
        kept = result.tangential_chi2 >= config.tangential_chi2
        print(f"  tangential p1, p2: Wald statistic {result.tangential_chi2:.1f} "
              f"({'>=' if kept else '<'} {config.tangential_chi2:g}, Akaike's 2 per term): "
              + ("the fit shows them, kept" if kept else "no evidence for them, left out"))
    for score in result.model_scores:
        print(f"  distortion model {score.model}: held-out RMS {score.held_out_rms:.4f} px, "
              f"{score.excess_se:+.1f} standard errors from the best{'  <- chosen' if score.chosen else ''}")
    for line in result.coverage.lines():
        print(f"  {line}")
    for warning in result.warnings():
        print(f"warning: {warning}")
    print(f"wrote {args.out} and {args.camera_info}")
    return 0


def _write_camera_info(args: argparse.Namespace, camera: Any) -> None:
    """The intrinsics as camera_calibration_parsers' YAML (a camera driver's camera_info_url reads it)."""
    from touchroller_bringup.camera_info_files import CameraCalibration, write_camera_info

    try:
        write_camera_info(args.camera_info, CameraCalibration.from_model(camera, args.camera_name))
    except OSError as exc:
        raise UserError(f"wrote --out {args.out} but cannot write --camera-info {args.camera_info}: "
                        f"{exc.strerror or exc} (free some space or choose another path)") from None
    _check_written(args.camera_info, "--camera-info")


def _view_progress(count: int):
    """One line per view as it is examined: found or why not, and the coverage so far (the bars of
    ROS camera_calibration, as percentages, and the image corners reached)."""
    def show(index: int, detection: Any, coverage: Any) -> None:
        state = "board found" if detection.corners is not None else f"rejected: {detection.reason}"
        print(f"  view {index + 1}/{count}: {state}; {coverage.one_line()}", flush=True)
    return show


def run_extrinsics(args: argparse.Namespace) -> int:
    import numpy as np

    from touchroller_perception import calibration as cal

    rows, columns = _grid(args.frame, "--frame")
    check_calibrate_outputs(args)
    camera = _load_camera(args.params)
    images, is_bag = load_images(args.input, args.topic)
    reference = None
    if args.reference is not None:
        import cv2

        reference = read_image(args.reference, cv2, "--reference")
    else:
        count = (5 if is_bag else 0) if args.reference_frames is None else args.reference_frames
        if count < 0 or count >= len(images):
            raise UserError(f"--reference-frames {count}: the input has {len(images)} images")
        if count:
            reference = np.median(np.stack(images[:count]), axis=0).astype(np.uint8)
            images = images[count:]
    dark = None
    if args.dark is not None:
        import cv2

        dark = read_image(args.dark, cv2, "--dark")
    if reference is None:
        print("note: no no-contact reference (--reference or --reference-frames): the imprint background is "
              "estimated per image, which is less precise and can mistake specks for imprints")
    try:
        frame = cal.HemisphereFrame(rows=rows, columns=columns, pitch_x=args.pitch[0], pitch_y=args.pitch[1],
                                    hemisphere_radius=args.hemisphere_radius, press_depth=args.press_depth)
        config = cal.ExtrinsicsConfig(frame=frame, balance_rows=not args.no_row_balance,
                                      max_view_rms=args.max_view_rms,
                                      detector=cal.ImprintDetectorConfig(centre=args.imprint_centre,
                                                                         strength=args.imprint_strength))
        result = cal.calibrate_extrinsics(images, camera, config, reference=reference, dark=dark,
                                          intrinsics_sigma=_intrinsics_sigma(args.params))
    except cal.CalibrationError as exc:
        raise UserError(f"calibrate extrinsics: {exc}") from None
    _write(args, result.camera, extrinsics=result)
    print(result.summary())
    print(f"  method: {result.method}")
    for choice in result.choices:
        print(f"  term {choice.line()}")
    for warning in result.warnings:
        print(f"warning: {warning}")
    plain = math.degrees(result.theta_plain_mean)
    print(f"  paper's plain mean theta = {plain:.4f}° (the result is {math.degrees(result.theta) - plain:+.4f}° "
          f"from it)")
    for index, reason in sorted(result.rejected.items()):
        print(f"  rejected image {index}: {reason}")
    print(f"wrote {args.out}")
    return 0


def _intrinsics_sigma(params: Path) -> dict[str, float]:
    """The intrinsics' one-sigma values an earlier `calibrate intrinsics` wrote (none for other files)."""
    from touchroller_perception import calibration as cal

    extras = cal.read_calibration_extras(str(params))
    prefix = "calibration.sigma."
    return {key[len(prefix):]: float(value) for key, value in extras.items()
            if key.startswith(prefix) and key[len(prefix):] in cal.INTRINSIC_NAMES}


def run_compare(args: argparse.Namespace) -> int:
    from touchroller_perception.calibration import compare_cameras

    a, b = _load_camera(args.a), _load_camera(args.b)
    if (a.width, a.height) != (b.width, b.height):
        raise UserError(f"the calibrations are for different image sizes: {a.width}x{a.height} and "
                        f"{b.width}x{b.height}")
    diff = compare_cameras(a, b)
    print(f"B - A: fx {diff['dfx_px']:+.3f} px, fy {diff['dfy_px']:+.3f} px, cx {diff['dcx_px']:+.3f} px, "
          f"cy {diff['dcy_px']:+.3f} px, theta {diff['dtheta_deg']:+.4f}°, d {diff['dd_mm']:+.4f} mm")
    print(f"back-projections apart: {diff['contact_band_mean_mm']:.3f} mm on average in the contact band, "
          f"{diff['image_mean_mm']:.3f} mm on average and {diff['image_max_mm']:.3f} mm at most over the image "
          f"({100 * diff['mapped_fraction']:.0f}% of the pixels map onto the membrane)")
    return 0


def check_calibrate_outputs(args: argparse.Namespace) -> None:
    """The shared output check, before any work: --out and --report never replace the input, the
    reference or dark image, each other, or anything that is not a regular file. (--out may be the
    --params file it updates: that is read whole before the write.)"""
    outputs = [Output("--out", args.out)] + ([Output("--report", args.report)] if args.report is not None else [])
    if getattr(args, "camera_info", None) is not None:
        outputs.append(Output("--camera-info", args.camera_info))
    check_outputs(outputs, {"INPUT": args.input, "--reference": getattr(args, "reference", None),
                            "--dark": getattr(args, "dark", None)})


def _write(args: argparse.Namespace, camera, intrinsics=None, extrinsics=None) -> None:
    import yaml

    from touchroller_perception import calibration as cal

    try:
        keep = cal.read_calibration_extras(str(args.params)) if getattr(args, "params", None) else {}
    except (OSError, ValueError) as exc:
        raise UserError(f"cannot read --params {args.params}: {getattr(exc, 'strerror', None) or exc}") from None
    try:
        cal.write_calibration(str(args.out), camera, intrinsics=intrinsics, extrinsics=extrinsics, keep=keep)
    except OSError as exc:
        raise UserError(f"cannot write --out {args.out}: {exc.strerror or exc}; nothing was written "
                        "(free some space or choose another path)") from None
    _check_written(args.out, "--out")
    if args.report is not None:
        report = {"intrinsics": intrinsics.to_dict() if intrinsics else None,
                  "extrinsics": extrinsics.to_dict() if extrinsics else None}
        try:
            with atomic_write(args.report) as stream:
                yaml.safe_dump(_plain(report), stream, sort_keys=False)
        except OSError as exc:
            raise UserError(f"wrote --out {args.out} but cannot write --report {args.report}: "
                            f"{exc.strerror or exc} (free some space or choose another path)") from None
        _check_written(args.report, "--report")


def _check_written(path: Path, label: str) -> None:
    """A command that says it wrote a file has: a non-empty regular file is there."""
    try:
        size = path.stat().st_size if path.is_file() else 0
    except OSError:
        size = 0
    if size == 0:
        raise UserError(f"{label} {path} was not written (it is missing or empty after the write); "
                        "check the disk and the path")


def _plain(value: Any) -> Any:
    """numpy scalars and tuples -> YAML-safe Python values."""
    if isinstance(value, dict):
        return {k: _plain(v) for k, v in value.items()}
    if isinstance(value, list | tuple):
        return [_plain(v) for v in value]
    if hasattr(value, "item"):
        return value.item()
    return value
