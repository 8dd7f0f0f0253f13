"""The hemisphere frame and its imprints: where each hemisphere pressed the membrane, and how hard.

`find_imprints` finds the frame's imprints in a press image, orders them as the frame's layout,
and measures each one's centre (subpixel) and strength (how deep it pressed, for the row
balance of `extrinsics`). Two things a roller's lighting does to imprints are handled here:

* light from one side makes an imprint bright on one slope and dark on the other, which pulls a
  change-weighted centroid away from the light: `_shading_symmetric_centre` measures the centre
  from the part of the pattern that is symmetric under any directional light; a slope facing away
  from a low light steeper than the light's elevation gets none of it (its shading stops at a
  floor), which breaks that symmetry and still pulls the centre towards the light:
  `_censored_centre` fits the imprint's pattern with the pixels at the floor censored, not
  symmetrised (`censored_centres`);
* the light falls off across the membrane, so an absolute strength reads the brighter row as the
  deeper one: strengths are taken relative to the light (`_relative_energy`): the no-contact
  reference's brightness, or, given a frame with the lights off, the reference minus it (`_light`);
  without that frame, a background the light does not make would be divided in with the light, so
  strengths are then the imprints' extent (`_window_sizes`), which no light level changes.
"""
from __future__ import annotations

import dataclasses
import math

import cv2
import numpy as np
from numpy.typing import NDArray

from touchroller_perception.calibration.common import CalibrationError, FloatArray

#: `ImprintDetectorConfig.centre`: "symmetric" (the default) corrects the centroid for one-sided light
#: (`_shading_symmetric_centre`), "shading" also for the slopes a low light leaves in shadow, "centroid" keeps it
CENTRE_ESTIMATORS = ("symmetric", "shading", "centroid")
#: `ImprintDetectorConfig.strength`: "auto" ("relative" given a lights-off frame, else "size"), "relative" to
#: the light (energy), "size" (the imprint's extent, which no light level changes), or "absolute" grey levels
STRENGTH_MEASURES = ("auto", "relative", "size", "absolute")


#: Most hemisphere rows or columns of a frame: the sizes of what the solve allocates (the paper's is 2x5).
MAX_FRAME_SIDE = 50


@dataclasses.dataclass(frozen=True)
class HemisphereFrame:
    """The paper's 3D-printed frame: `rows` x `columns` hemispheres on a flat plate.

    Columns run along the roller axis (x), rows across it (y, the rolling direction); `pitch_x`
    and `pitch_y` are centre distances in metres. The plate lies under the roller, the hemispheres
    pressed `press_depth` into the membrane at y = 0. Defaults match the simulator's
    `calibration_hemispheres` scene: 2 rows x 5 columns, 10 mm x 8 mm pitch, 1 mm hemispheres
    (the paper gives the layout and the radius, not the pitch).
    """

    rows: int = 2
    columns: int = 5
    pitch_x: float = 0.010
    pitch_y: float = 0.008
    hemisphere_radius: float = 0.001
    press_depth: float = 0.0005

    def __post_init__(self) -> None:
        if self.rows > MAX_FRAME_SIDE or self.columns > MAX_FRAME_SIDE:
            raise CalibrationError(f"a hemisphere frame has at most {MAX_FRAME_SIDE} rows and columns, got "
                                   f"{self.rows}x{self.columns}")
        if self.rows < 1 or self.columns < 1 or self.rows * self.columns < 4:
            raise CalibrationError(f"a hemisphere frame needs at least 4 hemispheres, got {self.rows}x{self.columns}")
        if self.rows < 2 or self.columns < 2:
            raise CalibrationError(f"the frame's {self.rows}x{self.columns} hemispheres are collinear: "
                                   "the pose solve needs at least 2 rows and 2 columns")
        if not (self.pitch_x > 0 and self.pitch_y > 0 and self.hemisphere_radius > 0):
            raise CalibrationError(f"frame pitches and hemisphere radius must be positive, got "
                                   f"{self.pitch_x}, {self.pitch_y}, {self.hemisphere_radius}")

    @property
    def count(self) -> int:
        return self.rows * self.columns

    def layout(self) -> FloatArray:
        """Hemisphere centres (rows*columns, 2) on the plate, row-major: rows by increasing y,
        columns by increasing x, centred on the frame's middle."""
        x = (np.arange(self.columns) - 0.5 * (self.columns - 1)) * self.pitch_x
        y = (np.arange(self.rows) - 0.5 * (self.rows - 1)) * self.pitch_y
        yy, xx = np.meshgrid(y, x, indexing="ij")
        return np.stack([xx.ravel(), yy.ravel()], axis=-1)

    def reference_points(self, radius: float, shift_x: float = 0.0, shift_y: float = 0.0,
                         yaw: float = 0.0) -> FloatArray:
        """Imprint centres (rows*columns, 3) in the cylinder frame for the frame placed at
        (shift_x, shift_y) with `yaw` (rad, about z) relative to the centre below the axis.

        A sphere pressed into a cylinder touches it on the line from the axis to the sphere's
        centre, so the imprint centre is the membrane point at alpha = atan2(y, plate_z)."""
        layout = self.layout()
        c, s = math.cos(yaw), math.sin(yaw)
        x = shift_x + c * layout[:, 0] - s * layout[:, 1]
        y = shift_y + s * layout[:, 0] + c * layout[:, 1]
        plate_z = radius + self.hemisphere_radius - self.press_depth
        if np.max(np.abs(y)) >= 0.5 * radius:
            raise CalibrationError(f"frame rows at |y| = {np.max(np.abs(y)) * 1e3:.1f} mm do not fit under a "
                                   f"roller of radius {radius * 1e3:.1f} mm")
        alpha = np.arctan2(y, plate_z)
        return np.stack([x, radius * np.sin(alpha), radius * np.cos(alpha)], axis=-1)


