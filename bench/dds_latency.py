"""DDS latency over loopback: image published -> contact received (p50/p99) at 30 Hz, losses at 60 Hz.

The real graph: `touchroller_bringup.nodes.camera_node.CameraNode` publishes 640x480 bgr8 frames (reliable)
from an in-memory source, `touchroller_bringup.nodes.perception_node.PerceptionNode` detects contacts,
and a probe node receives `/touchroller/contacts`. Latency = probe receive time - contact stamp,
where the contact carries the image's capture stamp (the moment the frame was due from the camera).
`--processes 2` runs the perception node in its own process (as `ros2 launch` would); 1 runs all
nodes in one process, each on its own executor thread (as `touchroller scan` does).

Frames that give no contact are split by where they went: late at the camera's publishing thread,
lost in transport (DDS's message_lost event on the perception node's subscription), or skipped as
stale by the perception node's keep-last history (a newer frame replaced it before it was taken).
`--qos` measures the perception node's image subscription at depth 1/2/3, best effort and reliable.

Goals (issue 7): p50 <= 5 ms and p99 <= 15 ms at 30 Hz; nothing lost at 60 Hz.
Report section: `run(quick)` and `to_markdown(result)`. Results: bench/results/dds_latency.md,
bench/results/dds_qos.md; docs/dds.md. dds_slow_consumer and dds_soak import the graph helpers from here.
"""
from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import threading
import time
from collections import deque
from collections.abc import Sequence
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np

from bench._common import load_json, machine, results_path, to_json  # one machine line for every bench and the report
from touchroller_bringup import names
from touchroller_bringup.image_conversion import stamp_to_ns
from touchroller_perception.files import atomic_write_text

ROOT = Path(__file__).resolve().parent.parent
RESULTS = ROOT / "bench" / "results"

WIDTH, HEIGHT = 640, 480
REFERENCE_FRAMES = 30  # no-contact frames first: the perception node takes its reference from the first 5 it gets


# ------------------------------------------------------------------ frames
def synthetic_frames(count: int = 16, seed: int = 0) -> tuple[list[np.ndarray], list[np.ndarray]]:
    """(reference frames without contact, frames with one GelSight-like contact each).

    A static gel background (illumination gradient + specks) with sensor noise; a contact lights
    one side and shades the other, per colour channel from a different direction.
    """
    rng = np.random.default_rng(seed)
    yy, xx = np.mgrid[0:HEIGHT, 0:WIDTH].astype(np.float32)
    base = np.empty((HEIGHT, WIDTH, 3), np.float32)
    for c, level in enumerate((110.0, 120.0, 100.0)):
        base[..., c] = level + 20 * np.sin(xx / WIDTH * np.pi) * np.cos(yy / HEIGHT * np.pi / 2)
    base += rng.normal(0, 3.0, (HEIGHT, WIDTH, 1)).astype(np.float32)  # static specks

    def noisy(image: np.ndarray) -> np.ndarray:
        return np.clip(image + rng.standard_normal(image.shape, dtype=np.float32), 0, 255).astype(np.uint8)

    references = [noisy(base) for _ in range(REFERENCE_FRAMES)]
    contacts = []
    sigma = 10.0
    for i in range(count):
        u = 100 + (i * 37) % (WIDTH - 200)
        v = 100 + (i * 53) % (HEIGHT - 200)
        g = np.exp(-((xx - u) ** 2 + (yy - v) ** 2) / (2 * sigma**2))
        gx, gy = -(xx - u) / sigma * g, -(yy - v) / sigma * g
        image = base.copy()
        for c, angle in enumerate((0.0, 2.1, 4.2)):
            image[..., c] += 40.0 * (np.cos(angle) * gx + np.sin(angle) * gy) + 15.0 * g
        contacts.append(noisy(image))
    return references, contacts


