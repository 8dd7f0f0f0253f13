"""The one home of TouchRoller's ROS names: namespace, node, topic, service and frame names.

Topics and services are RELATIVE to the node namespace, so one namespace argument moves a whole
roller (`namespace:=left` puts `image_raw` at `/left/image_raw` and the sweep's start service at
`/left/sweep/start`). The default namespace is `touchroller`, so the defaults resolve to the names in
docs/design.md (`/touchroller/image_raw`, ...). `/diagnostics` stays absolute (one aggregator per
robot). Frame ids take a prefix that follows the namespace: none in the default namespace
(`touchroller_cylinder`), `left/` in `left` (`left/touchroller_cylinder`).

No rclpy import here: the graph, the CLI and the bag tools use these names without ROS.
"""
from __future__ import annotations

import re

DEFAULT_NAMESPACE = "touchroller"

# -- nodes (names inside the namespace) ---------------------------------------------------------
CAMERA_NODE = "camera"
PERCEPTION_NODE = "perception"
SWEEP_NODE = "sweep"
CALIBRATION_NODE = "calibration"

# -- topics, relative to the namespace ---------------------------------------------------------
IMAGE = "image_raw"              # sensor_msgs/Image from the camera driver
CAMERA_INFO = "camera_info"      # sensor_msgs/CameraInfo
CONTACTS = "contacts"            # geometry_msgs/PointStamped, one per contact
MAP = "map"                      # sensor_msgs/Image, the tactile map (latched)
TCP_POSE = "tcp_pose"            # geometry_msgs/PoseStamped, the arm's tool pose
SWEEP_PROGRESS = "sweep_progress"  # std_msgs/Float32, 0..1 of the rolling (all passes of a raster)
COVERAGE = "coverage"            # std_msgs/Float32, percent of the sweep's rectangle rolled over
SWEEP_PASS = "sweep_pass"        # std_msgs/UInt32MultiArray [pass (1-based), passes]
MAP_HEIGHT = "map_height"        # sensor_msgs/Image 32FC1, the world height map in metres (latched)
MAP_METADATA = "map_metadata"    # nav_msgs/MapMetaData of the world map (resolution, size, origin)
MAP_MARKERS = "map_markers"      # visualization_msgs/MarkerArray: the world map's tiles, textured quads in place
IMAGE_DONE = "image_done"        # std_msgs/Header: the newest image perception has finished with
IMAGE_RECORDED = "image_raw/recorded"   # std_msgs/Header: the newest image a recorder has written
FINDINGS = "findings"            # visualization_msgs/MarkerArray: defects found in the world map (latched)
DIAGNOSTICS = "/diagnostics"     # absolute: shared by every node of the robot
TF = "/tf"                       # absolute, as tf2 publishes them; frame ids carry the prefix instead
TF_STATIC = "/tf_static"
CLOCK = "/clock"                 # absolute: the simulated clock (use_sim_time), as ROS defines it

# -- services (std_srvs/Trigger), under their node: `<namespace>/<node>/<service>` -------------
START = "start"                  # sweep: roll now
STOP = "stop"                    # sweep: stop and lift
RESET_FAULT = "reset_fault"      # sweep: clear an arm fault (unlock a protective stop, reconnect)
RECAPTURE_REFERENCE = "recapture_reference"  # perception
CAPTURE = "capture"              # calibration: take the current frame
SOLVE = "solve"                  # calibration: solve and write the calibration
RESET = "reset"                  # calibration: forget the captures
SOLVE_PHOTOMETRIC = "solve_photometric"  # calibration: the photometric model from the captured ball presses
SET_CAMERA_INFO = "set_camera_info"  # camera: sensor_msgs/srv/SetCameraInfo (camera_info_manager's)

# -- actions, relative to the namespace ----------------------------------------------------------
SWEEP_ACTION = "sweep"           # touchroller_interfaces/action/Sweep, served by the sweep node: /touchroller/sweep

