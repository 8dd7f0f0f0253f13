"""Calibration of the TouchRoller camera: intrinsics (Zhang) and the paper's extrinsics theta and d.

Two steps, as in the paper (section III-C):

1. `intrinsics`: the intrinsics and lens distortion from chessboard views, with per-view errors,
   rejection of bad and blurred views, a distortion model chosen by held-out views, and what
   the views cover (`coverage`: ROS camera_calibration's X / Y / size / skew bars and the image
   corners).
2. `extrinsics`: theta and d from images of the roller pressed on a flat frame of hemispheres
   (`imprints` finds and measures them), with the frame's placement taken out by the row balance
   and an uncertainty that includes the intrinsics'.

`uncertainty` gives the sigmas their meaning (docs/calibration.md, "Uncertainty"). `outputs`
writes the docs/design.md parameters file with the sigmas. Nothing here imports rclpy.
Degenerate input raises `CalibrationError` with one line naming what is missing, never a silently
wrong result. The names below are the package's interface.
"""
from touchroller_perception.calibration.common import CalibrationError
from touchroller_perception.calibration.coverage import BoardCoverage, CoverageBar, board_coverage
from touchroller_perception.calibration.extrinsics import (
                                                           ExtrinsicsConfig,
                                                           ExtrinsicsResult,
                                                           NeglectedTerms,
                                                           RowBalance,
                                                           ViewPose,
                                                           back_project_pose,
                                                           calibrate_extrinsics,
                                                           full_pose_rotation,
                                                           model_error_mm,
                                                           solve_view,
)
from touchroller_perception.calibration.imprints import (
                                                           CENTRE_ESTIMATORS,
                                                           MAX_FRAME_SIDE,
                                                           STRENGTH_MEASURES,
                                                           HemisphereFrame,
                                                           ImprintDetection,
                                                           ImprintDetectorConfig,
                                                           find_imprints,
)
from touchroller_perception.calibration.intrinsics import (
                                                           AUTO_CANDIDATES,
                                                           CORNER_METHODS,
                                                           DISTORTION_MODELS,
                                                           DISTORTION_NAMES,
                                                           MAX_BOARD_SIDE,
                                                           Chessboard,
                                                           ChessboardDetection,
                                                           IntrinsicsConfig,
                                                           IntrinsicsResult,
                                                           ModelChoice,
                                                           ModelScore,
                                                           calibrate_intrinsics,
                                                           chessboard_corners,
                                                           choose_distortion_model,
                                                           detect_chessboards,
                                                           find_chessboard,
                                                           fronto_parallel_corners,
                                                           select_distortion_model,
)
from touchroller_perception.calibration.outputs import (
                                                           calibration_sigma,
                                                           camera_info_fields,
                                                           compare_cameras,
                                                           read_calibration_extras,
                                                           write_calibration,
)
from touchroller_perception.calibration.plausibility import Plausibility, check_plausible
from touchroller_perception.calibration.selection import SIMULATED_VIEW_RMS, TermChoice, choose_term, gate_by_rms
from touchroller_perception.calibration.uncertainty import INTRINSIC_NAMES, jackknife_std, view_clustered_covariance

__all__ = [
    "AUTO_CANDIDATES", "CENTRE_ESTIMATORS", "CORNER_METHODS", "DISTORTION_MODELS", "DISTORTION_NAMES",
    "INTRINSIC_NAMES",
    "MAX_BOARD_SIDE", "MAX_FRAME_SIDE", "SIMULATED_VIEW_RMS", "STRENGTH_MEASURES",
    "BoardCoverage", "CalibrationError", "Chessboard", "ChessboardDetection", "CoverageBar", "ExtrinsicsConfig",
    "ExtrinsicsResult", "HemisphereFrame", "ImprintDetection", "ImprintDetectorConfig", "IntrinsicsConfig",
    "IntrinsicsResult", "ModelChoice", "ModelScore", "NeglectedTerms", "Plausibility", "RowBalance", "TermChoice",
    "ViewPose", "check_plausible", "choose_term", "gate_by_rms",
    "back_project_pose", "board_coverage", "calibrate_extrinsics", "calibrate_intrinsics", "calibration_sigma",
    "camera_info_fields", "chessboard_corners", "choose_distortion_model", "compare_cameras", "detect_chessboards",
    "find_chessboard",
    "find_imprints", "fronto_parallel_corners", "full_pose_rotation",
    "model_error_mm", "read_calibration_extras", "select_distortion_model", "solve_view",
    "jackknife_std", "view_clustered_covariance", "write_calibration",
]
