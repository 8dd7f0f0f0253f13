"""What the hostile probe modules share: running `touchroller` and the node scripts as a user does, small
bags made on the spot, tmpfs mounts, and the usual verdicts (one line, an exit code, nothing left behind)."""
from __future__ import annotations

import os
import signal
import subprocess
import sys
import tempfile
import time
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from bench._common import ROOT

BIN = Path(sys.executable).parent
_NEUTRAL = Path(tempfile.gettempdir())


def popen(args: list[str], **kwargs) -> subprocess.Popen:
    """`python -m touchroller_bringup.cli ARGS` started (not waited for), as `touchroller` runs."""
    return subprocess.Popen([sys.executable, "-m", "touchroller_bringup.cli", *args], cwd=_NEUTRAL,
                            env=_env(), **kwargs)


def touchroller(*args: object, cwd: Path | None = None, timeout: float = 120.0) -> subprocess.CompletedProcess:
    # never the checkout as the working directory: `-m` puts it first on sys.path, before HOSTILE_CODE
    return subprocess.run([sys.executable, "-m", "touchroller_bringup.cli", *map(str, args)], cwd=cwd or _NEUTRAL,
                          capture_output=True, text=True, timeout=timeout, env=_env())


def node(script: str, *ros_args: str, cwd: Path | None = None,
         timeout: float = 60.0) -> subprocess.CompletedProcess:
    """A node's console script with `--ros-args ...`; a node still running after `timeout` is stopped with
    SIGINT and its result returned with returncode None-like -999 in `returncode`."""
    process = subprocess.Popen([str(BIN / script), "--ros-args", *ros_args], cwd=cwd or _NEUTRAL,
                               stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=_env())
    try:
        out, err = process.communicate(timeout=timeout)
        return subprocess.CompletedProcess(process.args, process.returncode, out, err)
    except subprocess.TimeoutExpired:
        process.send_signal(signal.SIGINT)
        out, err = process.communicate(timeout=30)
        return subprocess.CompletedProcess(process.args, -999, out, err)


def _env() -> dict[str, str]:
    """The commands' environment: this checkout's code, or HOSTILE_CODE's (another checkout, e.g. to see the
    probes fail on code from before the fixes)."""
    code = os.environ.get("HOSTILE_CODE", str(ROOT))
    env = dict(os.environ, PYTHONPATH=os.pathsep.join(filter(None, [code, os.environ.get("PYTHONPATH")])))
    env.pop("TOUCHROLLER_DEBUG", None)
    env.setdefault("ROS_AUTOMATIC_DISCOVERY_RANGE", "LOCALHOST")
    return env


def one_line(done: subprocess.CompletedProcess, code: int | Sequence[int] = 2, *words: str) -> str | None:
    """None when the run exited with `code` and said one stderr line holding every word, without a traceback."""
    codes = (code,) if isinstance(code, int) else tuple(code)
    lines = [line for line in done.stderr.splitlines() if line.strip()]
    if done.returncode == -999:
        return f"still running after its time: {' / '.join(lines[-2:]) or 'no output'}"
    if "Traceback" in done.stderr:
        return f"a traceback (exit {done.returncode}): {lines[-1] if lines else ''}"
    if done.returncode not in codes:
        return f"exit {done.returncode}, expected {codes}: {' / '.join(lines[-2:]) or done.stdout.strip()[-200:]}"
    if len(lines) != 1:
        return f"{len(lines)} stderr lines: {' / '.join(lines[:3])}"
    missing = [w for w in words if w not in lines[0]]
    return f"the line does not say {missing}: {lines[0]}" if missing else None


def bag(folder: Path, frames: int = 8, shape: tuple[int, ...] = (24, 32, 3), storage: str = "sqlite3",
        name: str = "bag") -> Path:
    from touchroller_bringup.bags import write_images

    rng = np.random.default_rng(0)
    path = folder / name
    write_images(path, [(1_000_000_000 + k * 33_000_000, rng.integers(0, 255, shape, np.uint8))
                        for k in range(frames)], storage=storage)
    return path


