"""Output files are written whole or not at all."""
from __future__ import annotations

import os
import stat

import pytest

from touchroller_perception.files import atomic_path, atomic_write, atomic_write_text


def test_a_failing_write_leaves_the_old_file_and_no_temporary(tmp_path):
    out = tmp_path / "contacts.csv"
    out.write_text("old\n")
    with pytest.raises(RuntimeError, match="late"), atomic_write(out) as stream:
        stream.write("new, half written")
        raise RuntimeError("bad input found late")
    assert out.read_text() == "old\n"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["contacts.csv"]


def test_nothing_appears_until_the_block_ends(tmp_path):
    out = tmp_path / "report.md"
    with atomic_write(out) as stream:
        stream.write("whole")
        stream.flush()
        assert not out.exists()
    assert out.read_text() == "whole"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["report.md"]


def test_a_writer_that_takes_a_name_gets_one_with_the_targets_suffix(tmp_path):
    import cv2
    import numpy as np

    out = tmp_path / "map.png"
    with atomic_path(out) as temporary:
        assert temporary.parent == tmp_path and temporary.suffix == ".png" and temporary.name.startswith(".map.png.")
        assert cv2.imwrite(str(temporary), np.full((4, 5), 7, np.uint8))
    assert cv2.imread(str(out), cv2.IMREAD_UNCHANGED).shape == (4, 5)
    assert [p.name for p in tmp_path.iterdir()] == ["map.png"]


def test_permissions_are_the_replaced_files_or_the_usual_ones(tmp_path):
    kept = tmp_path / "kept.yaml"
    kept.write_text("a: 1\n")
    kept.chmod(0o640)
    atomic_write_text(kept, "a: 2\n")
    assert stat.S_IMODE(kept.stat().st_mode) == 0o640 and kept.read_text() == "a: 2\n"

    umask = os.umask(0o022)
    os.umask(umask)
    new = tmp_path / "new.yaml"
    atomic_write_text(new, "b: 1\n")
    assert stat.S_IMODE(new.stat().st_mode) == 0o666 & ~umask


def test_only_whole_file_modes(tmp_path):
    with pytest.raises(ValueError, match="mode"), atomic_write(tmp_path / "x", "a"):
        pass
    assert not list(tmp_path.iterdir())


def test_a_new_folder_appears_whole_or_not_at_all(tmp_path):
    from touchroller_perception.files import new_directory

    with pytest.raises(RuntimeError), new_directory(tmp_path / "bag") as folder:
        folder.mkdir()
        (folder / "bag.db3").write_bytes(b"half")
        raise RuntimeError("Ctrl-C while rendering")
    assert not list(tmp_path.iterdir())
    with new_directory(tmp_path / "bag") as folder:
        assert folder.name == "bag" and not folder.exists()
        folder.mkdir()
        (folder / "bag.db3").write_bytes(b"whole")
    assert [p.name for p in tmp_path.iterdir()] == ["bag"] and (tmp_path / "bag" / "bag.db3").read_bytes() == b"whole"
    with pytest.raises(FileExistsError), new_directory(tmp_path / "bag"):
        pass