@dataclasses.dataclass(frozen=True)
class ImprintDetectorConfig:
    """How `find_imprints` finds and measures imprints.

    Blobs with an area outside [`min_area`, `max_area`] px are not imprints; a median blob
    elongation above `max_elongation` means motion blur; centres whose cloud is thinner than
    `min_spread` (second / first singular value) are collinear. `centre` and `strength`: see
    CENTRE_ESTIMATORS and STRENGTH_MEASURES. `window_scale`: the disc over which a centre is
    refined, `strength_window_scale`: the one over which a strength is summed (wide, so that the
    slow tail of an imprint counts alike in both rows), `size_window_scale`: the one over which a
    "size" is measured (narrow: the light's fall-off across a wide disc weights one side of the
    imprint more), in median blob RMS radii.
    """

    min_area: float = 12.0
    max_area: float = 8000.0
    max_elongation: float = 1.8
    min_spread: float = 0.08
    centre: str = "symmetric"
    strength: str = "auto"
    window_scale: float = 2.5
    strength_window_scale: float = 4.0
    size_window_scale: float = 2.0

    def __post_init__(self) -> None:
        if self.centre not in CENTRE_ESTIMATORS:
            raise CalibrationError(f"centre must be one of {', '.join(CENTRE_ESTIMATORS)}, got {self.centre!r}")
        if self.strength not in STRENGTH_MEASURES:
            raise CalibrationError(f"strength must be one of {', '.join(STRENGTH_MEASURES)}, got {self.strength!r}")
        if not (0 < self.min_area <= self.max_area):
            raise CalibrationError(f"need 0 < min_area <= max_area, got {self.min_area}, {self.max_area}")
        if not (self.max_elongation >= 1 and 0 < self.min_spread < 1 and self.window_scale >= 1
                and self.strength_window_scale >= 1 and self.size_window_scale >= 1):
            raise CalibrationError("need max_elongation >= 1, 0 < min_spread < 1 and window scales >= 1")


@dataclasses.dataclass(frozen=True)
class ImprintDetection:
    centres: FloatArray | None       # (rows*columns, 2) in frame order, None if unusable
    elongation: float                # median ratio of the blobs' principal axes (1 = round)
    found: int                       # blobs found
    reason: str | None
    strengths: FloatArray | None = None   # each imprint's summed change (`ImprintDetectorConfig.strength`), frame order
    #: (rows*columns, 2) px, frame order: the size of the pull a shadow may still leave on each centre (for
    #: "shading", how far the centre moves when less of the imprint counts as shadow, `censored_centres`; for
    #: "symmetric", how far a squared weighting moves it, `shadow_pull`); None for "centroid"
    pull: FloatArray | None = None
    #: each imprint's extent (`_window_sizes`), frame order, when `strengths` are the energy relative to the light
    #: of a lights-off frame: the other measure of the rows' depths, whose disagreement is model error
    other_strengths: FloatArray | None = None


