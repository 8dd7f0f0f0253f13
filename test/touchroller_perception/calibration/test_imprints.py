"""Imprint centres and strengths under a roller's lighting: one-sided light and light that falls off."""
from __future__ import annotations

import math

import cv2
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from touchroller_perception import calibration as cal

FRAME = cal.HemisphereFrame()
SIZE = (480, 640)
#: the frame's imprints on a 2x5 grid of pixels, row-major like the frame's layout
GRID = np.array([(200.0 + 60.0 * c, 200.0 + 80.0 * r) for r in range(2) for c in range(5)])


def lit_membrane(centres: np.ndarray, *, elevation_deg: float = 35.0, azimuth_deg: float = 90.0,
                 falloff: float = 0.0, width: float = 3.0, height: float = 4.0, blur: float = 0.8,
                 noise: float = 0.0, seed: int = 0, ambient: np.ndarray | float = 0.0) -> tuple[np.ndarray, np.ndarray]:
    """(image, reference): smooth dents (Gaussian, `width` px sigma, `height` px high: slopes up to
    0.8) at `centres`, Lambert-shaded by one light at `elevation_deg` from `azimuth_deg` (90: from
    +v), whose irradiance changes by `falloff` per 100 px along v, over an `ambient` background
    (grey levels, per pixel or one value) that the light does not make."""
    el, az = math.radians(elevation_deg), math.radians(azimuth_deg)
    light = np.array([math.cos(el) * math.cos(az), math.cos(el) * math.sin(az), math.sin(el)])
    vv, uu = np.mgrid[0:SIZE[0], 0:SIZE[1]].astype(np.float64)
    gu, gv = np.zeros(SIZE), np.zeros(SIZE)
    for cu, cv in centres:
        du, dv = uu - cu, vv - cv
        bump = height * np.exp(-(du * du + dv * dv) / (2 * width**2))     # towards the camera
        gu += -du / width**2 * bump
        gv += -dv / width**2 * bump
    irradiance = 180.0 * (1.0 + falloff * (vv - 240.0) / 100.0)
    shade = (-gu * light[0] - gv * light[1] + light[2]) / np.sqrt(1 + gu * gu + gv * gv)
    rng = np.random.default_rng(seed)

    def finish(values: np.ndarray) -> np.ndarray:
        grey = cv2.GaussianBlur(values.astype(np.float32), (0, 0), blur) + rng.normal(0, noise, SIZE)
        return np.repeat(np.clip(np.rint(grey), 0, 255).astype(np.uint8)[..., None], 3, axis=2)

    return finish(ambient + irradiance * np.maximum(shade, 0.0)), finish(ambient + irradiance * light[2])


@pytest.mark.parametrize("rows, columns", [(100_000, 100_000), (2, cal.MAX_FRAME_SIDE + 1)])
def test_a_frame_too_large_to_solve_is_refused_before_anything_is_allocated(rows, columns):
    """`touchroller calibrate extrinsics --frame 100000x100000` tried to allocate 74.5 GiB."""
    with pytest.raises(cal.CalibrationError, match=f"at most {cal.MAX_FRAME_SIDE} rows and columns"):
        cal.HemisphereFrame(rows=rows, columns=columns)


@settings(max_examples=6, deadline=None)
@given(offset=st.tuples(st.floats(0.0, 1.0), st.floats(0.0, 1.0)), elevation=st.sampled_from([35.0, 60.0]))
def test_shading_centre_is_not_pulled_away_from_a_one_sided_light(offset, elevation):
    centres = GRID + np.asarray(offset)
    image, reference = lit_membrane(centres, elevation_deg=elevation)
    shading = cal.find_imprints(image, FRAME, cal.ImprintDetectorConfig(centre="shading"), reference=reference)
    centroid = cal.find_imprints(image, FRAME, cal.ImprintDetectorConfig(centre="centroid"), reference=reference)
    # the centroid sits on the dark side, away from the light (from +v): a bias along v only
    assert np.mean(centroid.centres[:, 1] - centres[:, 1]) < -0.25
    error = shading.centres - centres
    assert np.abs(error.mean(axis=0)).max() < 0.08 and np.abs(error).max() < 0.15


