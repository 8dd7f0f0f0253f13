"""The calibration graph: camera, perception and the calibration node.
`ros2 launch touchroller_bringup calibrate.launch.py output_file:=my_roller.yaml`

Arguments, nodes, parameters and the environment come from `touchroller_bringup.graph` (the one
definition, shared with `touchroller scan`) through `touchroller_bringup.launching`;
`ros2 launch touchroller_bringup calibrate.launch.py --show-args` lists the arguments.
"""
from touchroller_bringup.launching import launch_description

LAUNCH = "calibrate"


def generate_launch_description():
    return launch_description(LAUNCH)