def find_imprints(image: np.ndarray, frame: HemisphereFrame, config: ImprintDetectorConfig = ImprintDetectorConfig(),
                  reference: np.ndarray | None = None, dark: np.ndarray | None = None) -> ImprintDetection:
    """Subpixel imprint centres and strengths, ordered as `frame.reference_points`.

    The change is the image minus the no-contact reference, per colour channel (without a
    reference, a large median filter estimates the static background). Blobs: the change's
    magnitude summed over the channels, binarised at a noise-adapted threshold, opened, closed and
    filled; the strongest `frame.count` blobs are the imprints. Each blob's change-weighted
    centroid starts its centre, which `_shading_symmetric_centre` then refines (unless
    `config.centre` is "centroid") and `censored_centres` after it ("shading"). Strengths are
    summed over equal discs (`_window_strengths`).
    `dark`: a no-contact frame with the sensor's lights off; "relative" strengths are then taken
    relative to the light alone (reference - dark), see `_light`.
    """
    signed, background = _signed_change(image, reference)
    change = cv2.GaussianBlur(np.abs(signed).sum(axis=2), (0, 0), 1.0)
    sample = change[::3, ::3]        # statistics of a subsample: a full-image median costs ~10 ms
    median = float(np.median(sample))
    noise = 1.4826 * float(np.median(np.abs(sample - median))) + 1e-6
    peak = float(np.percentile(sample, 99.95))
    threshold = max(median + 6.0 * noise, median + 0.2 * (peak - median))
    blobs = _blobs(change > threshold, np.maximum(change - median, 0.0), config)
    found = len(blobs)
    if found < frame.count:
        return ImprintDetection(None, math.nan, found, f"too few imprints: found {found}, the "
                                f"{frame.rows}x{frame.columns} frame has {frame.count}")
    blobs = sorted(blobs, key=lambda b: -b.total)[:frame.count]
    elongation = float(np.median([b.elongation for b in blobs]))
    if elongation > config.max_elongation:
        return ImprintDetection(None, elongation, found, f"blurred: imprints smeared {elongation:.1f}:1 "
                                f"(> {config.max_elongation:.1f}:1); hold the roller still")
    centres = np.array([b.centroid for b in blobs])
    order, reason = _order_grid(centres, frame.rows, frame.columns, config.min_spread)
    if order is None:
        return ImprintDetection(None, elongation, found, reason)
    radius = float(np.median([b.radius for b in blobs]))
    pull = None
    if config.centre in ("shading", "symmetric"):
        centres = np.array([_shading_symmetric_centre(signed, b.centroid, config.window_scale * radius)
                            for b in blobs])
        if config.centre == "symmetric":
            pull = shadow_pull(signed, centres, config.window_scale * radius)
        else:
            centres, pull = censored_centres(signed, centres, config.window_scale * radius)
    measure = config.strength if config.strength != "auto" else ("relative" if dark is not None else "size")
    other = None
    if measure == "relative":
        strengths = _window_strengths(_relative_energy(signed, _light(background, dark)), centres,
                                      config.strength_window_scale * radius, clip=False)
        if dark is not None:
            other = _window_sizes(_relative_energy(signed, None), centres, config.size_window_scale * radius)
    elif measure == "size":
        strengths = _window_sizes(_relative_energy(signed, None), centres, config.size_window_scale * radius)
    else:
        magnitude = cv2.GaussianBlur(np.abs(signed).sum(axis=2), (0, 0), 1.0)
        strengths = _window_strengths(magnitude, centres, config.strength_window_scale * radius)
    return ImprintDetection(centres[order], elongation, found, None, strengths[order],
                            None if pull is None else pull[order], None if other is None else other[order])


def _blobs(mask: NDArray[np.bool_], weight: NDArray[np.float32], config: ImprintDetectorConfig) -> list[_Blob]:
    """The filled connected components of `mask`, measured with `weight`."""
    mask8 = mask.astype(np.uint8)
    mask8 = cv2.morphologyEx(mask8, cv2.MORPH_OPEN, cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (3, 3)))
    mask8 = cv2.morphologyEx(mask8, cv2.MORPH_CLOSE, cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (7, 7)))
    contours, _ = cv2.findContours(mask8, cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_SIMPLE)
    filled = np.zeros_like(mask8)
    cv2.drawContours(filled, contours, -1, 1, thickness=cv2.FILLED)
    count, labels, stats, _ = cv2.connectedComponentsWithStats(filled, connectivity=8)
    measured = (_measure_blob(label, labels, stats, weight, config.min_area, config.max_area)
                for label in range(1, count))
    return [blob for blob in measured if blob is not None]


