"""Camera frame sources behind one interface: a V4L2 webcam, a video file, the simulator, a recording.

No rclpy here: the camera node wraps a `FrameSource`, and so can tests and `touchroller scan`.

Every source hands out `Frame(stamp_ns, image, seq)`: `image` is an HxWx3 bgr8 uint8 array,
`stamp_ns` is the capture time (from the source's `clock_ns`, wall-clock ns by default, so a
ROS node can pass its own clock), and `seq` counts captured frames, so a gap in `seq` is a drop.
"""
from __future__ import annotations

import os
import threading
import time
from collections.abc import Callable, Iterable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Protocol, runtime_checkable

import cv2
import numpy as np

ClockNs = Callable[[], int]

SOURCE_KINDS = ("v4l2", "video", "sim", "bag")


@dataclass(frozen=True)
class Frame:
    stamp_ns: int
    image: np.ndarray
    seq: int


@runtime_checkable
class FrameSource(Protocol):
    """What the camera node needs from a camera."""

    @property
    def info(self) -> str:  # a one-line device description for logs and diagnostics
        ...

    def open(self) -> None: ...

    def read(self, timeout: float) -> Frame | None:
        """The next (newest) frame, or None when none arrived within `timeout` seconds."""
        ...

    def close(self) -> None: ...


@dataclass
class SourceStats:
    """Counters every source keeps; the node turns them into diagnostics."""

    captured: int = 0  # frames that came out of the device/file/renderer
    delivered: int = 0  # frames handed out by read()
    dropped: int = 0  # captured but never handed out (overwritten by a newer one)
    reconnects: int = 0
    connected: bool = False
    finished: bool = False  # a finite source (file, bag, scene) has no more frames
    last_error: str = ""


class SourceError(RuntimeError):
    """A source that cannot be opened at all (bad path, unknown kind); one clear line."""


def as_bgr8(image: np.ndarray) -> np.ndarray:
    """A contiguous HxWx3 uint8 view/copy of a camera image; grey and BGRA are converted, anything else rejected."""
    if not isinstance(image, np.ndarray) or image.dtype != np.uint8:
        raise ValueError(f"expected a uint8 image, got {getattr(image, 'dtype', type(image).__name__)}")
    if image.ndim == 2 or (image.ndim == 3 and image.shape[2] == 1):
        image = cv2.cvtColor(image.reshape(image.shape[:2]), cv2.COLOR_GRAY2BGR)
    elif image.ndim == 3 and image.shape[2] == 4:
        image = cv2.cvtColor(image, cv2.COLOR_BGRA2BGR)
    elif not (image.ndim == 3 and image.shape[2] == 3):
        raise ValueError(f"expected an HxW, HxWx3 or HxWx4 image, got shape {image.shape}")
    if image.shape[0] == 0 or image.shape[1] == 0:
        raise ValueError(f"empty image of shape {image.shape}")
    return np.ascontiguousarray(image)


class _Pacer:
    """Sleeps until a frame's due time on a monotonic clock; `rate` <= 0 means as fast as possible."""

    def __init__(self, rate: float = 1.0) -> None:
        self.rate = rate
        self._origin: float | None = None

    def reset(self) -> None:
        self._origin = None

    def wait(self, offset_s: float, timeout: float, stop: threading.Event | None = None) -> bool:
        """Wait until `offset_s` (scaled by rate) after the first call; False if `timeout` ran out first."""
        now = time.monotonic()
        if self._origin is None:
            self._origin = now - (offset_s / self.rate if self.rate > 0 else 0.0)
        if self.rate <= 0:
            return True
        due = self._origin + offset_s / self.rate
        remaining = due - now
        if remaining <= 0:
            return True
        if remaining > timeout:
            _sleep(timeout, stop)
            return False
        _sleep(remaining, stop)
        return True


def _sleep(seconds: float, stop: threading.Event | None) -> None:
    if stop is not None:
        stop.wait(seconds)
    else:
        time.sleep(seconds)


# --------------------------------------------------------------------------------------------
# Capture thread with a newest-frame buffer of one (V4L2, or anything shaped like cv2.VideoCapture)
# --------------------------------------------------------------------------------------------
class CaptureLike(Protocol):
    def isOpened(self) -> bool: ...  # noqa: N802 - cv2.VideoCapture's names
    def grab(self) -> bool: ...
    def retrieve(self) -> tuple[bool, np.ndarray | None]: ...
    def release(self) -> None: ...


