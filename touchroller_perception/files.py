"""Output files written whole or not at all.

Every file the package writes goes through `atomic_path` or `atomic_write`: the content is written to a
temporary name in the target's folder (`.NAME.XXXXXXXX.SUFFIX`, same file system, same suffix so that
writers which pick the format from the name still do), flushed to disk, and renamed over the target
only when the writing block ends without an error. A run that fails part-way (bad input found late,
a full disk, Ctrl-C) leaves an existing output as it was and no partial file. The new file gets the
permissions of the one it replaces, else the usual ones (0666 less the umask).

Only a regular file (or nothing) is ever replaced: a directory, device, FIFO or socket at the target is
refused (`NotARegularFile`) before the temporary is made, and again just before the rename. The writer
holds a lock on its temporary while it writes; a temporary of the same output left by a process that was
killed (SIGKILL, power loss) holds no lock, and the next write of that output removes it.
"""
from __future__ import annotations

import errno
import fcntl
import os
import re
import secrets
import stat
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import IO, Any


@contextmanager
def atomic_path(path: str | os.PathLike[str]) -> Iterator[Path]:
    """A new, empty temporary file beside `path` for a writer that wants a file name (cv2.imwrite, PIL,
    matplotlib); renamed over `path` when the block ends, removed if it raises."""
    target = Path(path)
    check_replaceable(target)
    sweep_stale_temporaries(target)
    try:
        temporary, lock = _create_temporary(target)
    except OSError as exc:
        raise _about(exc, target) from None
    try:
        yield temporary
        _sync(temporary)
        check_replaceable(target)   # something else may have appeared there while this was written
        os.replace(temporary, target)
    except OSError as exc:
        temporary.unlink(missing_ok=True)
        raise _about(exc, target) from None
    except BaseException:
        temporary.unlink(missing_ok=True)
        raise
    finally:
        os.close(lock)


def _about(exc: OSError, target: Path) -> OSError:
    """The error named after the output, not its hidden temporary (a full disk while writing says no file)."""
    named = exc.filename is None or os.fspath(exc.filename) == os.fspath(target) \
        or os.path.basename(os.fspath(exc.filename)).startswith(f".{target.name}.")
    if not named or exc.errno is None:
        return exc
    return type(exc)(exc.errno, exc.strerror, os.fspath(target))


class NotARegularFile(OSError):
    """The output path names something that is not a regular file (a directory, a device, a FIFO, a
    socket): it is never replaced."""


def file_kind(mode: int) -> str:
    """What `st_mode` names, in words: "a directory", "a character device", ..."""
    for test, name in ((stat.S_ISDIR, "a directory"), (stat.S_ISCHR, "a character device"),
                       (stat.S_ISBLK, "a block device"), (stat.S_ISFIFO, "a FIFO"), (stat.S_ISSOCK, "a socket"),
                       (stat.S_ISREG, "a regular file")):
        if test(mode):
            return name
    return "not a regular file"


def check_replaceable(target: str | os.PathLike[str]) -> None:
    """NotARegularFile when `target` exists (through symbolic links) and is not a regular file."""
    try:
        mode = os.stat(target).st_mode
    except (FileNotFoundError, NotADirectoryError):
        return
    if not stat.S_ISREG(mode):
        code = errno.EISDIR if stat.S_ISDIR(mode) else errno.EEXIST
        raise NotARegularFile(code, f"it is {file_kind(mode)}, not a regular file: refusing to replace it",
                              os.fspath(target))


def _temporary_pattern(target: Path) -> re.Pattern[str]:
    return re.compile(re.escape(f".{target.name}.") + "[0-9a-f]{8}" + re.escape(target.suffix) + r"\Z")


def sweep_stale_temporaries(target: str | os.PathLike[str]) -> list[Path]:
    """Remove the temporaries of `target` that no live writer holds (left by a killed process); returns
    them. A temporary being written holds its writer's lock and is left alone."""
    target = Path(target)
    pattern = _temporary_pattern(target)
    removed: list[Path] = []
    try:
        names = [name for name in os.listdir(target.parent or ".") if pattern.match(name)]
    except OSError:
        return removed
    for name in names:
        candidate = target.parent / name
        try:
            handle = os.open(candidate, os.O_RDONLY | os.O_NOFOLLOW)
        except OSError:
            continue
        try:
            if not stat.S_ISREG(os.fstat(handle).st_mode):
                continue
            fcntl.flock(handle, fcntl.LOCK_EX | fcntl.LOCK_NB)   # held by a live writer: BlockingIOError
        except OSError:
            continue
        else:
            try:
                candidate.unlink()
                removed.append(candidate)
            except OSError:
                pass
        finally:
            os.close(handle)
    return removed


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


def _create_temporary(target: Path) -> tuple[Path, int]:
    """The temporary's path and an open handle on it that holds its lock until closed."""
    mode = target.stat().st_mode & 0o7777 if target.is_file() else 0o666
    for _ in range(100):
        temporary = target.with_name(f".{target.name}.{secrets.token_hex(4)}{target.suffix}")
        try:
            handle = os.open(temporary, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o666)   # the umask applies
        except FileExistsError:
            continue
        try:
            fcntl.flock(handle, fcntl.LOCK_EX)   # a new file: nobody else holds it
            if mode != 0o666:
                os.fchmod(handle, mode)
        except BaseException:
            os.close(handle)
            temporary.unlink(missing_ok=True)
            raise
        return temporary, handle
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
