"""Hostile probes of recordings killed outright (#28 group 7): `touchroller record` SIGKILLed while the
simulated camera streams 30 Hz, with the machine made busy, must keep everything but its last second.

A SIGKILL runs no handler: what survives is what the writer had committed. The recorder commits by the
messages' arrival age (`recorder.COMMIT_AGE_S`), so the loss is bounded by that age plus one commit even
when the writer falls behind; the probe measures it as the time from the last message the bag kept (its
receive stamp, which the recorder takes on arrival) to the kill.
"""
from __future__ import annotations

import multiprocessing
import random
import signal
import subprocess
import time
from pathlib import Path

from bench.hostile import _kit as kit
from bench.hostile.arm import BIN, _domain
from bench.hostile.probe import Probe

KILLS = 5
LOSS_LIMIT_S = 1.0
BUSY_PROCESSES = 2      # as many as the cores of the machines this runs on: the commit timer has to compete


def _busy() -> None:
    while True:
        pass


def _kept_until(bag: Path) -> float | None:
    """The receive time (s) of the last image a killed bag kept, after `touchroller reindex`; None if none."""
    from rosbags.rosbag2 import Reader

    done = kit.touchroller("reindex", bag)
    if done.returncode != 0:
        return None
    with Reader(bag) as reader:
        stamps = [timestamp for _, timestamp, _ in reader.messages()]
    return max(stamps) / 1e9 if stamps else None


def _killed_recording_loss(storage: str):
    def check(scratch: Path) -> str | None:
        losses: list[float] = []
        busy = [multiprocessing.Process(target=_busy, daemon=True) for _ in range(BUSY_PROCESSES)]
        for process in busy:
            process.start()
        try:
            with _domain() as env:
                camera = subprocess.Popen([str(BIN / "camera_node"), "--ros-args", "-p", "source:=sim",
                                           "-p", "loop:=true", "-p", "fps:=30.0"], env=env,
                                          stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
                try:
                    if not _camera_streams(scratch / "warm_up", env):
                        return "the simulated camera published nothing within 120 s"
                    for k in range(KILLS):
                        loss = _one_kill(scratch / f"bag{k}", storage, env)
                        if isinstance(loss, str):
                            return f"kill {k + 1}: {loss}"
                        losses.append(loss)
                finally:
                    camera.send_signal(signal.SIGINT)
                    try:
                        camera.wait(timeout=20)
                    except subprocess.TimeoutExpired:
                        camera.kill()
        finally:
            for process in busy:
                process.kill()
        worst = max(losses)
        return None if worst <= LOSS_LIMIT_S else \
            f"lost up to {worst:.2f} s (losses {', '.join(f'{v:.2f}' for v in losses)} s)"
    return check


def _camera_streams(bag: Path, env: dict[str, str]) -> bool:
    """Whether a short recording gets images (the camera loads its scene first, slowly on a busy machine)."""
    import sys

    deadline = time.monotonic() + 120
    for attempt in range(1000):
        if time.monotonic() > deadline:
            return False
        done = subprocess.run([sys.executable, "-m", "touchroller_bringup.cli", "record", "--out",
                               str(bag.with_name(f"{bag.name}{attempt}")), "--duration", "2",
                               "--topics", "/touchroller/image_raw"],
                              env=env, capture_output=True, text=True, timeout=120)
        if done.returncode == 0 and "recorded 0 messages" not in done.stdout and "recorded" in done.stdout:
            return True
    return False


def _one_kill(bag: Path, storage: str, env: dict[str, str]) -> float | str:
    import sys
    import threading

    recorder = subprocess.Popen([sys.executable, "-m", "touchroller_bringup.cli", "record", "--out", str(bag),
                                 "--storage", storage, "--topics", "/touchroller/image_raw"], env=env,
                                stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
    log: list[str] = []
    reader = threading.Thread(target=lambda: log.extend(recorder.stderr), daemon=True)   # type: ignore[arg-type]
    reader.start()
    # recording for a while, counted from its subscription to the images (the recorder logs it once it has
    # found the camera's publisher; discovery on a machine this busy can take longer than the window)
    if not kit.wait_for(lambda: any("recording /touchroller/image_raw" in line for line in log)
                        or recorder.poll() is not None, 60):
        recorder.kill()
        return "the recorder never subscribed to the images"
    time.sleep(3.0 + random.uniform(0.0, 2.0))
    if recorder.poll() is not None:
        reader.join(5)
        return f"the recorder exited {recorder.returncode}: {''.join(log).strip()[-200:]}"
    killed_at = time.time()
    recorder.kill()
    recorder.wait(timeout=30)
    reader.join(5)
    kept = _kept_until(bag)
    if kept is None:
        return "nothing recovered"
    return killed_at - kept


def probes() -> list[Probe]:
    return [
        Probe("SIGKILL of record (sqlite3) under load", "recordings",
              f"the bag keeps all but the last {LOSS_LIMIT_S:.0f} s: {KILLS} kills while the simulated camera "
              f"streams 30 Hz and {BUSY_PROCESSES} busy processes compete, reindexed",
              _killed_recording_loss("sqlite3")),
        Probe("SIGKILL of record (mcap) under load", "recordings",
              f"the bag keeps all but the last {LOSS_LIMIT_S:.0f} s (as sqlite3)", _killed_recording_loss("mcap")),
    ]