class MemorySource:
    """A FrameSource that replays frames from memory at `fps`, stamped with their capture (due) time.

    The first frames are the no-contact reference; the rest cycle through contact frames.
    A frame is stamped at the moment a real camera would have captured it (start + seq / fps), so the
    latency includes any delay of the camera node's publishing thread. A frame read more than one
    period after that moment is counted in `late`: a real camera with a buffer of one would have
    replaced it by then (a drop on the publisher side); here it is still published.
    `contact_stamps` records every delivered contact frame's stamp (frames that should each give a contact).
    """

    def __init__(self, references, contacts, fps: float, count: int, record: bool = True):
        self.references, self.contacts = references, contacts
        self.period = 1.0 / fps
        self.count = count
        self.seq = 0
        self.start: float | None = None
        self.start_ns = 0
        self.late = 0
        self.contact_stamps: list[int] = []
        self.record = record
        from touchroller_driver.sources import SourceStats

        self.stats = SourceStats(connected=True)

    @property
    def info(self) -> str:
        return f"memory source {1 / self.period:g} Hz"

    def open(self) -> None:
        self.start = None

    def close(self) -> None:
        pass

    def read(self, timeout: float):
        from touchroller_driver.sources import Frame

        total = REFERENCE_FRAMES + self.count
        if self.seq >= total:
            self.stats.finished = True
            time.sleep(min(timeout, 0.01))
            return None
        if self.start is None:
            self.start, self.start_ns = time.monotonic(), time.time_ns()
        due = self.start + self.seq * self.period
        wait = due - time.monotonic()
        if wait > timeout:
            time.sleep(timeout)
            return None
        if wait > 0:
            time.sleep(wait)
        elif -wait > self.period:
            self.late += 1
        if self.seq < REFERENCE_FRAMES:
            image = self.references[self.seq]
        else:
            image = self.contacts[(self.seq - REFERENCE_FRAMES) % len(self.contacts)]
        stamp = self.start_ns + round(self.seq * self.period * 1e9)
        if self.seq >= REFERENCE_FRAMES and self.record:
            self.contact_stamps.append(stamp)
        frame = Frame(stamp, image, self.seq)
        self.seq += 1
        self.stats.captured += 1
        self.stats.delivered += 1
        return frame


# ------------------------------------------------------------------ graph
@dataclass
class Probe:
    """Receive time of the first contact of each image stamp; the perception node's last diagnostics."""

    arrivals: dict[int, int] = field(default_factory=dict)
    lock: threading.Lock = field(default_factory=threading.Lock)
    perception_status: dict[str, str] = field(default_factory=dict)
    status_time: float = 0.0  # time.monotonic() when perception_status last arrived
    record: bool = True  # False: keep only a count and the last latencies (the soak must not grow)
    count: int = 0
    recent_ms: deque = field(default_factory=lambda: deque(maxlen=2000))

    def on_diagnostics(self, msg) -> None:
        for status in msg.status:
            if "perception" in status.name:
                self.perception_status = {kv.key: kv.value for kv in status.values}
                self.status_time = time.monotonic()

    def on_contact(self, msg) -> None:
        now = time.time_ns()
        stamp = stamp_to_ns(msg.header.stamp)
        with self.lock:
            self.count += 1
            if self.record:
                self.arrivals.setdefault(stamp, now)
            else:
                self.recent_ms.append((now - stamp) * 1e-6)


