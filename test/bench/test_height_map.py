"""bench/height_map.py: the map's gain against the truth by wavelength."""
from __future__ import annotations

import argparse
import math
from pathlib import Path

import cv2
import numpy as np
import pytest

from bench.height_map import WAVELENGTH_BANDS, wavelength_gains


def _relief(shape: tuple[int, int] = (300, 260)) -> np.ndarray:
    rng = np.random.default_rng(4)
    return cv2.GaussianBlur(rng.standard_normal(shape), (0, 0), 0.7) * 1e-5


def test_a_map_equal_to_the_truth_reads_every_band_whole() -> None:
    truth = _relief()
    bands = wavelength_gains(truth.copy(), truth, 1e-4)
    assert len(bands) == len(WAVELENGTH_BANDS)
    assert sum(b.relief_share for b in bands) <= 1.0 + 1e-9
    for b in bands:
        assert b.gain == pytest.approx(1.0, abs=1e-9) and b.coherence == pytest.approx(1.0, abs=1e-9)


def test_a_blurred_map_reads_short_wavelengths_as_a_gaussian_keeps_them() -> None:
    truth = _relief()
    sigma = 1.0
    mine = cv2.GaussianBlur(truth, (0, 0), sigma)
    mine[:5] = np.nan                                   # unmapped rows are left out, not read as relief
    bands = wavelength_gains(mine, truth, 1e-4)
    for b in bands:
        wavelength = 0.5 * (b.shortest_mm + b.longest_mm) / 0.1   # cells, the band's middle
        kept = math.exp(-0.5 * (2 * math.pi * sigma / wavelength) ** 2)
        assert b.gain == pytest.approx(kept, abs=0.12), b
        assert b.coherence > 0.8
    assert bands[0].gain < 0.2 < 0.9 < bands[-1].gain


def test_too_little_mapped_gives_no_bands() -> None:
    truth = _relief((60, 60))
    assert wavelength_gains(truth, truth, 1e-4) == []


def test_the_second_generators_calibration_films_the_rasters_own_sensor() -> None:
    """The reference and the ball presses come from the sensor that films the raster: the same flat field (its
    dust specks) and lifted-roller frame; another sensor's dust reads as slopes that stay put in the image."""
    import dataclasses

    from bench.height_map import PARAMS, _calibration_renderer, second_raster_spec
    from bench.raster_generator import Look, load_camera, sensor
    from bench.raster_generator.render import BandRenderer

    camera, look = load_camera(str(PARAMS)), dataclasses.replace(Look(), exposure_samples=1, pixel_samples=1)
    calibration = _calibration_renderer(camera, look)
    raster = sensor(second_raster_spec(), camera, look, calibration.surface)   # type: ignore[attr-defined]
    np.testing.assert_array_equal(calibration.flat, raster.flat)               # type: ignore[attr-defined]
    # the lifted roller's frame, its noise included (pressed at another depth: a rounding apart)
    assert np.abs(calibration.static.astype(int) - raster.static).max() <= 1   # type: ignore[attr-defined]
    other = BandRenderer(camera, calibration.surface, look, seed=3)            # type: ignore[attr-defined]
    assert np.abs(other.flat - raster.flat).max() > 0.1                        # another sensor: other specks


def test_a_map_is_scored_1_mm_inside_its_mapped_area_also_where_that_reaches_the_rasters_edge() -> None:
    """height.tif spans the mapped cells alone: the cells within 1 mm of its edge are as far out as those
    within 1 mm of a NaN, and are left out alike (a map cropped to its cells scores as the same map padded)."""
    from bench.height_map import _score

    truth = _relief((200, 180))
    rng = np.random.default_rng(1)
    mine = truth + 2e-6 * rng.standard_normal(truth.shape)
    mine[:, -20:] += 3e-5                       # the map's last 2 mm along one edge read badly (a pass's end)
    padded_map = np.pad(mine, 30, constant_values=np.nan)
    padded_truth = np.pad(truth, 30)
    cropped = _score("cropped", mine, truth, 1, 1, 0.0, 1e-4)
    padded = _score("padded", padded_map, padded_truth, 1, 1, 0.0, 1e-4)
    assert cropped.cells == padded.cells == (200 - 20) * (180 - 20)
    assert cropped.rms_um == pytest.approx(padded.rms_um, rel=1e-6)


