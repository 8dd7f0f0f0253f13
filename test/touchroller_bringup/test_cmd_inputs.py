"""The offline commands' shared image input: folder, file, errors (recordings: test_cmd_calibrate/height)."""
from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest

from touchroller_bringup.commands.inputs import read_input_images
from touchroller_bringup.errors import UserError


def _write(path: Path, value: int) -> None:
    assert cv2.imwrite(str(path), np.full((4, 5, 3), value, np.uint8))


def test_a_folder_is_read_in_name_order_with_keys_and_stems(tmp_path: Path) -> None:
    for name, value in (("b.png", 2), ("a.png", 1), ("c.bmp", 3)):
        _write(tmp_path / name, value)
    (tmp_path / "notes.txt").write_text("not an image")
    found = read_input_images(tmp_path, "/unused")
    assert not found.from_recording
    assert [(i.key, i.stem, int(i.image[0, 0, 0])) for i in found.images] == [("a.png", "a", 1), ("b.png", "b", 2),
                                                                              ("c.bmp", "c", 3)]


def test_one_file_is_one_image(tmp_path: Path) -> None:
    _write(tmp_path / "press.png", 7)
    found = read_input_images(tmp_path / "press.png", "/unused")
    assert [(i.key, i.stem) for i in found.images] == [("press.png", "press")] and not found.from_recording


@pytest.mark.parametrize("make, message", [
    (lambda d: d / "missing", "no such input"),
    (lambda d: d, "no images"),
])
def test_bad_inputs_are_one_line(tmp_path: Path, make, message: str) -> None:
    with pytest.raises(UserError, match=message) as error:
        read_input_images(make(tmp_path), "/unused")
    assert "\n" not in str(error.value)


def test_an_undecodable_image_is_one_line(tmp_path: Path) -> None:
    (tmp_path / "broken.png").write_bytes(b"not a png")
    with pytest.raises(UserError, match="not an image OpenCV can decode"):
        read_input_images(tmp_path, "/unused")
