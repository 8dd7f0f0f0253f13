"""DDS latency over loopback: image published -> contact received (p50/p99) at 30 Hz, drops at 60 Hz.

The real graph: `touchroller_driver.camera_node.CameraNode` publishes 640x480 bgr8 frames (reliable)
from an in-memory source, `touchroller_perception.perception_node.PerceptionNode` detects contacts,
and a probe node receives `/touchroller/contacts`. Latency = probe receive time - contact stamp,
where the contact carries the image's capture stamp (taken just before the camera node publishes).
`--processes 2` runs the perception node in its own process (as `ros2 launch` would); 1 runs all
nodes in one process, each on its own executor thread (as `touchroller scan` does).

Goals (issue 7): p50 <= 5 ms and p99 <= 15 ms at 30 Hz; no drops at 60 Hz.
Results: bench/results/dds_latency.md. Other DDS benchmarks (dds_slow_consumer, dds_soak) import
the graph helpers from here.
"""
from __future__ import annotations

import argparse
import json
import os
import platform
import subprocess
import sys
import threading
import time
from collections import deque
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))
RESULTS = ROOT / "bench" / "results"

WIDTH, HEIGHT = 640, 480
REFERENCE_FRAMES = 30  # no-contact frames first: the perception node takes its reference from the first 5 it gets


# ------------------------------------------------------------------ frames
def synthetic_frames(count: int = 48, seed: int = 0) -> tuple[list[np.ndarray], list[np.ndarray]]:
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
        return np.clip(image + rng.normal(0, 1.0, image.shape), 0, 255).astype(np.uint8)

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
    """A FrameSource that replays frames from memory at `fps`, stamped at read (capture) time.

    The first frames are the no-contact reference; the rest cycle through contact frames.
    `stamps` records every delivered stamp (frames that should each produce a contact).
    """

    def __init__(self, references, contacts, fps: float, count: int, clock_ns=time.time_ns, record: bool = True):
        self.references, self.contacts = references, contacts
        self.period = 1.0 / fps
        self.count = count
        self.clock_ns = clock_ns
        self.seq = 0
        self.start: float | None = None
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
            self.start = time.monotonic()
        due = self.start + self.seq * self.period
        wait = due - time.monotonic()
        if wait > timeout:
            time.sleep(timeout)
            return None
        if wait > 0:
            time.sleep(wait)
        if self.seq < REFERENCE_FRAMES:
            image = self.references[self.seq]
        else:
            image = self.contacts[(self.seq - REFERENCE_FRAMES) % len(self.contacts)]
        stamp = self.clock_ns()
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
    record: bool = True  # False: keep only a count and the last latencies (the soak must not grow)
    count: int = 0
    recent_ms: deque = field(default_factory=lambda: deque(maxlen=2000))

    def on_diagnostics(self, msg) -> None:
        for status in msg.status:
            if "perception" in status.name:
                self.perception_status = {kv.key: kv.value for kv in status.values}

    def on_contact(self, msg) -> None:
        now = time.time_ns()
        stamp = msg.header.stamp.sec * 1_000_000_000 + msg.header.stamp.nanosec
        with self.lock:
            self.count += 1
            if self.record:
                self.arrivals.setdefault(stamp, now)
            else:
                self.recent_ms.append((now - stamp) * 1e-6)


class Graph:
    """Camera node + perception node (in-process or a child process) + contact probe, on one domain."""

    def __init__(self, processes: int = 1, domain_id: int | None = None, perception_prelude: str = "",
                 map_rate: float = 1.0, record: bool = True) -> None:
        import rclpy
        from geometry_msgs.msg import PointStamped
        from rclpy.context import Context
        from rclpy.executors import SingleThreadedExecutor
        from rclpy.node import Node
        from rclpy.parameter import Parameter

        self.domain_id = domain_id if domain_id is not None else 100 + os.getpid() % 100
        os.environ["ROS_DOMAIN_ID"] = str(self.domain_id)
        os.environ.setdefault("ROS_AUTOMATIC_DISCOVERY_RANGE", "LOCALHOST")
        self.context = Context()
        rclpy.init(context=self.context, domain_id=self.domain_id)
        self.probe = Probe(record=record)
        self.probe_node = Node("latency_probe", context=self.context)
        self.probe_node.create_subscription(PointStamped, "/touchroller/contacts", self.probe.on_contact, 100)
        from diagnostic_msgs.msg import DiagnosticArray

        self.probe_node.create_subscription(DiagnosticArray, "/diagnostics", self.probe.on_diagnostics, 10)
        self.executors = []
        self.threads = []
        self.child: subprocess.Popen | None = None
        self.perception = None
        if processes == 2:
            code = (f"{perception_prelude}\nfrom touchroller_perception.perception_node import main\n"
                    f"main(['--ros-args', '-p', 'map.publish_rate:={map_rate}'])")
            self.child = subprocess.Popen([sys.executable, "-c", code], cwd=ROOT, env=dict(os.environ),
                                          stdout=subprocess.DEVNULL, stderr=None if os.environ.get("DDS_BENCH_VERBOSE") else subprocess.DEVNULL)
        else:
            exec(perception_prelude, {})  # the same code the child process would run (e.g. a slow-down)
            from touchroller_perception.perception_node import PerceptionNode

            self.perception = PerceptionNode(context=self.context,
                                             parameter_overrides=[Parameter("map.publish_rate", value=map_rate)])
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
        from touchroller_driver.camera_node import CameraNode

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


