"""`touchroller scan` in one process: the scan graph of `graph.py` on a multi-threaded executor.

The same nodes, names, params files and overrides as `scan.launch.py`, made from their `NodeSpec`s
alone (nothing is handed between them in process). With `use_sim` (the default) the sweep node's
simulated arm publishes the simulated clock and its pose on TF, and the camera node's simulated sensor
renders each frame at its time on that clock where TF has the roller, so the images follow the sweep
exactly and the same sweep gives the same images (graph.py runs the nodes with use_sim_time). The runner waits
for the perception node's no-contact reference, calls the sweep node's `~/start` service (the same
call a user makes), prints progress, and when the sweep ends writes to the output folder:

Topics are in the graph's namespace (`namespace:=...`, `touchroller` by default):

- `map.png`: the last tactile map published on `map` (`/touchroller/map`);
- `contacts.csv`: every `contacts` point, columns of `touchroller contacts`
  (u, v re-projected through the perception node's camera model; score, area, ellipse and confidence
  are not carried by PointStamped and are `nan`);
- `report.md`: the map as a picture (`map_preview.png`, linked to `map.png`), duration, frames, contacts, map
  size, skipped/dropped frames, the sweep's outcome, the coverage of the requested area and passes, and
  the findings of `findings.csv` when there is one (`touchroller_bringup.scan_report`);
- with `inspect:=true` (`auto`, the default: for a raster) `findings.csv` + `findings.png`, the defects in
  the world map (its height layer when it has one, else its intensity: `scan_findings`, docs/inspection.md);
  simulated, a scene with planted defects also gives `truth_findings.csv`;
- with `record`: `recording/`, a rosbag2 folder of the namespace's topics and `/diagnostics`
  (the driver's `Recorder`), for `touchroller contacts`, `touchroller map` or `touchroller replay`. It holds
  every frame the camera published: the camera's first frame waits for the recorder's subscription
  (`wait_for_subscribers`), the recorder spins on an executor and thread of its own, simulated the clock
  waits for its writer (`image_raw/recorded`), and at the end the camera stops before the recording closes;
  what a recorder that cannot keep up with a real camera loses is counted and said (report, stderr).

SIGINT (Ctrl-C), SIGTERM and SIGHUP stop the scan in order, at any moment: the arm first (the sweep
node's stop), then the frames in flight through perception, the map finished, the recording closed,
and map, contacts and report written with what there is (outcome `interrupted`). More signals change
nothing (`ros_main.StopSignals`); SIGKILL ends it at once.

A recording that fails on the way (a full disk) stops the scan the same way: the arm stops, the bag keeps
what it had committed (indexed, readable), and map, contacts and report are still written (outcome
`recording failed`, the report says what the bag kept); the command then exits with the recorder's error.
"""
from __future__ import annotations

import csv
import math
import os
import signal
import sys
import threading
import time
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from touchroller_bringup import names
from touchroller_bringup.errors import UserError
from touchroller_bringup.graph import Graph, GraphError, build_graph
from touchroller_bringup.image_conversion import stamp_to_ns
from touchroller_bringup.outputs import Output, check_outputs
from touchroller_bringup.scan_report import (
    PREVIEW,
    ScanCoverage,
    preview_image,
    read_findings,
    report_markdown,
    write_png,
)
from touchroller_perception.files import atomic_write, atomic_write_text

# with `record`: these topics of the scan's namespace, and /diagnostics
STOP_SIGNALS = (signal.SIGINT, signal.SIGTERM, signal.SIGHUP)
RECORDED_TOPICS = (names.IMAGE, names.CAMERA_INFO, names.CONTACTS, names.MAP, names.MAP_METADATA, names.TCP_POSE,
                   names.SWEEP_PROGRESS, names.DIAGNOSTICS, names.TF, names.TF_STATIC,   # with TF: re-maps offline
                   names.FINDINGS)
# the topics of the scan's namespace that only its own nodes may publish (and /clock when simulated)
GRAPH_TOPICS = (names.IMAGE, names.CAMERA_INFO, names.CONTACTS, names.MAP, names.MAP_METADATA, names.MAP_HEIGHT,
                names.MAP_MARKERS, names.TCP_POSE, names.SWEEP_PROGRESS, names.COVERAGE, names.SWEEP_PASS,
                names.IMAGE_DONE, names.FINDINGS)


OUTPUT_FILES = ("contacts.csv", "report.md", PREVIEW, "map.png", "map.yaml")
#: with `record`, the camera holds its first frame until this many subscriptions take its images: the scan's
#: own counter (the probe), the perception node and the recorder
IMAGE_SUBSCRIBERS_WITH_RECORDER = 3


@dataclass
class ScanOptions:
    out_dir: Path
    arguments: Mapping[str, str] = field(default_factory=dict)   # scan launch arguments (use_sim, ...)
    params_files: Sequence[Path] = ()
    overrides: Mapping[str, Any] = field(default_factory=dict)   # ROS parameters for every node declaring them
    reference_timeout_s: float = 30.0
    discovery_s: float = 2.0   # how long discovery may take to show another graph in the namespace
    seed: int = 0
    progress: Callable[[str], None] | None = print
    record: bool = False
    storage: str = "sqlite3"
    bag_format: str = "auto"      # touchroller_bringup.bag_format: which distribution's rosbag2 reads the recording
    height: bool = False          # also the height map: simulated, a photometric model made on the fly
    compress: bool = True         # the recording's images as lossless PNG (image_raw/compressed), MCAP chunks zstd