@dataclasses.dataclass(frozen=True)
class _Blob:
    total: float                     # summed change magnitude (ranks the blobs)
    centroid: tuple[float, float]    # change-weighted, px
    radius: float                    # RMS radius of the change, px
    elongation: float                # ratio of the principal axes


def _measure_blob(label: int, labels: np.ndarray, stats: np.ndarray, weight: np.ndarray,
                  min_area: float, max_area: float) -> _Blob | None:
    area = stats[label, cv2.CC_STAT_AREA]
    if not (min_area <= area <= max_area):
        return None
    x0, y0, w, h = (stats[label, k] for k in (cv2.CC_STAT_LEFT, cv2.CC_STAT_TOP, cv2.CC_STAT_WIDTH, cv2.CC_STAT_HEIGHT))
    inside = labels[y0:y0 + h, x0:x0 + w] == label
    w_roi = weight[y0:y0 + h, x0:x0 + w] * inside
    total = float(w_roi.sum())
    if total <= 0:
        return None
    vs, us = np.mgrid[y0:y0 + h, x0:x0 + w]
    cu, cv_ = float((w_roi * us).sum() / total), float((w_roi * vs).sum() / total)
    cov = np.cov(np.stack([us.ravel() - cu, vs.ravel() - cv_]), aweights=w_roi.ravel() + 1e-12, bias=True)
    eig = np.linalg.eigvalsh(cov)
    return _Blob(total=total, centroid=(cu, cv_), radius=math.sqrt(max(float(eig.sum()), 1e-12)),
                 elongation=math.sqrt(max(eig[1], 1e-12) / max(eig[0], 1e-12)))


def _shading_symmetric_centre(signed: NDArray[np.float32], start: tuple[float, float], radius: float,
                              knot: float = 0.75, iterations: int = 12, power: float = 1.0) -> tuple[float, float]:
    """The centre of an imprint lit from one side, from its signed change (H, W, channels).

    A light from one side brightens the imprint's slope that faces it and darkens the other, and
    darkens both a little more where they are steep (Lambert's n.L falls as the normal tilts), so
    the change's magnitude is larger on the far side and its centroid moves away from the light
    (0.5 px for imprints lit at 35 degrees). Split the change around a centre c into its
    isotropic part E(rho) and the rest: for a radially symmetric imprint under directional light
    the rest is a dipole O(rho) cos(phi - light), whose magnitude is point-symmetric about the true
    centre, so its centroid is c. E, and the dipole's radial profiles (fitted beside it so they do
    not leak into E), are free piecewise-linear functions of rho (knots every `knot` px): no model
    of the imprint's profile or of the light is assumed. Iterate c <- centroid of the remainder's
    magnitude (tapered at the window's edge), within `radius` px. The magnitude, not its square:
    where a low light grazes the imprint's steep rim, the slope facing away falls into shadow and
    the remainder there is no longer a clean dipole; a squared weight lets those few pixels pull
    the centre towards the light (0.14 px on the simulator lit from one side at 25 degrees, half
    that with the magnitude). `power`: the weight is the remainder's magnitude to this power
    (`shadow_pull` compares 1 and 2). Keeps `start` where the window leaves the image or the fit
    degenerates.
    """
    height, width = signed.shape[:2]
    reach = int(math.ceil(radius)) + 2
    knots = np.arange(0.0, radius + knot, knot)
    centre = np.array(start, dtype=np.float64)
    for _ in range(iterations):
        u0, v0 = int(round(centre[0])), int(round(centre[1]))
        if not (reach <= u0 < width - reach and reach <= v0 < height - reach):
            return float(start[0]), float(start[1])
        vs, us = np.mgrid[v0 - reach:v0 + reach + 1, u0 - reach:u0 + reach + 1]
        du, dv = (us - centre[0]).ravel(), (vs - centre[1]).ravel()
        rho = np.hypot(du, dv)
        inside = rho <= radius
        du, dv, rho = du[inside], dv[inside], rho[inside]
        patch = signed[v0 - reach:v0 + reach + 1, u0 - reach:u0 + reach + 1].reshape(-1, signed.shape[2])[inside]
        hats = np.clip(1.0 - np.abs(rho[:, None] - knots[None, :]) / knot, 0.0, None)
        safe = np.maximum(rho, 1e-9)[:, None]
        design = np.hstack([hats, hats * (du[:, None] / safe), hats * (dv[:, None] / safe)])
        coefficients = _least_squares(design, patch.astype(np.float64))
        remainder = patch - cv2.gemm(hats, coefficients[:knots.size], 1.0, None, 0.0)
        edge = np.clip((radius - rho) / (0.4 * radius), 0.0, 1.0)
        weights = np.abs(remainder).sum(axis=1) ** power * edge * edge * (3.0 - 2.0 * edge)
        total = float(weights.sum())
        if not total > 0:
            return float(start[0]), float(start[1])
        moved = np.array([(weights * du).sum(), (weights * dv).sum()]) / total
        centre = centre + moved
        if float(np.abs(moved).max()) < 5e-3:
            break
    if not (np.all(np.isfinite(centre)) and np.hypot(*(centre - np.asarray(start))) <= 0.5 * radius):
        return float(start[0]), float(start[1])
    return float(centre[0]), float(centre[1])


