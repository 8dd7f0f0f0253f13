"""What the calibration steps share: the error type, the image size and the "enough views" check."""
from __future__ import annotations

from collections.abc import Mapping, Sequence

import numpy as np
from numpy.typing import NDArray

FloatArray = NDArray[np.float64]


class CalibrationError(ValueError):
    """Calibration input that cannot give a trustworthy result; the message is one line."""


def image_size(images: Sequence[np.ndarray]) -> tuple[int, int]:
    """(width, height) shared by all `images`."""
    sizes = {(int(img.shape[1]), int(img.shape[0])) for img in images}
    if len(sizes) != 1:
        raise CalibrationError(f"calibration images differ in size: {sorted(sizes)}")
    return sizes.pop()


def require_views(usable: int, needed: int, total: int, rejected: Mapping[int, str], what: str) -> None:
    """One line naming why there are too few usable views (the three commonest reasons)."""
    if total == 1 and needed > 1:
        raise CalibrationError(f"a single {what} image cannot be calibrated; capture at least {needed} views")
    if usable < needed:
        reasons: dict[str, int] = {}
        for reason in rejected.values():
            reasons[reason] = reasons.get(reason, 0) + 1
        listing = "; ".join(f"{n}x {r}" for r, n in sorted(reasons.items(), key=lambda kv: -kv[1])[:3])
        raise CalibrationError(f"only {usable} of {total} {what} images are usable, need {needed}"
                               + (f" ({listing})" if listing else ""))


def inliers(values: FloatArray, k: float, floor: float) -> NDArray[np.bool_]:
    """Values within k robust standard deviations (MAD, at least `floor`) of their median."""
    median = np.median(values)
    scale = max(1.4826 * float(np.median(np.abs(values - median))), floor)
    return np.asarray(np.abs(values - median) <= k * scale)
