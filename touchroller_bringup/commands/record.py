"""`touchroller record --out BAG [--storage sqlite3|mcap] [--topics T ...] [--duration S] [--uncompressed]
[--queue-mb MB]`.

Images are stored losslessly compressed (sensor_msgs/CompressedImage PNG on `<topic>/compressed`, MCAP
chunks zstd but for those of PNG frames; `touchroller_bringup.bag_compression`) unless `--uncompressed`.

Like `ros2 bag record`: raw subscriptions into a rosbag2 folder with the publishers' QoS in its
metadata. Ctrl-C, SIGTERM or SIGHUP (the terminal closed) stop it between callbacks; what had arrived is
written and the bag is finalised (a second signal during that short drain changes nothing). Killed
(SIGKILL, a crash), the bag keeps all but its last second: `touchroller reindex BAG` makes it readable.
A write that fails (a full disk) stops the recording at once: one line, exit 2, and what was written
before is kept and indexed. Messages the recorder could not keep (its queue at `--queue-mb`, or lost before
it took them) are counted and said at the end on stderr (and ERROR on /diagnostics while it records).
"""
from __future__ import annotations

import argparse
import signal
import sys
import threading
import time

from touchroller_bringup import bag_format
from touchroller_bringup.errors import UserError


def register(subparsers: argparse._SubParsersAction) -> None:
    parser = subparsers.add_parser(
        "record", help="record ROS topics to a rosbag2 folder (sqlite3 or MCAP)",
        description="Record topics (all but /rosout and /parameter_events unless --topics) until Ctrl-C or --duration.")
    parser.add_argument("--out", "-o", required=True, help="new bag folder to write")
    parser.add_argument("--storage", choices=("sqlite3", "mcap"), default="sqlite3", help="storage plugin")
    parser.add_argument("--uncompressed", action="store_true",
                        help="store images as raw sensor_msgs/Image (default: lossless PNG CompressedImage on "
                             "<topic>/compressed, and zstd MCAP chunks but for those of PNG frames)")
    parser.add_argument("--bag-format", choices=bag_format.CHOICES, default="auto", help=bag_format.HELP)
    parser.add_argument("--topics", nargs="+", metavar="TOPIC", help="topics to record (default: all)")
    parser.add_argument("--duration", type=float, metavar="S", help="stop after S seconds")
    parser.add_argument("--queue-mb", type=float, metavar="MB", help="messages taken but not written yet, at most "
                        "this many MiB (default 256; past it messages are refused, counted and reported)")
    parser.set_defaults(func=run)


def drain(executor, count, quiet_s: float = 0.2, max_s: float = 2.0) -> None:
    """Spin until `count()` has not grown for `quiet_s` (messages already in flight get recorded)."""
    deadline = time.monotonic() + max_s
    last, quiet_since = count(), time.monotonic()
    while time.monotonic() < deadline and time.monotonic() - quiet_since < quiet_s:
        executor.spin_once(timeout_sec=0.02)
        if count() != last:
            last, quiet_since = count(), time.monotonic()


def run(args: argparse.Namespace) -> int:
    if args.duration is not None and not args.duration > 0:
        raise UserError(f"--duration must be positive, got {args.duration}")
    if args.queue_mb is not None and not args.queue_mb >= 1:
        raise UserError(f"--queue-mb must be at least 1, got {args.queue_mb}")
    from touchroller_bringup.outputs import Output, check_outputs

    check_outputs([Output("--out", args.out, folder=True)])
    import rclpy
    from rclpy.context import Context
    from rclpy.executors import SingleThreadedExecutor
    from rclpy.signals import SignalHandlerOptions

    from touchroller_bringup.recorder import Recorder, RecorderConfig

    context = Context()
    # Our own Ctrl-C handling: rclpy's handler would shut the context down before the drain, and a
    # KeyboardInterrupt could land inside a callback. A flag stops the loop between callbacks instead.
    rclpy.init(context=context, signal_handler_options=SignalHandlerOptions.NO)
    stop = threading.Event()
    previous = {sig: signal.signal(sig, lambda signum, frame: stop.set())
                for sig in (signal.SIGINT, signal.SIGTERM, signal.SIGHUP)}
    recorder = None
    try:
        config = RecorderConfig() if args.queue_mb is None else \
            RecorderConfig(queue_max_bytes=round(args.queue_mb * 2**20))
        recorder = Recorder(args.out, topics=args.topics, storage=args.storage, distro=args.bag_format,
                            compress=not args.uncompressed, context=context, config=config)
        executor = SingleThreadedExecutor(context=context)
        executor.add_node(recorder)
        deadline = None if args.duration is None else time.monotonic() + args.duration
        kind = "" if args.uncompressed else ", images as PNG"
        print(f"recording to {args.out} ({args.storage}{kind}); Ctrl-C to stop", flush=True)
        while not stop.is_set() and not recorder.failed.is_set() \
                and (deadline is None or time.monotonic() < deadline):
            executor.spin_once(timeout_sec=0.1)
        if not recorder.failed.is_set():
            drain(executor, lambda: recorder.message_count)
        recorder.close()   # UserError (one line) when writing failed
        counts = ", ".join(f"{topic}: {n}" for topic, n in sorted(recorder.counts.items())) or "no topics seen"
        print(f"recorded {recorder.written} messages to {args.out} ({counts})")
        lost = recorder.stats().summary()
        if lost:
            print(f"touchroller: warning: {lost}", file=sys.stderr)
        return 0
    finally:
        if recorder is not None:
            recorder.destroy_node()
        for sig, handler in previous.items():
            signal.signal(sig, handler)
        context.try_shutdown()
