"""The TouchRoller camera driver node: a `FrameSource` -> `image_raw` + `camera_info`.

The graph's one publisher of `camera_info`, with camera_info_manager's conventions
(`touchroller_bringup.camera_info_manager`): `camera_name`, `camera_info_url` (a camera_calibration_parsers
YAML) and `~/set_camera_info`. Images and camera info are in `touchroller_camera_optical_frame`
(`frame_id`), which the node puts on /tf_static under `touchroller_camera` (the same axes: docs/design.md's
camera frame is optical already).

Topics are relative to the node's namespace (`touchroller` by default: `/touchroller/image_raw`; names
in `touchroller_bringup.names`); frame ids start with `frame_prefix`, which follows the namespace.

Thin ROS shell around `touchroller_driver.sources`: a publishing thread takes the newest frame
from the source and publishes it at once (no timer in the path, so no added latency), stamped
with the capture time. Images are always `bgr8`. Reliable QoS (REP 2003), overridable with
`qos_overrides./touchroller/image_raw.publisher.*` parameters. `/diagnostics` carries the
measured frame rate, publish lag (publish time - capture stamp) and drops.

Stamps are the source's capture time minus `camera.latency` (seconds, like v4l2_camera's
timestamp_offset): a webcam's frame reaches the host tens of milliseconds after its exposure.

`source=sim` is the simulator: with `sim.motion=scene` it plays the scene's own motion; with
`sim.motion=arm` it is the simulated sensor on the arm (`touchroller_driver.sim.camera.ArmCamera`):
frame k is rendered at exactly its time on the frame grid of the simulated clock (the node's ROS clock,
/clock from the sweep node's simulated arm under use_sim_time), with the roller where TF
(`world_frame` -> touchroller_cylinder, both after `frame_prefix`, from /tf and /tf_static) has it at
that time, over the scene's surface placed in `world_frame`; `sim.latency` stamps the frames that late
(the simulated webcam's latency). No frames are published before the arm's pose is known.
"""
from __future__ import annotations

import os
import threading
import time
from dataclasses import dataclass
from typing import Any

from rclpy.node import Node
from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy
from rclpy.qos_overriding_options import QoSOverridingOptions
from sensor_msgs.msg import CameraInfo, Image

from touchroller_bringup import names
from touchroller_bringup.bags import read_images
from touchroller_bringup.camera_info_manager import CameraInfoManager
from touchroller_bringup.errors import UserError
from touchroller_bringup.image_conversion import fill_image
from touchroller_bringup.ros_diagnostics import (
    ERROR,
    OK,
    WARN,
    DiagnosticsPublisher,
    LagWindow,
    RateMeter,
    Status,
)
from touchroller_bringup.ros_params import (
    ConfigParameters,
    GeometryParameters,
    ParameterField,
    declare_frame_prefix,
    frame_id_problem,
    parameter_values,
)
from touchroller_bringup.tf import TransformListener, TransformPublisher
from touchroller_driver.sources import SOURCE_KINDS, FrameSource, SourceStats, as_bgr8, make_source
from touchroller_perception.geometry import CameraModel
from touchroller_perception.transforms import Transform, TransformBuffer

SIM_MOTIONS = ("scene", "arm")


@dataclass(frozen=True)
class SourceSettings:
    """The source the camera node opens and how (its parameters: SOURCE_FIELDS; changing one reopens it)."""

    source: str = "v4l2"
    device: str = "0"
    width: int = 640
    height: int = 480
    fps: float = 30.0
    exposure: float = 0.0
    video_path: str = ""
    bag_path: str = ""
    bag_topic: str = names.topic(names.IMAGE)
    scene: str = "surface_mapping"
    seed: int = 0
    rate: float = 1.0
    loop: bool = False
    wait_for_subscribers: int = 0
    sim_motion: str = "scene"
    sim_latency: float = 0.0
    world_frame: str = names.BASE_FRAME

    def __post_init__(self) -> None:
        for name in ("device", "bag_topic"):
            if not str(getattr(self, name)).strip():
                raise ValueError(f"{name} must not be empty")
        problem = frame_id_problem("world_frame", self.world_frame)
        if problem:
            raise ValueError(problem)