@dataclass
class ScanResult:
    out_dir: Path
    outcome: str            # done, stopped, fault, timeout, interrupted (by a signal: `signal`), recording failed
    message: str
    duration_s: float
    frames_published: int   # by the camera node, from its start to the end of the scan
    frames_processed: int   # taken by the perception node over the same time
    frames_dropped: int
    frames_malformed: int
    contacts: int
    map_shape: tuple[int, ...] | None
    files: dict[str, Path]
    sweep: str = ""         # what the sweep node answered to ~/start (length, speed, depth)
    recorded: dict[str, int] = field(default_factory=dict)  # topic -> messages in recording/
    world_map: dict[str, Any] | None = None   # the world map's frame, resolution, origin, latency, passes
    findings_summary: str = ""   # with inspect: what findings.csv holds (scan_findings.ScanFindings.summary)
    signal: int | None = None   # the signal that interrupted the scan
    frames_during_sweep: int | None = None   # published from ~/start to the end of the sweep
    failed: dict[str, str] = field(default_factory=dict)   # output -> why it could not be written
    coverage: ScanCoverage | None = None   # the requested area and how much of it the world map covers
    findings: list[Any] | None = None      # of DIR/findings.csv when the scan wrote one
    findings_problem: str = ""             # why findings.csv could not be read
    recording_lost: str = ""               # what the recorder itself counted lost, and why (RecorderStats.summary)

    @property
    def ok(self) -> bool:
        return self.outcome == "done"

    @property
    def images_not_recorded(self) -> int:
        """Camera frames published but not in the recording (raw or PNG); 0 without a recording. The scan stops
        the camera before it closes the recording, so every frame published counts: one the recorder lost
        (refused at its queue's bound, lost on the way, published before it subscribed) is said, never hidden."""
        if not self.recorded:
            return 0
        image_topics = {f"/{names.IMAGE}", f"/{names.IMAGE}/compressed"}
        images = sum(count for topic, count in self.recorded.items()
                     if any(topic.endswith(suffix) for suffix in image_topics))
        return max(0, self.frames_published - images)

    @property
    def recording_warning(self) -> str:
        """What the recording misses and why, in one sentence; "" when it holds every frame and message."""
        missing = self.images_not_recorded
        if not missing:
            return self.recording_lost
        why = self.recording_lost or "not taken by the recorder before it closed"
        return f"the recording misses {missing} of the {self.frames_published} frames published ({why})"


@dataclass
class _Collected:
    lock: threading.Lock = field(default_factory=threading.Lock)
    frames: int = 0
    contacts: list[tuple[int, float, float, float]] = field(default_factory=list)
    map_msg: Any = None
    progress: float = 0.0
    findings: int = 0       # MarkerArrays seen on `findings`


class Interrupted(Exception):
    """A stop signal arrived (raised by the waits of the scan's main thread)."""


class RecordingFailed(UserError):
    """The recorder stopped writing (e.g. a full disk): the scan stops the arm and writes what it has."""


class NodeFailed(UserError):
    """A node's callback raised on the scan's executor: a fault, the scan stops the arm and writes what it has."""


def _checker(stop: Any, recorder: Any = None, failures: Sequence[str] = ()) -> Callable[[], None]:
    def check() -> None:
        if stop is not None and stop.requested.is_set():
            raise Interrupted(f"interrupted by {stop.name}")
        if failures:
            raise NodeFailed(f"a node failed: {failures[0]}")
        if recorder is not None and recorder.failed.is_set():
            raise RecordingFailed(f"recording {recorder.path} failed: {recorder._writer.error}")
    return check


def run_scan(options: ScanOptions) -> ScanResult:
    """Run the scan graph until the sweep ends; write map, contacts and report to `options.out_dir`."""
    import rclpy
    from rclpy.context import Context
    from rclpy.executors import MultiThreadedExecutor
    from rclpy.signals import SignalHandlerOptions

    # our handlers, not rclpy's (they shut the context down and raise KeyboardInterrupt wherever the
    # main thread is): a signal only asks to stop; installed only from the main thread (a CLI run)
    from touchroller_bringup.heap import bound_heap_growth
    from touchroller_bringup.ros_main import StopSignals

    bound_heap_growth()   # a long scan's frames must not creep up the C heap (touchroller_bringup.heap)
    stop = StopSignals.install(STOP_SIGNALS) if threading.current_thread() is threading.main_thread() else None
    try:
        return _run_scan(options, stop, rclpy, Context, MultiThreadedExecutor, SignalHandlerOptions)
    finally:
        if stop is not None:
            StopSignals.uninstall()


def _run_scan(options: ScanOptions, stop: Any, rclpy: Any, Context: Any, MultiThreadedExecutor: Any,  # noqa: N803
              SignalHandlerOptions: Any) -> ScanResult:  # noqa: N803
    try:
        graph = build_graph("scan", options.arguments, options.params_files)
    except GraphError as exc:
        raise UserError(str(exc)) from None
    say = options.progress or (lambda _text: None)
    out_dir = Path(options.out_dir)
    check_outputs([Output("--out", out_dir, folder=True),
                   *(Output(f"--out {out_dir}'s", out_dir / name) for name in OUTPUT_FILES)],
                  {f"params file {i + 1}": path for i, path in enumerate(options.params_files)})
    if out_dir.exists() and not out_dir.is_dir():
        raise UserError(f"--out {out_dir} is a file; give a folder")
    _check_writable(out_dir)
    made_out_dir = not out_dir.exists()
    try:
        return _run_graph(options, stop, rclpy, Context, MultiThreadedExecutor, SignalHandlerOptions, graph, say,
                          out_dir)
    except UserError:
        # refused (a parameter, the arm, another graph, ...): no folder of ours left behind, empty or with a
        # recording of a scan that never swept (a scan that ran writes its outputs and returns instead)
        if made_out_dir and out_dir.is_dir() and not (out_dir / "report.md").exists():
            import shutil

            shutil.rmtree(out_dir, ignore_errors=True)
        raise


def _check_writable(out_dir: Path) -> None:
    """Before any node starts: the output folder (or the folder it will be made in) must be writable."""
    existing = out_dir.absolute()
    while not existing.exists() and existing != existing.parent:
        existing = existing.parent
    if os.statvfs(existing).f_flag & os.ST_RDONLY:
        raise UserError(f"--out {out_dir}: {existing} is on a read-only file system; give a folder elsewhere")
    if not os.access(existing, os.W_OK | os.X_OK):
        raise UserError(f"--out {out_dir}: {existing} is not writable by this user; give a folder elsewhere")