def test_shading_centre_with_light_from_the_side_and_noise():
    centres = GRID + np.array([0.3, 0.6])
    image, reference = lit_membrane(centres, azimuth_deg=0.0, noise=2.0, seed=4)
    found = cal.find_imprints(image, FRAME, reference=reference)
    assert np.abs((found.centres - centres).mean(axis=0)).max() < 0.06


@pytest.mark.parametrize("azimuth", [0.0, 90.0])
def test_shadow_pull_measures_what_a_low_light_leaves_in_the_shading_centre(azimuth):
    """Under a light high enough that no slope falls into shadow (60 deg, slopes up to 0.8) both
    centres are right and the pull (the model error the extrinsics' sigma carries) is noise. Under a
    light at 15 deg the slopes facing away are in shadow: the shading-symmetric centre ("symmetric")
    is pulled towards the light by ~0.3 px and its pull (`shadow_pull`) says so, towards the light and
    of that size; the shadow-censored one ("shading") is not, and its pull is smaller."""
    towards = np.array([math.cos(math.radians(azimuth)), math.sin(math.radians(azimuth))])
    centres = GRID + np.array([0.3, 0.6])
    image, reference = lit_membrane(centres, elevation_deg=60.0, azimuth_deg=azimuth)
    for centre in ("shading", "symmetric"):
        high = cal.find_imprints(image, FRAME, cal.ImprintDetectorConfig(centre=centre), reference=reference)
        assert high.pull is not None and np.abs(high.pull.mean(axis=0)).max() < 0.03
        assert np.abs((high.centres - centres).mean(axis=0)).max() < 0.03
    image, reference = lit_membrane(centres, elevation_deg=15.0, azimuth_deg=azimuth)
    symmetric = cal.find_imprints(image, FRAME, cal.ImprintDetectorConfig(centre="symmetric"), reference=reference)
    assert symmetric.pull is not None
    error = float((symmetric.centres - centres).mean(axis=0) @ towards)
    pull = float(symmetric.pull.mean(axis=0) @ towards)
    assert error > 0.15 and 0.3 * error < pull < 1.5 * error
    shading = cal.find_imprints(image, FRAME, cal.ImprintDetectorConfig(centre="shading"), reference=reference)
    assert shading.pull is not None
    assert np.abs((shading.centres - centres).mean(axis=0)).max() < 0.06
    assert np.abs(shading.pull.mean(axis=0)).max() < 0.5 * pull
    centroid = cal.find_imprints(image, FRAME, cal.ImprintDetectorConfig(centre="centroid"), reference=reference)
    assert centroid.pull is None


def test_relative_strength_takes_the_light_falloff_out():
    """Equal dents, the light 20 % stronger per 100 px along v: absolute strengths read the brighter
    row as deeper pressed, relative ones do not."""
    image, reference = lit_membrane(GRID, falloff=0.2)
    relative = cal.find_imprints(image, FRAME, reference=reference).strengths
    absolute = cal.find_imprints(image, FRAME, cal.ImprintDetectorConfig(strength="absolute"),
                                 reference=reference).strengths

    def asymmetry(s: np.ndarray) -> float:
        return float((s[5:].sum() - s[:5].sum()) / s.sum())

    assert asymmetry(absolute) > 0.06
    assert abs(asymmetry(relative)) < 0.01


