"""Bags that Humble's, Jazzy's and Kilted's rosbag2 read: the metadata schema each one parses.

`reader_problems` restates, per distribution, what rosbag2's metadata decoder (yaml-cpp conversions in
rosbag2_storage) and its player's QoS decoder (rosbag2_transport) require of `metadata.yaml` and of the
QoS text stored with each topic: which fields each metadata version must have and of which YAML kind,
and how offered QoS profiles are written (Humble: a string of integer policies; version 9, Jazzy on: a
list with policies by name). A bag passes when the list is empty.
"""
from __future__ import annotations

import sqlite3
import struct
from pathlib import Path

import numpy as np
import pytest
import yaml

from touchroller_bringup import bag_format
from touchroller_bringup.bag_recovery import reindex
from touchroller_bringup.bags import ImageRecord, TransformRecord, read_images, write_scan
from touchroller_bringup.cli import main
from touchroller_bringup.errors import UserError

POLICY_NAMES = {
    "history": {"system_default", "keep_last", "keep_all", "unknown"},
    "reliability": {"system_default", "reliable", "best_effort", "unknown", "best_available"},
    "durability": {"system_default", "transient_local", "volatile", "unknown", "best_available"},
    "liveliness": {"system_default", "automatic", "manual_by_topic", "unknown", "best_available"},
}
DURATIONS = ("deadline", "lifespan", "liveliness_lease_duration")
UINT32 = 2**32 - 1


def _qos_problems(profiles, by_name: bool, distro: str, where: str) -> list[str]:
    """A list of QoS profiles as the player decodes them (`convert<Rosbag2QoS>::decode`)."""
    if not isinstance(profiles, list):
        return [f"{where}: QoS profiles are not a YAML list"]
    problems = []
    for profile in profiles:
        if not isinstance(profile, dict):
            return [f"{where}: a QoS profile is not a mapping"]
        for policy, names in POLICY_NAMES.items():
            value = profile.get(policy)
            ok = value in names if by_name else isinstance(value, int) and not isinstance(value, bool)
            if not ok:
                problems.append(f"{where}: {policy} {value!r} is not {'a policy name' if by_name else 'an integer'}")
        if not isinstance(profile.get("depth"), int):
            problems.append(f"{where}: depth is not an integer")
        for key in DURATIONS:
            duration = profile.get(key)
            if not isinstance(duration, dict) or not all(isinstance(duration.get(k), int) for k in ("sec", "nsec")):
                problems.append(f"{where}: {key} is not {{sec, nsec}}")
            elif distro == "humble" and max(duration["sec"], duration["nsec"]) > UINT32:
                problems.append(f"{where}: {key} {duration} overflows Humble's 32-bit fields")
        if not isinstance(profile.get("avoid_ros_namespace_conventions"), bool):
            problems.append(f"{where}: avoid_ros_namespace_conventions is not a bool")
    return problems


def _qos_text_problems(text, version: int, distro: str, where: str) -> list[str]:
    if not isinstance(text, str):
        return [f"{where}: offered_qos_profiles is a YAML {type(text).__name__}, not a string (yaml-cpp: bad "
                "conversion)"]
    if not text:
        return []
    return _qos_problems(yaml.safe_load(text), version >= 9 and distro != "humble", distro, where)


def reader_problems(bag: Path, distro: str) -> list[str]:
    """What `distro`'s `ros2 bag info` / `ros2 bag play` would fail on in `bag` ([] when nothing)."""
    document = yaml.safe_load((bag / "metadata.yaml").read_text())
    info = document.get("rosbag2_bagfile_information")
    if not isinstance(info, dict):
        return ["no rosbag2_bagfile_information mapping"]
    version = info.get("version")
    newest = {"humble": 5, "jazzy": 9, "kilted": 9}[distro]
    if not isinstance(version, int) or not 1 <= version:
        return [f"version {version!r}"]
    problems = [] if distro == "humble" or version <= newest else [f"version {version} is newer than {newest}"]
    required: dict[str, type | tuple[type, ...]] = {
        "storage_identifier": str, "message_count": int, "relative_file_paths": list,
        "topics_with_message_count": list, "duration": dict, "starting_time": dict}
    if version >= 3:
        required.update(compression_format=str, compression_mode=str)
    if version >= 5:
        required["files"] = list
    if distro != "humble" and version >= 6:
        required["custom_data"] = (dict, type(None))
    if distro != "humble" and version >= 8:
        required["ros_distro"] = str
    for key, kind in required.items():
        if not isinstance(info.get(key), kind):
            problems.append(f"{key} is {type(info.get(key)).__name__}, not {kind}")
    for entry in info.get("topics_with_message_count") or []:
        topic = entry.get("topic_metadata", {})
        name = topic.get("name", "?")
        for key in ("name", "type", "serialization_format"):
            if not isinstance(topic.get(key), str):
                problems.append(f"{name}: {key} is not a string")
        if distro != "humble" and version >= 7 and not isinstance(topic.get("type_description_hash"), str):
            problems.append(f"{name}: type_description_hash is not a string")
        if version >= 4:
            offered = topic.get("offered_qos_profiles")
            if version >= 9 and distro != "humble":
                problems += _qos_problems(offered, True, distro, f"{name} (metadata.yaml)")
            else:
                problems += _qos_text_problems(offered, version, distro, f"{name} (metadata.yaml)")
    for name, text in _stored_qos(bag).items():    # what the player offers from: the storage's own copy
        problems += _qos_text_problems(text, version, distro, f"{name} (storage)")
    return problems