class Graph:
    """Camera node + perception node (in-process or a child process) + contact probe, on one domain."""

    def __init__(self, processes: int = 1, domain_id: int | None = None, perception_prelude: str = "",
                 map_rate: float = 1.0, record: bool = True, perception_params: dict | None = None) -> None:
        import rclpy
        from geometry_msgs.msg import PointStamped
        from rclpy.context import Context
        from rclpy.executors import SingleThreadedExecutor
        from rclpy.node import Node
        from rclpy.parameter import Parameter

        from touchroller_bringup.ros_domains import reserve_domain_id

        # a domain no test run or other benchmark on this host uses (they would see each other's topics)
        self._lease = reserve_domain_id() if domain_id is None else None
        self.domain_id = domain_id if domain_id is not None else self._lease.domain_id
        os.environ["ROS_DOMAIN_ID"] = str(self.domain_id)
        os.environ.setdefault("ROS_AUTOMATIC_DISCOVERY_RANGE", "LOCALHOST")
        self.context = Context()
        rclpy.init(context=self.context, domain_id=self.domain_id)
        self.probe = Probe(record=record)
        self.probe_node = Node("latency_probe", context=self.context)
        self.probe_node.create_subscription(PointStamped, names.topic(names.CONTACTS), self.probe.on_contact, 100)
        from diagnostic_msgs.msg import DiagnosticArray

        self.probe_node.create_subscription(DiagnosticArray, names.DIAGNOSTICS, self.probe.on_diagnostics, 10)
        self.executors = []
        self.threads = []
        self.child: subprocess.Popen | None = None
        self.perception = None
        params = {"map.publish_rate": float(map_rate), **(perception_params or {})}
        if processes == 2:
            ros_args = [arg for name, value in params.items() for arg in ("-p", f"{name}:={value}")]
            code = (f"{perception_prelude}\nfrom touchroller_bringup.nodes.perception_node import main\n"
                    f"main(['--ros-args', *{ros_args!r}])")
            verbose = bool(os.environ.get("DDS_BENCH_VERBOSE"))
            self.child = subprocess.Popen([sys.executable, "-c", code], cwd=ROOT, env=dict(os.environ),
                                          stdout=subprocess.DEVNULL, stderr=None if verbose else subprocess.DEVNULL)
        else:
            exec(perception_prelude, {})  # the same code the child process would run (e.g. a slow-down)
            from touchroller_bringup.nodes.perception_node import PerceptionNode

            self.perception = PerceptionNode(
                context=self.context,
                parameter_overrides=[Parameter(name, value=value) for name, value in params.items()])
        nodes = [self.probe_node] + ([self.perception] if self.perception is not None else [])
        for node in nodes:
            executor = SingleThreadedExecutor(context=self.context)
            executor.add_node(node)
            thread = threading.Thread(target=self._spin, args=(executor,), daemon=True)
            thread.start()
            self.executors.append(executor)
            self.threads.append(thread)
        self.camera = None

    @staticmethod
    def _spin(executor) -> None:
        try:
            executor.spin()
        except Exception:  # noqa: BLE001 - shutdown races end the thread
            pass

    def run_camera(self, source, timeout_s: float, monitor=None) -> None:
        """Publish every frame of `source` through a CameraNode, wait for the last contacts."""
        from touchroller_bringup.nodes.camera_node import CameraNode

        self.camera = CameraNode(context=self.context, source=source, autostart=False)
        executor = __import__("rclpy.executors", fromlist=["x"]).SingleThreadedExecutor(context=self.context)
        executor.add_node(self.camera)
        thread = threading.Thread(target=self._spin, args=(executor,), daemon=True)
        thread.start()
        self.executors.append(executor)
        deadline = time.monotonic() + 30
        while self.camera.image_pub.get_subscription_count() == 0 and time.monotonic() < deadline:
            time.sleep(0.05)
        if self.camera.image_pub.get_subscription_count() == 0:
            raise RuntimeError("perception node never subscribed to the images")
        time.sleep(0.5)  # let the perception node and probe finish discovery both ways
        self.camera.start()
        end = time.monotonic() + timeout_s
        while not source.stats.finished and time.monotonic() < end:
            time.sleep(0.05)
            if monitor is not None:
                monitor()
        time.sleep(0.5)  # the last contacts in flight

    def final_status(self, timeout_s: float = 3.0) -> dict[str, str]:
        """The perception node's first /diagnostics status published after now (it sends one a second)."""
        asked = time.monotonic()
        while self.probe.status_time <= asked and time.monotonic() < asked + timeout_s:
            time.sleep(0.02)
        return dict(self.probe.perception_status)

    def close(self) -> None:
        for executor in self.executors:
            executor.shutdown(timeout_sec=1.0)
        if self.camera is not None:
            self.camera.destroy_node()
        if self.perception is not None:
            self.perception.destroy_node()
        self.probe_node.destroy_node()
        if self.child is not None:
            self.child.terminate()
            try:
                self.child.wait(timeout=10)
            except subprocess.TimeoutExpired:
                self.child.kill()
        self.context.try_shutdown()
        if self._lease is not None:
            self._lease.release()


def latencies_ms(source: MemorySource, probe: Probe) -> tuple[np.ndarray, int]:
    """Latency of each contact frame that got a contact (ms), and how many frames got none."""
    with probe.lock:
        arrivals = dict(probe.arrivals)
    got = [(arrivals[s] - s) * 1e-6 for s in source.contact_stamps if s in arrivals]
    return np.array(got), len(source.contact_stamps) - len(got)


@dataclass(frozen=True)
class LatencyStats:
    """Milliseconds; NaN when nothing was measured."""

    p50: float
    p99: float
    max: float
    mean: float


def summarise(values: np.ndarray) -> LatencyStats:
    if values.size == 0:
        return LatencyStats(float("nan"), float("nan"), float("nan"), float("nan"))
    return LatencyStats(float(np.percentile(values, 50)), float(np.percentile(values, 99)), float(values.max()),
                        float(values.mean()))


