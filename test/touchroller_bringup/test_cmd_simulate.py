"""`touchroller simulate`: its output is a new bag folder, whole or not at all; a disk that cannot take it
is one line naming --out."""
from __future__ import annotations

import pytest

from touchroller_bringup.cli import main

SHORT = ["--set", "motion.duration=3"]


@pytest.mark.parametrize("storage", ["sqlite3", "mcap"])
def test_a_full_disk_is_one_line_and_leaves_nothing(mount_tmpfs, storage, capsys):
    """#28: raw OperationalError (sqlite3) or OSError (MCAP) on a full disk."""
    folder = mount_tmpfs("16k", free_bytes=2048)
    assert main(["simulate", "surface_mapping", "--out", str(folder / "bag"), "--storage", storage, *SHORT]) == 2
    err = capsys.readouterr().err.strip()
    assert "\n" not in err and "Error:" not in err and f"--out {folder / 'bag'}" in err, err
    assert sorted(p.name for p in folder.iterdir()) == [".filler"]


def test_a_read_only_folder_is_refused_before_the_render(mount_tmpfs, capsys):
    folder = mount_tmpfs("16k", read_only=True)
    assert main(["simulate", "surface_mapping", "--out", str(folder / "bag"), *SHORT]) == 2
    assert "is not writable" in capsys.readouterr().err


def test_an_existing_output_is_refused(tmp_path, capsys):
    (tmp_path / "bag").mkdir()
    assert main(["simulate", "surface_mapping", "--out", str(tmp_path / "bag"), *SHORT]) == 2
    assert "already exists" in capsys.readouterr().err