def tf_bag(folder: Path, frames: int = 20, static: bool = True, tf: bool = True, tf_offset_ns: int = 0,
           loop: bool = False, name: str = "tfbag") -> tuple[Path, Path]:
    """A recording with images at the default camera size and TF (base -> tool0 moving on /tf, the mount
    tool0 -> touchroller_cylinder on /tf_static), and the calibration file for it."""
    from touchroller_bringup.bags import ImageRecord, TransformRecord, write_scan
    from touchroller_perception.geometry import CameraModel

    camera = CameraModel()
    rng = np.random.default_rng(0)
    identity = (0.0, 0.0, 0.0, 1.0)
    records: list = []
    if static:
        records.append(TransformRecord("tool0", "touchroller_cylinder", 0, (0.0, 0.0, 0.0), identity, True))
        if loop:
            records.append(TransformRecord("touchroller_cylinder", "tool0", 0, (0.0, 0.0, 0.0), identity, True))
    for k in range(frames):
        stamp = 1_000_000_000 + k * 33_000_000
        if tf:
            records.append(TransformRecord("base", "tool0", stamp + tf_offset_ns, (0.001 * k, 0.0, 0.0), identity,
                                           False))
        records.append(ImageRecord(stamp, rng.integers(0, 255, (camera.height, camera.width, 3), np.uint8)))
    path = folder / name
    write_scan(path, records)
    params = folder / f"{name}_cal.yaml"
    camera.to_yaml(params)
    return path, params


def snapshot(folder: Path) -> dict[str, bytes]:
    return {p.name: p.read_bytes() for p in sorted(folder.iterdir()) if p.is_file()}


def hidden(folder: Path, keep: Sequence[str] = ()) -> list[str]:
    return sorted(p.name for p in folder.iterdir() if p.name.startswith(".") and p.name not in keep)


class Mount:
    """A tmpfs mounted for one probe (`with Mount(folder, "16k") as point:`); None when mounting is refused."""

    def __init__(self, folder: Path, size: str = "16k", read_only: bool = False, free_bytes: int | None = None):
        self.point = folder / "tmpfs"
        self.size, self.read_only, self.free_bytes = size, read_only, free_bytes
        self.mounted = False

    def __enter__(self) -> Path | None:
        self.point.mkdir()
        options = f"size={self.size}" + (",ro" if self.read_only else "")
        self.mounted = subprocess.run(["mount", "-t", "tmpfs", "-o", options, "tmpfs", str(self.point)],
                                      capture_output=True, check=False).returncode == 0
        if self.mounted and self.free_bytes is not None:
            stats = os.statvfs(self.point)
            with open(self.point / ".filler", "wb", buffering=0) as stream:
                try:
                    stream.write(b"\0" * max(stats.f_bavail * stats.f_frsize - self.free_bytes, 0))
                except OSError:
                    pass
        return self.point if self.mounted else None

    def __exit__(self, *exc: object) -> None:
        if self.mounted:
            subprocess.run(["umount", "-l", str(self.point)], check=False)


NO_MOUNT = "not run: cannot mount a tmpfs here (needs root with the mount capability)"


def wait_for(predicate, timeout: float) -> bool:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if predicate():
            return True
        time.sleep(0.02)
    return False


def children(pid: int) -> list[int]:
    found = []
    for entry in Path("/proc").iterdir():
        if entry.name.isdigit():
            try:
                stat = (entry / "stat").read_text()
            except OSError:
                continue
            if int(stat.rsplit(")", 1)[1].split()[1]) == pid:
                found.append(int(entry.name))
    return found


def alive(pid: int) -> bool:
    try:
        stat = Path(f"/proc/{pid}/stat").read_text()
    except OSError:
        return False
    return stat.rsplit(")", 1)[1].split()[0] != "Z"