@dataclass(frozen=True)
class RateRun:
    """One run of the graph at one rate: its configuration and every figure of a table row."""

    transport: str
    processes: int
    fps: float
    seconds: float
    stats: LatencyStats      # image capture stamp -> contact received, of the frames that gave a contact
    missing: int             # contact frames that gave no contact
    sent: int                # contact frames
    published: int           # all frames, references included
    camera_late: int         # read by the publishing thread more than a frame period after capture
    received: float          # frames the perception node took
    lost: float              # reported lost in transport by the RMW (NaN: it does not report)
    gaps: float              # sequence gaps at the perception node
    skipped: float           # gaps not lost in transport: stale frames replaced in the history (by design)
    busy_skips: float        # of those, while the previous callback still ran
    callback_p50_ms: float
    callback_p99_ms: float
    busy_fraction: float     # share of the run the image callback ran
    qos: str                 # the perception node's image subscription, as it reported it
    map_rate: float = 1.0
    depth: int = 0
    reliability: str = "BEST_EFFORT"

    @property
    def dropped(self) -> float:
        """Frames dropped (not skipped by design): lost in transport plus late at the camera; NaN if unknown."""
        return self.lost + self.camera_late

    @classmethod
    def from_json(cls, row: dict) -> RateRun:
        return cls(**{**row, "stats": LatencyStats(**row["stats"])})


def measure_publish_path(frames: list[np.ndarray], repeats: int = 200) -> LatencyStats:
    """Time of CameraNode.publish_frame (fill the Image + CameraInfo, serialize, hand to DDS) for VGA."""
    import rclpy
    from rclpy.context import Context
    from rclpy.node import Node
    from sensor_msgs.msg import Image

    from touchroller_bringup.nodes.camera_node import CameraNode
    from touchroller_bringup.ros_domains import reserve_domain_id

    lease = reserve_domain_id()
    context = Context()
    rclpy.init(context=context, domain_id=lease.domain_id)
    camera = CameraNode(context=context, source=MemorySource(frames, frames, 1.0, 0), autostart=False)
    listener = Node("publish_path_listener", context=context)
    listener.create_subscription(Image, names.topic(names.IMAGE), lambda m: None, 1)
    times = []
    try:
        for i in range(repeats):
            start = time.perf_counter()
            camera.publish_frame(frames[i % len(frames)], time.time_ns())
            times.append((time.perf_counter() - start) * 1e3)
    finally:
        camera.destroy_node()
        listener.destroy_node()
        context.try_shutdown()
        lease.release()
    return summarise(np.array(times))


TRANSPORTS = {
    "default": None,  # rmw_fastrtps_cpp's built-in transports (UDPv4 + SHM with 512 KB segments)
    "shm": ROOT / "config" / "fastdds_shm.xml",  # shared memory with segments that hold a whole image
    "shm_udp": ROOT / "config" / "fastdds_shm_udp.xml",  # the same plus UDPv4: the launch files' default
}
RECOMMENDED = "shm_udp"   # what `ros2 launch` uses unless the user names a profile


def use_transport(transport: str) -> None:
    """Select the Fast DDS profile; must run before rclpy creates the first participant in this process."""
    profile = TRANSPORTS[transport]
    if profile is None:
        os.environ.pop("FASTDDS_DEFAULT_PROFILES_FILE", None)
    else:
        os.environ["FASTDDS_DEFAULT_PROFILES_FILE"] = str(profile)


