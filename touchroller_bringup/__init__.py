"""TouchRoller bringup: the node graph, the `touchroller` CLI, and rosbag2 recording and replay."""