def _run_graph(options: ScanOptions, stop: Any, rclpy: Any, Context: Any, MultiThreadedExecutor: Any,  # noqa: N803
               SignalHandlerOptions: Any, graph: Graph, say: Callable[[str], None],  # noqa: N803
               out_dir: Path) -> ScanResult:
    # rclpy's executor loop is CPU-bound Python; the camera's render and perception make dozens of
    # short GIL-releasing OpenCV calls per frame, and each waits up to the switch interval to get the
    # GIL back (the convoy effect). At the default 5 ms the camera fell to 2-8 Hz here; at 0.5 ms it
    # keeps 30 Hz with every frame processed.
    switch_interval = sys.getswitchinterval()
    sys.setswitchinterval(min(switch_interval, 0.0005))
    # fastdds_profile:=...: the graph's own messages go intra-process (one participant), so the profile
    # only shapes how other processes (ros2 topic echo, rviz, a recorder elsewhere) reach this one; and
    # Fast DDS reads it when the process creates its first participant (normally this run's).
    saved_environment = {name: os.environ.get(name) for name in graph.environment}
    os.environ.update(graph.environment)
    context = Context()
    try:
        # not sys.argv: rcl would take `name:=value` items for remaps
        rclpy.init(context=context, args=[], signal_handler_options=SignalHandlerOptions.NO)
    except BaseException:
        sys.setswitchinterval(switch_interval)
        _restore_environment(saved_environment)
        raise
    from rclpy.executors import SingleThreadedExecutor

    nodes: list[Any] = []
    executor = MultiThreadedExecutor(num_threads=4, context=context)
    spinner: threading.Thread | None = None
    recorder_executor: Any = None
    recorder_spinner: threading.Thread | None = None
    stop_spinning = threading.Event()
    sweep = None
    try:
        # The probe first: DDS discovery finds another graph in our namespace while the node classes
        # import, and the scan stops before any of its nodes publishes an image or a transform.
        check = _checker(stop)
        probe, collected, start_client = _make_probe(context, nodes, graph.namespace)
        probe_made = time.monotonic()
        try:
            classes = {spec.key: spec.load_class() for spec in graph.nodes}
        except GraphError as exc:
            raise UserError(str(exc)) from None
        topics = _graph_topics(graph)
        _check_namespace_is_free(probe, graph.namespace, probe_made + options.discovery_s, topics)
        sweep, camera, perception = _make_nodes(graph, classes, context, options, nodes)
        out_dir.mkdir(parents=True, exist_ok=True)   # only now: a scan that cannot start leaves no folder
        recorder = _make_recorder(out_dir, options, context, nodes, graph.namespace) if options.record else None
        failures: list[str] = []   # callbacks that raised on the executor (`_spin`)
        check = _checker(stop, recorder, failures)
        for node in nodes:
            if node is not recorder:
                executor.add_node(node)
        spinner = threading.Thread(target=_spin, args=(executor, stop_spinning, failures),
                                   name="scan-executor", daemon=True)
        spinner.start()
        if recorder is not None:
            # its own executor and thread: its callbacks only queue, and must not wait behind the perception
            # node's (a map update, a whole-map flat field) while the camera goes on publishing
            recorder_executor = SingleThreadedExecutor(context=context)
            recorder_executor.add_node(recorder)
            recorder_spinner = threading.Thread(target=_spin, args=(recorder_executor, stop_spinning, failures),
                                                name="scan-recorder-executor", daemon=True)
            recorder_spinner.start()
        say(f"scan: graph up ({', '.join(n.get_name() for n in (sweep, camera, perception))}); "
            f"{'simulated sensor and arm' if graph.arguments['use_sim'] == 'true' else 'camera and UR5'}")
        if graph.rviz_config:
            say("scan: rviz:=true starts RViz 2 under `ros2 launch`; beside this scan run: "
                f"rviz2 -d {graph.rviz_config}")
        started = time.monotonic()
        published_at_start: int | None = None
        try:
            _wait_for_reference(perception, sweep, collected, options.reference_timeout_s, check)
            _check_namespace_is_ours(probe, graph.namespace, topics, nodes)
            if recorder is not None:
                _wait_for_recorder(recorder, options.reference_timeout_s, check)
            started = time.monotonic()
            published_at_start = _published(camera, collected)
            _call_start(start_client, sweep, check)
            # the perception node starts a new map when the roll starts (it follows /touchroller/sweep_progress)
            outcome, message = _follow_sweep(sweep, collected, say, check)
        except (Interrupted, RecordingFailed, NodeFailed) as exc:
            _stop_arm(sweep)   # the arm first
            outcome = ("interrupted" if isinstance(exc, Interrupted) else "fault" if isinstance(exc, NodeFailed)
                       else "recording failed")
            message = str(exc)
            say(f"scan: {message}: arm stopped; writing what there is")
        duration = time.monotonic() - started
        during_sweep = None if published_at_start is None else _published(camera, collected) - published_at_start
        _wait_for_perception(sweep, perception)
        _flush_map(perception, collected)
        answer = sweep.last_answer[2] if sweep.last_answer else ""
        recorded: dict[str, int] = {}
        recording_lost = ""
        if recorder is not None:
            # the recording ends with the camera's last frame: none published after it closed, none in flight
            camera.stop()
            _wait_for_recorder_to_take(recorder, camera)
            try:
                recorder.close()  # drains and finalises the bag (UserError if writing failed)
                recorded = dict(recorder.counts)
                recording_lost = recorder.stats().summary()
            except UserError as exc:   # what the bag kept is in the message; the map must not be lost too
                outcome, message = "recording failed", str(exc)
        result = _write_outputs(out_dir, graph, perception, collected, outcome, message, duration, answer, recorded,
                                camera, during_sweep, sweep, recording_lost)
        if stop is not None and outcome == "interrupted":
            result.signal = stop.last_signal
        return result
    finally:
        _stop_arm(sweep)   # a sweep still moving (an error above): stopped before anything is destroyed
        stop_spinning.set()
        for thread in (spinner, recorder_spinner):
            if thread is not None:
                # Nodes must not be destroyed under a running spin_once (rclpy then raises in the thread):
                # wait for it however loaded the machine is; it ends within one spin_once and its callbacks.
                thread.join(timeout=60.0)
        _drain(executor)
        executor.shutdown(timeout_sec=2.0)
        if recorder_executor is not None:
            recorder_executor.shutdown(timeout_sec=2.0)
        for node in reversed(nodes):
            node.destroy_node()
        context.try_shutdown()
        sys.setswitchinterval(switch_interval)
        _restore_environment(saved_environment)


