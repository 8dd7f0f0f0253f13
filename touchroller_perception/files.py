"""Output files written whole or not at all.

Every file the package writes goes through `atomic_path` or `atomic_write`: the content is written to a
temporary name in the target's folder (`.NAME.XXXXXXXX.SUFFIX`, same file system, same suffix so that
writers which pick the format from the name still do), flushed to disk, and renamed over the target
only when the writing block ends without an error. A run that fails part-way (bad input found late,
a full disk, Ctrl-C) leaves an existing output as it was and no partial file. The new file gets the
permissions of the one it replaces, else the usual ones (0666 less the umask).
"""
from __future__ import annotations

import os
import secrets
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import IO, Any


@contextmanager
def atomic_path(path: str | os.PathLike[str]) -> Iterator[Path]:
    """A new, empty temporary file beside `path` for a writer that wants a file name (cv2.imwrite, PIL,
    matplotlib); renamed over `path` when the block ends, removed if it raises."""
    target = Path(path)
    temporary = _create_temporary(target)
    try:
        yield temporary
        _sync(temporary)
        os.replace(temporary, target)
    except BaseException:
        temporary.unlink(missing_ok=True)
        raise


@contextmanager
def atomic_write(path: str | os.PathLike[str], mode: str = "w", **open_kwargs: Any) -> Iterator[IO[Any]]:
    """`open(path, mode)` that replaces `path` only when the block ends without an error ("w" or "wb")."""
    if mode not in ("w", "wb"):
        raise ValueError(f"atomic_write writes a whole file: mode 'w' or 'wb', got {mode!r}")
    if mode == "w":
        open_kwargs.setdefault("encoding", "utf-8")
    with atomic_path(path) as temporary, open(temporary, mode, **open_kwargs) as stream:
        yield stream


def atomic_write_text(path: str | os.PathLike[str], text: str, encoding: str = "utf-8") -> None:
    """`Path.write_text`, whole or not at all."""
    with atomic_write(path, "w", encoding=encoding) as stream:
        stream.write(text)


def _create_temporary(target: Path) -> Path:
    mode = target.stat().st_mode & 0o7777 if target.is_file() else 0o666
    for _ in range(100):
        temporary = target.with_name(f".{target.name}.{secrets.token_hex(4)}{target.suffix}")
        try:
            handle = os.open(temporary, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o666)   # the umask applies
        except FileExistsError:
            continue
        try:
            if mode != 0o666:
                os.fchmod(handle, mode)
        finally:
            os.close(handle)
        return temporary
    raise FileExistsError(f"no free temporary name beside {target}")


def _sync(path: Path) -> None:
    """The data on disk before the rename, so a crash right after it cannot leave an empty file."""
    handle = os.open(path, os.O_RDONLY)
    try:
        os.fsync(handle)
    finally:
        os.close(handle)


@contextmanager
def new_directory(path: str | os.PathLike[str]) -> Iterator[Path]:
    """For an output that is a new folder (a recording and its side files): a path of the same name inside
    a hidden staging folder beside `path` (not created: writers such as rosbags' make it themselves, and
    name their files after it), moved to `path` when the block ends; removed with everything in it if the
    block raises. The folder appears whole or not at all."""
    import shutil

    target = Path(path)
    if target.exists():
        raise FileExistsError(f"{target} already exists")
    staging = target.with_name(f".{target.name}.{secrets.token_hex(4)}.partial")
    staging.mkdir()
    try:
        yield staging / target.name
        os.rename(staging / target.name, target)
        staging.rmdir()
    except BaseException:
        shutil.rmtree(staging, ignore_errors=True)
        raise
