"""`touchroller reindex BAG`: make a recording that was killed readable again (like `ros2 bag reindex`).

A bag whose recorder was SIGKILLed, lost its terminal or filled the disk has no metadata.yaml (and an
MCAP file no footer). The recorder commits at least once a second, so the storage file holds the
recording up to its last second: this rebuilds metadata.yaml from it, and closes an MCAP file after
its last complete record (see `touchroller_bringup.bag_recovery`).
"""
from __future__ import annotations

import argparse


def register(subparsers: argparse._SubParsersAction) -> None:
    parser = subparsers.add_parser(
        "reindex", help="rebuild a killed recording's metadata.yaml (and MCAP footer) from its storage file",
        description=__doc__.split("\n\n", 1)[1] if __doc__ else None)
    parser.add_argument("bag", help="rosbag2 folder (sqlite3 or MCAP)")
    parser.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from touchroller_bringup.bag_recovery import counts_by_topic, reindex

    found = reindex(args.bag)
    repaired = f"; {found.storage_file.name} closed after its last complete record" if found.repaired else ""
    dropped = f" ({found.dropped_bytes} bytes of an unfinished record dropped)" if found.dropped_bytes else ""
    print(f"reindexed {found.path}: {found.message_count} messages ({counts_by_topic(found)}){repaired}{dropped}")
    return 0
