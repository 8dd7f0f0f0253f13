"""TouchRoller driver: camera sources, the simulated sensor and arm, and the UR5 via ur_rtde."""
