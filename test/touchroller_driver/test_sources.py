"""Camera sources: capture thread (newest frame only, capture stamps, reconnect), files, sim, bags."""
from __future__ import annotations

import itertools
import threading
import time
from types import SimpleNamespace

import cv2
import numpy as np
import pytest

from touchroller_bringup.bags import read_images
from touchroller_driver.sources import (
    Backoff,
    BagSource,
    CaptureThread,
    Frame,
    FrameSource,
    SimulatedSource,
    SourceError,
    V4L2Source,
    VideoFileSource,
    as_bgr8,
    make_source,
    resolve_device,
)

FAST = Backoff(initial_s=0.005, factor=2.0, max_s=0.02)


def write_avi(path, count: int, fps: float = 5.0, size=(64, 48)) -> list[int]:
    """An MJPG avi whose frame i is uniformly grey 40*i; returns the grey levels."""
    writer = cv2.VideoWriter(str(path), cv2.VideoWriter.fourcc(*"MJPG"), fps, size)
    assert writer.isOpened()
    levels = [(40 * i) % 250 for i in range(count)]
    for level in levels:
        writer.write(np.full((size[1], size[0], 3), level, np.uint8))
    writer.release()
    return levels


class FakeCapture:
    """Shaped like cv2.VideoCapture; frame i has pixel value i % 256 and fails after `fail_after` grabs."""

    def __init__(self, counter, fail_after: int | None = None, gate: threading.Event | None = None,
                 done: threading.Event | None = None):
        self.counter = counter
        self.fail_after = fail_after
        self.gate = gate
        self.done = done or threading.Event()
        self.grabs = 0
        self.released = False
        self.value = 0

    def isOpened(self):  # noqa: N802
        return True

    def grab(self):
        if self.gate is not None:   # grab only when the test allows it (or ends), however late that is
            while not self.gate.wait(0.05) and not self.done.is_set():
                pass
            self.gate.clear()
        if self.fail_after is not None and self.grabs >= self.fail_after:
            time.sleep(0.001)
            return False
        self.grabs += 1
        self.value = next(self.counter)
        return True

    def retrieve(self):
        return True, np.full((4, 6, 3), self.value % 256, np.uint8)

    def release(self):
        self.released = True


def test_as_bgr8_converts_grey_and_bgra_and_rejects_bad_input():
    grey = np.arange(12, dtype=np.uint8).reshape(3, 4)
    bgr = as_bgr8(grey)
    assert bgr.shape == (3, 4, 3) and np.array_equal(bgr[..., 1], grey)
    bgra = np.zeros((3, 4, 4), np.uint8)
    bgra[..., 2] = 7
    assert as_bgr8(bgra).shape == (3, 4, 3) and as_bgr8(bgra)[0, 0, 2] == 7
    with pytest.raises(ValueError, match="uint8"):
        as_bgr8(np.zeros((3, 4, 3), np.float32))
    with pytest.raises(ValueError, match="shape"):
        as_bgr8(np.zeros((3, 4, 2), np.uint8))
    with pytest.raises(ValueError, match="empty"):
        as_bgr8(np.zeros((0, 4, 3), np.uint8))


def test_backoff_grows_exponentially_up_to_its_cap():
    delays = list(itertools.islice(Backoff(0.1, 2.0, 0.5).delays(), 5))
    assert delays == pytest.approx([0.1, 0.2, 0.4, 0.5, 0.5])


def test_resolve_device_keeps_indices_and_follows_stable_symlinks(tmp_path):
    target = tmp_path / "video7"
    target.touch()
    link = tmp_path / "usb-TouchRoller_cam-video-index0"
    link.symlink_to(target)
    assert resolve_device(2) == 2
    assert resolve_device("3") == 3
    assert resolve_device(str(link)) == str(target)


def test_capture_thread_keeps_only_the_newest_frame_and_counts_drops():
    counter = itertools.count()
    thread = CaptureThread(lambda: FakeCapture(counter), backoff=FAST)
    thread.start()
    try:
        first = thread.read(timeout=20.0)
        assert first is not None
        deadline = time.monotonic() + 20
        while thread.stats.captured < first.seq + 20 and time.monotonic() < deadline:
            time.sleep(0.01)
        newest = thread.read(timeout=20.0)
        assert newest is not None
        # everything between the two reads was replaced, not queued
        assert newest.seq - first.seq > 10
        assert thread.stats.dropped >= newest.seq - first.seq - 1
        assert int(newest.image[0, 0, 0]) == newest.seq % 256
    finally:
        thread.stop()


