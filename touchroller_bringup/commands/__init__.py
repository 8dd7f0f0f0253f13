"""The `touchroller` subcommands, one module each; helpers they share."""
from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING

from touchroller_bringup.errors import UserError

if TYPE_CHECKING:
    from touchroller_perception.geometry import CameraModel


def read_calibration(path: str | Path) -> CameraModel:
    """The camera model of a `--params` calibration file, or a one-line UserError."""
    from touchroller_perception.geometry import CameraModel

    if not Path(path).is_file():
        raise UserError(f"no such calibration file: {path}")
    try:
        return CameraModel.from_yaml(path)
    except Exception as exc:  # noqa: BLE001 - YAML, type and range errors all mean a bad file
        detail = str(exc) if isinstance(exc, ValueError | TypeError) else f"{type(exc).__name__}: {exc}"
        raise UserError(f"cannot read calibration {path}: {detail}") from None
