"""TouchRoller perception: geometry, contact detection, map stitching, calibration and metrics."""