@dataclass(frozen=True)
class Backoff:
    """Exponential back-off between reconnect attempts."""

    initial_s: float = 0.1
    factor: float = 2.0
    max_s: float = 5.0

    def delays(self) -> Iterator[float]:
        delay = self.initial_s
        while True:
            yield delay
            delay = min(delay * self.factor, self.max_s)


class CaptureThread:
    """Grabs frames on its own thread and keeps only the newest one (a buffer of one).

    Latency cannot build up: a frame that was not read before the next one arrived is counted
    as dropped and replaced. The stamp is taken when `grab()` returns, before decoding. When
    the device fails (open fails, or `max_failures` grabs in a row fail) it is released and
    reopened with exponential back-off until `close()`. `log` gets what happens to the device
    (reconnected), `warn` what goes wrong (cannot open, with the reason, once per reason; lost).
    """

    def __init__(
        self,
        open_capture: Callable[[], CaptureLike],
        *,
        clock_ns: ClockNs = time.time_ns,
        backoff: Backoff = Backoff(),
        max_failures: int = 5,
        name: str = "touchroller-capture",
        log: Callable[[str], None] | None = None,
        warn: Callable[[str], None] | None = None,
    ) -> None:
        self._open_capture = open_capture
        self._clock_ns = clock_ns
        self._backoff = backoff
        self._max_failures = max_failures
        self._name = name
        self._log = log or (lambda message: None)
        self._warn = warn or self._log
        self._reported_error = ""   # the open failure last reported: each reason once, not every retry
        self.stats = SourceStats()
        self._condition = threading.Condition()
        self._latest: Frame | None = None
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._seq = 0

    def start(self) -> None:
        if self._thread is not None:
            return
        self._stop.clear()
        self._thread = threading.Thread(target=self._run, name=self._name, daemon=True)
        self._thread.start()

    def stop(self) -> None:
        self._stop.set()
        with self._condition:
            self._condition.notify_all()
        if self._thread is not None:
            self._thread.join(timeout=5.0)
            self._thread = None

    def read(self, timeout: float) -> Frame | None:
        deadline = time.monotonic() + max(timeout, 0.0)
        with self._condition:
            while self._latest is None and not self._stop.is_set():
                remaining = deadline - time.monotonic()
                if remaining <= 0 or not self._condition.wait(remaining):
                    break
            frame, self._latest = self._latest, None
        if frame is not None:
            self.stats.delivered += 1
        return frame

    # -- the capture thread --------------------------------------------------------------
    def _run(self) -> None:
        delays = self._backoff.delays()
        while not self._stop.is_set():
            capture = self._connect()
            if capture is None:
                self._stop.wait(next(delays))
                continue
            delays = self._backoff.delays()  # connected: the next outage starts at the initial delay
            try:
                self._grab_until_failure(capture)
            finally:
                _release(capture)
                self.stats.connected = False

    def _connect(self) -> CaptureLike | None:
        try:
            capture = self._open_capture()
        except Exception as exc:  # noqa: BLE001 - a device that fails to open is retried, not fatal
            self._open_failed(f"open failed: {exc}")
            return None
        if capture is None or not capture.isOpened():
            self._open_failed("open failed: device not available")
            _release(capture)
            return None
        self._reported_error = ""
        if self.stats.captured or self.stats.reconnects or self.stats.last_error:
            self.stats.reconnects += 1
            self._log("camera reconnected")
        self.stats.connected = True
        return capture

    def _open_failed(self, reason: str) -> None:
        self.stats.last_error = reason
        if reason != self._reported_error:
            self._reported_error = reason
            self._warn(f"cannot open the camera ({reason}); retrying with back-off")

    def _grab_until_failure(self, capture: CaptureLike) -> None:
        failures = 0
        while not self._stop.is_set():
            try:
                ok = capture.grab()
                stamp_ns = self._clock_ns()
                ok, image = capture.retrieve() if ok else (False, None)
                frame_image = as_bgr8(image) if ok and image is not None else None
            except Exception as exc:  # noqa: BLE001 - a vanished device raises in some backends
                self.stats.last_error = f"grab failed: {exc}"
                frame_image = None
            if frame_image is None:
                failures += 1
                if failures >= self._max_failures:
                    self.stats.last_error = self.stats.last_error or "grab failed"
                    self._warn(f"camera lost ({self.stats.last_error}); reconnecting with back-off")
                    return
                continue
            failures = 0
            self._publish(Frame(stamp_ns, frame_image, self._seq))
            self._seq += 1

    def _publish(self, frame: Frame) -> None:
        with self._condition:
            if self._latest is not None:
                self.stats.dropped += 1
            self._latest = frame
            self.stats.captured += 1
            self._condition.notify()