def _stop_arm(sweep: Any) -> None:
    """The sweep node's stop path (the arm halts) while the sweep is moving; waits for its answer."""
    if sweep is not None and getattr(sweep, "active", sweep.sequencer.active):
        sweep.request_stop()


def _restore_environment(saved: Mapping[str, str | None]) -> None:
    for name, value in saved.items():
        if value is None:
            os.environ.pop(name, None)
        else:
            os.environ[name] = value


def _spin(executor: Any, stop: threading.Event, failures: list[str] | None = None) -> None:
    """Spin until `stop`. A callback that raises must not end this thread (no callback of the graph would
    run again while the arm goes on): its error goes to `failures`, which the scan's checks turn into a
    fault that stops the arm."""
    while not stop.is_set():
        try:
            executor.spin_once(timeout_sec=0.05)
        except Exception as exc:  # noqa: BLE001 - whatever a callback raised, the executor goes on
            if failures is None:
                raise
            if len(failures) < 10:
                failures.append(f"{type(exc).__name__}: {' '.join(str(exc).split())}")
            time.sleep(0.05)   # an error that repeats does not make this a busy loop


def _drain(executor: Any, timeout: float = 2.0) -> None:
    """Let callbacks already handed to the thread pool finish before `shutdown` destroys the executor's
    guard condition: rclpy's MultiThreadedExecutor.shutdown destroys it first, and a queued callback
    then dies on it ("cannot use Destroyable because destruction was requested")."""
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline and any(not f.done() for f in list(getattr(executor, "_futures", []))):
        time.sleep(0.01)


# -- building the graph ---------------------------------------------------------------------------

def _make_nodes(graph: Graph, classes: Mapping[str, type], context: Any, options: ScanOptions,
                nodes: list[Any]) -> tuple[Any, Any, Any]:
    from rclpy.exceptions import ParameterException

    overrides = dict(options.overrides)

    def create(key: str) -> Any:
        spec = graph.node(key)
        while True:
            try:
                node = classes[key](context=context, **spec.node_kwargs(overrides))
                break
            except (ParameterException, ValueError) as exc:  # bad parameter types or values
                name = _integer_for_double(exc, overrides)
                if name is None:
                    raise UserError(f"cannot start node {spec.full_name}: {' '.join(str(exc).split())}") from None
                overrides[name] = float(overrides[name])  # `speed:=1` means 1.0, as ros2 param set would not
            except UserError as exc:   # a start-up value a node's config binding refused (one line already)
                raise UserError(f"cannot start node {spec.full_name}: {exc}") from None
        nodes.append(node)
        return node

    if graph.arguments["use_sim"] == "true":
        from touchroller_driver.sim import load_scene

        try:   # the camera node would only log it: say it here, in one line
            load_scene(graph.arguments["scene"])
        except (OSError, ValueError, KeyError) as exc:
            raise UserError(f"scene {graph.arguments['scene']!r}: {exc}") from None
        overrides.setdefault("seed", options.seed)
        if options.height and not overrides.get("map.height.photometric"):
            overrides.update(_sim_photometric(options.out_dir, graph.arguments["scene"], int(overrides["seed"])))
    if options.height and not (overrides.get("map.height.photometric") and overrides.get("map.height.reference")):
        raise UserError("--height on a real sensor needs its photometric model: map.height.photometric:=P.npz "
                        "map.height.reference:=REF.png ('touchroller calibrate photometric', docs/height.md)")
    if options.record:   # the camera's first frame only once the recorder takes it too: the recording is whole
        overrides.setdefault("wait_for_subscribers", IMAGE_SUBSCRIBERS_WITH_RECORDER)
    sweep = create("sweep")
    camera = create("camera")
    perception = create("perception")
    _check_overrides({name: value for name, value in options.overrides.items()
                      if not (options.record and name in _recorder_parameters())}, nodes)
    return sweep, camera, perception


def _sim_photometric(out_dir: Path, scene_name: str, seed: int) -> dict[str, str]:
    """The simulated sensor's photometric model, calibrated on the fly (`touchroller_driver.sim.photometric`)
    and written to out_dir as photometric.npz + reference.png: the perception node's map.height.* overrides."""
    import cv2

    from touchroller_driver.sim import SimulatedSensor, load_scene
    from touchroller_driver.sim.photometric import sim_photometric

    try:
        made = sim_photometric(SimulatedSensor(load_scene(scene_name), seed=seed))
    except ValueError as exc:
        raise UserError(f"--height: cannot calibrate the simulated sensor of scene {scene_name!r}: {exc}") from None
    out_dir.mkdir(parents=True, exist_ok=True)
    model, reference = out_dir / "photometric.npz", out_dir / "reference.png"
    encoded, data = cv2.imencode(".png", made.reference)
    if not encoded:
        raise UserError("--height: cannot encode the reference frame as PNG")
    with atomic_write(model, "wb") as stream:
        made.calibration.model.save_to(stream)
    with atomic_write(reference, "wb") as stream:
        stream.write(data.tobytes())
    return {"map.height.photometric": str(model), "map.height.reference": str(reference)}


def _integer_for_double(exc: Exception, overrides: Mapping[str, Any]) -> str | None:
    """The override that was an integer where the node declared a double, if that is what failed."""
    text = str(exc)
    if "of type 'INTEGER', expecting type 'DOUBLE'" not in text:
        return None
    for name, value in overrides.items():
        if f"parameter '{name}'" in text and isinstance(value, int) and not isinstance(value, bool):
            return name
    return None


