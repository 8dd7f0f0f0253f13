"""The scan graph: camera, perception and sweep (UR5 or simulated).
`ros2 launch touchroller_bringup scan.launch.py use_sim:=false robot_ip:=192.168.1.10 camera_device:=/dev/v4l/by-id/...`

Arguments, nodes, parameters and the environment come from `touchroller_bringup.graph` (the one
definition, shared with `touchroller scan`) through `touchroller_bringup.launching`;
`ros2 launch touchroller_bringup scan.launch.py --show-args` lists the arguments.
"""
from touchroller_bringup.launching import launch_description

LAUNCH = "scan"


def generate_launch_description():
    return launch_description(LAUNCH)
