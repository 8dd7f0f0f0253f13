"""bench/raster_score.py's seam measure: a line or a step at a pass border is reported, the texture a map
shares with the truth is not (however its gain, blur and subpixel phase drift across the passes), and
a nearly flat truth does not let the texture fit run away; and, on the second generator's plain glass,
a line detector over `touchroller map`'s own map finds nothing above the map's noise."""
from __future__ import annotations

import dataclasses
import functools
import math
import subprocess
import sys
from pathlib import Path
from types import SimpleNamespace

import cv2
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from bench.raster_generator import MotionConfig, RasterSpec, generate
from bench.raster_generator.render import Camera, Look, appearance
from bench.raster_generator.surfaces import Feature, _plant, make_surface
from bench.raster_score import (
    SEAM_SIDES,
    _borders,
    _features,
    _profiles,
    _seam_floor,
    _seams,
    _standard,
    read_map,
    seam_at,
)

ROOT = Path(__file__).resolve().parents[2]
RES = 1e-4
WIDTH, LENGTH = 0.11, 0.03
LINES = (0.032, 0.055, 0.078)        # 3 passes 23 mm apart: borders at 43.5 and 66.5 mm, band edges at 23, 46, 64, 87
WS = (np.arange(int(WIDTH / RES)) + 0.5) * RES
TRUTH = SimpleNamespace(spec=SimpleNamespace(width=WIDTH), passes=[SimpleNamespace(w=w) for w in LINES])


@functools.cache
def weave_truth(seed: int = 0) -> np.ndarray:
    """The second generator's periodic weave (threads along and across the roll, 1.2 mm) as an ideal map
    shows it: rows across the passes (w), columns along them (u)."""
    surface = make_surface("weave", (LENGTH, WIDTH + 0.002), (0.0, -0.001, 0.0), features=0, seed=seed)
    return appearance(surface, Camera(), Look(), (0.0, 0.0), (len(WS), int(LENGTH / RES)), RES, np.array([1.0, 0.0]))


def drifted(truth: np.ndarray, phase_m: float, gain_swing: float, seed: int = 0) -> np.ndarray:
    """A map of `truth` with what the world map does to a weave's texture and no line anywhere: a gain that
    swings by `gain_swing` across the passes, a subpixel phase drifting linearly to +-`phase_m` at the
    rectangle's edges, a slight blur, and sensor noise."""
    cols = np.arange(truth.shape[1], dtype=np.float32)
    phase = phase_m * (WS - WIDTH / 2) / (WIDTH / 2)
    map_y = np.repeat(((WS + phase) / RES - 0.5).astype(np.float32)[:, None], truth.shape[1], axis=1)
    moved = cv2.remap(truth, np.repeat(cols[None, :], len(WS), axis=0), map_y, cv2.INTER_CUBIC,
                      borderMode=cv2.BORDER_REFLECT)
    gain = 0.75 + gain_swing * np.cos(2 * np.pi * WS / 0.05)
    noise = np.random.default_rng(seed).standard_normal(truth.shape)
    level = float(truth.mean())
    return (level + gain[:, None] * (cv2.GaussianBlur(moved, (0, 0), 0.7) - level)
            + 0.3 * float(truth.std()) * noise).astype(np.float32)


def planted(image: np.ndarray, border: float, kind: str, depth: float, width: float = 1e-3) -> np.ndarray:
    """`image` with a dark line (`width` m wide) or a step up across `border`, `depth` of its std."""
    out = image.copy()
    size = depth * float(image.std())
    if kind == "line":
        out[np.abs(WS - border) <= width / 2] -= size
    else:
        out[WS > border] += size
    return out


def seams_of(image: np.ndarray, truth: np.ndarray) -> dict[float, float]:
    """The scorer's reading at every border (w mm -> the larger of dip and step)."""
    region = np.ones(image.shape, bool)
    return {round(w, 1): max(dip, step)
            for w, dip, step in _seams(_standard(image, region), _standard(truth, region), region, WS, TRUTH)}


def plain_difference(image: np.ndarray, truth: np.ndarray, border: float) -> float:
    """The same measure on the map less the truth with no texture fit (what the scorer read before)."""
    region = np.ones(image.shape, bool)
    profile, truth_profile = _profiles(_standard(image, region), _standard(truth, region), region)
    found = seam_at(WS, profile - truth_profile, np.zeros_like(truth_profile), border, 0.0)
    assert found is not None
    return max(found)


def test_the_borders_are_the_pass_borders_and_band_edges_inside_the_rectangle() -> None:
    assert [round(b * 1e3, 1) for b in _borders(WS, TRUTH)] == [43.5, 66.5, 64.0, 23.0, 87.0, 46.0]