def _stored_qos(bag: Path) -> dict[str, str]:
    """topic -> offered_qos_profiles as the storage file holds it (sqlite3 topics table, MCAP channels)."""
    storage = next(p for p in bag.iterdir() if p.suffix in (".db3", ".mcap"))
    if storage.suffix == ".db3":
        with sqlite3.connect(storage) as db:
            return dict(db.execute("SELECT name, offered_qos_profiles FROM topics").fetchall())
    data, found, at = storage.read_bytes(), {}, 8     # MCAP: top-level records after the magic
    while at + 9 <= len(data):
        opcode, length = data[at], struct.unpack_from("<Q", data, at + 1)[0]
        if opcode == 0x04:                             # Channel: id, schema id, topic, encoding, metadata
            pos = at + 9 + 4
            size = struct.unpack_from("<I", data, pos)[0]
            topic = data[pos + 4:pos + 4 + size].decode()
            pos += 4 + size
            pos += 4 + struct.unpack_from("<I", data, pos)[0]
            end, pos = pos + 4 + struct.unpack_from("<I", data, pos)[0], pos + 4
            while pos < end:
                key_size = struct.unpack_from("<I", data, pos)[0]
                key = data[pos + 4:pos + 4 + key_size].decode()
                pos += 4 + key_size
                value_size = struct.unpack_from("<I", data, pos)[0]
                value = data[pos + 4:pos + 4 + value_size].decode()
                pos += 4 + value_size
                if key == "offered_qos_profiles":
                    found[topic] = value
        at += 9 + length
    assert found, f"no channel records found in {storage}"
    return found


def scan_records(n: int = 12):
    records = [TransformRecord("tool0", "touchroller_cylinder", 0, (0.0, 0.0, 0.1), (0.0, 0.0, 0.0, 1.0), True)]
    for i in range(n):
        stamp = 1_000_000_000 + i * 33_000_000
        records.append(TransformRecord("base", "tool0", stamp, (0.4 + 0.001 * i, 0.0, 0.2), (0.0, 0.0, 0.0, 1.0),
                                       False))
        records.append(ImageRecord(stamp, np.full((24, 32, 3), i, np.uint8)))
    return records


def write(bag: Path, storage: str, distro: str) -> None:
    write_scan(bag, scan_records(), storage=storage, distro=distro)


@pytest.mark.parametrize("storage", ["sqlite3", "mcap"])
@pytest.mark.parametrize("distro", bag_format.DISTROS)
def test_a_bag_written_for_a_distribution_passes_its_readers_rules(tmp_path, storage, distro):
    bag = tmp_path / "bag"
    write(bag, storage, distro)
    assert reader_problems(bag, distro) == []
    info = yaml.safe_load((bag / "metadata.yaml").read_text())["rosbag2_bagfile_information"]
    assert info["version"] == (5 if distro == "humble" else 9)
    if distro != "humble":
        assert info["ros_distro"] == distro
    static_qos = next(t["topic_metadata"]["offered_qos_profiles"] for t in info["topics_with_message_count"]
                      if t["topic_metadata"]["name"] == "/tf_static")
    assert "transient_local" in str(static_qos) if distro != "humble" else "durability: 1" in static_qos
    assert [r.stamp_ns for r in read_images(bag)] == [1_000_000_000 + i * 33_000_000 for i in range(12)]


@pytest.mark.parametrize("storage", ["sqlite3", "mcap"])
def test_humbles_form_is_read_by_every_supported_distribution_and_the_newer_form_is_not_read_by_humble(
        tmp_path, storage):
    humble, kilted = tmp_path / "humble", tmp_path / "kilted"
    write(humble, storage, "humble")
    write(kilted, storage, "kilted")
    for distro in bag_format.DISTROS:
        assert reader_problems(humble, distro) == [], distro
    problems = reader_problems(kilted, "humble")
    assert any("offered_qos_profiles is a YAML list" in p for p in problems), problems