def latencies_ms(source: MemorySource, probe: Probe) -> tuple[np.ndarray, int]:
    """Latency of each contact frame that got a contact (ms), and how many frames got none."""
    with probe.lock:
        arrivals = dict(probe.arrivals)
    got = [(arrivals[s] - s) * 1e-6 for s in source.contact_stamps if s in arrivals]
    return np.array(got), len(source.contact_stamps) - len(got)


def machine() -> str:
    cpu = "unknown CPU"
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                cpu = line.split(":", 1)[1].strip()
                break
    except OSError:
        pass
    return f"{os.cpu_count()} cores (nproc {len(os.sched_getaffinity(0))}), {cpu}, Python {platform.python_version()}"


def summarise(values: np.ndarray) -> dict[str, float]:
    if values.size == 0:
        return {"p50": float("nan"), "p99": float("nan"), "max": float("nan"), "mean": float("nan")}
    return {"p50": float(np.percentile(values, 50)), "p99": float(np.percentile(values, 99)),
            "max": float(values.max()), "mean": float(values.mean())}


def measure_publish_path(frames: list[np.ndarray], repeats: int = 200) -> dict[str, float]:
    """Time of CameraNode.publish_frame (fill the Image + CameraInfo, serialize, hand to DDS) for VGA."""
    import rclpy
    from rclpy.context import Context
    from rclpy.node import Node
    from sensor_msgs.msg import Image

    from touchroller_driver.camera_node import CameraNode

    context = Context()
    rclpy.init(context=context, domain_id=(os.getpid() % 100) + 2)
    camera = CameraNode(context=context, source=MemorySource(frames, frames, 1.0, 0), autostart=False)
    listener = Node("publish_path_listener", context=context)
    listener.create_subscription(Image, "/touchroller/image_raw", lambda m: None, 1)
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
    return summarise(np.array(times))


TRANSPORTS = {
    "default": None,  # rmw_fastrtps_cpp's built-in transports (UDPv4 + SHM with 512 KB segments)
    "shm": ROOT / "config" / "fastdds_shm.xml",  # shared memory with segments that hold a whole image
}


def use_transport(transport: str) -> None:
    """Select the Fast DDS profile; must run before rclpy creates the first participant in this process."""
    profile = TRANSPORTS[transport]
    if profile is None:
        os.environ.pop("FASTDDS_DEFAULT_PROFILES_FILE", None)
    else:
        os.environ["FASTDDS_DEFAULT_PROFILES_FILE"] = str(profile)


def run_rate(fps: float, count: int, processes: int, map_rate: float) -> dict:
    references, contacts = synthetic_frames()
    source = MemorySource(references, contacts, fps=fps, count=count)
    graph = Graph(processes=processes, map_rate=map_rate)
    try:
        graph.run_camera(source, timeout_s=count / fps + 60)
        time.sleep(1.2)  # one more diagnostics period from the perception node
        values, missing = latencies_ms(source, graph.probe)
        perception = dict(graph.probe.perception_status)
    finally:
        graph.close()
    return {"stats": summarise(values), "missing": missing, "sent": len(source.contact_stamps),
            "perception_dropped": perception.get("frames_dropped", "?"),
            "perception_received": perception.get("frames_received", "?")}


