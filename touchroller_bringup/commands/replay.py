"""`touchroller replay BAG [--rate F] [--loop] [--topics T ...] [--delay S]`.

Like `ros2 bag play`: serialized messages at their recorded timing (scaled by --rate) with the
recorded QoS. Ends when the bag ends (never with --loop) or on Ctrl-C.
"""
from __future__ import annotations

import argparse
import math
import time

from touchroller_bringup.errors import UserError


def register(subparsers: argparse._SubParsersAction) -> None:
    parser = subparsers.add_parser(
        "replay", help="play a rosbag2 folder back at its recorded timing",
        description="Publish a bag's messages at their recorded timing with the recorded QoS.")
    parser.add_argument("bag", help="rosbag2 folder (sqlite3 or MCAP)")
    parser.add_argument("--rate", type=float, default=1.0, help="playback rate factor (default 1.0)")
    parser.add_argument("--loop", action="store_true", help="play again from the start at the end")
    parser.add_argument("--topics", nargs="+", metavar="TOPIC", help="only these topics")
    parser.add_argument("--delay", type=float, default=0.0, metavar="S",
                        help="wait S seconds before playing (lets subscribers connect)")
    parser.set_defaults(func=run)


#: --delay's limit, s: a day (a wait for ever is no use, and an infinite one is refused)
MAX_DELAY_S = 86400.0


def run(args: argparse.Namespace) -> int:
    from touchroller_bringup.replayer import check_rate

    check_rate(args.rate)
    if not (math.isfinite(args.delay) and 0 <= args.delay <= MAX_DELAY_S):
        raise UserError(f"--delay must be a number of seconds from 0 to {MAX_DELAY_S:g}, got {args.delay:g}")
    import rclpy
    from rclpy.context import Context
    from rclpy.executors import SingleThreadedExecutor
    from rclpy.signals import SignalHandlerOptions

    from touchroller_bringup.replayer import Replayer

    context = Context()
    rclpy.init(context=context, signal_handler_options=SignalHandlerOptions.NO)
    replayer = None
    try:
        replayer = Replayer(args.bag, rate=args.rate, loop=args.loop, topics=args.topics, context=context)
        executor = SingleThreadedExecutor(context=context)
        executor.add_node(replayer)
        print(f"replaying {args.bag} ({', '.join(replayer.topics) or 'no playable topics'}) at rate {args.rate:g}",
              flush=True)
        started = time.monotonic()
        try:
            while time.monotonic() - started < args.delay:
                executor.spin_once(timeout_sec=0.05)
            replayer.start()
            while not replayer.finished:
                executor.spin_once(timeout_sec=0.05)
        except KeyboardInterrupt:
            replayer.stop()
        if replayer.error:
            raise UserError(replayer.error)
        print(f"replayed {replayer.published} messages in {time.monotonic() - started:.1f} s")
        return 0
    finally:
        if replayer is not None:
            replayer.destroy_node()
        context.try_shutdown()