def test_infinite_durations_and_policies_humble_lacks_are_written_as_humble_writes_them():
    from rosbags.interfaces import Qos, QosDurability, QosHistory, QosLiveliness, QosReliability, QosTime

    infinite = QosTime(9223372036, 854775807)   # Jazzy's and Kilted's infinity
    offered = Qos(QosHistory.KEEP_LAST, 10, QosReliability.BEST_AVAILABLE, QosDurability.TRANSIENT_LOCAL, infinite,
                  QosTime(1, 5), QosLiveliness.AUTOMATIC, infinite, False)
    humble = bag_format.offered_qos([offered], "humble")[0]
    assert (humble.deadline.sec, humble.deadline.nsec) == bag_format.HUMBLE_INFINITE
    assert (humble.liveliness_lease_duration.sec, humble.liveliness_lease_duration.nsec) == bag_format.HUMBLE_INFINITE
    assert (humble.lifespan.sec, humble.lifespan.nsec) == (1, 5)
    assert humble.reliability.name.lower() == "system_default"
    assert humble.durability == QosDurability.TRANSIENT_LOCAL and humble.depth == 10
    assert bag_format.offered_qos([offered], "kilted") == [offered]


@pytest.mark.parametrize("storage", ["sqlite3", "mcap"])
@pytest.mark.parametrize("distro", bag_format.DISTROS)
def test_a_killed_recording_is_reindexed_in_the_form_it_was_written_in(tmp_path, storage, distro, capsys):
    """The player offers the QoS the storage holds, so the metadata must be of the same form."""
    bag = tmp_path / "bag"
    write(bag, storage, distro)
    (bag / "metadata.yaml").unlink()
    assert main(["reindex", str(bag)]) == 0
    assert reader_problems(bag, distro) == []
    version = yaml.safe_load((bag / "metadata.yaml").read_text())["rosbag2_bagfile_information"]["version"]
    assert version == (5 if distro == "humble" else 9)
    assert len(list(read_images(bag))) == 12 and reindex(bag).message_count == 25


def test_auto_follows_the_sourced_distribution_else_the_form_all_read():
    assert bag_format.resolve("auto", {"ROS_DISTRO": "jazzy"}) == "jazzy"
    assert bag_format.resolve("auto", {"ROS_DISTRO": "rolling"}) == "humble"
    assert bag_format.resolve("auto", {}) == "humble"
    assert bag_format.resolve("Kilted") == "kilted"
    assert bag_format.stored_form(["", "history: 1"]) == "humble"
    assert bag_format.stored_form(["- history: keep_last\n  depth: 1"], {"ROS_DISTRO": "jazzy"}) == "jazzy"
    assert bag_format.stored_form(["- history: keep_last\n  depth: 1"], {}) == "kilted"
    with pytest.raises(UserError, match="unknown bag format 'iron'"):
        bag_format.resolve("iron")


@pytest.mark.ros
@pytest.mark.parametrize("distro", bag_format.DISTROS)
def test_a_recording_of_live_publishers_passes_its_readers_rules(ros_context, spin_until, tmp_path, distro):
    """The QoS a DDS publisher really offers (Fast DDS reports infinite durations as Jazzy's and Kilted's
    infinity) stored in the form each distribution reads."""
    pytest.importorskip("rclpy")
    from rclpy.executors import SingleThreadedExecutor
    from rclpy.node import Node
    from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy
    from std_msgs.msg import String

    from touchroller_bringup.recorder import Recorder

    talker = Node("talker", context=ros_context)
    latched = talker.create_publisher(String, "/touchroller/status", QoSProfile(
        depth=1, reliability=ReliabilityPolicy.RELIABLE, durability=DurabilityPolicy.TRANSIENT_LOCAL))
    latched.publish(String(data="latched"))
    recorder = Recorder(tmp_path / "bag", distro=distro, context=ros_context)
    executor = SingleThreadedExecutor(context=ros_context)
    executor.add_node(talker)
    executor.add_node(recorder)
    try:
        assert spin_until(executor, lambda: recorder.counts.get("/touchroller/status", 0) == 1, timeout=20)
    finally:
        recorder.destroy_node()
        executor.shutdown()
        talker.destroy_node()
    assert reader_problems(tmp_path / "bag", distro) == []
    stored = _stored_qos(tmp_path / "bag")["/touchroller/status"]
    assert "transient_local" in stored if distro != "humble" else "durability: 1" in stored