def test_weave_texture_alone_is_not_a_seam() -> None:
    """The weave's texture drifting 0.1 mm in phase and +-0.15 in gain across the passes (as the world map
    of the second generator's weave does): the plain difference reads a third of a std at borders where
    nothing is; the scorer's fit of the truth's texture reads no seam."""
    truth = weave_truth()
    image = drifted(truth, 1e-4, 0.15)
    assert max(plain_difference(image, truth, b) for b in _borders(WS, TRUTH)) > 0.25   # the texture is there
    found = seams_of(image, truth)
    assert len(found) == 6 and max(found.values()) < 0.15, found
    region = np.ones(image.shape, bool)
    assert _seam_floor(_standard(image, region), _standard(truth, region), region, WS, TRUTH) < 0.15


@pytest.mark.parametrize("kind", ["line", "step"])
@pytest.mark.parametrize("texture", ["weave", "noise"])
def test_a_planted_line_or_step_at_a_pass_border_is_reported(kind: str, texture: str) -> None:
    """0.3 of the map's std, a 1 mm dark line or a step, at the pass border at 43.5 mm: read above 0.25
    there, on the drifting weave as on a clean map of a random texture; the other borders stay clean."""
    if texture == "weave":
        truth = weave_truth()
        clean = drifted(truth, 1e-4, 0.15)
    else:
        rng = np.random.default_rng(4)
        truth = cv2.GaussianBlur(rng.standard_normal((len(WS), 300)).astype(np.float32), (0, 0), 2.0)
        clean = (truth + 0.3 * float(truth.std()) * rng.standard_normal(truth.shape)).astype(np.float32)
    assert max(seams_of(clean, truth).values()) < 0.15
    found = seams_of(planted(clean, 0.0435, kind, 0.3), truth)
    assert found[43.5] > 0.25, found
    assert max(v for w, v in found.items() if abs(w - 43.5) > SEAM_SIDES[1] * 1e3) < 0.15, found


def test_a_dark_line_half_a_std_deep_reads_half_a_std() -> None:
    rng = np.random.default_rng(1)
    truth = rng.standard_normal((len(WS), 400)).astype(np.float32)
    clean = truth + 0.3 * rng.standard_normal(truth.shape).astype(np.float32)
    assert max(seams_of(clean, truth).values()) < 0.1
    found = seams_of(planted(clean, 0.0435, "line", 0.5), truth)
    assert found[43.5] == pytest.approx(0.5, abs=0.1)


@settings(max_examples=12, deadline=None)
@given(border=st.sampled_from([0.023, 0.0435, 0.046, 0.064, 0.0665, 0.087]), kind=st.sampled_from(["line", "step"]),
       depth=st.floats(0.3, 0.6), width=st.floats(5e-4, 2e-3), phase=st.floats(0.0, 1e-4),
       swing=st.floats(0.0, 0.2), seed=st.integers(0, 3))
def test_property_a_line_or_step_at_any_border_of_a_drifting_weave_is_reported(
        border: float, kind: str, depth: float, width: float, phase: float, swing: float, seed: int) -> None:
    truth = weave_truth()
    found = seams_of(planted(drifted(truth, phase, swing, seed), border, kind, depth, width), truth)
    assert found[round(border * 1e3, 1)] > 0.25, found


def test_a_nearly_flat_truth_with_a_speck_near_a_border_reads_no_seam() -> None:
    """Glass: the truth's profile barely varies, so the texture fit has nothing to go by; a speck (a dent)
    in both, 0.5 mm from a border, must not be multiplied into a line by a filter fitted on nothing."""
    rng = np.random.default_rng(2)
    truth = np.repeat((1e-3 * np.sin(2 * np.pi * WS / 0.02))[:, None], 300, axis=1).astype(np.float32)
    truth += 1e-4 * rng.standard_normal(truth.shape).astype(np.float32)
    speck = np.abs(WS - 0.0465) < 2.5e-4
    truth[speck, 100:200] -= 0.2
    image = (truth + 0.05 * rng.standard_normal(truth.shape)).astype(np.float32)
    found = seams_of(image, truth)
    assert max(found.values()) < 0.25, found