#: `_censored_centre`'s floor: the pixels within this fraction of the window's range above its lowest value
#: count as shadow. Blur spreads a shadow's edge over a pixel or two, which a floor at 0.1 leaves in (0.04 px of
#: pull on a blurred imprint lit at 15 degrees); well past a third, slopes that get light are treated as shadow.
SHADOW_FLOOR = 0.3
#: the floor `censored_centres` compares with, for the size of the pull that is left
SHADOW_FLOOR_LOW = 0.15


def censored_centres(signed: NDArray[np.float32], centres: FloatArray, radius: float) -> tuple[FloatArray, FloatArray]:
    """The imprints' shadow-censored centres (`_censored_centre` at `SHADOW_FLOOR`) from their
    shading-symmetric ones, (n, 2) px, and the size of the pull a shadow may still leave on them,
    (n, 2) px: how far each centre moves when only the pixels within `SHADOW_FLOOR_LOW` count as
    shadow. A shadow's blurred edge left uncensored pulls the centre towards the light, and the less
    is censored the further; where no slope is in shadow the two agree within noise. Like
    `shadow_pull`, it is no correction but the size of an error the presses share: `extrinsics` adds
    it to theta's and d's sigma as model error."""
    censored = np.array([_censored_centre(signed, (float(u), float(v)), radius)
                         for u, v in np.asarray(centres, dtype=np.float64)])
    less = np.array([_censored_centre(signed, (float(u), float(v)), radius, floor_fraction=SHADOW_FLOOR_LOW)
                     for u, v in censored])
    return censored, less - censored