#: Parameters that select or configure the source (SourceSettings' fields): changing one reopens it.
SOURCE_FIELDS: dict[str, ParameterField] = {
    "source": ParameterField("source", f"Camera source: one of {', '.join(SOURCE_KINDS)}", choices=SOURCE_KINDS,
                             constraints=f"one of {', '.join(SOURCE_KINDS)}"),
    "device": ParameterField("device", "V4L2 device: an index or a path (prefer a stable /dev/v4l/by-id/... path)"),
    "width": ParameterField("width", "Requested capture width, pixels (v4l2)", 16, 8192),
    "height": ParameterField("height", "Requested capture height, pixels (v4l2)", 16, 8192),
    "fps": ParameterField("fps", "Requested frame rate, Hz (v4l2; sim when bound to an arm)", 0.1, 1000.0),
    "exposure": ParameterField("exposure", "Manual exposure in V4L2 units; 0 = auto exposure", 0.0, 100000.0),
    "video_path": ParameterField("video_path", "Video file to play (source=video)"),
    "bag_path": ParameterField("bag_path", "rosbag2 folder to play images from (source=bag)"),
    "bag_topic": ParameterField("bag_topic", "Image topic inside the bag (source=bag)"),
    "scene": ParameterField("scene", "Simulator scene: NAME, NAME:VARIANT or a YAML path (source=sim)"),
    "seed": ParameterField("seed", "Simulator random seed (source=sim)", 0, 2**31 - 1),
    "rate": ParameterField("rate", "Playback rate for video/bag/sim: 1 real time, 0 as fast as possible", 0.0, 100.0),
    "loop": ParameterField("loop", "Restart video/bag/sim sources at their end"),
    "wait_for_subscribers": ParameterField(
        "wait_for_subscribers", f"Open the source only once {names.IMAGE} has this many subscribers (replay: "
        "perception must see a recording's first, reference frames); 0: at once", 0, 100),
    "sim.motion": ParameterField(
        "sim_motion", "source=sim: 'scene' plays the scene's own motion; 'arm' renders the roller where TF "
        "(world_frame -> touchroller_cylinder) has it, on the simulated clock", choices=SIM_MOTIONS,
        constraints="scene or arm"),
    "sim.latency": ParameterField("sim_latency", "source=sim, sim.motion=arm: how late the simulated webcam stamps "
                                  "its frames after exposure, s (an effect the mapper is not told)", 0.0, 1.0),
    "world_frame": ParameterField("world_frame", "source=sim, sim.motion=arm: the frame the scene's surface lies in "
                                  "(the arm's base, as the robot driver names it: frame_prefix does not apply)"),
}


@dataclass(frozen=True)
class StampSettings:
    """What the published images carry: their frame id (before frame_prefix) and the camera's latency, taken
    off their capture stamps (its parameters: STAMP_FIELDS; applied to the next frame)."""

    frame_id: str = names.CAMERA_OPTICAL_FRAME
    latency: float = 0.0

    def __post_init__(self) -> None:
        problem = frame_id_problem("frame_id", self.frame_id)
        if problem:
            raise ValueError(problem)


STAMP_FIELDS: dict[str, ParameterField] = {
    "frame_id": ParameterField("frame_id", "frame_id of published images and camera info (after frame_prefix); "
                               f"other than {names.CAMERA_FRAME}, it is published on /tf_static as "
                               f"{names.CAMERA_FRAME} with its axes (that frame is optical already: z along the "
                               "view, x along u, y along v)"),
    "camera.latency": ParameterField("latency", "Seconds from a frame's exposure to its capture stamp, subtracted "
                                     "from the stamps (like v4l2_camera's timestamp_offset); 0: stamps as captured",
                                     0.0, 1.0),
}


def image_qos() -> QoSProfile:
    """Reliable keep-last 5 (REP 2003). A new object per publisher: QoS overrides modify it in place."""
    return QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=5, reliability=ReliabilityPolicy.RELIABLE,
                      durability=DurabilityPolicy.VOLATILE)



def source_problem(values: dict[str, Any]) -> str:
    """Why the source these parameter values name cannot be opened and will not appear by waiting ("" when
    it can, or may: a camera device that is unplugged is retried)."""
    kind = str(values.get("source", ""))
    if kind == "video":
        path = str(values.get("video_path", ""))
        if not path:
            return "source=video needs video_path"
        if not os.path.isfile(path):
            return f"source=video: video_path {path} " + ("is not a file" if os.path.exists(path) else "does not exist")
    elif kind == "bag":
        from touchroller_bringup.bags import check_image_bag

        path = str(values.get("bag_path", ""))
        if not path:
            return "source=bag needs bag_path"
        if not os.path.exists(path):
            return f"source=bag: bag_path {path} does not exist"
        try:
            check_image_bag(path, str(values.get("bag_topic", names.topic(names.IMAGE))))
        except UserError as exc:
            # a bag that does not open (truncated by a crash) is the source's to report while the node
            # serves on; one that opens without images on the topic, or of the wrong type, is refused
            if "cannot open bag" not in str(exc):
                return f"source=bag: {exc}"
    elif kind == "sim":
        from touchroller_driver.sim import load_scene  # lazy: heavy and optional

        try:
            load_scene(str(values.get("scene", "")))
        except (OSError, ValueError, KeyError, TypeError) as exc:
            return f"source=sim: scene {values.get('scene')!r}: {exc}"
    return ""