def test_capture_thread_stamps_at_grab_time_not_read_time():
    gate, done = threading.Event(), threading.Event()
    ticks = itertools.count(1000)
    thread = CaptureThread(lambda: FakeCapture(itertools.count(), gate=gate, done=done),
                           clock_ns=lambda: next(ticks))
    thread.start()
    try:
        gate.set()  # exactly one grab (the next waits for the gate: no second frame 1 s later on a slow run)
        frame = thread.read(timeout=20.0)
        assert frame is not None
        stamp_at_grab = frame.stamp_ns
        time.sleep(0.05)
        assert thread.read(timeout=0.05) is None  # nothing new: no duplicate of the old frame
        assert stamp_at_grab == 1000  # the clock was read once, when the grab returned
    finally:
        done.set()
        gate.set()
        thread.stop()


def test_capture_thread_reconnects_with_backoff_after_the_device_disappears():
    counter = itertools.count()
    opened: list[FakeCapture] = []
    attempts = {"n": 0}

    def open_capture():
        attempts["n"] += 1
        if attempts["n"] in (1, 2):
            raise OSError("No such device")  # not plugged in yet
        if 4 <= attempts["n"] <= 5:
            return None  # unplugged: open fails twice
        capture = FakeCapture(counter, fail_after=3 if attempts["n"] == 3 else None)
        opened.append(capture)
        return capture

    logs: list[str] = []
    thread = CaptureThread(open_capture, backoff=FAST, log=logs.append)
    thread.start()
    try:
        seqs = []
        deadline = time.monotonic() + 20
        while len(seqs) < 6 and time.monotonic() < deadline:
            frame = thread.read(timeout=0.5)
            if frame is not None:
                seqs.append(frame.seq)
        assert len(seqs) >= 6, f"no frames after reconnect; stats {thread.stats}"
        assert attempts["n"] >= 6
        assert opened[0].released  # the dead device was released before reopening
        assert thread.stats.reconnects >= 2
        assert any("lost" in line for line in logs) and any("reconnected" in line for line in logs)
        assert seqs == sorted(seqs) and len(set(seqs)) == len(seqs)
    finally:
        thread.stop()


def test_v4l2_source_through_opencv_videocapture_on_an_mjpg_file(tmp_path):
    path = tmp_path / "cam.avi"
    levels = write_avi(path, 5)
    gate, done = threading.Event(), threading.Event()

    class Paced:
        """The file's VideoCapture, grabbing only when the test allows (like a camera at its frame rate)."""

        def __init__(self):
            self.capture = cv2.VideoCapture(str(path))

        def isOpened(self):  # noqa: N802
            return self.capture.isOpened()

        def grab(self):   # however late the test allows it: an unasked grab would drop a frame
            while not gate.wait(0.05) and not done.is_set():
                pass
            gate.clear()
            return self.capture.grab()

        def retrieve(self):
            return self.capture.retrieve()

        def release(self):
            self.capture.release()

    source = V4L2Source("/dev/v4l/by-id/usb-fake-video-index0", open_capture=Paced, backoff=FAST)
    assert isinstance(source, FrameSource)
    assert "by-id" in source.info
    source.open()
    try:
        got = []
        for _ in levels:
            gate.set()
            frame = source.read(timeout=20.0)
            assert frame is not None
            got.append(float(frame.image.mean()))
            assert frame.image.shape == (48, 64, 3) and frame.image.dtype == np.uint8
        assert got == pytest.approx(levels, abs=3)  # MJPG is lossy
        assert source.stats.dropped == 0
    finally:
        done.set()
        gate.set()
        source.close()


def test_v4l2_source_on_a_missing_device_keeps_retrying_without_raising(tmp_path):
    source = V4L2Source(str(tmp_path / "no-such-camera"), backoff=FAST)
    source.open()
    try:
        assert source.read(timeout=0.1) is None
        assert not source.stats.connected
        assert "open failed" in source.stats.last_error
    finally:
        source.close()


def test_video_file_source_fast_pacing_reads_every_frame_then_finishes(tmp_path):
    path = tmp_path / "clip.avi"
    levels = write_avi(path, 4)
    stamps = itertools.count(10)
    source = make_source("video", path=path, rate=0.0, clock_ns=lambda: next(stamps))
    source.open()
    frames = [source.read(timeout=1.0) for _ in range(4)]
    assert all(isinstance(f, Frame) for f in frames)
    assert [f.seq for f in frames] == [0, 1, 2, 3]
    assert [f.stamp_ns for f in frames] == [10, 11, 12, 13]
    assert [float(f.image.mean()) for f in frames] == pytest.approx(levels, abs=3)
    assert source.read(timeout=0.1) is None and source.stats.finished
    source.close()


class VirtualTime:
    """Stands in for the `time` module of touchroller_driver.sources: monotonic time advances only when
    the code under test sleeps, so pacing checks do not depend on how busy the machine is."""

    def __init__(self) -> None:
        self.now = 1000.0

    def monotonic(self) -> float:
        return self.now

    def sleep(self, seconds: float) -> None:
        self.now += max(seconds, 0.0)

    time_ns = staticmethod(time.time_ns)