def _censored_centre(signed: NDArray[np.float32], start: tuple[float, float], radius: float,
                     knot: float = 0.75, floor_fraction: float = SHADOW_FLOOR, iterations: int = 8,
                     tolerance: float = 3e-3, step: float = 0.05) -> tuple[float, float]:
    """The centre of an imprint lit from one side, where the light leaves part of it in shadow.

    Under a directional light, an imprint's change about its true centre is an isotropic part
    E(rho) plus a dipole O(rho) cos(phi - light) (`_shading_symmetric_centre`) only while every
    slope gets some light: a slope facing away from the light and steeper than the light's
    elevation gets none (Lambert's n.L clamps at 0), its change stops at a floor, and the pattern
    there is no longer a dipole. Any weighted centroid of it is then pulled towards the light
    (weighting by the magnitude left 0.1-0.15 px on a sphere cap lit at 25 degrees), and leaving
    those pixels out symmetrically does not help: on a pixel grid the mirror of a pixel is no pixel,
    and a hole cut at pixel scale is never point-symmetric. A fit is not a centroid, it needs no
    symmetry: choose c so that E(rho) + the dipole's two radial profiles (free piecewise-linear
    functions, knots every `knot` px, as in `_shading_symmetric_centre`) fit the change best,
    treating each pixel near the window's lowest value (within `floor_fraction` of the window's
    range, per channel) as censored: it counts only where the model would be brighter than what it
    saw (a floor says "no brighter than this", not "this"). Leaving out pixels that were not in
    shadow costs a little precision; leaving in a shadow's blurred edge leaves some pull
    (`SHADOW_FLOOR`). The profiles enter linearly (solved at each c); c by Gauss-Newton with a
    numerical Jacobian of `step` px (of the whole projection: with the profiles held, a shift of c is
    nearly a dipole the profiles absorb, and the information is in how they refit), at most
    `iterations` steps of at most 0.5 px, from `start` (the shading-symmetric centre), until a step is
    under `tolerance` px. Keeps `start` where the window leaves the
    image or the fit runs further than half the window."""
    height, width = signed.shape[:2]
    reach = int(math.ceil(radius)) + 2
    u0, v0 = int(round(start[0])), int(round(start[1]))
    if not (reach <= u0 < width - reach and reach <= v0 < height - reach):
        return float(start[0]), float(start[1])
    vs, us = np.mgrid[v0 - reach:v0 + reach + 1, u0 - reach:u0 + reach + 1]
    near = np.hypot(us - start[0], vs - start[1]).ravel() <= radius + 1.0    # the disc the steps can reach
    us_f, vs_f = us.ravel()[near].astype(np.float64), vs.ravel()[near].astype(np.float64)
    patch = signed[v0 - reach:v0 + reach + 1, u0 - reach:u0 + reach + 1].reshape(-1, signed.shape[2])[near]
    patch = patch.astype(np.float64)
    ordered = np.sort(patch, axis=0)
    low, high = ordered[2], ordered[-3]          # the third lowest and highest: one hot pixel does not set them
    floor = np.any(patch <= low + floor_fraction * (high - low), axis=1)
    lit = (~floor).astype(np.float64)
    knots = np.arange(0.0, radius + knot, knot)

    def fit(c: FloatArray, use: FloatArray) -> tuple[FloatArray, FloatArray]:
        du, dv = us_f - c[0], vs_f - c[1]
        rho = np.hypot(du, dv)
        edge = np.clip((radius - rho) / (0.4 * radius), 0.0, 1.0)
        root = np.sqrt(edge * edge * (3.0 - 2.0 * edge) * use)[:, None]
        hats = np.clip(1.0 - np.abs(rho[:, None] - knots[None, :]) / knot, 0.0, None)
        safe = np.maximum(rho, 1e-9)[:, None]
        design = np.hstack([hats, hats * (du[:, None] / safe), hats * (dv[:, None] / safe)])
        fitted = cv2.gemm(design, _least_squares(design * root, patch * root), 1.0, None, 0.0)
        return fitted, ((patch - fitted) * root).ravel()

    centre = np.array(start, dtype=np.float64)
    for _ in range(iterations):
        fitted, _ = fit(centre, lit)
        # a pixel at the floor counts only where the model of the lit pixels would be brighter than what it saw
        use = (~floor | np.any(fitted > patch, axis=1)).astype(np.float64)
        _, residual = fit(centre, use)
        jacobian = np.stack([(fit(centre + delta, use)[1] - residual) / step
                             for delta in (np.array([step, 0.0]), np.array([0.0, step]))], axis=1)
        gram = jacobian.T @ jacobian
        if not (np.all(np.isfinite(gram)) and np.linalg.det(gram) > 0):
            return float(start[0]), float(start[1])
        moved = -np.linalg.solve(gram, jacobian.T @ residual)
        norm = float(np.hypot(*moved))
        if norm > 0.5:
            moved *= 0.5 / norm
        centre = centre + moved
        if norm < tolerance:
            break
    if not (np.all(np.isfinite(centre)) and np.hypot(*(centre - np.asarray(start))) <= 0.5 * radius):
        return float(start[0]), float(start[1])
    return float(centre[0]), float(centre[1])


def shadow_pull(signed: NDArray[np.float32], centres: FloatArray, radius: float) -> FloatArray:
    """An estimate of how far a shadow still pulls each shading-symmetric centre towards the light:
    the centre refined with the remainder's squared magnitude as weight, less the centre with its
    magnitude (`_shading_symmetric_centre`), (n, 2) px.

    Where the dipole form holds (no slope in shadow), the remainder is point-symmetric about the
    true centre under any weighting, both centres are right and the difference is noise. Where a low
    light leaves the slope facing away in shadow, the few pixels that break the dipole pull each
    centre towards the light, the squared weight about twice as far as the magnitude (the pull grows
    with the weight's power); the difference is then about the magnitude-weighted centre's own pull.
    It is no correction (how far the pull is linear in the power is not known), it is the size of an
    error the presses share, which no spread over presses shows: `extrinsics` adds it to theta's and
    d's sigma as model error."""
    squared = np.array([_shading_symmetric_centre(signed, (float(u), float(v)), radius, power=2.0)
                        for u, v in np.asarray(centres, dtype=np.float64)])
    return squared - np.asarray(centres, dtype=np.float64)