# ------------------------------------------------------------------ where frames go missing
# Runs in the perception node's process before the node is built (in-process or in the child). It asks
# DDS to report lost samples (RMW message_lost event), and watches the
# publication sequence numbers: a gap is a frame the node never processed. A gap that DDS did not report
# lost is a frame replaced in the keep-last history by a newer one before the node took it (skipped as
# stale); "while busy" = the newer frame had already arrived when the previous callback ended. The counts
# ride on the node's own /diagnostics status, so the probe receives them from either process.
INSTRUMENT_PRELUDE = r"""
import dataclasses as _dc, time as _time
import touchroller_bringup.nodes.perception_node as _pn
from touchroller_bringup import names as _names
_bench = {"gaps": 0, "busy": 0, "last_seq": None, "last_end": 0, "busy_ns": 0, "first": None,
          "durations": [], "qos": "?"}
_create = _pn.PerceptionNode.create_subscription
def _create_subscription(self, msg_type, topic, callback, qos_profile, **kwargs):
    sub = _create(self, msg_type, topic, callback, qos_profile, **kwargs)
    if topic == _names.IMAGE:
        _bench["qos"] = f"{sub.qos_profile.reliability.name.lower()} depth {sub.qos_profile.depth}"
    return sub
_pn.PerceptionNode.create_subscription = _create_subscription
_on_image_with_info = _pn.PerceptionNode._on_image_with_info
def _instrumented(self, msg, info):
    start = _time.time_ns()
    seq = info.get("publication_sequence_number") or 0
    received = info.get("received_timestamp") or 0
    last = _bench["last_seq"]
    if last is not None and seq > last + 1:
        _bench["gaps"] += seq - last - 1
        if received <= _bench["last_end"]:
            _bench["busy"] += seq - last - 1
    _bench["last_seq"] = seq
    _on_image_with_info(self, msg, info)
    end = _time.time_ns()
    _bench["first"] = _bench["first"] or start
    _bench["last_end"] = end
    _bench["busy_ns"] += end - start
    _bench["durations"].append((end - start) * 1e-6)
_pn.PerceptionNode._on_image_with_info = _instrumented
_status = _pn.PerceptionNode._diagnostic_status
def _diagnostic_status(self):
    status = _status(self)
    durations = sorted(_bench["durations"])
    pick = lambda q: durations[min(len(durations) - 1, int(q * len(durations)))] if durations else float("nan")
    span = _bench["last_end"] - (_bench["first"] or _bench["last_end"])
    values = dict(status.values, bench_lost=-1 if self.lost_in_transport is None else self.lost_in_transport,
                  bench_gaps=_bench["gaps"], bench_busy_skips=_bench["busy"], bench_callbacks=len(durations),
                  bench_callback_p50_ms=pick(0.5), bench_callback_p99_ms=pick(0.99),
                  bench_busy_fraction=_bench["busy_ns"] / span if span > 0 else float("nan"), bench_qos=_bench["qos"])
    return _dc.replace(status, values=values)
_pn.PerceptionNode._diagnostic_status = _diagnostic_status
"""


def image_qos_parameters(depth: int = 0, reliability: str = "BEST_EFFORT") -> dict[str, object]:
    """The perception node's QoS override parameters for its image subscription; depth 0: the node's default."""
    if reliability not in ("BEST_EFFORT", "RELIABLE"):
        raise ValueError(f"reliability must be BEST_EFFORT or RELIABLE, got {reliability!r}")
    if depth <= 0:
        return {}
    return {names.qos_override(names.IMAGE, names.DEFAULT_NAMESPACE, "subscription", "depth"): int(depth),
            names.qos_override(names.IMAGE, names.DEFAULT_NAMESPACE, "subscription", "reliability"):
                reliability.lower()}


def _number(values: dict[str, str], key: str) -> float:
    try:
        return float(values[key])
    except (KeyError, ValueError):
        return float("nan")


def run_rate(fps: float, count: int, processes: int, map_rate: float = 1.0, depth: int = 0,
             reliability: str = "BEST_EFFORT", extra_prelude: str = "") -> dict:
    """One run of the real graph in this process (and a child with processes=2); the figures of a `RateRun`."""
    references, contacts = synthetic_frames()
    source = MemorySource(references, contacts, fps=fps, count=count)
    graph = Graph(processes=processes, map_rate=map_rate, perception_prelude=INSTRUMENT_PRELUDE + extra_prelude,
                  perception_params=image_qos_parameters(depth, reliability))
    try:
        graph.run_camera(source, timeout_s=count / fps + 60)
        perception = graph.final_status()
        values, missing = latencies_ms(source, graph.probe)
    finally:
        graph.close()
    lost = _number(perception, "bench_lost")
    gaps = _number(perception, "bench_gaps")
    return {"stats": summarise(values), "missing": missing, "sent": len(source.contact_stamps),
            "published": source.seq, "camera_late": source.late,
            "received": _number(perception, "frames_received"),
            "lost": lost if lost >= 0 else float("nan"), "gaps": gaps,
            # lost also counts samples outside the window between the first and last frame processed
            "skipped": max(0.0, gaps - lost) if lost >= 0 else float("nan"),
            "busy_skips": _number(perception, "bench_busy_skips"),
            "callback_p50_ms": _number(perception, "bench_callback_p50_ms"),
            "callback_p99_ms": _number(perception, "bench_callback_p99_ms"),
            "busy_fraction": _number(perception, "bench_busy_fraction"),
            "qos": perception.get("bench_qos", "?")}