def _release(capture: Any) -> None:
    if capture is None:
        return
    try:
        capture.release()
    except Exception:  # noqa: BLE001, S110 - releasing a dead device may fail; nothing to do
        pass


def resolve_device(device: str | int) -> str | int:
    """An index stays an index; a path (e.g. a stable /dev/v4l/by-id symlink) resolves to /dev/videoN."""
    if isinstance(device, int):
        return device
    text = str(device).strip()
    if text.lstrip("-").isdigit():
        return int(text)
    return os.path.realpath(text)


class V4L2Source:
    """A V4L2 webcam via OpenCV (CAP_V4L2) with a capture thread and a newest-frame buffer of one.

    `device` is an index or a path; prefer the stable `/dev/v4l/by-id/...` path, which survives
    replugging (it is resolved again on every reconnect). `exposure` <= 0 keeps auto exposure.
    `open_capture` replaces the OpenCV device (tests inject fakes or a VideoCapture on a file).
    """

    def __init__(
        self,
        device: str | int = 0,
        *,
        width: int = 640,
        height: int = 480,
        fps: float = 30.0,
        exposure: float = 0.0,
        fourcc: str = "MJPG",
        clock_ns: ClockNs = time.time_ns,
        backoff: Backoff = Backoff(),
        open_capture: Callable[[], CaptureLike] | None = None,
        log: Callable[[str], None] | None = None,
        warn: Callable[[str], None] | None = None,
    ) -> None:
        self.device = device
        self.width, self.height, self.fps, self.exposure, self.fourcc = width, height, fps, exposure, fourcc
        self._thread = CaptureThread(
            open_capture or self._open_device, clock_ns=clock_ns, backoff=backoff, log=log, warn=warn
        )

    @property
    def info(self) -> str:
        return f"v4l2 {self.device} {self.width}x{self.height}@{self.fps:g}"

    @property
    def stats(self) -> SourceStats:
        return self._thread.stats

    def _open_device(self) -> CaptureLike:
        capture = cv2.VideoCapture(resolve_device(self.device), cv2.CAP_V4L2)
        if not capture.isOpened():
            return capture
        if self.fourcc:
            capture.set(cv2.CAP_PROP_FOURCC, cv2.VideoWriter.fourcc(*self.fourcc[:4].ljust(4)))
        capture.set(cv2.CAP_PROP_FRAME_WIDTH, self.width)
        capture.set(cv2.CAP_PROP_FRAME_HEIGHT, self.height)
        capture.set(cv2.CAP_PROP_FPS, self.fps)
        capture.set(cv2.CAP_PROP_BUFFERSIZE, 1)  # the driver's own queue must not add latency either
        if self.exposure > 0:
            capture.set(cv2.CAP_PROP_AUTO_EXPOSURE, 1)  # V4L2: 1 = manual, 3 = aperture priority (auto)
            capture.set(cv2.CAP_PROP_EXPOSURE, self.exposure)
        else:
            capture.set(cv2.CAP_PROP_AUTO_EXPOSURE, 3)
        return capture

    def open(self) -> None:
        self._thread.start()

    def read(self, timeout: float) -> Frame | None:
        return self._thread.read(timeout)

    def close(self) -> None:
        self._thread.stop()


