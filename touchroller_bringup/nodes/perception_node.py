"""The TouchRoller perception node: images -> contacts on the cylinder, and the stitched tactile map.

Thin ROS shell around `touchroller_perception.contacts` (detection), `.localisation`
(back-projection through the calibrated camera model) and `.stitching` (the map, imported lazily):

Topics are relative to the node's namespace (`touchroller` by default; names in
`touchroller_bringup.names`), frame ids start with `frame_prefix` (which follows the namespace):

* subscribes `image_raw` (best effort, keep-last depth 1: a slow consumer skips
  stale frames instead of queueing them; overridable at start-up with the read-only parameters
  `qos_overrides./touchroller/image_raw.subscription.{history,depth,reliability}`);
* publishes one `geometry_msgs/PointStamped` per contact on `contacts`, frame
  `touchroller_cylinder`, stamped with the source image's stamp;
* publishes the map on `map` (transient local, reliable, depth 1) at `map.publish_rate` Hz: with
  `map.world` and TF linking `world_frame` to touchroller_cylinder (/tf, /tf_static) one mosaic in the
  world frame (`touchroller_perception.world_map`: placed by TF at the latency-corrected stamps,
  refined by registration; mono8, row 0 the largest y, frame_id `world_frame`) with its resolution and
  origin on `map_metadata` (nav_msgs/MapMetaData, as nav2's map_server), at the level of detail that
  fits `map.view_max_pixels` (the map downsampled by 2, 4, ... as it grows), and the map in place for
  RViz on `map_markers` (visualization_msgs/MarkerArray: one textured quad per `map.tile_px` tile,
  sent again only where the map changed; `touchroller_bringup.map_markers`); else the strip map of
  `touchroller_perception.stitching` (frame touchroller_cylinder);
  follows the sweep on `sweep_progress` (std_msgs/Float32, 0..1 of the rolling, all passes; only from
  the sweep node of its namespace, told by the publisher of each message: any other is ignored): a new
  map when the roll starts (a world map that has mapped nothing yet keeps the approach, so that it is
  the map `touchroller map` makes of a recording of the scan), and when it ends the map is finalised
  (whole-map flat field), published, and saved to `map.save_path` if that is set (a world map: the PNG,
  grey plus alpha, and a nav2 map.yaml beside it);
* publishes on `findings` (visualization_msgs/MarkerArray, transient local, in `world_frame`) the defects
  found in the world map as it grows (`touchroller_bringup.live_findings`, `findings.*` parameters): the
  newly mapped region inspected at most once per `findings.period` (on a timer of its own when that is
  shorter than the map's publication period), the whole map when it is finished;
* `~/recapture_reference` (std_srvs/Trigger) re-captures the no-contact reference from the next
  `reference.frames` frames (and starts a new map);
* `/diagnostics`: frame rate, processing time, contacts/s, malformed frames, and frames missed: all
  sequence gaps (`frames_dropped`, mostly stale frames skipped while busy) and, of those, the ones DDS
  reports lost in transport (`frames_lost_in_transport`). Bad input is never silent: a malformed frame
  (dropped), a frame the map stage cannot take (skipped; the map goes on with the next) keep the status
  WARN for `BAD_INPUT_HOLD_S`; a frame that does not match the reference is ERROR until one matches
  again, and so is a map stage that fails on every frame.
* publishes on `image_done` (std_msgs/Header) the stamp up to which it is done: the newest image it
  has finished with (taken or refused), once its TF reaches that time too (the arm's poses of the frames
  it maps); the simulated scan's clock follows it (`sweep` node, `sim.lockstep`), so a loaded machine
  slows the simulation down instead of making perception miss frames or map them without their poses.

Geometry parameters (docs/design.md names) are declared by `touchroller_bringup.ros_params` and can be
set at run time (the calibration node sets `extrinsics.theta` and `extrinsics.d`).
"""
from __future__ import annotations

import math
import sys
import threading
import time
from collections.abc import Sequence
from typing import Any

import numpy as np
from geometry_msgs.msg import PointStamped
from nav_msgs.msg import MapMetaData
from rcl_interfaces.msg import SetParametersResult
from rclpy.node import Node
from rclpy.parameter import Parameter
from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy
from rclpy.qos_overriding_options import QoSOverridingOptions
from rclpy.time import Time
from sensor_msgs.msg import Image
from std_msgs.msg import Float32, Header
from visualization_msgs.msg import MarkerArray