def run_plan(plan: list[dict]) -> list[Any]:
    """Run configurations one after the other in this process (all on the transport already selected):
    a `RateRun` for each rate, a `dds_slow_consumer.SlowConsumerRun` for each configuration with a delay."""
    rows: list[Any] = []
    for config in plan:
        if config.get("delay_ms"):
            from bench import dds_slow_consumer  # it imports this module: load it only when needed

            rows.append(dds_slow_consumer.run_and_judge(config["processes"], config["transport"],
                                                        config["seconds"], config["delay_ms"]))
            continue
        result = run_rate(config["fps"], int(config["seconds"] * config["fps"]), config["processes"],
                          config.get("map_rate", 1.0), config.get("depth", 0), config.get("reliability", "BEST_EFFORT"))
        rows.append(RateRun(**{**config, **result}))
    return rows


def measure_plan(transport: str, plan: list[dict]) -> list[Any]:
    """`run_plan` in a fresh interpreter with `transport` (Fast DDS reads its profile once per process)."""
    from bench.dds_slow_consumer import SlowConsumerRun

    plan = [{"transport": transport, **config} for config in plan]
    result = subprocess.run([sys.executable, "-m", __spec__.name, "--child", "--transports", transport,
                             "--plan", json.dumps(plan)], cwd=ROOT, capture_output=True, text=True, timeout=1800)
    for line in reversed(result.stdout.splitlines()):
        if line.startswith("["):
            return [SlowConsumerRun.from_json(row) if "delay_ms" in row else RateRun.from_json(row)
                    for row in json.loads(line)]
    raise RuntimeError(f"benchmark child failed: {result.stderr.strip().splitlines()[-3:]}")


def measure(transport: str, processes: int, fps: float, seconds: float, map_rate: float = 1.0, depth: int = 0,
            reliability: str = "BEST_EFFORT") -> RateRun:
    """One `run_rate` row in a fresh interpreter with `transport`; the row carries its configuration."""
    return measure_plan(transport, [{"processes": processes, "fps": fps, "seconds": seconds, "map_rate": map_rate,
                                     "depth": depth, "reliability": reliability}])[0]


# ------------------------------------------------------------------ the report section
SLOW_DELAY_MS = 50.0


@dataclass(frozen=True)
class DdsSection:
    """The DDS report section (or a latency/QoS table of `main`): the runs and how they were obtained."""

    quick: bool
    command: str
    machine: str
    date: str
    load: tuple[float, ...]           # load average at the end
    map_rate: float
    seconds: float                    # the whole measurement
    rows: tuple[RateRun, ...]
    slow_consumer: tuple[Any, ...] = ()     # dds_slow_consumer.SlowConsumerRun
    publish_path: LatencyStats | None = None
    publish_calls: int = 0


def run(quick: bool = False) -> DdsSection:
    """Latency, losses and skips at 30/60 Hz, and the slow-consumer check (report section, issue 7).

    quick: the launch default (shm_udp), perception in its own process, 2 s per rate, slow consumer 2.5 s
    (~20 s in all);
    full: the three transports x 1 and 2 processes x 30/60 Hz, 8 s each, slow consumer in 1 and 2 processes.
    """
    started = time.perf_counter()
    seconds = 2.0 if quick else 8.0
    process_counts = [2] if quick else [1, 2]
    rows: list[RateRun] = []
    slow: list[Any] = []
    for transport in [RECOMMENDED] if quick else list(TRANSPORTS):
        plan = [{"processes": processes, "fps": fps, "seconds": seconds}
                for processes in process_counts for fps in (30.0, 60.0)]
        if transport == RECOMMENDED:  # the slow consumer on the launch files' default transport
            plan += [{"processes": processes, "seconds": 2.5 if quick else 8.0, "delay_ms": SLOW_DELAY_MS}
                     for processes in process_counts]
        for row in measure_plan(transport, plan):
            (rows if isinstance(row, RateRun) else slow).append(row)
    calls = 50 if quick else 300
    publish = measure_publish_path(synthetic_frames(8)[1], calls)
    return DdsSection(quick, f"python -m bench.dds_latency {'--quick' if quick else '--section'}", machine(),
                      time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime()), os.getloadavg(), 1.0,
                      time.perf_counter() - started, tuple(rows), tuple(slow), publish, calls)


def _fmt(value: float, digits: int = 2) -> str:
    return "n/a" if value is None or not np.isfinite(value) else f"{value:.{digits}f}"


def _count(value: float) -> str:
    return "n/a" if value is None or not np.isfinite(value) else f"{value:.0f}"