def _recorder_parameters() -> tuple[str, ...]:
    """The recorder's ROS parameters (queue.max_bytes, ...): with `record`, overrides the recorder takes."""
    from touchroller_bringup.recorder import RECORDER_PARAMETERS

    return tuple(RECORDER_PARAMETERS)


def _check_overrides(overrides: Mapping[str, Any], nodes: Sequence[Any]) -> None:
    unknown = [name for name in overrides if not any(node.has_parameter(name) for node in nodes)]
    if unknown:
        raise UserError(f"no node of the scan graph has parameter(s) {', '.join(unknown)}")


def _make_recorder(out_dir: Path, options: ScanOptions, context: Any, nodes: list[Any], namespace: str) -> Any:
    from touchroller_bringup.recorder import Recorder

    path = out_dir / "recording"
    if path.exists():
        raise UserError(f"{path} already exists; choose another --out")
    topics = [names.topic(name, namespace) for name in RECORDED_TOPICS]
    from rclpy.exceptions import ParameterException
    from rclpy.parameter import Parameter

    mine = [Parameter(name, value=value) for name, value in options.overrides.items() if name in _recorder_parameters()]
    try:
        recorder = Recorder(path, topics=topics, storage=options.storage, distro=options.bag_format,
                            compress=options.compress, context=context, parameter_overrides=mine)
    except (ParameterException, ValueError) as exc:
        raise UserError(f"cannot start the recorder: {' '.join(str(exc).split())}") from None
    nodes.append(recorder)
    return recorder


def _wait_for_recorder(recorder: Any, timeout: float, check: Callable[[], None] = lambda: None) -> None:
    """The recorder subscribes once it has seen a publisher; start the sweep only after it has."""
    deadline = time.monotonic() + timeout
    image_topic = recorder.topics[0]
    while image_topic not in recorder.counts:
        check()
        if time.monotonic() > deadline:
            raise UserError(f"the recorder did not find {image_topic} within {timeout:.0f} s")
        time.sleep(0.02)


def _wait_for_recorder_to_take(recorder: Any, camera: Any, timeout: float = 10.0) -> None:
    """Once the camera has stopped: until the recorder has taken (or counted lost) every image it published,
    so none is in flight when the recording closes."""
    published = getattr(camera, "published", None)
    if not isinstance(published, int):
        return
    image_topic = recorder.topics[0]
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        stats = recorder.stats()
        taken = (stats.received.get(image_topic, 0) + stats.overflowed.get(image_topic, 0)
                 + stats.lost_in_transport.get(image_topic, 0))
        if taken >= published:
            return
        time.sleep(0.02)


def _make_probe(context: Any, nodes: list[Any], namespace: str) -> tuple[Any, _Collected, Any]:
    from geometry_msgs.msg import PointStamped
    from rclpy.node import Node
    from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy
    from sensor_msgs.msg import Image
    from std_msgs.msg import Float32
    from std_srvs.srv import Trigger
    from visualization_msgs.msg import MarkerArray

    probe = Node("scan", namespace=namespace, context=context)   # relative names: the graph's namespace
    nodes.append(probe)
    collected = _Collected()

    def on_frame(_raw: bytes) -> None:
        with collected.lock:
            collected.frames += 1

    def on_contact(msg: PointStamped) -> None:
        stamp_ns = stamp_to_ns(msg.header.stamp)
        with collected.lock:
            collected.contacts.append((stamp_ns, msg.point.x, msg.point.y, msg.point.z))

    def on_map(msg: Image) -> None:
        with collected.lock:
            collected.map_msg = msg

    def on_progress(msg: Float32) -> None:
        collected.progress = float(msg.data)

    def on_findings(_raw: bytes) -> None:
        with collected.lock:
            collected.findings += 1

    reliable = QoSProfile(depth=100, reliability=ReliabilityPolicy.RELIABLE)
    latched = QoSProfile(depth=1, reliability=ReliabilityPolicy.RELIABLE,
                         durability=DurabilityPolicy.TRANSIENT_LOCAL)
    probe.create_subscription(Image, names.IMAGE, on_frame, reliable, raw=True)  # count only: no decoding
    probe.create_subscription(PointStamped, names.CONTACTS, on_contact, QoSProfile(depth=1000))
    probe.create_subscription(Image, names.MAP, on_map, latched)
    probe.create_subscription(Float32, names.SWEEP_PROGRESS, on_progress, 10)
    probe.create_subscription(MarkerArray, names.FINDINGS, on_findings, latched, raw=True)   # count only
    start_client = probe.create_client(Trigger, f"{names.SWEEP_NODE}/{names.START}")
    return probe, collected, start_client


# -- running ----------------------------------------------------------------------------------------

def _wait_for_reference(perception: Any, sweep: Any, collected: _Collected, timeout: float,
                        check: Callable[[], None] = lambda: None) -> None:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        check()
        status = sweep.status
        if status.phase.value == "fault":
            raise UserError(f"arm: {status.message}")
        detector = getattr(perception, "detector", None)
        ready = detector.reference_ready if detector is not None else collected.frames >= 5
        if ready:
            return
        time.sleep(0.05)
    raise UserError(f"no usable camera frames within {timeout:.0f} s ({collected.frames} received)")


def _namespace_taken(namespace: str, seen: str) -> UserError:
    return UserError(f"another TouchRoller graph runs in namespace /{namespace} on this ROS domain ({seen}): give "
                     "this scan its own namespace (touchroller scan --namespace NAME) or its own ROS_DOMAIN_ID")


def _graph_topics(graph: Graph) -> list[str]:
    """The absolute topics only this scan's nodes may publish: its namespace's, and /clock when simulated."""
    topics = [names.topic(name, graph.namespace) for name in GRAPH_TOPICS]
    return topics + [names.CLOCK] if graph.arguments.get("use_sim") == "true" else topics


UNKNOWN_NODE = "_NODE_NAME_UNKNOWN_"   # rmw's name for a node discovery has not told yet
UNKNOWN_NODE_TEXT = "a node not discovered yet"


