"""The image inputs the offline commands share: an image folder, one image file or a rosbag2 recording."""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any

from touchroller_bringup.errors import UserError

IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg", ".bmp", ".tif", ".tiff")


@dataclass(frozen=True)
class InputImage:
    key: str      # how a labels file names it: the file's name, or in a recording its index on the topic
    stem: str     # how an output per image is named: the file's stem, or in a recording its stamp in ns
    image: Any    # as decoded (OpenCV's channel order for files, the message's for a recording)


@dataclass(frozen=True)
class InputImages:
    images: list[InputImage]
    from_recording: bool


def read_input_images(path: Path, topic: str) -> InputImages:
    """The images of a folder (sorted by name, png/jpg/bmp/tif), a file or a recording's `topic`; one-line
    UserErrors for a missing input, an empty folder or a recording without the topic's images."""
    import cv2

    if not path.exists():
        raise UserError(f"no such input: {path}")
    if path.is_dir() and not (path / "metadata.yaml").exists():
        files = sorted(p for p in path.iterdir() if p.suffix.lower() in IMAGE_SUFFIXES)
        if not files:
            raise UserError(f"{path}: no images ({', '.join(IMAGE_SUFFIXES)}) and no rosbag2 metadata.yaml")
        return InputImages([InputImage(f.name, f.stem, read_image(f, cv2)) for f in files], False)
    if path.is_file() and path.suffix.lower() in IMAGE_SUFFIXES:
        return InputImages([InputImage(path.name, path.stem, read_image(path, cv2))], False)
    from touchroller_bringup.bags import read_images

    images = [InputImage(str(i), str(record.stamp_ns), record.image)
              for i, record in enumerate(read_images(path, topic))]
    if not images:
        raise UserError(f"recording {path} has no images on {topic}")
    return InputImages(images, True)


def read_image(path: Path, cv2: Any, label: str = "") -> Any:
    """One image file as OpenCV decodes it (unchanged depth and channels); a one-line UserError otherwise."""
    # checked first: OpenCV prints a WARN line of its own for a file it cannot open
    name = f"{label} {path}" if label else str(path)
    if not path.is_file():
        raise UserError(f"cannot read image {name}: " + ("no such file" if not path.exists() else "not a file"))
    image = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if image is None:
        raise UserError(f"cannot read image {name}: not an image OpenCV can decode")
    return image