def latency_goal(row: RateRun) -> str:
    """30 Hz: p50 <= 5 ms and p99 <= 15 ms; any rate: nothing dropped (skips of stale frames are by design)."""
    stats = row.stats
    problems = []
    if row.fps == 30.0 and not (stats.p50 <= 5 and stats.p99 <= 15):
        problems.append("p50 <= 5, p99 <= 15 ms")
    if not row.dropped == 0:  # NaN (the RMW does not report losses) is not a pass either
        problems.append(f"{_count(row.lost)} lost in transport, {row.camera_late} late at the camera")
    return "met" if not problems else f"NOT met ({'; '.join(problems)})"


def rows_table(rows: Sequence[RateRun]) -> list[str]:
    lines = [
        "| transport | processes | image QoS | rate (Hz) | contact frames | without contact | late at camera | "
        "lost in transport | skipped stale (while busy) | callback p50/p99 (ms) | consumer busy | "
        "latency p50 (ms) | p99 (ms) | max (ms) | goal |",
        "|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for row in rows:
        stats = row.stats
        lines.append(
            f"| {row.transport} | {row.processes} | {row.qos} | {row.fps:g} | {row.sent} | "
            f"{row.missing} | {row.camera_late} | {_count(row.lost)} | {_count(row.skipped)} "
            f"({_count(row.busy_skips)}) | {_fmt(row.callback_p50_ms, 1)}/{_fmt(row.callback_p99_ms, 1)} | "
            f"{_fmt(100 * row.busy_fraction, 0)}% | {_fmt(stats.p50)} | {_fmt(stats.p99)} | "
            f"{_fmt(stats.max)} | {latency_goal(row)} |")
    return lines


def to_markdown(result: DdsSection) -> str:
    """The section's tables; every number comes from `result` (a `run` or `main` result)."""
    rows = result.rows
    seconds = sorted({row.seconds for row in rows})
    lines = [
        f"Command: `{result.command}` ({_fmt(result.seconds, 0)} s); machine: {result.machine}; "
        f"{result.date}; timings depend on the machine's load (load average "
        f"{'/'.join(f'{x:.1f}' for x in result.load)} at the end). RMW "
        f"{os.environ.get('RMW_IMPLEMENTATION', 'rmw_fastrtps_cpp')} over loopback, 640x480 bgr8, "
        f"{'/'.join(f'{s:g}' for s in seconds)} s per run, perception map.publish_rate {result.map_rate:g} Hz.",
        "",
        "Latency = contact received by a probe node − the image's capture stamp. "
        "'shm_udp' = `config/fastdds_shm_udp.xml` "
        "(the launch files' default: shared memory with segments that hold a whole image, plus UDP for other hosts); "
        "'shm' = `config/fastdds_shm.xml` (the same without UDP); 'default' = Fast DDS built-in transports. With one "
        "process all nodes share an interpreter (as `touchroller scan`); with two the perception node runs in its "
        "own (as `ros2 launch`). 'late at camera' = frames the publishing thread read more than a frame period "
        "after capture (a real camera would have replaced them). 'lost in transport' = samples DDS reported lost "
        "to the perception node's subscription; 'skipped stale' = frames replaced in its keep-last history by a "
        "newer frame before it took them (by design when the node is slower than the camera); in brackets, the "
        "frames missing (lost or skipped) where the next frame arrived while the previous callback still ran. "
        "'consumer busy' = share of "
        "the run the image callback was running. Goals (issue 7): p50 ≤ 5 ms and p99 ≤ 15 ms at 30 Hz; no drops "
        "at 60 Hz (a drop = lost in transport or late at the camera; a stale frame skipped by a busy node is not).",
        "",
        *rows_table(rows),
        "",
    ]
    slow = result.slow_consumer
    if slow:
        lines += [
            f"Slow consumer: camera at 60 Hz, the perception callback slowed by {slow[0].delay_ms:g} ms (it "
            "can take 20 frames/s). Met when the latency stays bounded (max ≤ 4 × delay + a period) and does not "
            "grow (last second's median ≤ first second's + one delay); queueing would add ~0.67 s per second.",
            "",
            "| processes | seconds | frames sent | with a contact | p50 (ms) | p99 (ms) | max (ms) | first-second "
            "median | last-second median | result |",
            "|---|---|---|---|---|---|---|---|---|---|",
        ]
        for r in slow:
            s = r.stats
            lines.append(f"| {r.processes} | {r.seconds:g} | {r.sent} | {r.processed} | "
                         f"{_fmt(s.p50, 1)} | {_fmt(s.p99, 1)} | {_fmt(s.max, 1)} | "
                         f"{_fmt(r.first_second_median, 1)} | {_fmt(r.last_second_median, 1)} | "
                         f"{'met' if r.met else 'NOT met'} |")
        lines.append("")
    publish = result.publish_path
    if publish:
        lines += [f"Camera publish path (`CameraNode.publish_frame`: fill Image + CameraInfo and publish, VGA bgr8, "
                  f"{result.publish_calls} calls): p50 {_fmt(publish.p50, 3)} ms, "
                  f"p99 {_fmt(publish.p99, 3)} ms.", ""]
    lines += ["The 20 000-frame memory soak takes minutes and is not part of this section: see "
              "`bench/results/dds_soak.md` (command `python -m bench.dds_soak`) and `docs/dds.md`.", ""]
    return "\n".join(lines)


QOS_VARIANTS = [(depth, reliability) for reliability in ("BEST_EFFORT", "RELIABLE") for depth in (1, 2, 3)]

#: the report renders this bench's section from `--section`'s result (the full table is another run)
RECORDED = "dds_latency_section"
RECORDED_BY = "--section"

def load(path: Path) -> DdsSection:
    """A result this bench wrote (its JSON), for the report to render without running it again."""
    result: DdsSection = load_json(DdsSection, path)
    if result.slow_consumer:   # typed Any above (another bench's type): rebuilt by its own from_json
        from bench.dds_slow_consumer import SlowConsumerRun

        result = replace(result, slow_consumer=tuple(
            SlowConsumerRun.from_json(r) if isinstance(r, dict) else r for r in result.slow_consumer))
    return result



def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="the report's quick section (~20 s)")
    parser.add_argument("--section", action="store_true", help="the report's full section (~2 min)")
    parser.add_argument("--qos", action="store_true",
                        help="the perception image subscription's depth 1/2/3 x best effort/reliable at 60 Hz "
                             "(shm) instead of the latency table; writes bench/results/dds_qos.md")
    parser.add_argument("--processes", type=int, choices=(1, 2), nargs="+", default=[1, 2])
    parser.add_argument("--transports", choices=tuple(TRANSPORTS), nargs="+", default=list(TRANSPORTS))
    parser.add_argument("--seconds", type=float, default=20.0, help="length of each run")
    parser.add_argument("--map-rate", type=float, default=1.0, help="perception node's map.publish_rate")
    parser.add_argument("--out", default="")
    parser.add_argument("--child", action="store_true", help=argparse.SUPPRESS)
    parser.add_argument("--plan", default="[]", help=argparse.SUPPRESS)
    args = parser.parse_args(argv)
    if args.child:
        use_transport(args.transports[0])
        print(to_json(run_plan(json.loads(args.plan))), flush=True)
        return 0
    command = ("python -m bench.dds_latency " + " ".join(argv if argv is not None else sys.argv[1:])).strip()
    if args.quick or args.section:
        result = run(quick=args.quick)
        out = Path(args.out or results_path(f"dds_latency{'' if args.quick else '_section'}", args.quick))
    else:
        started = time.perf_counter()
        if args.qos:
            configs = [("shm", processes, 60.0, depth, reliability)
                       for processes in args.processes for depth, reliability in QOS_VARIANTS]
        else:
            configs = [(transport, processes, fps, 0, "BEST_EFFORT")
                       for transport in args.transports for processes in args.processes for fps in (30.0, 60.0)]
        rows = []
        for transport, processes, fps, depth, reliability in configs:  # one interpreter each: no carry-over
            rows.append(measure(transport, processes, fps, args.seconds, args.map_rate, depth, reliability))
            print("\n".join(rows_table(rows[-1:])[2:]), flush=True)
        publish = None if args.qos else measure_publish_path(synthetic_frames(8)[1], 300)
        result = DdsSection(False, command, machine(), time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime()),
                            os.getloadavg(), args.map_rate, time.perf_counter() - started, tuple(rows), (),
                            publish, 300)
        out = Path(args.out or RESULTS / ("dds_qos.md" if args.qos else "dds_latency.md"))
    title = ("# DDS: the perception node's image QoS at 60 Hz" if args.qos
             else "# DDS latency: image published -> contact received")
    out.parent.mkdir(parents=True, exist_ok=True)
    atomic_write_text(out, f"{title}\n\n{to_markdown(result)}")
    atomic_write_text(out.with_suffix(".json"), to_json(result, indent=1))
    print(f"wrote {out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
