"""Which ROS 2 distribution's rosbag2 reads the bags we write: Humble, Jazzy or Kilted.

rosbag2 changed how `metadata.yaml` stores a topic's offered QoS profiles in metadata version 9 (Jazzy
on): a YAML list of profiles with policies by name (`history: keep_last`). Humble's rosbag2 reads a
YAML *string* holding the profiles with policies as integers (`history: 1`) and stops with
"yaml-cpp: bad conversion" on a list. The newer readers still read the older form (rosbag2 keeps
backward compatibility), so a bag in Humble's form plays on all three; a bag in the newer form plays on
Jazzy and Kilted only. The same QoS text is stored with each topic in the storage file (the sqlite3
`topics` table, the MCAP channel's metadata), which is what `ros2 bag play` offers from.

- `humble`: metadata version 5 (the version Humble writes), QoS as a string of integer policies, every
  infinite duration in the form Humble's own recordings hold (2147483647 s, 4294967295 ns), no policy
  Humble lacks (best_available becomes system_default).
- `jazzy`, `kilted`: metadata version 9 with the QoS list, `ros_distro` naming the distribution.

`auto` takes `ROS_DISTRO` when it names one of them (a sourced ROS 2), else `humble`, the form every
supported distribution reads.
"""
from __future__ import annotations

import os
from collections.abc import Mapping
from pathlib import Path
from typing import Any

from touchroller_bringup.errors import UserError
from touchroller_perception.files import atomic_write

DISTROS = ("humble", "jazzy", "kilted")
CHOICES = ("auto", *DISTROS)
HELP = ("which ROS 2 must read the bag: humble (the form every supported distribution reads), jazzy or kilted; "
        "auto (default): $ROS_DISTRO when a ROS 2 is sourced, else humble")
HUMBLE_METADATA_VERSION = 5
# Humble's recordings hold an infinite duration as DDS's: the largest 32-bit seconds and nanoseconds.
HUMBLE_INFINITE = (2147483647, 4294967295)


def resolve(name: str = "auto", environ: Mapping[str, str] | None = None) -> str:
    """The distribution a bag is written for: `name`, or for `auto` the sourced ROS 2 (else humble)."""
    name = name.strip().lower()
    if name == "auto":
        sourced = (os.environ if environ is None else environ).get("ROS_DISTRO", "").strip().lower()
        return sourced if sourced in DISTROS else "humble"
    if name not in DISTROS:
        raise UserError(f"unknown bag format {name!r} (use one of {', '.join(CHOICES)})")
    return name


def stored_form(stored_qos: list[Any], environ: Mapping[str, str] | None = None) -> str:
    """The distribution whose form the QoS text a storage file holds (one entry per topic) is in: policies
    by name are the version-9 form (Jazzy or Kilted: the sourced one, else kilted), integers or nothing
    Humble's. A reindexed bag keeps that form, since the player reads the storage's copy."""
    import yaml

    def named(text: Any) -> bool:
        try:
            profiles = yaml.safe_load(text) if isinstance(text, str) else text
        except yaml.YAMLError:
            return False
        return isinstance(profiles, list) and any(
            isinstance(p, dict) and isinstance(p.get("history"), str) for p in profiles)

    if not any(named(text) for text in stored_qos):
        return "humble"
    sourced = resolve("auto", environ)
    return sourced if sourced != "humble" else "kilted"


def writer_version(distro: str) -> int:
    """The rosbags Writer version to write with (rosbags writes 8 or 9; Humble's 5 is made from 8)."""
    return 8 if distro == "humble" else 9


def offered_qos(profiles: list[Any], distro: str) -> list[Any]:
    """`profiles` (rosbags Qos) as `distro`'s rosbag2 can parse them back."""
    if distro != "humble":
        return list(profiles)
    from rosbags.interfaces import QosDurability, QosLiveliness, QosReliability, QosTime

    def duration(value: Any) -> Any:
        # Anything at or past Humble's infinity (Jazzy's is 9223372036 s) is infinite there too.
        infinite = value.sec > HUMBLE_INFINITE[0] or (value.sec, value.nsec) >= HUMBLE_INFINITE
        return QosTime(*HUMBLE_INFINITE) if infinite else value

    def known(policy: Any, enum: Any) -> Any:
        return enum(0) if policy.name.lower() == "best_available" else policy

    return [p._replace(deadline=duration(p.deadline), lifespan=duration(p.lifespan),
                    liveliness_lease_duration=duration(p.liveliness_lease_duration),
                    reliability=known(p.reliability, QosReliability), durability=known(p.durability, QosDurability),
                    liveliness=known(p.liveliness, QosLiveliness))
            for p in profiles]


def metadata(information: dict[str, Any], distro: str) -> dict[str, Any]:
    """The `rosbag2_bagfile_information` mapping (as rosbags or `reindex` write it, version 8 or 9) in
    the form `distro` reads."""
    if distro != "humble":
        return {**information, "ros_distro": distro}
    from rosbags.rosbag2.metadata import dump_qos_v8, parse_qos

    keep = ("version", "storage_identifier", "duration", "starting_time", "message_count",
            "topics_with_message_count", "compression_format", "compression_mode", "relative_file_paths", "files")
    converted = {key: information[key] for key in keep if key in information}
    converted["version"] = HUMBLE_METADATA_VERSION
    topics = []
    for entry in information.get("topics_with_message_count", []):
        topic = entry["topic_metadata"]
        qos = dump_qos_v8(offered_qos(parse_qos(topic.get("offered_qos_profiles") or ""), "humble"))
        topics.append({"topic_metadata": {"name": topic["name"], "type": topic["type"],
                                          "serialization_format": topic["serialization_format"],
                                          "offered_qos_profiles": qos},
                       "message_count": entry["message_count"]})
    converted["topics_with_message_count"] = topics
    return converted


def rewrite_metadata(bag: str | Path, distro: str) -> None:
    """Rewrite `bag`/metadata.yaml (whole or not at all) in the form `distro` reads."""
    from ruamel.yaml import YAML

    path = Path(bag) / "metadata.yaml"
    yaml = YAML(typ="safe")
    document = yaml.load(path.read_text())
    information = metadata(document["rosbag2_bagfile_information"], distro)
    write_metadata(bag, information)


def write_metadata(bag: str | Path, information: dict[str, Any]) -> None:
    from ruamel.yaml import YAML

    yaml = YAML(typ="safe")
    yaml.default_flow_style = False
    with atomic_write(Path(bag) / "metadata.yaml", "wb") as stream:
        yaml.dump({"rosbag2_bagfile_information": information}, stream)
