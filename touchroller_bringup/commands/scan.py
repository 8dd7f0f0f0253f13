"""`touchroller scan [params.yaml ...] [name:=value ...] [--out DIR]`: the scan graph in one process.

`name:=value` sets a launch argument of scan.launch.py when `name` is one (use_sim, camera_device,
robot_ip, params_file, calibration_file, sweep_speed, sweep_length, scene, namespace, ...), else a ROS
parameter on every node of the graph that declares it (e.g. `sweep.depth:=0.0008`, `map.publish_rate:=5.0`).
With no arguments: the simulated sensor and arm over the built-in `surface_mapping` scene, in the
namespace `touchroller`. Two scans on one ROS domain need different namespaces (`--namespace left`) or
different ROS_DOMAIN_IDs; a scan that finds its namespace taken stops at start-up, before it publishes.
Ctrl-C, SIGTERM or SIGHUP stop the arm and write map, contacts, report (and the recording) with what
there is; the exit code is then 128 + the signal's number.
"""
from __future__ import annotations

import argparse
import signal
import sys
import time
from pathlib import Path
from typing import Any

import yaml

from touchroller_bringup import bag_format
from touchroller_bringup.errors import UserError


def register(subparsers: argparse._SubParsersAction) -> None:
    parser = subparsers.add_parser(
        "scan", help="run the whole graph (camera, perception, sweep) in one process; write map, contacts, report",
        description=__doc__.split("\n\n", 1)[1] if __doc__ else None)
    _add_options(parser)
    # Options may follow the items (`touchroller scan a.yaml --out X k:=v`): argparse cannot mix a '*'
    # positional with later options, so the rest is taken whole and re-parsed intermixed in run().
    parser.add_argument("rest", nargs=argparse.REMAINDER, help=argparse.SUPPRESS)
    parser.set_defaults(func=run)