class VideoFileSource:
    """Frames of a video file, at the file's frame rate (`rate` 1.0), scaled, or as fast as possible (0)."""

    def __init__(
        self,
        path: str | Path,
        *,
        rate: float = 1.0,
        loop: bool = False,
        clock_ns: ClockNs = time.time_ns,
    ) -> None:
        self.path = Path(path)
        self.rate, self.loop = rate, loop
        self._clock_ns = clock_ns
        self._capture: cv2.VideoCapture | None = None
        self._pacer = _Pacer(rate)
        self._period = 1.0 / 30.0
        self._index = 0  # frames into the current pass
        self._played = 0.0  # seconds of earlier passes, so looping keeps pace
        self._pending: np.ndarray | None = None
        self._seq = 0
        self.stats = SourceStats()

    @property
    def info(self) -> str:
        return f"video {self.path}"

    def open(self) -> None:
        if not self.path.is_file():
            raise SourceError(f"video file not found: {self.path}")
        self._capture = cv2.VideoCapture(str(self.path))
        if not self._capture.isOpened():
            raise SourceError(f"cannot decode video file: {self.path}")
        fps = self._capture.get(cv2.CAP_PROP_FPS)
        self._period = 1.0 / fps if fps and np.isfinite(fps) and fps > 0 else 1.0 / 30.0
        self.stats.connected = True

    def read(self, timeout: float) -> Frame | None:
        if self._capture is None or self.stats.finished:
            return None
        if self._pending is None:
            self._pending = self._next_image()
            if self._pending is None:
                return None
        if not self._pacer.wait(self._played + self._index * self._period, timeout):
            return None
        image, self._pending = self._pending, None
        frame = Frame(self._clock_ns(), image, self._seq)
        self._seq += 1
        self._index += 1
        self.stats.captured += 1
        self.stats.delivered += 1
        return frame

    def _next_image(self) -> np.ndarray | None:
        assert self._capture is not None
        ok, image = self._capture.read()
        if not ok and self.loop and self._index > 0:
            self._played += self._index * self._period
            self._index = 0
            self._capture.set(cv2.CAP_PROP_POS_FRAMES, 0)
            ok, image = self._capture.read()
        if not ok or image is None:
            self.stats.finished = True
            return None
        return as_bgr8(image)

    def close(self) -> None:
        if self._capture is not None:
            self._capture.release()
            self._capture = None
        self.stats.connected = False


class SimulatedSource:
    """The simulated sensor (`touchroller_driver.sim.SimulatedSensor`) playing the scene's own motion
    (`sensor.frames()`), paced by the frames' stamps (`rate` 1.0 real time, 0 as fast as possible) and
    stamped from `clock_ns` at capture. The sensor on a (simulated) arm is `touchroller_driver.sim.camera.ArmCamera`.
    """

    def __init__(
        self,
        sensor: Any,
        *,
        fps: float | None = None,
        rate: float = 1.0,
        loop: bool = False,
        clock_ns: ClockNs = time.time_ns,
    ) -> None:
        self.sensor = sensor
        scene_fps = getattr(getattr(sensor, "scene", None), "fps", None)
        self.fps = float(fps or scene_fps or 30.0)
        self.rate, self.loop = rate, loop
        self._clock_ns = clock_ns
        self._pacer = _Pacer(rate)
        self._frames: Iterator[Any] | None = None
        self._first_stamp: int | None = None
        self._pending: Any = None
        self._offset_s = 0.0  # for looping: the played length of earlier passes
        self._last_offset = 0.0
        self._seq = 0
        self.stats = SourceStats()

    @property
    def info(self) -> str:
        scene = getattr(self.sensor, "scene", None)
        name = getattr(scene, "name", None) or type(self.sensor).__name__
        return f"sim {name} (scene motion)"

    def open(self) -> None:
        self.stats.connected = True
        self._frames = iter(self.sensor.frames())

    def read(self, timeout: float) -> Frame | None:
        if self.stats.finished:
            return None
        return self._read_scene(timeout)

    def _read_scene(self, timeout: float) -> Frame | None:
        if self._pending is None:
            self._pending = self._next_scene_frame()
            if self._pending is None:
                return None
        stamp = int(self._pending.stamp_ns)
        if self._first_stamp is None:
            self._first_stamp = stamp
        self._last_offset = self._offset_s + (stamp - self._first_stamp) * 1e-9
        if not self._pacer.wait(self._last_offset, timeout):
            return None
        frame, self._pending = self._pending, None
        return self._deliver(self._clock_ns(), as_bgr8(frame.image))

    def _next_scene_frame(self) -> Any:
        assert self._frames is not None, "open() first"
        frame = next(self._frames, None)
        if frame is None and self.loop and self._seq > 0:
            self._offset_s = self._last_offset + 1.0 / self.fps
            self._first_stamp = None
            self._frames = iter(self.sensor.frames())
            frame = next(self._frames, None)
        if frame is None:
            self.stats.finished = True
        return frame

    def _deliver(self, stamp_ns: int, image: np.ndarray) -> Frame:
        frame = Frame(stamp_ns, image, self._seq)
        self._seq += 1
        self.stats.captured += 1
        self.stats.delivered += 1
        return frame

    def close(self) -> None:
        self._frames = None
        self.stats.connected = False