def test_a_lights_off_frame_tells_the_light_from_an_uneven_background():
    """Equal dents under an even light, over a background that is brighter towards +v but is not
    light (an uneven gel, ambient light): relative to the whole reference the darker row reads as
    the deeper pressed; relative to the light alone (reference minus a lights-off frame) it does not,
    and neither does the imprints' extent, the default without a lights-off frame."""
    vv = np.mgrid[0:SIZE[0], 0:SIZE[1]][0].astype(np.float64)
    ambient = 20.0 + 40.0 * (vv - 120.0) / 360.0
    image, reference = lit_membrane(GRID, ambient=ambient, noise=1.0, seed=3)
    dark = np.repeat(np.clip(np.rint(ambient), 0, 255).astype(np.uint8)[..., None], 3, axis=2)

    def asymmetry(s: np.ndarray) -> float:
        return float((s[5:].sum() - s[:5].sum()) / s.sum())

    whole = cal.find_imprints(image, FRAME, cal.ImprintDetectorConfig(strength="relative"),
                              reference=reference).strengths
    light = cal.find_imprints(image, FRAME, reference=reference, dark=dark).strengths
    extent = cal.find_imprints(image, FRAME, reference=reference).strengths
    assert asymmetry(whole) < -0.03
    assert abs(asymmetry(light)) < 0.01
    assert abs(asymmetry(extent)) < 0.01
    with pytest.raises(cal.CalibrationError, match="lights-off frame"):
        cal.find_imprints(image, FRAME, reference=reference, dark=dark[:100])


def test_strength_noise_floor_does_not_favour_the_darker_row():
    """Equal dents, the light 20 % stronger per 100 px along v, read noise: the noise floor is the
    same in grey levels everywhere, so counted relative to the light it would add more to the
    darker row; it is taken out before dividing."""
    image, reference = lit_membrane(GRID, falloff=0.2, noise=3.0, seed=5)
    strengths = cal.find_imprints(image, FRAME, reference=reference).strengths
    assert abs(float((strengths[5:].sum() - strengths[:5].sum()) / strengths.sum())) < 0.01


@settings(max_examples=5, deadline=None)
@given(gain=st.floats(0.3, 1.0), ambient=st.floats(0.0, 60.0), azimuth=st.sampled_from([0.0, 90.0, 180.0, 270.0]))
def test_the_imprints_extent_is_the_same_under_any_light_level(gain, ambient, azimuth):
    """The "size" strength of the same dents does not change when the light is dimmed or an ambient
    level the light does not make is added, from whichever side the light comes."""
    image, reference = lit_membrane(GRID, azimuth_deg=azimuth)
    dimmed, dim_reference = lit_membrane(GRID, azimuth_deg=azimuth, ambient=ambient)
    dimmed = np.clip(np.rint(ambient + gain * (dimmed.astype(float) - ambient)), 0, 255).astype(np.uint8)
    dim_reference = np.clip(np.rint(ambient + gain * (dim_reference.astype(float) - ambient)), 0, 255).astype(np.uint8)
    config = cal.ImprintDetectorConfig(strength="size")
    bright = cal.find_imprints(image, FRAME, config, reference=reference).strengths
    dim = cal.find_imprints(dimmed, FRAME, config, reference=dim_reference).strengths
    assert np.all(np.isfinite(bright)) and np.abs(dim / bright - 1.0).max() < 0.03


def test_deeper_dents_are_stronger():
    image, reference = lit_membrane(GRID[:5], height=3.0)
    deep, _ = lit_membrane(GRID[5:], height=4.5)
    combined = np.minimum(image.astype(int) + deep.astype(int) - reference.astype(int), 255).clip(0).astype(np.uint8)
    for strength in ("relative", "size"):
        strengths = cal.find_imprints(combined, FRAME, cal.ImprintDetectorConfig(strength=strength),
                                      reference=reference).strengths
        assert strengths[5:].min() > strengths[:5].max()


def test_detector_config_is_checked_when_made():
    with pytest.raises(cal.CalibrationError, match="centre must be one of"):
        cal.ImprintDetectorConfig(centre="peak")
    with pytest.raises(cal.CalibrationError, match="strength must be one of"):
        cal.ImprintDetectorConfig(strength="max")
    with pytest.raises(cal.CalibrationError, match="min_area"):
        cal.ImprintDetectorConfig(min_area=0)