def test_the_correlation_by_low_pass_cut_off_tells_where_it_is_lost() -> None:
    from bench.height_map import CUTOFFS_MM, cutoff_correlations

    long = cv2.GaussianBlur(np.random.default_rng(3).standard_normal((300, 260)), (0, 0), 6.0)
    truth = _relief() + 2e-4 * long   # relief at every wavelength, short and long
    same = cutoff_correlations(truth.copy(), truth, 1e-4)
    assert [c.longer_than_mm for c in same] == list(CUTOFFS_MM)
    assert all(c.correlation == pytest.approx(1.0, abs=1e-9) and c.rms_um == pytest.approx(0.0, abs=1e-9)
               for c in same)
    # white noise at the cell scale: lost at the short wavelengths, regained as the cut-off lengthens
    noisy = truth + 1e-5 * np.random.default_rng(2).standard_normal(truth.shape)
    cuts = cutoff_correlations(noisy, truth, 1e-4)
    assert cuts[0].correlation < 0.9 < cuts[-1].correlation
    assert all(b.correlation >= a.correlation - 1e-3 for a, b in zip(cuts, cuts[1:], strict=False))
    assert cutoff_correlations(truth[:60, :60], truth[:60, :60], 1e-4) == []


def test_the_maps_by_height_configuration_are_a_table_and_survive_the_json(tmp_path: Path) -> None:
    """The rows of other `WorldHeightConfig`s (the default first, the one it replaced kept) are one table with
    a column per surface and seed, and come back from the recorded JSON."""
    import json

    from bench._common import provenance, to_json
    from bench.height_map import HEIGHT_CONFIGS, ConfigScore, HeightMapResult, load, to_markdown
    from touchroller_perception.world_height import WorldHeightConfig

    assert HEIGHT_CONFIGS[0][1] == {}                                    # the first row is the default
    assert any(fields == {"slopes": "centre"} for _, fields in HEIGHT_CONFIGS)   # the earlier default kept
    for _, fields in HEIGHT_CONFIGS:
        WorldHeightConfig(**fields)                                      # each a valid configuration
    rows = [ConfigScore(label, surface, seed, 4.0 + k, 0.97 - 0.01 * k, [0.6, 0.7, 0.8])
            for k, (label, _) in enumerate(HEIGHT_CONFIGS)
            for surface, seed in (("grain", 0), ("grained (second generator)", 0), ("grained (second generator)", 1))]
    result = HeightMapResult(provenance("height_map", True), True, 8, 0.5, [], configs=rows)
    text = to_markdown(result)
    header = next(line for line in text.splitlines() if line.startswith("| configuration |"))
    assert header.count("|") == 5 and "grained (second generator), seed 1" in header
    assert f"| {HEIGHT_CONFIGS[1][0]} | 5.0 um, 0.960, 0.60 / 0.70 / 0.80 |" in text
    path = tmp_path / "height_map.json"
    path.write_text(to_json(result, indent=1))
    assert load(path).configs == rows
    assert json.loads(path.read_text())["configs"][0]["config"] == HEIGHT_CONFIGS[0][0]


def test_the_map_command_reads_the_height_with_the_configuration_given_and_then_as_before() -> None:
    from bench.height_map import _height_config
    from touchroller_bringup.commands import map as command
    from touchroller_perception.world_height import WorldHeightConfig

    original = command._height_source
    config = WorldHeightConfig(slopes="centre")
    with _height_config(config):
        assert command._height_source is not original
        assert command._height_source(argparse.Namespace(photometric=None)) is None
    assert command._height_source is original
    with _height_config(None):
        assert command._height_source is original


def test_frames_read_one_at_a_time_are_scored_by_wavelength_and_set_beside_the_map() -> None:
    from bench._common import provenance
    from bench.height_map import HEIGHT_CONFIGS, ConfigScore, FrameGain, HeightMapResult, _band_gains, to_markdown

    truth = _relief((80, 560))
    gains, coherences = _band_gains([(truth.copy(), truth), (2 * truth[::-1].copy(), truth[::-1].copy())])
    assert len(gains) == len(WAVELENGTH_BANDS)
    # a frame read whole and one (of the same relief's power) read twice as deep: pooled, the gain is their mean
    # and the coherence (1 + 2) / sqrt((1 + 1) (1 + 4)), less than either's own 1
    assert all(g == pytest.approx(1.5, abs=1e-9) and c == pytest.approx(3 / math.sqrt(10), abs=1e-9)
               for g, c in zip(gains, coherences, strict=True))
    blurred, _ = _band_gains([(cv2.GaussianBlur(truth, (0, 0), 1.0), truth)])
    assert blurred[1] < 0.3 < 0.9 < blurred[-1]   # 0.3-0.4 mm lost, 3.2-6.4 mm kept
    label = HEIGHT_CONFIGS[0][0]
    result = HeightMapResult(provenance("height_map", True), True, 8, 0.5, [],
                             configs=[ConfigScore(label, "grained (second generator)", 0, 4.0, 0.97, [0.6, 0.7, 0.8])],
                             frames=[FrameGain(label, 0, 12, gains, coherences)])
    assert f"| {label} | 0 | 1.50 (0.95) / 1.50 (0.95) / 1.50 (0.95) | 0.60 / 0.70 / 0.80 |" in to_markdown(result)