from touchroller_bringup import names
from touchroller_bringup.errors import UserError
from touchroller_bringup.image_conversion import image_to_array, stamp_to_ns
from touchroller_bringup.live_findings import LIVE_FINDINGS_PARAMETERS, LiveFindings, LiveFindingsConfig, markers
from touchroller_bringup.map_files import write_world_map
from touchroller_bringup.map_markers import MapViewPublisher
from touchroller_bringup.perception_parameters import (
    DETECTOR_PARAMETERS,
    HEIGHT_PARAMETERS,
    PERCEPTION_FIELDS,
    STITCHER_PARAMETERS,
    VIEW_PARAMETERS,
    WORLD_FIELDS,
    PerceptionSettings,
    WorldSettings,
    check_save_path,
)
from touchroller_bringup.publisher_filter import PublisherFilter
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
    check_start_up,
    declare_frame_prefix,
)
from touchroller_bringup.ros_services import create_trigger_service
from touchroller_bringup.tf import TransformListener, TransformPublisher, camera_in_cylinder
from touchroller_perception.contacts import ContactDetector, DetectorConfig
from touchroller_perception.geometry import CameraModel
from touchroller_perception.localisation import SurfaceLookup, localise
from touchroller_perception.map_tiles import TileConfig
from touchroller_perception.map_windows import MapWindows
from touchroller_perception.stitching import Stitcher, StitcherConfig
from touchroller_perception.transforms import TransformBuffer, TransformError
from touchroller_perception.world_map import (
    WorldMapper,
    buffer_lookup,
    check_band_fits,
    latency_summary,
)


def image_qos() -> QoSProfile:
    """Keep-last 1, best effort: a busy node skips stale frames instead of queueing them (and matches
    reliable and best-effort publishers). A new object per subscription: QoS overrides
    (`qos_overrides./touchroller/image_raw.subscription.{history,depth,reliability}`) modify it in place."""
    return QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=1, reliability=ReliabilityPolicy.BEST_EFFORT,
                      durability=DurabilityPolicy.VOLATILE)


MAP_QOS = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=1, reliability=ReliabilityPolicy.RELIABLE,
                     durability=DurabilityPolicy.TRANSIENT_LOCAL)



#: the parameters of the band that must fit the world map (check_band_fits), from two bindings
BAND_PARAMETERS = ("map.world", "map.resolution", "map.band_rows")
#: /diagnostics stays WARN this long after a malformed, refused or unmappable frame (published once a second)
BAD_INPUT_HOLD_S = 10.0
#: the map stage is reported as failing (ERROR) after this many frames in a row it could not map
MAP_FAILING_FRAMES = 10