def run_isolated(args: list[str]) -> dict:
    """Run one configuration in a fresh interpreter (Fast DDS reads its profile once per process)."""
    result = subprocess.run([sys.executable, __file__, "--child", *args], cwd=ROOT, capture_output=True, text=True,
                            timeout=900)
    for line in reversed(result.stdout.splitlines()):
        if line.startswith("{"):
            return json.loads(line)
    raise RuntimeError(f"benchmark child failed: {result.stderr.strip().splitlines()[-1:]}")


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="short runs (CI sized)")
    parser.add_argument("--processes", type=int, choices=(1, 2), nargs="+", default=[1, 2])
    parser.add_argument("--transports", choices=tuple(TRANSPORTS), nargs="+", default=list(TRANSPORTS))
    parser.add_argument("--seconds", type=float, default=20.0, help="length of each run")
    parser.add_argument("--map-rate", type=float, default=1.0, help="perception node's map.publish_rate")
    parser.add_argument("--out", default=str(RESULTS / "dds_latency.md"))
    parser.add_argument("--child", action="store_true", help=argparse.SUPPRESS)
    parser.add_argument("--fps", type=float, default=30.0, help=argparse.SUPPRESS)
    args = parser.parse_args(argv)
    seconds = 4.0 if args.quick else args.seconds
    if args.child:
        use_transport(args.transports[0])
        print(json.dumps(run_rate(args.fps, int(seconds * args.fps), args.processes[0], args.map_rate)), flush=True)
        return 0
    command = "python bench/dds_latency.py " + " ".join(argv if argv is not None else sys.argv[1:])
    rows = []
    frames = synthetic_frames(8)[1]
    publish = measure_publish_path(frames, 50 if args.quick else 300)
    for transport in args.transports:
        for processes in args.processes:
            for fps in (30.0, 60.0):
                result = run_isolated(["--processes", str(processes), "--transports", transport, "--fps", str(fps),
                                       "--seconds", str(seconds), "--map-rate", str(args.map_rate)])
                rows.append((transport, processes, fps, result))
                stats = result["stats"]
                print(f"{transport} {processes} process(es) {fps:g} Hz: {result['sent']} frames, "
                      f"{result['missing']} without contact, p50 {stats['p50']:.2f} ms, p99 {stats['p99']:.2f} ms, "
                      f"max {stats['max']:.2f} ms", flush=True)
    lines = [
        "# DDS latency: image published -> contact received",
        "",
        f"Command: `{command.strip()}`  ",
        f"Machine: {machine()}  ",
        f"Date: {time.strftime('%Y-%m-%d %H:%M UTC', time.gmtime())}  ",
        f"RMW: {os.environ.get('RMW_IMPLEMENTATION', 'default (rmw_fastrtps_cpp)')}, loopback, "
        f"perception map.publish_rate={args.map_rate:g} Hz, {seconds:g} s per run",
        "",
        "Latency = probe receive time - image capture stamp (the contact carries the image stamp). "
        "Frames: 640x480 bgr8, synthetic gel with one contact each after 30 no-contact frames. "
        "'missed' = contact frames for which no contact arrived (a drop anywhere in the graph); "
        "'perception drops' = gaps in the publication sequence seen by the perception node "
        "(its /diagnostics, includes the reference frames). Transport 'default' = Fast DDS built-ins; "
        "'shm' = config/fastdds_shm.xml (shared memory, segments that hold a whole image). "
        "With 1 process, Fast DDS delivers intra-process and the transport does not matter.",
        "",
        "| transport | processes | rate (Hz) | frames | missed | perception drops | p50 (ms) | p99 (ms) | max (ms) | goal |",
        "|---|---|---|---|---|---|---|---|---|---|",
    ]
    for transport, processes, fps, result in rows:
        stats, missing = result["stats"], result["missing"]
        if fps == 30.0:
            goal = "met" if stats["p50"] <= 5 and stats["p99"] <= 15 else "NOT met (p50 <= 5, p99 <= 15)"
        else:
            goal = "met" if missing == 0 else f"NOT met ({missing} dropped)"
        lines.append(f"| {transport} | {processes} | {fps:g} | {result['sent']} | {missing} | "
                     f"{result['perception_dropped']} of {result['perception_received']} | {stats['p50']:.2f} | "
                     f"{stats['p99']:.2f} | {stats['max']:.2f} | {goal} |")
    lines += [
        "",
        f"Camera publish path (CameraNode.publish_frame: fill Image + CameraInfo, publish; VGA bgr8, "
        f"{50 if args.quick else 300} calls): p50 {publish['p50']:.3f} ms, p99 {publish['p99']:.3f} ms.",
        "",
    ]
    Path(args.out).parent.mkdir(parents=True, exist_ok=True)
    Path(args.out).write_text("\n".join(lines))
    print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