@pytest.fixture
def virtual_time(monkeypatch) -> VirtualTime:
    import touchroller_driver.sources as sources

    clock = VirtualTime()
    monkeypatch.setattr(sources, "time", clock)
    return clock


def test_video_file_source_loops_and_paces_real_time(tmp_path, virtual_time):
    path = tmp_path / "slow.avi"
    write_avi(path, 2, fps=1.0)
    looping = VideoFileSource(path, rate=0.0, loop=True)
    looping.open()
    assert [looping.read(1.0).seq for _ in range(5)] == [0, 1, 2, 3, 4]
    looping.close()

    paced = VideoFileSource(path, rate=1.0)
    paced.open()
    assert paced.read(timeout=1.0) is not None
    assert paced.read(timeout=0.01) is None  # the next frame is due a second later
    assert paced.read(timeout=0.5) is None
    assert paced.read(timeout=0.6) is not None   # ... and comes then
    assert virtual_time.now - 1000.0 == pytest.approx(1.0)
    assert not paced.stats.finished
    paced.close()


def test_video_file_source_reports_a_missing_file(tmp_path):
    with pytest.raises(SourceError, match="not found"):
        VideoFileSource(tmp_path / "nope.avi").open()


class FakeSensor:
    def __init__(self, n: int = 3):
        self.scene = SimpleNamespace(name="fake_scene", fps=100.0)
        self.rendered = []
        self.n = n

    def render(self, state):
        self.rendered.append(state)
        return np.full((4, 6, 3), int(state * 10) % 256, np.uint8)

    def frames(self):
        for i in range(self.n):
            yield SimpleNamespace(stamp_ns=i * 10_000_000, image=np.full((4, 6, 3), i, np.uint8), truth={})



def test_simulated_source_plays_the_scene_motion_standalone_and_loops():
    source = make_source("sim", sensor=FakeSensor(3), rate=0.0, loop=True)
    source.open()
    values = [int(source.read(1.0).image[0, 0, 0]) for _ in range(7)]
    assert values == [0, 1, 2, 0, 1, 2, 0]
    once = SimulatedSource(FakeSensor(2), rate=0.0)
    once.open()
    assert once.read(1.0) is not None and once.read(1.0) is not None
    assert once.read(0.1) is None and once.stats.finished


def test_bag_source_keeps_recorded_stamps_and_reads_compressed_images(tmp_path):
    from touchroller_bringup.bags import write_images

    bag = tmp_path / "rec"
    images = [np.full((8, 10, 3), 20 * i, np.uint8) for i in range(3)]
    write_images(bag, [(1_000_000_000 + i * 33_000_000, im) for i, im in enumerate(images)])
    source = BagSource(bag, rate=0.0, reader=read_images)
    source.open()
    frames = [source.read(1.0) for _ in range(3)]
    assert [f.stamp_ns for f in frames] == [1_000_000_000, 1_033_000_000, 1_066_000_000]
    assert all(np.array_equal(f.image, im) for f, im in zip(frames, images, strict=True))
    assert source.read(0.1) is None and source.stats.finished

    compressed = tmp_path / "compressed"
    _write_compressed(compressed, images)
    source = make_source("bag", path=compressed, reader=read_images, rate=0.0, restamp=True, clock_ns=lambda: 42)
    source.open()
    frame = source.read(1.0)
    assert frame.stamp_ns == 42 and frame.image.shape == (8, 10, 3)
    assert np.array_equal(frame.image, images[0])  # PNG is lossless


def _write_compressed(path, images):
    from rosbags.rosbag2 import Writer
    from rosbags.typesys import Stores, get_typestore

    store = get_typestore(Stores.ROS2_KILTED)
    msg_type = store.types["sensor_msgs/msg/CompressedImage"]
    header_type = store.types["std_msgs/msg/Header"]
    time_type = store.types["builtin_interfaces/msg/Time"]
    with Writer(path, version=9) as writer:
        connection = writer.add_connection("/touchroller/image_raw", "sensor_msgs/msg/CompressedImage", typestore=store)
        for i, image in enumerate(images):
            data = np.frombuffer(cv2.imencode(".png", image)[1].tobytes(), np.uint8)
            header = header_type(stamp=time_type(sec=1, nanosec=i), frame_id="cam")
            msg = msg_type(header=header, format="png", data=data)
            writer.write(connection, 1_000_000_000 + i, store.serialize_cdr(msg, "sensor_msgs/msg/CompressedImage"))


def test_bag_source_missing_bag_and_unknown_kind_are_clear_errors(tmp_path):
    with pytest.raises(SourceError, match="bag not found"):
        BagSource(tmp_path / "missing", reader=read_images).open()
    with pytest.raises(SourceError, match="unknown camera source 'usb'"):
        make_source("usb")