class PerceptionNode(Node):
    """Images -> contacts (PointStamped) and the tactile map; see the module docstring and docs/contacts.md."""

    def __init__(self, node_name: str = names.PERCEPTION_NODE, **node_kwargs: Any) -> None:
        node_kwargs.setdefault("namespace", names.DEFAULT_NAMESPACE)
        super().__init__(node_name, **node_kwargs)
        self._declare_parameters()
        self.frame_prefix = declare_frame_prefix(self)
        self.geometry = GeometryParameters(self, on_change=self._on_geometry)
        self.camera: CameraModel = self.geometry.model
        self.lookup = SurfaceLookup(self.camera)   # per-pixel back-projection: microseconds per contact
        # the band that must fit map.resolution spans two bindings: checked in its own on-set callback, added
        # after the node's settings' binding (rclpy runs the newest first), and at start-up before it
        check_start_up(self, self._validate_band, BAND_PARAMETERS)
        self.settings_parameters = ConfigParameters(self, PerceptionSettings(), PERCEPTION_FIELDS,
                                                    check=check_save_path, on_change=self._on_settings)
        self.add_on_set_parameters_callback(self._validate_band)
        self.detector = ContactDetector(self.detector_parameters.config, self.settings.reference_frames)
        self.frame_id = names.frame(self.settings.contacts_frame_id, self.frame_prefix)
        self.stitcher: Any = None
        self.world: WorldMapper | None = None   # the world map, once TF links world_frame to the cylinder
        self.world_frame = self.world_parameters.config.world_frame   # the robot's: no prefix
        self.tf_listener = TransformListener(self, TransformBuffer(cache_ns=20_000_000_000),
                                             on_update=self._on_transforms)
        self._done_ns = 0             # the stamp last published on image_done
        self._done_frame_id = ""
        self._map_dirty = False
        self._map_timer = None
        self._map_rate_hz = 0.0   # the map timer's rate (0: none)
        self._map_lock = threading.Lock()   # `touchroller scan` finishes the map from its own thread
        self._rolling = False
        self._finish_after_ns: int | None = None   # a world map is finished with the first frame after this
        self.saved_maps = 0
        self.live_findings = LiveFindings(self.findings_parameters.config)   # `findings`: markers of the defects found
        self.findings_pub = self.create_publisher(MarkerArray, names.FINDINGS, MAP_QOS)
        self.findings_published = 0
        self._findings_timer: Any = None
        self._views_touched: set[tuple[int, int]] = set()   # tiles a findings tick took before the views saw them

        self.frames = RateMeter()
        self.contact_rate = RateMeter()
        self.processing = LagWindow(200)
        self.received = 0
        self.last_stamp_ns = 0        # stamp of the newest image taken
        self.malformed = 0
        self.refused = 0              # frames whose format differs from the reference
        self._last_malformed = ""     # why the latest malformed frame was dropped
        self._last_refused = ""       # why the latest frame was refused ("" once one is accepted again)
        self.map_errors = 0           # frames the map stage failed on (skipped; the map goes on)
        self._map_error = ""          # the latest map failure
        self._map_failing = 0         # frames in a row the map stage failed on (0 once one is mapped)
        self._finish_error = ""       # why the last map could not be finished ("" once a new map starts)
        self._last_bad: dict[str, float] = {}   # malformed / refused / map -> monotonic time of the latest
        self.dropped = 0              # sequence gaps: stale frames skipped while busy, plus any lost
        self.lost_in_transport: int | None = None   # DDS message_lost total; None if the RMW lacks it
        self.published_contacts = 0
        self.unmapped_contacts = 0
        self._last_sequence: dict[Any, int] = {}   # per publisher: several cameras may share the topic

        self.contacts_pub = self.create_publisher(PointStamped, names.CONTACTS, 10)
        self.map_pub = self.create_publisher(Image, names.MAP, MAP_QOS)
        self.map_metadata_pub = self.create_publisher(MapMetaData, names.MAP_METADATA, MAP_QOS)
        self.map_height_pub = self.create_publisher(Image, names.MAP_HEIGHT, MAP_QOS)
        self.map_views = MapViewPublisher(self, self.map_pub, self.map_metadata_pub, self.view_parameters.config)
        self.done_pub = self.create_publisher(Header, names.IMAGE_DONE, QoSProfile(
            history=HistoryPolicy.KEEP_LAST, depth=10, reliability=ReliabilityPolicy.RELIABLE))
        # progress only from the sweep node of this namespace: another publisher must not cut a map short
        namespace = self.get_namespace().strip("/")
        self.progress_filter = PublisherFilter(self, names.topic(names.SWEEP_PROGRESS, namespace),
                                               names.topic(names.SWEEP_NODE, namespace))
        on_progress = self._on_progress_with_info if _has_message_info() else self._on_progress
        self.progress_sub = self.create_subscription(Float32, names.SWEEP_PROGRESS, on_progress, 10)
        # Humble has no MessageInfo, so no drop count there
        on_image = self._on_image_with_info if _has_message_info() else self._on_image
        self.image_sub = self._subscribe_images(on_image)
        self._create_recapture_interface()
        self._set_map_rate(self.settings.publish_rate)
        self._set_findings_timer()
        self.tf = TransformPublisher(self)
        self._publish_camera_frame()
        self.diagnostics = DiagnosticsPublisher(self, self.get_fully_qualified_name())
        self.diagnostics.add(self._diagnostic_status)

    # ------------------------------------------------------------------ parameters
    def _declare_parameters(self) -> None:
        # the algorithms' configs, each bound to its table (declared, checked on set, applied after set)
        self.detector_parameters = ConfigParameters(self, DetectorConfig(), DETECTOR_PARAMETERS,
                                                    on_change=self._on_detector_config)
        self.stitcher_parameters = ConfigParameters(self, StitcherConfig(), STITCHER_PARAMETERS,
                                                    on_change=lambda _: self.reset_map())
        self.world_parameters = ConfigParameters(self, WorldSettings(), WORLD_FIELDS, on_change=self._on_world_settings)
        from touchroller_perception.world_height import WorldHeightConfig

        self.height_parameters = ConfigParameters(self, WorldHeightConfig(), HEIGHT_PARAMETERS,
                                                  on_change=lambda _: self.reset_map())
        self.view_parameters = ConfigParameters(self, TileConfig(), VIEW_PARAMETERS, on_change=self._on_view_config)
        self.findings_parameters = ConfigParameters(self, LiveFindingsConfig(), LIVE_FINDINGS_PARAMETERS,
                                                    on_change=self._on_findings_config)

    @property
    def stitcher_config(self) -> StitcherConfig:
        return self.stitcher_parameters.config

    def _on_detector_config(self, config: DetectorConfig) -> None:
        self.detector.config = config

    def _on_view_config(self, config: TileConfig) -> None:
        with self._map_lock:
            self.map_views.configure(config)
            self._map_dirty = True

    def _on_world_settings(self, settings: WorldSettings) -> None:
        self.world_frame = settings.world_frame   # the robot's: no prefix
        self.reset_map()   # a map is stitched one way throughout

    def _on_findings_config(self, config: LiveFindingsConfig) -> None:
        self.live_findings.config = config
        self._set_findings_timer()

    def _validate_band(self, parameters: Sequence[Parameter]) -> SetParametersResult:
        """The band that must fit the world map (map.world, map.resolution: WORLD_FIELDS; map.band_rows:
        STITCHER_PARAMETERS), which no one binding holds."""
        band = {p.name: p.value for p in parameters if p.name in BAND_PARAMETERS}
        if band:   # a world map whose every band would be refused (too many map pixels) maps nothing
            values = {name: self.get_parameter(name).value for name in BAND_PARAMETERS}
            values.update(band)
            if values["map.world"]:
                try:
                    check_band_fits(self.camera, int(values["map.band_rows"]), float(values["map.resolution"]))
                except ValueError as exc:
                    return SetParametersResult(successful=False, reason=f"map.resolution {exc}")
        return SetParametersResult(successful=True)

    @property
    def settings(self) -> PerceptionSettings:
        return self.settings_parameters.config

    def _on_settings(self, settings: PerceptionSettings) -> None:
        self.detector.reference_frames = settings.reference_frames
        self.frame_id = names.frame(settings.contacts_frame_id, self.frame_prefix)
        if settings.publish_rate != self._map_rate_hz:
            self._set_map_rate(settings.publish_rate)
            self._set_findings_timer()

    def _publish_camera_frame(self) -> None:
        """touchroller_cylinder -> touchroller_camera on /tf_static, from extrinsics.theta and d."""
        self.tf.set_static(names.frame(names.CYLINDER_FRAME, self.frame_prefix),
                           names.frame(names.CAMERA_FRAME, self.frame_prefix), camera_in_cylinder(self.camera))

    def _on_geometry(self, model: CameraModel) -> None:
        self.lookup = SurfaceLookup(model)
        self.camera = model
        self._publish_camera_frame()
        if self.stitcher is not None or self.world is not None:
            self.stitcher = self.world = None   # the map's band and scale follow the camera: start a new map
        self.get_logger().info(f"camera model updated: theta={model.theta:g} rad, d={model.d:g} m")

    # ------------------------------------------------------------------ reference
    def _create_recapture_interface(self) -> None:
        def recapture() -> tuple[bool, str]:
            self.recapture_reference()
            return True, f"capturing the reference from the next {self.detector.reference_frames} frames"

        self.recapture_srv = create_trigger_service(self, "~/recapture_reference", recapture, log=False)

    def recapture_reference(self) -> None:
        self.detector.recapture()
        self.reset_map()   # a new reference means new sensor conditions (maybe another frame size): a new map
        self.get_logger().info(f"recapturing the no-contact reference ({self.detector.reference_frames} frames)")

    # ------------------------------------------------------------------ images
    def _subscribe_images(self, on_image: Any) -> Any:
        """The image subscription, with DDS's message_lost event where the RMW has it: it tells frames
        lost in transport apart from stale frames skipped on purpose (both leave sequence gaps)."""
        def subscribe(**events: Any) -> Any:
            return self.create_subscription(Image, names.IMAGE, on_image, image_qos(), **events,
                                            qos_overriding_options=QoSOverridingOptions.with_default_policies())

        try:
            from rclpy.event_handler import SubscriptionEventCallbacks, UnsupportedEventTypeError
        except ImportError:   # Humble names the module rclpy.qos_event: count gaps only
            return subscribe()
        try:
            subscription = subscribe(event_callbacks=SubscriptionEventCallbacks(message_lost=self._on_message_lost))
        except UnsupportedEventTypeError:
            return subscribe()
        self.lost_in_transport = 0
        return subscription

    def _on_message_lost(self, info: Any) -> None:
        self.lost_in_transport = int(info.total_count)
        self.get_logger().warning(f"{info.total_count_change} image(s) lost in transport "
                                  f"({info.total_count} in total)", throttle_duration_sec=5.0)

    def _on_image_with_info(self, msg: Image, info: Any) -> None:
        sequence = info.get("publication_sequence_number") if isinstance(info, dict) else None
        if sequence:
            gid = info.get("publisher_gid")
            publisher = tuple(gid.get("data", ())) if isinstance(gid, dict) else None
            last = self._last_sequence.get(publisher)
            if last is not None and sequence > last + 1:
                self.dropped += sequence - last - 1
            self._last_sequence[publisher] = sequence
        self._on_image(msg)

    def _on_image(self, msg: Image) -> None:
        try:
            self._take_image(msg)
        finally:   # taken, refused or dropped: perception is done with it (the simulated clock may go on)
            self._done_frame_id = msg.header.frame_id
            self._report_done()

    def _on_transforms(self, static: bool) -> None:
        if not static and self.last_stamp_ns:
            self._report_done()

    def _report_done(self) -> None:
        """Publish on image_done the newest image stamp this node is done with, held back to the newest
        time its TF links world_frame to the cylinder (when it does): the poses of the frames it maps
        must be here before the simulated clock moves on (TF and images share the executor)."""
        done = self.last_stamp_ns
        cylinder = names.frame(names.CYLINDER_FRAME, self.frame_prefix)
        with self.tf_listener.lock:
            try:
                linked = self.tf_listener.buffer.latest_common_stamp(self.world_frame, cylinder)
            except TransformError:   # no such chain (no arm on TF): the images alone
                linked = None
        if linked is not None:
            done = min(done, linked)
        if done <= self._done_ns:
            return
        self._done_ns = done
        header = Header(frame_id=self._done_frame_id)
        header.stamp.sec, header.stamp.nanosec = divmod(int(done), 1_000_000_000)
        try:
            self.done_pub.publish(header)
        except Exception:  # noqa: BLE001 - the context went down while the frame was processed
            if self.context.ok():
                raise

    def _take_image(self, msg: Image) -> None:
        start = time.perf_counter()
        self.received += 1
        self.last_stamp_ns = stamp_to_ns(msg.header.stamp)
        self.frames.tick()
        try:
            image = image_to_array(msg)
        except ValueError as exc:
            self.malformed += 1
            self._last_malformed = str(exc)
            self._last_bad["malformed"] = time.monotonic()
            self.get_logger().warning(f"dropping malformed image: {exc}", throttle_duration_sec=5.0)
            return
        try:
            contacts = self.detector.process(image)
        except ValueError as exc:
            # another size or encoding: the reference stays until the user captures a new one
            self.refused += 1
            self._last_refused = str(exc)
            self._last_bad["refused"] = time.monotonic()
            self.get_logger().error(f"{exc}; call ~/recapture_reference once the sensor is free",
                                    throttle_duration_sec=5.0)
            return
        self._last_refused = ""
        if contacts:
            self._publish_contacts(msg, contacts)
        self._push_map(image, msg)
        if self._finish_after_ns is not None and self.last_stamp_ns >= self._finish_after_ns:
            self._finish_after_ns = None
            self.finish_map()
        self.processing.add(time.perf_counter() - start)

    def _publish_contacts(self, msg: Image, contacts: list) -> None:
        # PointStamped carries no covariance, so it is not computed here
        for located in localise(self.lookup.camera, contacts, covariance=False, lookup=self.lookup):
            if not located.valid:
                self.unmapped_contacts += 1
                continue
            point = PointStamped()
            point.header.stamp = msg.header.stamp
            point.header.frame_id = self.frame_id
            point.point.x, point.point.y, point.point.z = (float(c) for c in located.point)
            self.contacts_pub.publish(point)
            self.published_contacts += 1
            self.contact_rate.tick()

    # ------------------------------------------------------------------ map
    def _set_map_rate(self, rate_hz: float) -> None:
        self._map_rate_hz = rate_hz
        if self._map_timer is not None:
            self.destroy_timer(self._map_timer)
            self._map_timer = None
        if rate_hz > 0:
            self._map_timer = self.create_timer(1.0 / rate_hz, self.publish_map)

    def _set_findings_timer(self) -> None:
        """The live findings at `findings.period` on a timer of their own when that is shorter than the map's
        publication period (else at the map's publications, as many as are due)."""
        if self._findings_timer is not None:
            self.destroy_timer(self._findings_timer)
            self._findings_timer = None
        config = self.live_findings.config
        rate = self.settings.publish_rate
        if config.enabled and rate > 0 and 0 < config.period_s < 1.0 / rate:
            self._findings_timer = self.create_timer(config.period_s, self.publish_findings)

    def publish_findings(self) -> None:
        """Between the map's publications: inspect what frames mapped since the last inspection when due
        (the tiles they touched are kept for the views' next publication)."""
        with self._map_lock:
            world = self.world
            now = self.get_clock().now().nanoseconds
            if world is None or not self.live_findings.due(now * 1e-9):
                return
            touched = world.touched_tiles()
            self.live_findings.note(touched)
            self._views_touched |= touched
        self._publish_findings(MapWindows(world, self._map_lock), now, False)

    def _push_map(self, image: np.ndarray, msg: Image) -> None:
        if self._map_timer is None:
            return
        try:
            with self._map_lock:
                stamp_ns = stamp_to_ns(msg.header.stamp)
                if self.stitcher is None and self.world is None:
                    self._start_map()
                if self.world is not None:
                    self.world.push(image, stamp_ns)
                else:
                    self.stitcher.push(image, stamp_ns)
                self._map_dirty = True
        except Exception as exc:  # noqa: BLE001 - the map is optional; contacts must keep flowing
            # skip this frame, count it, say it (diagnostics WARN, ERROR while every frame fails); the
            # next frame is mapped as before, so one bad frame never switches the map off
            self.map_errors += 1
            self._map_failing += 1
            self._map_error = f"{type(exc).__name__}: {exc}"
            self._last_bad["map"] = time.monotonic()
            self.get_logger().warning(f"tactile map skipped a frame: {self._map_error}", throttle_duration_sec=5.0)
            return
        self._map_failing = 0

    def _start_map(self) -> None:
        """A world map if TF links world_frame to the cylinder now, else the strip map."""
        cylinder = names.frame(names.CYLINDER_FRAME, self.frame_prefix)
        linked = self.tf_listener.lookup(self.world_frame, cylinder) is not None
        if self.world_parameters.config.world and linked:
            listener = self.tf_listener
            lookup = buffer_lookup(listener.buffer, self.world_frame, cylinder)

            def poses(stamps: np.ndarray) -> np.ndarray:
                with listener.lock:
                    return lookup(stamps)

            self.world = WorldMapper(self.camera, poses, self.world_parameters.config.map_config(),
                                     self.stitcher_config, height=self._height_source())
            self.get_logger().info(f"world map in {self.world_frame} at {self.world.config.resolution * 1e3:g} mm/px")
        else:
            self.stitcher = Stitcher(self.stitcher_config, camera=self.camera)

    def _on_progress_with_info(self, msg: Float32, info: Any) -> None:
        if self.progress_filter.accepts(info):
            self._on_progress(msg)
        else:
            source = self.progress_filter.last_rejected or "another node"
            self.get_logger().warning(f"ignoring {names.SWEEP_PROGRESS} from {source}: only "
                                      f"{self.progress_filter.source} starts and ends maps", throttle_duration_sec=10.0)

    def _on_progress(self, msg: Float32) -> None:
        progress = float(msg.data)
        if not math.isfinite(progress):
            return
        if not self._rolling and 0.0 < progress < 1.0:
            self._rolling = True
            # A new map per roll; a world map that has mapped nothing yet keeps what it has (the approach:
            # it maps from where the arm first moved, as `touchroller map` does from a recording of the scan)
            if self.world is None or self.world.stats.mapped > 0:
                self.reset_map()
        elif self._rolling and progress >= 1.0:
            self._rolling = False
            if self.world is None:
                self.finish_map()
            else:   # the frames of the sweep's last moments may still be on their way: finish after them
                self._finish_after_ns = self.get_clock().now().nanoseconds

    def reset_map(self) -> None:
        """Start a new map with the next frame (called when a roll begins, so one map per roll)."""
        with self._map_lock:
            self.stitcher = self.world = None
            self._map_dirty = False
            self._finish_error = ""
            self._finish_after_ns = None
            self.map_views.reset()
            self._views_touched = set()
            gone = self.live_findings.reset()
        if gone:   # the previous map's findings: their markers go with it
            self.findings_pub.publish(markers([], gone, self.world_frame, self.get_clock().now().to_msg(), 0.0,
                                              self.live_findings.config))

    def finish_map(self) -> None:
        """The roll ended: correct the whole map with its final flat field, publish it, and save it
        to `map.save_path` if set. Frames pushed afterwards extend the map as before."""
        with self._map_lock:
            if self.stitcher is None and self.world is None:
                return
            try:
                if self.world is not None:
                    self.world.finalise()
                    self._log_world_stats()
                else:
                    self.stitcher.finalise()
            except Exception as exc:  # noqa: BLE001 - the map is optional; the node (and its executor) goes on
                self.map_errors += 1
                self._map_error = self._finish_error = f"{type(exc).__name__}: {exc}"
                self._last_bad["map"] = time.monotonic()
                self.get_logger().error(f"the tactile map could not be finished: {self._map_error}")
                return
            self._map_dirty = True
        tactile_map = self.publish_map(all_findings=True)
        path = self.settings.save_path
        if path and tactile_map is not None:
            self._save_map(tactile_map, path)

    def _log_world_stats(self) -> None:
        assert self.world is not None
        stats = self.world.stats
        mm = self.world.config.resolution * 1e3
        latency = latency_summary(stats)[0]
        self.get_logger().info(
            f"world map: {stats.mapped} of {stats.frames} frames mapped in {stats.passes} pass(es); camera "
            f"latency {latency}; passes off TF and the latency by "
            + (", ".join(f"({dx * mm:+.2f}, {dy * mm:+.2f}) mm" for dx, dy in stats.pass_residuals_px) or "-"))

    def _save_map(self, tactile_map: np.ndarray, path: str) -> None:
        import cv2

        world = self.world
        if world is not None:
            try:
                png, yaml_path = write_world_map(path, world.view(), self.world_frame,
                                                 latency_summary(world.stats)[1])
            except UserError as exc:
                self.get_logger().error(f"map not saved: {exc}")
                return
            self.saved_maps += 1
            self.get_logger().info(f"map saved: {png} and {yaml_path.name} "
                                   f"({tactile_map.shape[1]}x{tactile_map.shape[0]})")
            return

        from touchroller_perception.files import atomic_path

        reason = "cv2.imwrite failed (missing folder or unknown extension?)"
        try:
            with atomic_path(path) as temporary:   # a failed save leaves the previous map as it was
                if not cv2.imwrite(str(temporary), tactile_map):
                    raise OSError(reason)
            ok = True
        except OSError as exc:
            ok, reason = False, exc.strerror or str(exc)
        except cv2.error as exc:
            ok, reason = False, str(exc).strip().splitlines()[-1]
        if ok:
            self.saved_maps += 1
            self.get_logger().info(f"map saved: {path} ({tactile_map.shape[1]}x{tactile_map.shape[0]})")
        else:
            self.get_logger().error(f"map not saved to {path}: {reason}")

    def _height_source(self) -> Any:
        """The world mapper's HeightSource from map.height.*; None when not both are set or they do not load."""
        model_path = self.world_parameters.config.photometric
        reference_path = self.world_parameters.config.reference
        if not model_path or not reference_path:
            return None
        import cv2

        from touchroller_perception.height import PhotometricModel
        from touchroller_perception.world_height import HeightSource

        try:
            model = PhotometricModel.load(model_path)
            reference = cv2.imread(reference_path, cv2.IMREAD_COLOR)
            if reference is None:
                raise ValueError(f"cannot read {reference_path}")
        except (OSError, ValueError, KeyError) as exc:
            self.get_logger().error(f"no height map: {exc}")
            return None
        return HeightSource(model, reference, self.height_parameters.config)

    def _publish_height(self, height: np.ndarray, stamp_ns: int) -> None:
        """The world height map on map_height: 32FC1 metres (REP 118), row 0 the top as the map, NaN unmapped,
        at the level of detail of the map view (`map.view_max_pixels`; kept by the view's `LiveMapView`)."""
        if height.size == 0:
            return
        values = np.ascontiguousarray(height, np.float32)
        msg = Image()
        msg.header.stamp.sec, msg.header.stamp.nanosec = divmod(int(stamp_ns), 1_000_000_000)
        msg.header.frame_id = self.world_frame
        msg.height, msg.width = values.shape
        msg.encoding = "32FC1"
        msg.is_bigendian = int(sys.byteorder == "big")
        msg.step = 4 * values.shape[1]
        msg.data = values.tobytes()
        self.map_height_pub.publish(msg)

    def publish_map(self, all_findings: bool = False) -> np.ndarray | None:
        """Publish the map if it changed since the last publication; returns what was published (a
        world map: its view within `map.view_max_pixels`). A world map's views are updated from the tiles
        frames touched since the last publication (`LiveMapView`), and its newly mapped region is
        inspected (`findings.period` apart; `all_findings`: now), read from the tiles."""
        world = live = None
        inspect = False
        with self._map_lock:
            if (self.stitcher is None and self.world is None) or not self._map_dirty:
                return None
            now = self.get_clock().now().nanoseconds
            try:
                if self.world is not None:
                    world = self.world
                    touched = world.touched_tiles()
                    self.live_findings.note(touched)
                    touched |= self._views_touched
                    self._views_touched = set()
                    live = self.map_views.publish(world, touched, self.world_frame, now)
                    if live is not None and live.height is not None:
                        self._publish_height(live.height, now)
                    inspect = all_findings or self.live_findings.due(now * 1e-9)
                else:
                    tactile_map = self.stitcher.map_image()
            except Exception as exc:  # noqa: BLE001
                self.get_logger().warning(f"map not available: {exc}", throttle_duration_sec=10.0)
                return None
            self._map_dirty = False
        if world is not None:
            if inspect:   # read from the tiles a window at a time (each read under the lock), inspected outside it
                self._publish_findings(MapWindows(world, self._map_lock), now, all_findings)
            return None if live is None else live.view.grey
        from touchroller_bringup.image_conversion import array_to_image

        if tactile_map.size == 0:
            return None
        if tactile_map.dtype != np.uint8:
            tactile_map = np.clip(tactile_map, 0, 255).astype(np.uint8)
        frame_id = names.frame(names.CYLINDER_FRAME, self.frame_prefix)
        self.map_pub.publish(array_to_image(tactile_map, now, frame_id=frame_id))
        return tactile_map

    def _publish_findings(self, source: MapWindows, now_ns: int, force: bool) -> None:
        """Inspect the newly mapped region and publish every finding so far (and the DELETEs of those gone)."""
        try:
            update = self.live_findings.update_tiles(source, now_ns * 1e-9, force=force, whole=force)
        except (ValueError, MemoryError) as exc:
            self.get_logger().warning(f"findings not updated: {exc}", throttle_duration_sec=10.0)
            return
        if update is None:
            return
        pressed = self.world.stats.pressed_height if self.world is not None else None
        z = pressed - self.camera.radius if pressed is not None else 0.0   # the surface under the roller
        stamp = Time(nanoseconds=int(now_ns)).to_msg()
        self.findings_pub.publish(markers(update.findings, update.removed, self.world_frame, stamp, z,
                                          self.live_findings.config))
        self.findings_published += 1

    # ------------------------------------------------------------------ diagnostics
    def _diagnostic_status(self) -> Status:
        median_s, max_s = self.processing.summary()
        values = {
            "frame_rate_hz": self.frames.rate(),
            "processing_ms_median": median_s * 1e3 if math.isfinite(median_s) else float("nan"),
            "processing_ms_max": max_s * 1e3 if math.isfinite(max_s) else float("nan"),
            "contacts_per_s": self.contact_rate.rate(),
            "contacts_total": self.published_contacts,
            "contacts_unmapped": self.unmapped_contacts,
            "frames_received": self.received,
            "frames_dropped": self.dropped,
            "frames_lost_in_transport": "unknown" if self.lost_in_transport is None else self.lost_in_transport,
            "frames_malformed": self.malformed,
            "frames_refused": self.refused,
            "reference_ready": self.detector.reference_ready,
            "reference_noise_std": self.detector.reference.noise_std if self.detector.reference else float("nan"),
            "difference_noise_std": _or_nan(self.detector.background.noise),
            "method": self.detector.config.method,
            "map": "world" if self.world is not None else "strip" if self.stitcher is not None else "none",
        }
        world, stitcher = self.world, self.stitcher
        dropped_rows = stitcher.dropped_rows if stitcher is not None else 0
        left_out = world.stats.left_out_storage_full if world is not None else 0
        values.update({"map_rows_dropped": dropped_rows, "map_frames_left_out_disk_full": left_out})
        if world is not None:
            values.update({"map_frames_mapped": world.stats.mapped, "map_passes": world.stats.passes,
                           "map_latency_ms": float("nan") if world.stats.latency_s is None
                           else world.stats.latency_s * 1e3,
                           "map_latency_estimated": world.stats.latency_estimated,
                           "map_latency": latency_summary(world.stats)[0]})
        values.update({"map_frames_failed": self.map_errors, "map_last_error": self._map_error or "none",
                       "last_malformed": self._last_malformed or "none"})
        if self._last_refused:
            return Status(ERROR, f"frames do not match the reference: {self._last_refused}; "
                                 "call ~/recapture_reference", values)
        if self._finish_error:
            return Status(ERROR, f"the tactile map could not be finished: {self._finish_error}", values)
        if self._map_failing >= MAP_FAILING_FRAMES:
            return Status(ERROR, f"tactile map failing on every frame ({self._map_failing} in a row): "
                                 f"{self._map_error}", values)
        if self.received == 0:
            return Status(WARN, "no images received", values)
        now = time.monotonic()
        recent = [kind for kind, when in self._last_bad.items() if now - when <= BAD_INPUT_HOLD_S]
        if recent:
            said = {"malformed": f"{self.malformed} malformed frame(s) dropped (latest: {self._last_malformed})",
                    "refused": f"{self.refused} frame(s) refused (did not match the reference)",
                    "map": f"the tactile map skipped {self.map_errors} frame(s) (latest: {self._map_error})"}
            return Status(WARN, "; ".join(said[kind] for kind in ("malformed", "refused", "map") if kind in recent),
                          values)
        if not self.detector.reference_ready:
            return Status(WARN, "capturing the no-contact reference", values)
        if dropped_rows:
            return Status(WARN, f"map longer than map.max_rows: its {dropped_rows} oldest rows dropped (a sweep "
                                "starts a new map)", values)
        if left_out and world is not None:
            return Status(WARN, f"world map: the disk is full, {left_out} frames not mapped "
                                f"({world.stats.storage_warning})", values)
        if world is not None and world.stats.latency_warning:
            return Status(WARN, world.stats.latency_warning, values)
        return Status(OK, "detecting contacts", values)


def _or_nan(value: float | None) -> float:
    return float("nan") if value is None else float(value)


def _has_message_info() -> bool:
    import rclpy.subscription

    return hasattr(rclpy.subscription, "MessageInfo")


def main(args: list[str] | None = None) -> None:
    from touchroller_bringup.ros_main import run_node

    run_node(PerceptionNode, args)


if __name__ == "__main__":
    main()
