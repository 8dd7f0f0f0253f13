"""Is a calibration result believable at all? Checked before anything is returned or applied.

A pose solve always returns numbers. Given intrinsics from another camera (a focal length of 500 px
for a camera of 380 px), the hemisphere frame's scale is absorbed by d, and the solve reports d to a
hundredth of a millimetre, 17 mm from where the mechanical design puts the camera. Such a result
must be refused with its reason, never written or set on other nodes: `check_plausible` raises a
`CalibrationError` naming the check that failed.
"""
from __future__ import annotations

import dataclasses
import math
from typing import TYPE_CHECKING

import numpy as np

from touchroller_perception.calibration.common import CalibrationError
from touchroller_perception.geometry import CameraModel

if TYPE_CHECKING:
    from touchroller_perception.calibration.extrinsics import ExtrinsicsResult


@dataclasses.dataclass(frozen=True)
class Plausibility:
    """Limits of a believable extrinsics result.

    `max_d_from_prior` (m) and `max_theta_from_prior` (rad): how far theta and d may lie from the
    prior the solve started from (the design's values: the camera sits on the roller's axis, a
    millimetre or two from the middle, tilted by a few degrees). `max_median_rms` (px): a median
    view reprojection RMS above it is more than imprint noise can explain (wrong intrinsics, a
    different frame, or not a hemisphere frame at all)."""

    max_d_from_prior: float = 0.005
    max_theta_from_prior: float = math.radians(10.0)
    max_median_rms: float = 3.0

    def __post_init__(self) -> None:
        if not (self.max_d_from_prior > 0 and self.max_theta_from_prior > 0 and self.max_median_rms > 0):
            raise CalibrationError("plausibility limits must be positive")


def check_plausible(result: ExtrinsicsResult, prior: CameraModel, limits: Plausibility = Plausibility()) -> None:
    """Raise a `CalibrationError` with the reason when `result` is not believable (see `Plausibility`)."""
    problems = []
    d_off = result.d - prior.d
    if not (math.isfinite(result.d) and abs(d_off) <= limits.max_d_from_prior):
        problems.append(
            f"d = {result.d * 1e3:.2f} mm is {abs(d_off) * 1e3:.1f} mm from the prior {prior.d * 1e3:.2f} mm (limit "
            f"{limits.max_d_from_prior * 1e3:g} mm): d carries the image's scale, so the intrinsics (fx "
            f"{prior.fx:.0f} px) most likely do not belong to this camera; calibrate the intrinsics first")
    theta_off = result.theta - prior.theta
    if not (math.isfinite(result.theta) and abs(theta_off) <= limits.max_theta_from_prior):
        limit = math.degrees(limits.max_theta_from_prior)
        problems.append(f"theta = {math.degrees(result.theta):.2f}° is {abs(math.degrees(theta_off)):.1f}° from the "
                        f"prior {math.degrees(prior.theta):.2f}° (limit {limit:g}°)")
    median_rms = float(np.median([v.rms for v in result.views])) if result.views else math.nan
    if not median_rms <= limits.max_median_rms:
        problems.append(f"the views' median reprojection RMS is {median_rms:.2f} px (limit {limits.max_median_rms:g} "
                        "px), more than imprint noise explains: wrong intrinsics or frame dimensions")
    if problems:
        raise CalibrationError("implausible result, not applied: " + "; ".join(problems))
