"""The ROS 2 nodes: thin shells over the driver and perception packages (camera, perception, sweep, calibration)."""
