"""No output destroys an input (#28 group 1): the shared check every writing command makes before any
work, and the writers' own refusal to rename over anything but a regular file."""
from __future__ import annotations

import os
import stat

import numpy as np
import pytest

from touchroller_bringup.cli import main
from touchroller_bringup.errors import UserError
from touchroller_bringup.outputs import Output, check_outputs
from touchroller_perception.files import NotARegularFile, atomic_write_text


@pytest.fixture
def small_bag(bag_factory):
    rng = np.random.default_rng(0)
    return bag_factory([(k * 33_000_000, rng.integers(0, 255, (24, 32, 3), np.uint8)) for k in range(8)])


def _storage(bag):
    return next(p for p in bag.iterdir() if p.suffix == ".db3")


def _bag_snapshot(bag):
    return {p.name: p.read_bytes() for p in sorted(bag.iterdir())}


def _one_line_refusal(capsys, code):
    assert code == 2
    err = capsys.readouterr().err.strip()
    assert "\n" not in err and "Traceback" not in err
    return err


def test_contacts_into_the_bags_storage_file_is_refused_and_the_bag_is_intact(small_bag, capsys):
    before = _bag_snapshot(small_bag)
    err = _one_line_refusal(capsys, main(["contacts", str(small_bag), "--out", str(_storage(small_bag))]))
    assert "destroy the input" in err and "BAG" in err
    assert _bag_snapshot(small_bag) == before


def test_contacts_over_the_bags_metadata_through_a_relative_path_is_refused(small_bag, capsys, monkeypatch):
    monkeypatch.chdir(small_bag)
    before = _bag_snapshot(small_bag)
    err = _one_line_refusal(capsys, main(["contacts", str(small_bag), "--out", "../" + small_bag.name
                                                                                + "/./metadata.yaml"]))
    assert "inside the input BAG" in err
    assert _bag_snapshot(small_bag) == before


def test_map_with_steps_and_out_the_same_file_is_refused(small_bag, tmp_path, capsys):
    out = tmp_path / "x.png"
    err = _one_line_refusal(capsys, main(["map", str(small_bag), "--out", str(out), "--steps", str(out),
                                          "--strip"]))
    assert "same path" in err and "--steps" in err
    assert not out.exists()


def test_calibrate_intrinsics_over_the_bags_metadata_is_refused(small_bag, capsys):
    before = _bag_snapshot(small_bag)
    err = _one_line_refusal(capsys, main(["calibrate", "intrinsics", str(small_bag), "--out",
                                          str(small_bag / "metadata.yaml")]))
    assert "INPUT" in err
    assert _bag_snapshot(small_bag) == before


def test_a_device_is_refused_by_the_check_and_never_replaced_by_the_writer(small_bag, tmp_path, capsys):
    """#28: as root, --out /dev/full replaced the device node with a regular file. A private node of the same
    device here (never the system's own)."""
    device = tmp_path / "full"
    try:
        os.mknod(device, 0o666 | stat.S_IFCHR, os.makedev(1, 7))
    except OSError as exc:
        pytest.skip(f"cannot make a device node here: {exc.strerror}")
    err = _one_line_refusal(capsys, main(["contacts", str(small_bag), "--out", str(device)]))
    assert "character device" in err
    assert stat.S_ISCHR(os.stat(device).st_mode)
    with pytest.raises(NotARegularFile):      # the writer alone refuses it too (as root the rename would work)
        atomic_write_text(device, "x")
    assert stat.S_ISCHR(os.stat(device).st_mode)


def test_a_fifo_is_refused_and_stays_a_fifo(small_bag, tmp_path, capsys):
    fifo = tmp_path / "pipe.csv"
    os.mkfifo(fifo)
    err = _one_line_refusal(capsys, main(["contacts", str(small_bag), "--out", str(fifo)]))
    assert "FIFO" in err
    assert stat.S_ISFIFO(os.stat(fifo).st_mode)
    with pytest.raises(NotARegularFile):
        atomic_write_text(fifo, "x")
    assert stat.S_ISFIFO(os.stat(fifo).st_mode)
    assert [p.name for p in tmp_path.iterdir() if p.name.startswith(".")] == []


def test_a_directory_where_a_file_is_written_is_refused(small_bag, tmp_path, capsys):
    folder = tmp_path / "folder"
    folder.mkdir()
    err = _one_line_refusal(capsys, main(["contacts", str(small_bag), "--out", str(folder)]))
    assert "directory" in err


def test_the_check_itself(tmp_path):
    data = tmp_path / "in.csv"
    data.write_text("x")
    link = tmp_path / "link.csv"
    link.symlink_to(data)
    with pytest.raises(UserError, match="is the input"):
        check_outputs([Output("--out", link)], {"IN": data})
    with pytest.raises(UserError, match="same path"):
        check_outputs([Output("--a", tmp_path / "o"), Output("--b", tmp_path / "." / "o")])
    # a folder output around an input is fine: the files written in it are checked one by one
    check_outputs([Output("--out", tmp_path, folder=True)], {"IN": data})
    with pytest.raises(UserError, match="is the input"):
        check_outputs([Output("--out", tmp_path, folder=True), Output("OUT's", data)], {"IN": data})
    with pytest.raises(UserError, match="not a folder"):
        check_outputs([Output("--out", data, folder=True)])
    check_outputs([Output("--out", tmp_path / "new.csv")], {"IN": data, "none": None})   # fine: no error