def _foreign_publishers(probe: Any, topics: Sequence[str], ours: set[str]) -> list[str]:
    """'topic (node)' for every publisher on `topics` whose node is not one of `ours` (full names)."""
    found = []
    for topic in topics:
        for endpoint in probe.get_publishers_info_by_topic(topic):
            if endpoint.node_name == UNKNOWN_NODE:   # DDS showed the endpoint before its node
                found.append(f"{topic} ({UNKNOWN_NODE_TEXT})")
                continue
            node = names.topic(endpoint.node_name, endpoint.node_namespace.strip("/"))
            if node not in ours:
                found.append(f"{topic} ({node})")
    return sorted(set(found))


def _publishers_taken(found: Sequence[str]) -> UserError:
    return UserError(f"another node publishes on this scan's topics: {', '.join(found)} (a touchroller replay, a "
                     "ros2 topic pub, another graph): stop it, or give this scan its own namespace (touchroller scan "
                     "--namespace NAME) or its own ROS_DOMAIN_ID")


def _check_namespace_is_free(probe: Any, namespace: str, until: float, topics: Sequence[str] = ()) -> None:
    """Refuse to start when another graph (a scan, a launch file) has nodes in this namespace on this ROS
    domain: our `~/start` call would start its sweep too, and our camera's images and our arm's
    transforms (the same frame names) would mix with its own; or when any node publishes on `topics`
    (a `touchroller replay` runs in no namespace of ours). Only the probe exists yet; discovery is given
    until `until` (monotonic) to show the others."""
    here = names.topic("x", namespace)
    while True:
        found = sorted(names.topic(name, ns) for name, ns in probe.get_node_names_and_namespaces()
                       if names.topic("x", ns) == here)   # nodes in this very namespace
        ours = names.topic(probe.get_name(), namespace)
        if found.count(ours) > 1 or any(name != ours for name in found):
            raise _namespace_taken(namespace, ", ".join(sorted(set(found))))
        foreign = _foreign_publishers(probe, topics, set())
        late = time.monotonic() >= until
        if foreign and (late or not any(UNKNOWN_NODE_TEXT in f for f in foreign)):   # a moment for its name
            raise _publishers_taken(foreign)
        if late:
            return
        time.sleep(0.05)


def _check_namespace_is_ours(probe: Any, namespace: str, topics: Sequence[str] = (), nodes: Sequence[Any] = ()) -> None:
    """The same once the reference is captured, for two scans that started at the same moment (neither
    saw the other yet), and for a publisher that appeared on our topics since: both stop before the arm
    moves."""
    ours = [node.get_fully_qualified_name() for node in nodes]
    seen = [names.topic(name, ns.strip("/")) for name, ns in probe.get_node_names_and_namespaces()]
    twice = sorted({name for name in ours if seen.count(name) > 1})
    if twice:
        raise _namespace_taken(namespace, f"{', '.join(twice)} exists twice")
    full = names.topic(names.SWEEP_NODE, namespace)
    if seen.count(full) > 1:
        raise _namespace_taken(namespace, f"{full} exists twice")
    foreign = _foreign_publishers(probe, topics, set(ours))
    if foreign:
        raise _publishers_taken(foreign)


def _call_start(client: Any, sweep: Any, check: Callable[[], None] = lambda: None) -> None:
    deadline = time.monotonic() + 20.0   # in-process, but discovery is slow on a loaded machine
    while not client.wait_for_service(timeout_sec=0.1):
        check()
        if time.monotonic() > deadline:
            raise UserError("the sweep node's ~/start service is not available")
    future = client.call_async(client.srv_type.Request())
    deadline = time.monotonic() + 10.0
    while not future.done() and time.monotonic() < deadline:
        time.sleep(0.01)
    if not future.done():
        raise UserError("the sweep node did not answer ~/start")
    response = future.result()
    if not response.success:
        message = getattr(response, "message", "") or (sweep.last_answer or ("", False, ""))[2]
        raise UserError(f"sweep refused to start: {message or sweep.status.message}")


def _follow_sweep(sweep: Any, collected: _Collected, say: Callable[[str], None],
                  check: Callable[[], None] = lambda: None) -> tuple[str, str]:
    plan = getattr(sweep, "plan", sweep.sequencer.plan)   # also a simulated sweep waiting for its whole second
    durations = 0.0
    if plan is not None:
        from touchroller_driver.motion import TrapezoidProfile

        position = sweep.last_pose  # not sweep.arm.tcp_pose(): only the sweep node's thread calls the arm
        position = plan.segments[0].target if position is None else position
        for segment in plan.segments:
            distance = float(np.linalg.norm(segment.target[:3] - position[:3]))
            durations += TrapezoidProfile(distance, segment.speed, segment.accel).duration
            position = segment.target
    started = time.monotonic()
    limit = 2.0 * durations + 20.0
    elapsed = SweepTime(getattr(sweep, "sim_clock", None))
    last_report = 0.0
    while not sweep.finished.wait(0.02):
        try:
            check()
        except RecordingFailed:   # stop the arm; the caller writes what there is
            sweep.request_stop()
            raise
        now = time.monotonic()
        if elapsed.beyond(limit):
            sweep.request_stop()
            return "timeout", f"the sweep did not end within {limit:.0f} s{elapsed.unit}; stopped"
        if now - last_report >= 1.0:
            last_report = now
            status = sweep.status
            with collected.lock:
                frames, contacts = collected.frames, len(collected.contacts)
            rolled = f" ({100 * status.roll_progress * plan.length:.1f} of {100 * plan.length:.1f} cm)" if plan else ""
            if plan is not None and len(plan.rolls) > 1 and status.roll is not None:
                rolled += f" pass {status.roll + 1}/{len(plan.rolls)}"
            say(f"scan: {status.phase.value:8s} {100.0 * status.roll_progress:5.1f}%{rolled}  "
                f"{frames} frames, {contacts} contacts, {now - started:4.1f} s")
    status = sweep.status
    say(f"scan: sweep {status.phase.value}: {status.message}")
    return status.phase.value, status.message