@pytest.mark.slow
def test_a_line_detector_over_the_map_of_plain_glass_finds_nothing_above_the_maps_noise(tmp_path: Path) -> None:
    """The second generator's glass (no planted features), 3 passes of 4.5 cm over 11 cm, through
    `touchroller map`: the map's own mean profile across the passes (no truth), searched at every line
    0.5 mm apart for a dip or a step (the scorer's measure with no texture), finds nothing above 0.25 of
    the map's standard deviation, at pass borders and band edges as anywhere else."""
    spec = RasterSpec(surface="glass", corner=(0.40, -0.055), length=0.045, width=0.11, passes=3, latency=0.03,
                      motion=MotionConfig(profile="blend"), features=0, seed=5)
    truth = generate(spec, tmp_path / "raster", look=Look(exposure_samples=1))
    subprocess.run([sys.executable, "-m", "touchroller_bringup.cli", "map", str(tmp_path / "raster" / "bag"),
                    "--out", str(tmp_path / "map.png"), "--latency", "0.03"], capture_output=True, text=True,
                   cwd=ROOT, check=True)
    grey, weight, origin, resolution = read_map(tmp_path / "map.yaml")
    c0 = int(round((spec.corner[0] - origin[0]) / resolution)) + 30   # 3 mm in from the passes' ends
    c1 = int(round((spec.corner[0] + spec.length - origin[0]) / resolution)) - 30
    r0 = int(round((spec.corner[1] - origin[1]) / resolution))
    r1 = int(round((spec.corner[1] + spec.width - origin[1]) / resolution))
    inside, mapped = grey[r0:r1, c0:c1], weight[r0:r1, c0:c1] > 0
    assert mapped.all()
    profile = (inside.mean(axis=1) - inside.mean()) / float(inside.std())
    ws = (np.arange(r1 - r0) + 0.5) * resolution
    flat = np.zeros_like(profile)
    lines = np.arange(0.006, spec.width - 0.006, 5e-4)
    readings = [max(found) for line in lines if (found := seam_at(ws, profile, flat, line, 0.0)) is not None]
    assert len(readings) == len(lines)
    assert max(readings) < 0.25, (max(readings), lines[int(np.argmax(readings))])
    assert len(_borders(ws, truth)) == 6   # the pass borders and band edges were among the lines searched


def _crack_on_glass(shift_mm: float) -> tuple[np.ndarray, np.ndarray, SimpleNamespace]:
    """Glass 4 x 4 cm with one 15 mm crack at 133 deg through its middle (no other feature), its ideal map
    and the same map with the surface slid `shift_mm` along the crack (so the crack runs through its
    8 mm window unchanged, and only its ends have moved), a little noise on the map."""
    size, res = 0.04, RES
    surface = make_surface("glass", (size, size), (0.0, 0.0, 0.0), features=0, seed=3)
    angle = math.radians(133.0)
    direction = np.array([math.cos(angle), math.sin(angle)])
    half = 0.0075 * direction
    mid = np.array([0.02, 0.02])
    _plant(surface.height, surface.resolution, ("crack", tuple(mid - half), tuple(mid + half), 0.25e-3, 30e-6))
    crack = Feature("crack", tuple(mid - half), tuple(mid + half), 0.25e-3, 30e-6)
    surface = dataclasses.replace(surface, features=(crack,))
    roll = np.array([1.0, 0.0])
    shape = (int(size / res), int(size / res))
    expected = appearance(surface, Camera(), Look(), (0.0, 0.0), shape, res, roll)
    shift = shift_mm * 1e-3 * direction   # the map's content lies here relative to the truth
    moved = appearance(surface, Camera(), Look(), (-shift[0], -shift[1]), shape, res, roll)
    noise = np.random.default_rng(0).standard_normal(shape).astype(np.float32)
    grey = moved + 0.05 * float(expected.std()) * noise
    spec = SimpleNamespace(corner=(0.0, 0.0), roll=roll, across=np.array([0.0, 1.0]), length=size, width=size)
    return grey, expected, SimpleNamespace(spec=spec, surface=surface)


@pytest.mark.parametrize("shift_mm", [0.0, 0.3])
def test_a_long_crack_slid_along_itself_reads_the_slide(shift_mm: float) -> None:
    """A crack longer than the 8 mm window (as the second generator plants up to 20 mm long) is scored in
    a window holding its ends: a map slid 0.3 mm along the crack reads 0.3 mm off, along it (the 8 mm
    window saw the same groove either way and could read anything along it), and an unmoved one 0."""
    grey, expected, truth = _crack_on_glass(shift_mm)
    [score] = _features(grey, np.ones_like(grey), expected, (0.0, 0.0), RES, truth)
    direction = np.array([math.cos(math.radians(133.0)), math.sin(math.radians(133.0))])
    offset = np.array(score.offset_mm)
    assert abs(float(offset @ direction) - shift_mm) < 0.03, score
    assert abs(float(offset @ np.array([-direction[1], direction[0]]))) < 0.03, score