# -- frames (before the frame prefix) -----------------------------------------------------------
BASE_FRAME = "base"              # the robot's base (UR convention)
TOOL_FRAME = "tool0"             # the arm's flange (UR convention)
CYLINDER_FRAME = "touchroller_cylinder"  # the cylinder frame of the geometry
CAMERA_FRAME = "touchroller_camera"      # the camera (optical axes: z along the view), from theta and d
CAMERA_OPTICAL_FRAME = "touchroller_camera_optical_frame"   # frame_id of images and camera_info (the same axes)

_TOKEN = re.compile(r"[A-Za-z_][A-Za-z0-9_]*\Z")


class InvalidName(ValueError):
    """A namespace that ROS would refuse (the message is one line)."""


def check_namespace(namespace: str) -> str:
    """`namespace` without surrounding slashes ("left", "robot1/left"); InvalidName if ROS would refuse it.
    An empty namespace is the root (topics at `/image_raw`)."""
    text = str(namespace).strip().strip("/")
    for token in text.split("/") if text else ():
        if not _TOKEN.match(token):
            raise InvalidName(f"namespace {namespace!r} is not a valid ROS namespace: each part must start "
                             "with a letter or _ and hold only letters, digits and _")
    return text


def topic(name: str, namespace: str = DEFAULT_NAMESPACE) -> str:
    """The absolute name of a relative topic (or service) in `namespace`: topic("image_raw") is
    "/touchroller/image_raw"; absolute names are returned unchanged."""
    if name.startswith("/"):
        return name
    ns = check_namespace(namespace)
    return f"/{ns}/{name}" if ns else f"/{name}"


def service(node: str, name: str, namespace: str = DEFAULT_NAMESPACE) -> str:
    """The absolute name of node `node`'s private service `name` (`~/name`) in `namespace`:
    service("sweep", "start") is "/touchroller/sweep/start"."""
    return topic(f"{node}/{name}", namespace)


def frame_prefix(namespace: str) -> str:
    """The frame-id prefix for nodes in `namespace`: "" in the default namespace (frame ids as in
    docs/design.md), else the namespace and a slash ("left/")."""
    ns = check_namespace(namespace)
    return "" if ns in ("", DEFAULT_NAMESPACE) else f"{ns}/"


_FRAME = re.compile(r"[A-Za-z_][A-Za-z0-9_]*(/[A-Za-z_][A-Za-z0-9_]*)*\Z")


def check_frame_id(name: str, what: str = "frame id") -> str:
    """`name` if it is a usable TF frame id (parts of letters, digits and _, not starting with a digit,
    joined by /; no leading slash, tf2 refuses one); InvalidName saying what is wrong otherwise."""
    text = str(name)
    if not text.strip():
        raise InvalidName(f"{what} must not be empty")
    if not _FRAME.match(text):
        raise InvalidName(f"{what} {text!r} is not a valid frame id: parts of letters, digits and _ (not "
                          "starting with a digit) joined by /, with no leading or trailing / or spaces")
    return text


def check_frame_prefix(prefix: str) -> str:
    """`prefix` if it is "" or a frame id followed by a slash ("left/"); InvalidName otherwise."""
    text = str(prefix)
    if text and not (text.endswith("/") and _FRAME.match(text[:-1])):
        raise InvalidName(f"frame_prefix {text!r} must be empty or a frame id followed by a slash, e.g. 'left/'")
    return text


def frame(name: str, prefix: str = "") -> str:
    """A frame id with its prefix: frame("touchroller_cylinder", "left/") is "left/touchroller_cylinder"."""
    return f"{prefix}{name}"


def qos_override(topic_name: str, namespace: str, entity: str, policy: str) -> str:
    """The parameter rclpy reads for a QoS override of a relative topic in `namespace`
    (entity "publisher" or "subscription"): `qos_overrides./touchroller/image_raw.subscription.depth`."""
    return f"qos_overrides.{topic(topic_name, namespace)}.{entity}.{policy}"


# The image topic of recordings made in the default namespace (`touchroller record`, `touchroller scan
# record:=true`, `touchroller simulate`): what the bag tools read unless told otherwise.
IMAGE_TOPIC = topic(IMAGE)