class CameraNode(Node):
    """Publishes camera frames; `source=` supplies an external FrameSource (then `source.*` params are ignored)."""

    def __init__(self, node_name: str = names.CAMERA_NODE, *, source: FrameSource | None = None,
                 autostart: bool = True, **node_kwargs: Any) -> None:
        node_kwargs.setdefault("namespace", names.DEFAULT_NAMESPACE)
        # What destroy_node (stop) uses comes before Node.__init__: from there on the context tracks the
        # node and destroys it at shutdown, also when the rest of this constructor raises.
        self._external_source = source is not None
        self.source: FrameSource | None = source
        self._opened = False
        self._open_error = ""
        self._restart = threading.Event()
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._lock = threading.Lock()  # guards source swaps against diagnostics reads
        self._closed_stats = SourceStats()  # drops etc. of sources closed by a restart
        super().__init__(node_name, **node_kwargs)
        self._declare_parameters()
        self.frame_prefix = declare_frame_prefix(self)
        self.geometry = GeometryParameters(self, on_change=self._on_geometry)
        self.camera_info = CameraInfoManager(self, self.geometry)
        self.stamp_parameters = ConfigParameters(self, StampSettings(), STAMP_FIELDS, on_change=self._on_stamp)
        self.camera_info.load()
        self.frame_id = names.frame(self.stamp_parameters.config.frame_id, self.frame_prefix)
        self.tf = TransformPublisher(self)
        self._publish_optical_frame()
        self._image_msg = Image()
        self.published = 0
        self.malformed = 0
        self.rate_meter = RateMeter()
        self.lag = LagWindow(200)
        self._finished_logged = False
        self._streaming_logged = False
        self._last_error_log = 0.0

        overrides = QoSOverridingOptions.with_default_policies()
        self.image_pub = self.create_publisher(Image, names.IMAGE, image_qos(), qos_overriding_options=overrides)
        self.info_pub = self.create_publisher(CameraInfo, names.CAMERA_INFO, image_qos(),
                                              qos_overriding_options=overrides)
        self.tf_listener: TransformListener | None = None   # source=sim with sim.motion=arm: the arm's pose
        self._listen_to_tf_if_on_arm()
        self.diagnostics = DiagnosticsPublisher(self, self.get_fully_qualified_name(), hardware_id="")
        self.diagnostics.add(self._diagnostic_status)
        if autostart:
            self.start()

    # ------------------------------------------------------------------ parameters
    def _declare_parameters(self) -> None:
        # the source: checked whole on set and at start-up (a file, bag or scene that does not exist stops the
        # node in one line: unlike a camera device, it will not come back by itself), reopened after a change
        self.source_parameters = ConfigParameters(self, SourceSettings(), SOURCE_FIELDS, check=self._check_source,
                                                  on_change=self._on_source)

    @property
    def source_settings(self) -> SourceSettings:
        return self.source_parameters.config

    def _check_source(self, settings: SourceSettings) -> None:
        if not self._external_source:
            problem = source_problem(parameter_values(settings, SOURCE_FIELDS))
            if problem:
                raise ValueError(problem)

    def _on_source(self, _settings: SourceSettings) -> None:
        if not self._external_source:
            self._listen_to_tf_if_on_arm()
            self._restart.set()  # the publishing thread reopens the source

    def _on_stamp(self, settings: StampSettings) -> None:
        frame_id = names.frame(settings.frame_id, self.frame_prefix)
        if frame_id != self.frame_id:
            self.frame_id = frame_id
            self._publish_optical_frame()

    # ------------------------------------------------------------------ the simulated sensor on the arm
    def _on_arm(self) -> bool:
        return (not self._external_source and self.source_settings.source == "sim"
                and self.source_settings.sim_motion == "arm")

    def _listen_to_tf_if_on_arm(self) -> None:
        # Created here (executor or constructing thread), never from the publishing thread; kept once made.
        if self.tf_listener is None and self._on_arm():
            self.tf_listener = TransformListener(self, TransformBuffer(cache_ns=10_000_000_000))

    def _cylinder_pose(self, t_ns: int) -> Transform | None:
        listener = self.tf_listener
        world = self.source_settings.world_frame   # the robot's frame: the driver's name, no prefix
        cylinder = names.frame(names.CYLINDER_FRAME, self.frame_prefix)
        return None if listener is None else listener.lookup(world, cylinder, t_ns)

    def _publish_optical_frame(self) -> None:
        """touchroller_camera -> frame_id on /tf_static: the identity, as docs/design.md's touchroller_camera is
        an optical frame already (the REP 103 body-to-optical rotation would turn the image's axes away)."""
        camera = names.frame(names.CAMERA_FRAME, self.frame_prefix)
        if self.frame_id != camera:
            self.tf.set_static(camera, self.frame_id, Transform((0.0, 0.0, 0.0), (0.0, 0.0, 0.0, 1.0)))

    def _on_geometry(self, model: CameraModel) -> None:
        self.camera_info.geometry_changed(model)
        self.get_logger().info(f"camera model updated: fx={model.fx:g} fy={model.fy:g} theta={model.theta:g} "
                               f"d={model.d:g}")
        if self._on_arm():
            self._restart.set()

    def _make_source(self) -> FrameSource:
        param = self.source_parameters.values()
        kind = str(param["source"])
        clock_ns = self._now_ns
        if kind == "v4l2":
            return make_source("v4l2", device=param["device"], width=param["width"], height=param["height"],
                               fps=param["fps"], exposure=param["exposure"], clock_ns=clock_ns,
                               log=self.get_logger().info, warn=self.get_logger().warning)
        if kind == "video":
            return make_source("video", path=param["video_path"], rate=param["rate"], loop=param["loop"],
                               clock_ns=clock_ns)
        if kind == "bag":
            return make_source("bag", path=param["bag_path"], topic=param["bag_topic"], rate=param["rate"],
                               loop=param["loop"], clock_ns=clock_ns, reader=read_images)
        if self._on_arm():
            from touchroller_driver.sim import SimulatedSensor, load_scene  # lazy: heavy and optional
            from touchroller_driver.sim.camera import ArmCamera

            sensor = SimulatedSensor(load_scene(param["scene"]), seed=param["seed"])
            return ArmCamera(sensor, now_ns=self._now_ns, cylinder_pose=self._cylinder_pose, fps=param["fps"],
                             latency_s=float(param["sim.latency"]))
        if kind != "sim":   # never the simulator in place of a source that was misspelt
            raise UserError(f"source must be one of {', '.join(SOURCE_KINDS)}, got {kind!r}")
        return make_source("sim", scene=param["scene"], seed=param["seed"], rate=param["rate"],
                           loop=param["loop"], clock_ns=clock_ns)

    def _latency_ns(self) -> int:
        return round(self.stamp_parameters.config.latency * 1e9)

    def _now_ns(self) -> int:
        return self.get_clock().now().nanoseconds

    # ------------------------------------------------------------------ publishing thread
    def start(self) -> None:
        if self._thread is None:
            self._stop.clear()
            self._thread = threading.Thread(target=self._run, name="touchroller-camera-publish", daemon=True)
            self._thread.start()

    def stop(self) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout=5.0)
            self._thread = None
        self._close_source()

    def destroy_node(self) -> None:
        self.stop()
        super().destroy_node()

    @property
    def finished(self) -> bool:
        """A finite source (file, bag, scene) has delivered all its frames."""
        return self.source is not None and _stats(self.source).finished

    def _run(self) -> None:
        needs_open = True
        while not self._stop.is_set():
            if needs_open or self._restart.is_set():
                needs_open = False
                self._wait_for_subscribers()
                self._open_source()
            if not self._opened:  # opening failed (logged once): wait for a parameter change
                self._restart.wait(0.2)
                continue
            try:
                frame = self.source.read(timeout=0.1)
            except Exception as exc:  # noqa: BLE001 - a bad frame is one log line; the node keeps running
                self.malformed += 1
                self._log_error(f"camera source failed to deliver a frame: {type(exc).__name__}: {exc}")
                self._stop.wait(0.01)
                continue
            if frame is None:
                if self.finished and not self._finished_logged:
                    self._finished_logged = True
                    error = _stats(self.source).last_error
                    if error:
                        self.get_logger().error(f"source stopped after {self.published} frames: {error}")
                    else:
                        self.get_logger().info(f"source finished after {self.published} frames: {self.source.info}")
                continue
            try:
                published = self.publish_frame(frame.image, frame.stamp_ns - self._latency_ns())
            except Exception as exc:  # noqa: BLE001 - e.g. the context was shut down by Ctrl-C
                if not self.context.ok():
                    break
                self._log_error(f"publishing failed: {type(exc).__name__}: {exc}")
                continue
            if published and not self._streaming_logged:
                self._streaming_logged = True
                self.get_logger().info(f"streaming from {self.source.info}")

    def _wait_for_subscribers(self) -> None:
        """Hold the source until `wait_for_subscribers` subscriptions match the image topic, so that a
        replayed recording's first (reference) frames reach perception started in another process."""
        wanted = self.source_settings.wait_for_subscribers
        if wanted > 0 and self.image_pub.get_subscription_count() < wanted:
            self.get_logger().info(f"waiting for {wanted} subscriber(s) on {self.image_pub.topic_name}")
            while (self.image_pub.get_subscription_count() < wanted and not self._stop.is_set()
                   and not self._restart.is_set()):
                self._stop.wait(0.05)

    def _open_source(self) -> bool:
        self._restart.clear()
        self._close_source()
        try:
            source = self.source if self._external_source else self._make_source()
            source.open()
        except Exception as exc:  # noqa: BLE001 - a bad path/device is one log line; retried after a change
            self._open_error = f"cannot open camera source: {exc}"
            self.get_logger().error(self._open_error)
            if not self._external_source:
                with self._lock:
                    self.source = None
            return False
        with self._lock:
            self.source = source
            self._opened = True
            self._open_error = ""
        self._finished_logged = False
        self._streaming_logged = False
        self.diagnostics.hardware_id = source.info
        self.get_logger().info(f"opening {source.info}")   # "streaming" only once a frame is out
        return True

    def _close_source(self) -> None:
        with self._lock:
            source = self.source
            if source is None or not self._opened:
                return
            self._opened = False
            stats = _stats(source)
            self._closed_stats.dropped += stats.dropped
            self._closed_stats.reconnects += stats.reconnects
            if not self._external_source:
                self.source = None
        try:
            source.close()
        except Exception as exc:  # noqa: BLE001
            self._log_error(f"closing the camera source failed: {exc}")

    def publish_frame(self, image: Any, stamp_ns: int) -> bool:
        """Publish one bgr8 frame and its CameraInfo; a malformed image is logged and skipped."""
        try:
            fill_image(self._image_msg, as_bgr8(image), stamp_ns, self.frame_id, encoding="bgr8")
        except (ValueError, AttributeError, TypeError) as exc:
            self.malformed += 1
            self._log_error(f"dropping a malformed camera frame: {exc}")
            return False
        self.image_pub.publish(self._image_msg)
        self.info_pub.publish(self.camera_info.fill(CameraInfo(), stamp_ns, self.frame_id))
        self.published += 1
        self.rate_meter.tick()
        self.lag.add((self._now_ns() - stamp_ns) * 1e-9)
        return True

    def _log_error(self, message: str) -> None:
        now = time.monotonic()
        if now - self._last_error_log >= 1.0:  # throttled: one line a second at most
            self._last_error_log = now
            self.get_logger().error(message)

    # ------------------------------------------------------------------ diagnostics
    def _diagnostic_status(self) -> Status:
        with self._lock:
            source = self.source
            stats = _stats(source) if source is not None else SourceStats()
            info = source.info if source is not None else "none"
        lag_median, lag_max = self.lag.summary()
        rate = self.rate_meter.rate()
        values = {
            "source": info,
            "frame_rate_hz": rate,
            "lag_median_ms": lag_median * 1e3,
            "lag_max_ms": lag_max * 1e3,
            "published": self.published,
            "captured": stats.captured,
            "dropped": stats.dropped + self._closed_stats.dropped,
            "malformed": self.malformed,
            "reconnects": stats.reconnects + self._closed_stats.reconnects,
            "connected": stats.connected,
            "finished": stats.finished,
        }
        if stats.last_error:
            values["last_error"] = stats.last_error
        if source is None or (not stats.connected and not stats.finished):
            reason = stats.last_error or self._open_error or "no source"
            return Status(ERROR, f"camera not available: {reason}", values)
        if stats.finished:
            if stats.last_error:
                return Status(ERROR, f"source stopped: {stats.last_error}", values)
            return Status(OK, "source finished", values)
        if rate == 0.0:
            return Status(WARN, "no frames", values)
        return Status(OK, "streaming", values)


def _stats(source: Any) -> SourceStats:
    stats = getattr(source, "stats", None)
    return stats if isinstance(stats, SourceStats) else SourceStats(connected=True)


def main(args: list[str] | None = None) -> None:
    from touchroller_bringup.ros_main import run_node

    run_node(CameraNode, args)


if __name__ == "__main__":
    main()