class SweepTime:
    """How long the sweep has run, against its time limit: simulated seconds when the arm is simulated (the
    clock waits for the frames on a loaded machine, so the wall clock says nothing), else wall seconds. A
    simulated clock that does not move for `stall_s` wall seconds is beyond any limit."""

    def __init__(self, sim_clock: Any = None, stall_s: float = 60.0) -> None:
        self.clock = sim_clock
        self.stall_s = stall_s
        self.unit = " of simulated time" if sim_clock is not None else ""
        self._started_wall = self._moved_wall = time.monotonic()
        self._started_ns = self._last_ns = sim_clock.now_ns() if sim_clock is not None else 0

    def beyond(self, limit_s: float) -> bool:
        now = time.monotonic()
        if self.clock is None:
            return now - self._started_wall > limit_s
        sim_ns = self.clock.now_ns()
        if sim_ns != self._last_ns:
            self._last_ns, self._moved_wall = sim_ns, now
        return (sim_ns - self._started_ns) * 1e-9 > limit_s or now - self._moved_wall > self.stall_s


def _wait_for_perception(sweep: Any, perception: Any, timeout: float = 30.0) -> None:
    """Let the frames of the sweep's last moments through perception. Simulated, the camera renders
    every frame of the sweep however far it falls behind the clock: wait until perception has the frame
    of the moment the sweep ended (or the timeout); on hardware, a moment for the last frames."""
    clock = getattr(sweep, "sim_clock", None)
    if clock is None or not hasattr(perception, "last_stamp_ns"):
        time.sleep(0.3)
        return
    end_ns = clock.now_ns()
    deadline = time.monotonic() + timeout
    while perception.last_stamp_ns < end_ns and time.monotonic() < deadline:
        time.sleep(0.02)
    time.sleep(0.1)   # the map update of that frame


def _flush_map(perception: Any, collected: _Collected) -> None:
    """Finish the map (whole-map flat field; the node did it already if it saw the roll end) and wait
    until the scan's own subscription has it."""
    publish = getattr(perception, "finish_map", None)
    if publish is None:
        return
    before = collected.map_msg
    findings_before = getattr(perception, "findings_published", 0)
    with collected.lock:
        seen_before = collected.findings
    publish()
    findings_after = getattr(perception, "findings_published", 0)
    deadline = time.monotonic() + 3.0
    while time.monotonic() < deadline:   # the map, and the last findings if the map gave new ones
        with collected.lock:
            if collected.map_msg is not None and collected.map_msg is not before \
                    and (findings_after == findings_before or collected.findings > seen_before):
                return
        time.sleep(0.02)


# -- outputs ----------------------------------------------------------------------------------------

def _published(camera: Any, collected: _Collected) -> int:
    """Frames the camera node has published (its own count; the scan's subscription may miss the first
    ones while discovery matches it, which made 'processed' exceed 'published')."""
    count = getattr(camera, "published", None)
    if isinstance(count, int):
        return count
    with collected.lock:
        return collected.frames


def _write_outputs(out_dir: Path, graph: Graph, perception: Any, collected: _Collected, outcome: str,
                   message: str, duration: float, sweep_answer: str,
                   recorded: Mapping[str, int] | None = None, camera: Any = None,
                   during_sweep: int | None = None, sweep: Any = None, recording_lost: str = "") -> ScanResult:
    """The small, irreplaceable outputs first (contacts.csv, report.md), then the map's preview (the report
    again without it if it does not fit) and the map: every output is tried, and each that could not be
    written is named in `ScanResult.failed` (a nearly full disk keeps a completed sweep's contacts when the
    map does not fit)."""
    from touchroller_bringup.image_conversion import image_to_array

    files: dict[str, Path] = {}
    failed: dict[str, str] = {}
    with collected.lock:
        contacts = list(collected.contacts)
        map_msg = collected.map_msg
        frames = collected.frames
    map_shape = None
    world = getattr(perception, "world", None)
    world_map = None
    world_image = tactile_map = None
    if world is not None:   # the world map in the robot's frame: map.png (grey + alpha) and map.yaml
        world_image = world.view()   # read a tile at a time (the map may be far larger than memory)
        extent = world_image.extent()
        if extent is not None:
            map_shape = (extent[1] - extent[0], extent[3] - extent[2])
            origin = (world_image.origin[0] + extent[2] * world_image.resolution,
                      world_image.origin[1] + extent[0] * world_image.resolution)
            world_map = _world_summary(world, perception.world_frame, world_image.resolution, origin)
        else:
            world_image = None
    # the report's picture and coverage: the map at the level map.png has (full resolution up to 16 MP)
    small_image = None
    if world_image is not None and map_shape is not None:
        from touchroller_bringup.geotiff import view_level
        from touchroller_bringup.map_files import VIEW_MAX_PIXELS

        small_image = world.level_image(view_level(map_shape, VIEW_MAX_PIXELS))
    elif map_msg is not None:
        tactile_map = image_to_array(map_msg)
        map_shape = tuple(int(n) for n in tactile_map.shape)

    def attempt(key: str, path: Path, write: Callable[[], Any]) -> None:
        try:
            write()
            files[key] = path
        except (OSError, UserError) as exc:
            failed[path.name] = (f"{exc.strerror or exc}" if isinstance(exc, OSError) else str(exc))

    from touchroller_bringup import scan_findings

    found = inspected = None
    if world_image is not None and scan_findings.enabled(graph.arguments):
        # the inspection reads the map from its tiles, window by window when it is large; its picture is
        # drawn on the map at the level map.png has
        found = scan_findings.inspect_world(world, perception.live_findings.config.blur_m)
        inspected = small_image

    attempt("contacts", out_dir / "contacts.csv",
            lambda: _write_contacts(out_dir / "contacts.csv", contacts, getattr(perception, "camera", None),
                                    float(_parameter(perception, "contacts.pixel_sigma", 0.3))))
    processed = int(getattr(perception, "received", 0))
    frames = _published(camera, collected) if camera is not None else frames
    result = ScanResult(out_dir, outcome, message, duration, frames, processed,
                        int(getattr(perception, "dropped", 0)), int(getattr(perception, "malformed", 0)),
                        len(contacts), map_shape, files, sweep_answer, dict(recorded or {}), world_map,
                        frames_during_sweep=during_sweep, failed=failed,
                        findings_summary=found.summary() if found is not None else "", recording_lost=recording_lost)
    if recorded:
        files["recording"] = out_dir / "recording"
    if found is not None:   # before the report, which shows them
        attempt("findings", out_dir / "findings.csv",
                lambda: files.update(scan_findings.write_findings(out_dir, inspected, found)))
    result.coverage = _coverage(sweep, small_image, world_map, getattr(perception, "world_frame", names.BASE_FRAME))
    result.findings, result.findings_problem = read_findings(out_dir)
    preview = None
    if small_image is not None:
        preview = preview_image(small_image.grey, small_image.alpha > 0, small_image.resolution, small_image.origin,
                                result.coverage.rectangle if result.coverage else None, result.findings or ())
    elif tactile_map is not None:
        preview = preview_image(tactile_map)
    if preview is not None:
        files["preview"] = out_dir / PREVIEW    # the report links it; taken back if it cannot be written

    def write_report() -> None:
        atomic_write_text(out_dir / "report.md", report_markdown(result, graph))

    attempt("report", out_dir / "report.md", write_report)
    if preview is not None:
        attempt("preview", out_dir / PREVIEW, lambda: write_png(out_dir / PREVIEW, preview))
        if PREVIEW in failed:
            files.pop("preview", None)
            attempt("report", out_dir / "report.md", write_report)   # without the picture, saying why
    if world_image is not None:
        from touchroller_bringup.map_files import write_world_map

        def write_world() -> None:
            files["map"], files["map_yaml"] = write_world_map(out_dir / "map.png", world_image,
                                                              perception.world_frame, _latency_yaml(world))
        attempt("map", out_dir / "map.png", write_world)
        height = world.height_view()
        if height is not None and height.extent() is not None:
            from touchroller_bringup.map_files import write_height_tif

            attempt("height", out_dir / "height.tif",
                    lambda: write_height_tif(out_dir / "height.tif", height, perception.world_frame))
    elif tactile_map is not None:
        attempt("map", out_dir / "map.png", lambda: write_png(out_dir / "map.png", tactile_map))
    if graph.arguments.get("use_sim") == "true" and scan_findings.plants_defects(_parameter(camera, "scene", "")):
        scene = str(_parameter(camera, "scene", ""))
        attempt("truth_findings", out_dir / "truth_findings.csv", lambda: scan_findings.write_truth(out_dir, scene))
    return result