def _least_squares(design: FloatArray, values: FloatArray) -> FloatArray:
    """Linear least squares by the normal equations (OpenCV, single-threaded) with a tiny ridge.
    These systems are small (~700 x 60) and well conditioned; numpy's lstsq and matmul go through
    threaded BLAS, which costs 10-100x more when other processes share the cores."""
    gram = cv2.mulTransposed(design, True)
    gram[np.diag_indices_from(gram)] += 1e-9 * float(np.trace(gram)) / gram.shape[0] + 1e-12
    rhs = cv2.gemm(design, values, 1.0, None, 0.0, flags=cv2.GEMM_1_T)
    ok, solution = cv2.solve(gram, rhs, flags=cv2.DECOMP_CHOLESKY)
    if not ok:
        ok, solution = cv2.solve(gram, rhs, flags=cv2.DECOMP_SVD)
    return np.asarray(solution, dtype=np.float64)


def _signed_change(image: np.ndarray, reference: np.ndarray | None) -> tuple[NDArray[np.float32], NDArray[np.float32]]:
    """(image - background, background), both (H, W, channels) float32."""
    array = np.asarray(image)
    if array.ndim == 2:
        array = array[..., None]
    array = array.astype(np.float32)
    if reference is not None:
        ref = np.asarray(reference)
        if ref.shape[:2] != array.shape[:2]:
            raise CalibrationError(f"reference frame is {ref.shape[1]}x{ref.shape[0]}, "
                                   f"images are {array.shape[1]}x{array.shape[0]}")
        ref = ref[..., None] if ref.ndim == 2 else ref
        background = ref.astype(np.float32)
    else:
        # a median over ~5 imprint diameters, on a half-size image (cheap, and still far larger than an imprint)
        small = cv2.resize(np.clip(array, 0, 255).astype(np.uint8), None, fx=0.5, fy=0.5,
                           interpolation=cv2.INTER_AREA)
        small = small[..., None] if small.ndim == 2 else small
        planes = [cv2.medianBlur(np.ascontiguousarray(small[..., c]), 31) for c in range(small.shape[2])]
        background = np.stack([cv2.resize(p, (array.shape[1], array.shape[0]), interpolation=cv2.INTER_LINEAR)
                               for p in planes], axis=-1).astype(np.float32)
    if background.shape[2] != array.shape[2]:
        background = np.broadcast_to(background.mean(axis=2, keepdims=True), array.shape).astype(np.float32)
    return array - background, background


def _window_strengths(relative: NDArray[np.float32], centres: FloatArray, radius: float,
                      clip: bool = True) -> FloatArray:
    """Each imprint's change above the image's level (`clip`: the median, and nothing below it counted;
    else as it is, for a change whose noise floor is already out), summed over a disc of `radius` px
    (the same disc for every imprint: a threshold-cut blob would reach further around the imprint
    with more light and so count it stronger)."""
    level = float(np.median(relative[::3, ::3])) if clip else 0.0
    reach = int(math.ceil(radius))
    offsets = np.arange(-reach, reach + 1)
    strengths = []
    for u, v in centres:
        us = np.clip(int(round(u)) + offsets, 0, relative.shape[1] - 1)
        vs = np.clip(int(round(v)) + offsets, 0, relative.shape[0] - 1)
        disc = (offsets[None, :] + round(u) - u) ** 2 + (offsets[:, None] + round(v) - v) ** 2 <= radius * radius
        window = relative[np.ix_(vs, us)] - level
        strengths.append(float(((np.maximum(window, 0.0) if clip else window) * disc).sum()))
    return np.array(strengths)


def _window_sizes(energy: NDArray[np.float32], centres: FloatArray, radius: float) -> FloatArray:
    """Each imprint's extent: the second moment about its centre (px^2) of the change's energy
    (less the noise's) over a disc of `radius` px.

    What the light does to an imprint's change is to scale it: the change is the light reaching the
    membrane there times what the slopes do to it, and a background the light does not make
    (ambient light, an uneven gel) is in the reference and the press alike, so it cancels in the
    change. A ratio of two sums of the same energy is therefore the same under any light level,
    with no lights-off frame and no division by the reference; a deeper press leaves a wider
    imprint (a sphere's contact radius grows as the square root of its depth), so the extent
    measures the depth. An area, like `_window_strengths`' sums, so it is made per mm^2 of membrane
    the same way."""
    reach = int(math.ceil(radius))
    offsets = np.arange(-reach, reach + 1, dtype=np.float64)
    sizes = []
    for u, v in centres:
        us = np.clip(int(round(u)) + offsets.astype(int), 0, energy.shape[1] - 1)
        vs = np.clip(int(round(v)) + offsets.astype(int), 0, energy.shape[0] - 1)
        rho2 = (offsets[None, :] + round(u) - u) ** 2 + (offsets[:, None] + round(v) - v) ** 2
        window = energy[np.ix_(vs, us)] * (rho2 <= radius * radius)
        total = float(window.sum())
        sizes.append(float((window * rho2).sum()) / total if total > 0 else math.nan)
    return np.array(sizes)


