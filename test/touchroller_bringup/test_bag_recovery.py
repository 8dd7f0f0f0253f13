"""`touchroller reindex`: bags whose writer never closed them (no metadata.yaml, an MCAP file without
footer or cut off anywhere) are made readable up to their last complete record."""
from __future__ import annotations

import numpy as np
import pytest

from touchroller_bringup.bag_recovery import reindex
from touchroller_bringup.bags import read_images, write_images
from touchroller_bringup.cli import main
from touchroller_bringup.errors import UserError


def frames(n):
    return [(1_000_000_000 + i * 10_000_000, np.full((48, 64, 3), i % 256, np.uint8)) for i in range(n)]


def storage_file(bag):
    return next(p for p in bag.iterdir() if p.suffix in (".db3", ".mcap"))


@pytest.mark.parametrize("storage", ["sqlite3", "mcap"])
def test_a_bag_without_metadata_is_reindexed_whole(tmp_path, storage, capsys):
    bag = tmp_path / "bag"
    write_images(bag, frames(300), storage=storage)
    (bag / "metadata.yaml").unlink()
    assert main(["reindex", str(bag)]) == 0
    assert "300 messages (/touchroller/image_raw: 300)" in capsys.readouterr().out
    assert [r.stamp_ns for r in read_images(bag)] == [s for s, _ in frames(300)]


@pytest.mark.parametrize("fraction", [0.45, 0.6, 0.97, 0.999])
def test_an_mcap_cut_off_anywhere_keeps_its_complete_chunks(tmp_path, fraction):
    """Cut in a chunk, in the summary, in the footer: what was complete is read, in order, no more."""
    from rosbags.rosbag2 import Reader

    bag = tmp_path / "bag"
    write_images(bag, frames(300), storage="mcap")
    (bag / "metadata.yaml").unlink()
    mcap = storage_file(bag)
    size = mcap.stat().st_size
    with open(mcap, "r+b") as stream:
        stream.truncate(int(size * fraction))
    found = reindex(bag)
    kept = list(read_images(bag))
    assert 0 < len(kept) == found.message_count <= 300 and found.repaired
    assert [r.stamp_ns for r in kept] == [s for s, _ in frames(300)][:len(kept)]
    for record in kept:
        assert record.image[0, 0, 0] == (record.stamp_ns - 1_000_000_000) // 10_000_000 % 256
    with Reader(bag) as reader:   # any rosbag2 reader: rosbags reads the file without its summary
        assert reader.message_count == len(kept) == sum(1 for _ in reader.messages())
    if fraction < 0.9:
        assert len(kept) < 300
    assert not reindex(bag).repaired   # closed now: a second reindex changes nothing