def _add_options(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("items", nargs="*", metavar="PARAMS.yaml | name:=value",
                        help="params files (applied after config/touchroller.yaml and config/scan.yaml, in order) "
                             "and launch arguments or parameter overrides")
    parser.add_argument("--out", type=Path, default=None,
                        help="output folder (default: scan_output/<UTC timestamp>/)")
    parser.add_argument("--height", action="store_true",
                        help="also the world height map, height.tif beside map.png (docs/height.md): simulated, the "
                             "sensor's photometric model is calibrated on the fly (photometric.npz and reference.png "
                             "in --out); a real scan names its own: map.height.photometric:=P.npz "
                             "map.height.reference:=REF.png")
    parser.add_argument("--seed", type=int, default=0, help="simulator random seed (use_sim:=true)")
    parser.add_argument("--namespace", default=None, metavar="NS",
                        help="ROS namespace of the graph (default touchroller: /touchroller/contacts, ...); "
                             "the same as namespace:=NS")
    parser.add_argument("--quiet", action="store_true", help="no progress lines")
    parser.add_argument("--record", action="store_true",
                        help="also record the graph's topics to OUT/recording (rosbag2)")
    parser.add_argument("--storage", choices=("sqlite3", "mcap"), default=None,
                        help="storage of the --record bag (default sqlite3)")
    parser.add_argument("--bag-format", choices=bag_format.CHOICES, default=None,
                        help="the --record bag: " + bag_format.HELP)
    parser.add_argument("--uncompressed", action="store_true",
                        help="the --record bag stores raw sensor_msgs/Image (default: lossless PNG on "
                             "image_raw/compressed, zstd MCAP chunks but for those of PNG frames)")


class _RestParser(argparse.ArgumentParser):
    def error(self, message: str) -> None:
        raise UserError(f"scan: {message}")


def _reparse(args: argparse.Namespace) -> argparse.Namespace:
    rest = _RestParser(prog="touchroller scan", add_help=False)
    _add_options(rest)
    parsed = rest.parse_intermixed_args(list(args.items) + list(args.rest))
    parsed.out = parsed.out or args.out
    parsed.seed = parsed.seed or args.seed
    parsed.quiet = parsed.quiet or args.quiet
    parsed.record = parsed.record or args.record
    parsed.uncompressed = parsed.uncompressed or args.uncompressed
    parsed.storage = parsed.storage or args.storage or "sqlite3"
    parsed.bag_format = parsed.bag_format or args.bag_format or "auto"
    parsed.namespace = parsed.namespace if parsed.namespace is not None else args.namespace
    return parsed


def parse_items(items: list[str]) -> tuple[list[Path], dict[str, str], dict[str, Any]]:
    """Split CLI items into params files, launch arguments and parameter overrides."""
    from touchroller_bringup.graph import LAUNCH_ARGUMENTS

    launch_names = {arg.name for arg in LAUNCH_ARGUMENTS["scan"]}
    files: list[Path] = []
    arguments: dict[str, str] = {}
    overrides: dict[str, Any] = {}
    for item in items:
        if ":=" in item:
            name, _, text = item.partition(":=")
            name = name.strip()
            if not name:
                raise UserError(f"{item!r}: expected name:=value")
            if name in launch_names:
                arguments[name] = text
            else:
                overrides[name] = _parse_value(name, text)
        else:
            path = Path(item)
            if not path.is_file():
                raise UserError(f"{item}: not a params file (and not name:=value)")
            _check_params_file(path)
            files.append(path)
    return files, arguments, overrides


def _check_params_file(path: Path) -> None:
    """A params file rcl can read, or one line saying why not (rcl's own error is a raw RCLInvalidROSArgsError)."""
    from touchroller_bringup.ros_main import params_file_problem

    try:
        document = yaml.safe_load(path.read_text(encoding="utf-8"))
    except (yaml.YAMLError, UnicodeDecodeError) as exc:
        mark = getattr(exc, "problem_mark", None)
        where = f" at line {mark.line + 1}" if mark is not None else ""
        raise UserError(f"{path} is not YAML ({getattr(exc, 'problem', None) or exc}{where})") from None
    except OSError as exc:
        raise UserError(f"{path}: {exc.strerror or exc}") from None
    problem = params_file_problem(document)
    if problem:
        raise UserError(f"{path} is not a ROS 2 parameters file: {problem}")


def _parse_value(name: str, text: str) -> Any:
    """YAML scalars and lists, as `ros2 run ... -p name:=value` reads them."""
    try:
        value = yaml.safe_load(text) if text.strip() else ""
    except yaml.YAMLError as exc:
        raise UserError(f"{name}:={text}: not a YAML value ({' '.join(str(exc).split())})") from None
    if isinstance(value, dict) or value is None:
        raise UserError(f"{name}:={text}: expected a number, string, boolean or list")
    if isinstance(value, str):   # YAML 1.1 reads 1e-6 (no dot) as a string: the number it means
        try:
            value = float(value) if value.strip().lower() not in ("nan", "inf", "-inf", "infinity") else value
        except ValueError:
            pass
    if isinstance(value, list) and value and all(isinstance(v, (int, float)) and not isinstance(v, bool)
                                                  for v in value):
        if any(isinstance(v, float) for v in value):
            value = [float(v) for v in value]  # ROS double arrays: [1, 0.5] means [1.0, 0.5]
    return value


def run(args: argparse.Namespace) -> int:
    from touchroller_bringup.scan import ScanOptions, run_scan

    args = _reparse(args)
    files, arguments, overrides = parse_items(args.items)
    if args.namespace is not None:
        arguments["namespace"] = args.namespace
    out = args.out or Path("scan_output") / time.strftime("%Y%m%d-%H%M%S", time.gmtime())
    progress = None if args.quiet else (lambda line: print(line, flush=True))
    result = run_scan(ScanOptions(out_dir=out, arguments=arguments, params_files=files, overrides=overrides,
                                  seed=args.seed, progress=progress, record=args.record, storage=args.storage,
                                  bag_format=args.bag_format, height=args.height,
                                  compress=not args.uncompressed))
    map_text = "x".join(map(str, result.map_shape)) if result.map_shape else "no map"
    print(f"scan {result.outcome}: {result.duration_s:.1f} s, {result.frames_published} frames "
          f"({result.frames_processed} processed), {result.contacts} contacts, map {map_text} -> {result.out_dir}/")
    if result.recording_warning:
        print(f"touchroller: warning: {result.recording_warning}", file=sys.stderr)
    if result.failed:
        written = ", ".join(sorted(path.name for path in result.files.values())) or "nothing"
        failures = "; ".join(f"{name}: {why}" for name, why in result.failed.items())
        raise UserError(f"scan {result.outcome} but could not write {failures} (written to {result.out_dir}/: "
                        f"{written}); free some space or give another --out folder")
    if result.outcome == "interrupted":
        print(f"touchroller: scan {result.message}: arm stopped, outputs written to {result.out_dir}/", file=sys.stderr)
        return 128 + int(result.signal or signal.SIGINT)
    if result.outcome == "recording failed":
        raise UserError(f"{result.message}; arm stopped, map, contacts and report written to {result.out_dir}/")
    if not result.ok:
        raise UserError(f"the sweep ended in {result.outcome}: {result.message} (outputs in {result.out_dir}/)")
    return 0
