"""The one check every writing command makes before any work: no output may destroy an input.

`check_outputs(outputs, inputs)` refuses, in one line (UserError), an output path that resolves
(symbolic links and `..` followed) to

- an input file, or anything inside an input folder (a bag's storage file or metadata.yaml, an image
  of a calibration folder);
- another output of the same command (`map --steps X --out X`);
- something that exists and is not what the output is: a directory, device, FIFO or socket where a
  file is written, a file where a folder is written.

The writers themselves (`touchroller_perception.files`) never rename over anything but a regular file;
this check says so before the work, and names the argument.
"""
from __future__ import annotations

import os
import stat
from collections.abc import Iterable, Mapping
from dataclasses import dataclass

from touchroller_bringup.errors import UserError
from touchroller_perception.files import file_kind

PathLike = str | os.PathLike[str]


@dataclass(frozen=True)
class Output:
    """One output of a command: what the user called it (`--out`, `--steps`, `OUT/contacts.csv`), its
    path, and whether it is a folder (a bag, a scan's output folder) rather than a file."""

    label: str
    path: PathLike
    folder: bool = False


def _resolved(path: PathLike) -> str:
    return os.path.realpath(os.fspath(path))


def _inside(path: str, folder: str) -> bool:
    return path == folder or path.startswith(folder.rstrip(os.sep) + os.sep)


def check_outputs(outputs: Iterable[Output], inputs: Mapping[str, PathLike | None] | None = None) -> None:
    """UserError (one line, before any work) when an output would destroy an input, another output, or
    something that is not a regular file (see the module docstring). `inputs`: label -> path (None:
    not given); a folder input protects everything inside it."""
    given = [(label, path) for label, path in (inputs or {}).items() if path is not None]
    resolved_inputs = [(label, os.fspath(path), _resolved(path), os.path.isdir(path)) for label, path in given]
    seen: dict[str, str] = {}
    for output in outputs:
        target = _resolved(output.path)
        name = os.fspath(output.path)
        for label, shown, source, is_folder in resolved_inputs:
            if target == source or (is_folder and _inside(target, source)):
                where = "is" if target == source else "is inside"
                raise UserError(f"{output.label} {name} {where} the input {label} {shown}: writing it would "
                                f"destroy the input; choose another path")
        for other_target, other_label in seen.items():
            if target == other_target or (output.folder and _inside(other_target, target)):
                raise UserError(f"{output.label} {name} is the same path as {other_label}: give each output "
                                "its own path")
        seen[target] = f"{output.label} {name}"
        _check_kind(output, name)


def _check_kind(output: Output, name: str) -> None:
    try:
        mode = os.stat(output.path).st_mode
    except FileNotFoundError:
        return
    except NotADirectoryError:
        raise UserError(f"{output.label} {name}: a part of the path is a file, not a folder") from None
    except OSError as exc:
        raise UserError(f"{output.label} {name}: {exc.strerror or exc}") from None
    if output.folder:
        if not stat.S_ISDIR(mode):
            raise UserError(f"{output.label} {name} is {file_kind(mode)}, not a folder; choose another path")
        return
    if stat.S_ISDIR(mode):
        raise UserError(f"{output.label} {name} is a directory; give a file name")
    if not stat.S_ISREG(mode):
        raise UserError(f"{output.label} {name} is {file_kind(mode)}, not a regular file: it is never "
                        "replaced; choose another path")
