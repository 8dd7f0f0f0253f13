"""What a calibration produces: the parameters file, CameraInfo fields, and comparisons."""
from __future__ import annotations

import math
from collections.abc import Mapping
from typing import Any

import numpy as np

from touchroller_perception.calibration.extrinsics import ExtrinsicsResult
from touchroller_perception.calibration.intrinsics import IntrinsicsResult
from touchroller_perception.geometry import CameraModel


def compare_cameras(a: CameraModel, b: CameraModel, band_px: float = 35.0, step: int = 4) -> dict[str, float]:
    """How two calibrations differ: parameter differences (b - a) and how far apart they put the
    back-projections of the same pixels on the membrane (mm): mean in the central contact band
    |v - cy| <= band_px, and mean and max over the pixels both models can map."""
    us, vs = np.meshgrid(np.arange(0, a.width, step, dtype=np.float64), np.arange(0, a.height, step, dtype=np.float64))
    uv = np.stack([us, vs], axis=-1)
    pa, va = a.back_project(uv)
    pb, vb = b.back_project(uv)
    both = va & vb
    distance = 1e3 * np.linalg.norm(pa - pb, axis=-1)
    band = both & (np.abs(vs - a.cy) <= band_px)
    out = {f"d{name}_px": getattr(b, name) - getattr(a, name) for name in ("fx", "fy", "cx", "cy")}
    out.update({"dtheta_deg": math.degrees(b.theta - a.theta), "dd_mm": 1e3 * (b.d - a.d),
                "dradius_mm": 1e3 * (b.radius - a.radius),
                "contact_band_mean_mm": float(distance[band].mean()) if band.any() else math.nan,
                "image_mean_mm": float(distance[both].mean()) if both.any() else math.nan,
                "image_max_mm": float(distance[both].max()) if both.any() else math.nan,
                "mapped_fraction": float(both.mean())})
    return out


def calibration_sigma(intrinsics: IntrinsicsResult | None, extrinsics: ExtrinsicsResult | None) -> dict[str, float]:
    """One-sigma uncertainties in `CameraModel.contact_covariance`'s names (theta in rad, d in m).
    Intrinsics: OpenCV's, for the terms the model fitted (a term held at 0 has none). theta and d:
    the standard error over the presses with the intrinsics' uncertainty propagated."""
    sigma: dict[str, float] = {}
    if intrinsics is not None:
        sigma.update({k: v for k, v in intrinsics.sigma.items() if math.isfinite(v) and v > 0})
    if extrinsics is not None:
        for name, value in (("theta", extrinsics.theta_sigma), ("d", extrinsics.d_sigma)):
            if math.isfinite(value):
                sigma[name] = value
    return sigma


def write_calibration(path: str, camera: CameraModel, intrinsics: IntrinsicsResult | None = None,
                      extrinsics: ExtrinsicsResult | None = None, keep: Mapping[str, Any] | None = None) -> None:
    """The docs/design.md parameters file, plus `calibration.sigma.*` and RMS figures as extra parameters
    (`keep`: extra parameters of an earlier step to carry over, overridden by this step's)."""
    extra: dict[str, Any] = dict(keep or {})
    extra.update({f"calibration.sigma.{k}": float(v) for k, v in calibration_sigma(intrinsics, extrinsics).items()})
    if intrinsics is not None:
        extra["calibration.intrinsics_rms_px"] = float(intrinsics.rms)
    if extrinsics is not None:
        extra["calibration.extrinsics_rms_px"] = float(extrinsics.rms)
        extra["calibration.extrinsics_views"] = len(extrinsics.views)
        # the optional terms and their held-out margins, and how theta and d were combined
        extra["calibration.extrinsics_method"] = extrinsics.method
        extra["calibration.extrinsics_terms"] = [choice.line() for choice in extrinsics.choices] or [""]
    camera.to_yaml(path, extra=extra)


def read_calibration_extras(path: str) -> dict[str, Any]:
    """The `calibration.*` parameters of a parameters file (uncertainties and RMS of earlier steps)."""
    import yaml

    with open(path, encoding="utf-8") as stream:
        document = yaml.safe_load(stream) or {}
    for value in document.values() if isinstance(document, Mapping) else ():
        if isinstance(value, Mapping) and isinstance(value.get("ros__parameters"), Mapping):
            params = value["ros__parameters"]
            flat = {f"calibration.{k}": v for k, v in params.get("calibration", {}).items()} \
                if isinstance(params.get("calibration"), Mapping) else {}
            flat.update({k: v for k, v in params.items() if str(k).startswith("calibration.")})
            return flat
    return {}


def camera_info_fields(camera: CameraModel) -> dict[str, Any]:
    """sensor_msgs/CameraInfo fields (plumb_bob) for `camera`; R is identity, P = [K | 0]."""
    k_matrix = camera.K
    projection = np.hstack([k_matrix, np.zeros((3, 1))])
    return {"width": camera.width, "height": camera.height, "distortion_model": "plumb_bob",
            "d": [float(v) for v in camera.distortion], "k": [float(v) for v in k_matrix.ravel()],
            "r": [float(v) for v in np.eye(3).ravel()], "p": [float(v) for v in projection.ravel()]}