class BagSource:
    """Images from a rosbag2 recording (Image or CompressedImage), paced by their recorded stamps.

    `reader(path, topic)` (`reader(path)` when `topic` is None: the reader's default topic) yields records
    with `stamp_ns` and `image` (`touchroller_bringup.bags.read_images` in the product: reading bags belongs
    to the layer above, this class only paces and stamps).
    `restamp` False keeps the recorded capture stamps (so contacts match the recording);
    True stamps frames with `clock_ns` at replay.
    """

    def __init__(
        self,
        path: str | Path,
        topic: str | None = None,
        *,
        reader: Callable[..., Iterable[Any]],
        rate: float = 1.0,
        loop: bool = False,
        restamp: bool = False,
        clock_ns: ClockNs = time.time_ns,
    ) -> None:
        self.path = Path(path)
        self.topic = topic
        self._reader = reader
        self.rate, self.loop, self.restamp = rate, loop, restamp
        self._clock_ns = clock_ns
        self._pacer = _Pacer(rate)
        self._records: Iterator[Any] | None = None
        self._pending: Any = None
        self._first_stamp: int | None = None
        self._offset_s = 0.0
        self._last_offset = 0.0
        self._seq = 0
        self.stats = SourceStats()

    @property
    def info(self) -> str:
        return f"bag {self.path} {self.topic or ''}".rstrip()

    def _iterate(self) -> Iterator[Any]:
        return iter(self._reader(self.path) if self.topic is None else self._reader(self.path, self.topic))

    def open(self) -> None:
        if not self.path.exists():
            raise SourceError(f"bag not found: {self.path}")
        self._records = self._iterate()
        self.stats.connected = True

    def read(self, timeout: float) -> Frame | None:
        if self._records is None or self.stats.finished:
            return None
        if self._pending is None:
            self._pending = self._next_record()
            if self._pending is None:
                return None
        stamp = int(self._pending.stamp_ns)
        if self._first_stamp is None:
            self._first_stamp = stamp
        self._last_offset = self._offset_s + max(stamp - self._first_stamp, 0) * 1e-9
        if not self._pacer.wait(self._last_offset, timeout):
            return None
        record, self._pending = self._pending, None
        frame = Frame(self._clock_ns() if self.restamp else stamp, as_bgr8(record.image), self._seq)
        self._seq += 1
        self.stats.captured += 1
        self.stats.delivered += 1
        return frame

    def _next_record(self) -> Any:
        assert self._records is not None
        try:
            record = next(self._records, None)
        except Exception as exc:  # noqa: BLE001 - a truncated bag ends the source with one clear line
            self.stats.last_error = (str(exc).splitlines() or [type(exc).__name__])[0]
            record = None
            self.loop = False
        if record is None and self.loop and self._seq > 0:
            self._offset_s = self._last_offset + 1e-3
            self._first_stamp = None
            self._records = self._iterate()
            record = next(self._records, None)
        if record is None:
            self.stats.finished = True
        return record

    def close(self) -> None:
        self._records = None
        self.stats.connected = False


def make_source(kind: str, **params: Any) -> FrameSource:
    """A source by kind: v4l2(device, width, height, fps, exposure), video(path), sim(scene | sensor),
    bag(path, reader)."""
    kind = kind.strip().lower()
    if kind == "v4l2":
        return V4L2Source(**params)
    if kind == "video":
        return VideoFileSource(**params)
    if kind == "bag":
        return BagSource(**params)
    if kind == "sim":
        sensor = params.pop("sensor", None)
        scene = params.pop("scene", "surface_mapping")
        seed = params.pop("seed", 0)
        if sensor is None:
            from touchroller_driver.sim import SimulatedSensor, load_scene  # lazy: heavy and optional

            sensor = SimulatedSensor(load_scene(scene), seed=seed)
        return SimulatedSource(sensor, **params)
    raise SourceError(f"unknown camera source {kind!r}; expected one of {', '.join(SOURCE_KINDS)}")