def test_reindex_errors_are_one_line(tmp_path, capsys):
    assert main(["reindex", str(tmp_path / "missing")]) == 2
    (tmp_path / "empty").mkdir()
    assert main(["reindex", str(tmp_path / "empty")]) == 2
    (tmp_path / "notmcap").mkdir()
    (tmp_path / "notmcap" / "notmcap.mcap").write_bytes(b"hello, not an MCAP file")
    assert main(["reindex", str(tmp_path / "notmcap")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 3 and all(line.startswith("touchroller: error: ") for line in err), err
    assert "no such bag folder" in err[0] and "no .db3 or .mcap" in err[1] and "not an MCAP file" in err[2]
    with pytest.raises(UserError, match="empty"):
        (tmp_path / "zero").mkdir()
        (tmp_path / "zero" / "zero.mcap").write_bytes(b"")
        reindex(tmp_path / "zero")


@pytest.mark.parametrize("storage", ["sqlite3", "mcap"])
def test_a_split_bag_is_reindexed_file_by_file_in_split_order(tmp_path, storage):
    """rosbag2 splits a long recording into NAME_0 ... NAME_10: metadata.yaml lists them in that order
    (not as text, where _10 comes before _2), each with its own message count, start and duration."""
    from rosbags.rosbag2 import Reader
    from ruamel.yaml import YAML

    bag = tmp_path / "split"
    bag.mkdir()
    stamps = [s for s, _ in frames(33)]
    for part in range(11):
        piece = tmp_path / f"piece{part}"
        write_images(piece, frames(33)[3 * part:3 * part + 3], storage=storage)
        storage_file(piece).rename(bag / f"split_{part}{storage_file(piece).suffix}")
    found = reindex(bag)
    assert found.message_count == 33
    info = YAML(typ="safe").load((bag / "metadata.yaml").read_text())["rosbag2_bagfile_information"]
    suffix = ".db3" if storage == "sqlite3" else ".mcap"
    assert info["relative_file_paths"] == [f"split_{part}{suffix}" for part in range(11)]
    assert [f["message_count"] for f in info["files"]] == [3] * 11
    assert [f["starting_time"]["nanoseconds_since_epoch"] for f in info["files"]] == stamps[::3]
    assert all(f["duration"]["nanoseconds"] == stamps[2] - stamps[0] for f in info["files"])
    assert [r.stamp_ns for r in read_images(bag)] == stamps
    with Reader(bag) as reader:
        assert [timestamp for _, timestamp, _ in reader.messages()] == stamps


@pytest.mark.parametrize("command", ["map", "contacts"])
def test_a_bag_without_metadata_names_reindex_as_the_way_out(tmp_path, capsys, command):
    bag = tmp_path / "bag"
    write_images(bag, frames(20))
    (bag / "metadata.yaml").unlink()
    out = tmp_path / ("map.png" if command == "map" else "contacts.csv")
    assert main([command, str(bag), "--out", str(out)]) == 2
    error = capsys.readouterr().err.strip()
    assert len(error.splitlines()) == 1 and f"touchroller reindex {bag}" in error
    assert main(["reindex", str(bag)]) == 0


def test_reindex_of_a_bag_on_a_read_only_disk_is_one_line_saying_what_to_do(bag_factory, mount_tmpfs, capsys):
    """#28: raw OSError for a bag in a read-only folder."""
    import shutil
    import subprocess

    import numpy as np

    from touchroller_bringup.cli import main

    bag = bag_factory([(k, np.zeros((8, 8, 3), np.uint8)) for k in range(3)])
    folder = mount_tmpfs("1m")
    shutil.copytree(bag, folder / "bag")
    (folder / "bag" / "metadata.yaml").unlink()
    if subprocess.run(["mount", "-o", "remount,ro", str(folder)], check=False).returncode != 0:
        pytest.skip("cannot remount the tmpfs read-only")
    assert main(["reindex", str(folder / "bag")]) == 2
    err = capsys.readouterr().err.strip()
    assert "\n" not in err and "copy the bag" in err and "metadata.yaml" in err, err


@pytest.mark.parametrize("damage", ["garbage", "zeros"])
def test_a_compressed_mcap_whose_last_chunk_was_overwritten_keeps_the_chunks_before(tmp_path, damage):
    """A full disk can leave a zstd chunk of the right length whose bytes are not what was written: it
    does not decompress (or not to its CRC). Reindex keeps the chunks before it instead of failing."""
    from touchroller_bringup.bag_compression import compress_recording
    from touchroller_bringup.bag_recovery import OP_CHUNK, _records

    rng = np.random.default_rng(0)
    noisy = [(s, rng.integers(0, 256, (48, 64, 3), dtype=np.uint8)) for s, _ in frames(300)]
    write_images(tmp_path / "raw", noisy, storage="mcap")
    bag = tmp_path / "bag"
    compress_recording(tmp_path / "raw", bag)
    (bag / "metadata.yaml").unlink()
    mcap = storage_file(bag)
    data = bytearray(mcap.read_bytes())
    chunks = [(content, stop) for op, _start, content, stop in _records(bytes(data), 8, len(data)) if op == OP_CHUNK]
    assert len(chunks) >= 2
    content, stop = chunks[-1]
    middle = (content + stop) // 2
    data[middle:middle + 64] = rng.integers(0, 256, 64, dtype=np.uint8).tobytes() if damage == "garbage" \
        else bytes(64)
    mcap.write_bytes(bytes(data[:stop]))   # cut after the damaged chunk, as a failed write leaves it
    found = reindex(bag)
    kept = list(read_images(bag))
    assert 0 < len(kept) == found.message_count < 300 and found.repaired
    for record, (stamp, image) in zip(kept, noisy, strict=False):
        assert record.stamp_ns == stamp and np.array_equal(record.image, image)
