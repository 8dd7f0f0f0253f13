"""Height from a GelSight-type image: slopes from colour (`photometric`), slopes to metres (`integrate`).

The membrane is lit by three coloured lights from different directions, so each pixel's colour change
against the no-contact reference encodes the membrane's slope (dz/dx, dz/dy); `photometric` learns that
map from presses of a ball of known radius, and `integrate` turns slopes into height with an exact
least-squares Poisson solver. `estimate` applies both to one image (a whole frame or the roller's contact
band): the per-frame height the CLI writes and a world mapper can place. Nothing here imports rclpy.
"""
from touchroller_perception.height.estimate import (
    ContactBand,
    HeightConfig,
    HeightEstimator,
    band_height,
    contact_band,
    pixel_size_at,
    slopes_to_height,
)
from touchroller_perception.height.integrate import divergence, forward_differences, integrate, poisson_solve
from touchroller_perception.height.photometric import (
    MAP_PHOTOMETRIC,
    PhotometricConfig,
    PhotometricModel,
    SlopeLookup,
    colour_features,
    fit_model,
)
from touchroller_perception.height.presses import (
    MAP_CALIBRATION,
    BallPress,
    DegreeScore,
    FittedCircle,
    PhotometricCalibration,
    PressCalibrationConfig,
    PressFit,
    calibrate_photometric,
    change_magnitude,
    find_press,
    normal_angles_deg,
    refine_circle,
    sphere_slopes,
)

__all__ = [
    "MAP_CALIBRATION", "MAP_PHOTOMETRIC", "BallPress", "ContactBand", "DegreeScore", "FittedCircle",
    "HeightConfig", "HeightEstimator", "PhotometricCalibration", "PhotometricConfig", "PhotometricModel",
    "PressCalibrationConfig", "PressFit", "SlopeLookup", "band_height", "calibrate_photometric", "change_magnitude",
    "colour_features", "contact_band", "divergence", "find_press", "fit_model", "forward_differences", "integrate",
    "normal_angles_deg", "pixel_size_at", "poisson_solve", "refine_circle", "slopes_to_height", "sphere_slopes",
]