def _light(background: NDArray[np.float32], dark: np.ndarray | None) -> NDArray[np.float32]:
    """What of the no-contact background the sensor's lights make: the background minus the frame
    with the lights off, when there is one; else the whole background.

    Only the light scales an imprint's shading. A background the light does not make (ambient
    light, an uneven gel that glows or absorbs independently of the LEDs) makes the reference
    brighter without making imprints stronger; divided by the whole reference, a row over a
    brighter patch reads weaker. A single lit reference cannot tell the two apart (a gel texture
    that scales the light, as dust in front of an LED does, must stay in; one that adds to it must
    come out), a frame with the lights off can."""
    if dark is None:
        return background
    off = np.asarray(dark)
    if off.shape[:2] != background.shape[:2]:
        raise CalibrationError(f"the lights-off frame is {off.shape[1]}x{off.shape[0]}, "
                               f"images are {background.shape[1]}x{background.shape[0]}")
    off = (off[..., None] if off.ndim == 2 else off).astype(np.float32)
    if off.shape[2] != background.shape[2]:
        off = np.broadcast_to(off.mean(axis=2, keepdims=True), background.shape)
    return np.asarray(background - off, dtype=np.float32)


def _relative_energy(signed: NDArray[np.float32], light: NDArray[np.float32] | None) -> NDArray[np.float32]:
    """The change's energy relative to the light, per pixel: sum over the channels of
    (change^2 - noise^2) / light^2 (a flat-field correction).

    The light of a roller falls off across the membrane, and an imprint's change scales with the
    light it gets: an absolute strength reads a brighter row as a deeper press (on an image lit
    15 % more per 10 mm towards one row, as if the frame sat 0.18 mm off centre). Dividing by the
    light takes it out, per channel (each colour's light may fall off its own way). The noise is
    the same in grey levels everywhere, so it must come out before dividing, or it counts more
    where the light is weaker: squared, its share is one constant per channel (the median square
    of the change over the image, which imprints hardly touch, / 0.4549, the median of chi-square
    with 1 degree of freedom), and subtracting it leaves no bias (the magnitude's floor, |change|,
    depends on the signal under it and cannot be taken out exactly). `light` None: the energy as it
    is, in grey levels squared (for `_window_sizes`, which a light level does not change)."""
    change = signed.astype(np.float64)
    noise = np.median(change[::3, ::3].reshape(-1, change.shape[2]) ** 2, axis=0) / 0.4549
    energy = change**2 - noise
    if light is not None:
        energy /= np.maximum(light.astype(np.float64), 1.0) ** 2
    return np.asarray(energy.sum(axis=2), dtype=np.float32)


def _order_grid(centres: FloatArray, rows: int, columns: int,
                min_spread: float) -> tuple[NDArray[np.intp] | None, str | None]:
    """The permutation ordering blob centres row-major (rows by increasing v, columns by increasing u) using the
    cloud's principal axes, so a tilted frame still sorts correctly."""
    mean = centres.mean(axis=0)
    _, singular, vt = np.linalg.svd(centres - mean, full_matrices=False)
    if singular[1] < min_spread * singular[0]:
        return None, (f"imprint centres are collinear (spread ratio {singular[1] / singular[0]:.3f} "
                      f"< {min_spread}): the pose is undetermined")
    long_axis = vt[0] if columns >= rows else vt[1]
    if long_axis[0] < 0:
        long_axis = -long_axis
    across = np.array([-long_axis[1], long_axis[0]])   # +v for an axis along +u
    along_c = (centres - mean) @ long_axis
    across_c = (centres - mean) @ across
    by_row = np.argsort(across_c, kind="stable")
    ordered: list[int] = []
    for r in range(rows):
        members = by_row[r * columns:(r + 1) * columns]
        ordered.extend(members[np.argsort(along_c[members], kind="stable")])
    # the rows must separate: the gap between rows larger than the scatter within a row
    row_values = across_c[by_row].reshape(rows, columns)
    if rows > 1:
        gap = np.min(row_values[1:].min(axis=1) - row_values[:-1].max(axis=1))
        if gap <= 0:
            return None, "imprints do not form the frame's grid (rows overlap)"
    return np.asarray(ordered), None


