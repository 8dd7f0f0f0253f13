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
    import sqlite3

    from touchroller_bringup.bag_recovery import counts_by_topic, reindex
    from touchroller_bringup.errors import UserError

    try:
        found = reindex(args.bag)
    except (OSError, sqlite3.Error) as exc:
        why = getattr(exc, "strerror", None) or str(exc)
        where = f" ({exc.filename})" if getattr(exc, "filename", None) else ""
        raise UserError(f"cannot reindex {args.bag}{where}: {why}; reindex rewrites the bag's metadata.yaml (and "
                        "an MCAP file's end) in place: copy the bag to a writable folder with free space and "
                        "reindex the copy") from None
    repaired = f"; {found.storage_file.name} closed after its last complete record" if found.repaired else ""
    dropped = f" ({found.dropped_bytes} bytes of an unfinished record dropped)" if found.dropped_bytes else ""
    print(f"reindexed {found.path}: {found.message_count} messages ({counts_by_topic(found)}){repaired}{dropped}")
    return 0