def _latency_yaml(world: Any) -> dict[str, Any]:
    from touchroller_perception.world_map import latency_summary

    return latency_summary(world.stats)[1]


def _world_summary(world: Any, frame: str, resolution: float, origin: tuple[float, float]) -> dict[str, Any]:
    from touchroller_perception.world_map import latency_summary

    stats = world.stats
    return {"frame": frame, "resolution_m": resolution, "origin": tuple(origin),
            "frames_mapped": stats.mapped, "passes": stats.passes,
            "latency_ms": None if stats.latency_s is None else stats.latency_s * 1e3,
            "latency_estimated": stats.latency_estimated,
            "latency": latency_summary(stats)[0],
            "pass_corrections_mm": [(dx * resolution * 1e3, dy * resolution * 1e3)
                                    for dx, dy in stats.pass_corrections_px],
            "pass_residuals_mm": [(dx * resolution * 1e3, dy * resolution * 1e3)
                                  for dx, dy in stats.pass_residuals_px]}


def _parameter(node: Any, name: str, default: Any) -> Any:
    return node.get_parameter(name).value if node is not None and node.has_parameter(name) else default


def _write_contacts(path: Path, contacts: Sequence[tuple[int, float, float, float]], camera: Any,
                    pixel_sigma: float) -> None:
    from touchroller_bringup.commands.contacts import COLUMNS, CONTACT_COLUMNS

    points = np.array([c[1:] for c in contacts], dtype=np.float64).reshape(-1, 3)
    if camera is not None and len(points):
        uv, valid = camera.project(points)
        uv = np.where(valid[:, None], uv, np.nan)
        covariance = camera.contact_covariance(uv, pixel_sigma=pixel_sigma)
        variances = np.diagonal(covariance, axis1=-2, axis2=-1)
    else:
        uv = np.full((len(points), 2), np.nan)
        variances = np.full((len(points), 3), np.nan)
    with atomic_write(path, newline="") as stream:
        writer = csv.writer(stream)
        writer.writerow(COLUMNS)
        for (stamp_ns, *_), (u, v), point, var in zip(contacts, uv, points, variances, strict=True):
            row = [stamp_ns, _f(u), _f(v), *(_f(p, "%.9g") for p in point), *(["nan"] * len(CONTACT_COLUMNS)),
                   *(_f(x, "%.6g") for x in var)]
            writer.writerow(row[:len(COLUMNS)])


def _f(value: float, fmt: str = "%.4f") -> str:
    value = float(value)
    return fmt % value if math.isfinite(value) else "nan"


def _coverage(sweep: Any, world_image: Any, world_map: Mapping[str, Any] | None, frame: str) -> ScanCoverage | None:
    """The requested area (the sweep node's sweep.area and sweep.direction), the passes its plan has, and how
    much of the area the world map covers; None without a sweep node."""
    from touchroller_bringup.scan_report import scan_coverage
    from touchroller_perception.map_coverage import AreaRectangle

    if sweep is None or not hasattr(sweep, "has_parameter"):
        return None
    try:
        rectangle = AreaRectangle.from_sweep_area(_parameter(sweep, "sweep.area", [0.0] * 4),
                                                  list(_parameter(sweep, "sweep.direction", [1.0, 0.0, 0.0])))
    except ValueError:
        rectangle = None
    plan = getattr(getattr(sweep, "sequencer", None), "plan", None)
    planned = len(plan.rolls) if plan is not None and getattr(plan, "rolls", None) is not None else None
    mapped = int(world_map["passes"]) if world_map else None
    return scan_coverage(rectangle, world_image, planned, mapped, frame)
