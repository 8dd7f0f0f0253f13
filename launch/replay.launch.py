"""A recording replayed through the camera node into perception.
`ros2 launch touchroller_bringup replay.launch.py bag:=recording/ rate:=1.0`

Arguments, nodes, parameters and the environment come from `touchroller_bringup.graph` (the one
definition, shared with `touchroller scan`) through `touchroller_bringup.launching`;
`ros2 launch touchroller_bringup replay.launch.py --show-args` lists the arguments.
"""
from touchroller_bringup.launching import launch_description

LAUNCH = "replay"


def generate_launch_description():
    return launch_description(LAUNCH)
