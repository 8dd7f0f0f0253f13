"""bench/map_scale.py: its synthesised frames land where its texture is, and its goal rows judge the figures."""
from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from touchroller_bringup.report import load_bench_script


def test_the_raster_rolls_pressed_and_moves_across_lifted():
    bench = load_bench_script("map_scale")
    raster = bench.Raster(0.2)
    assert raster.passes == 5   # 64 mm bands 45 mm apart over 0.2 m
    t = np.array([0.0, raster.pass_s / 2, raster.pass_s + 0.5, raster.pass_s + raster.move_s + 1.0]) * 1e9
    poses = raster.poses(t.astype(np.int64))
    assert poses[:2, 2, 3].tolist() == [bench.PRESSED_Z] * 2 and poses[2, 2, 3] > bench.PRESSED_Z
    assert poses[1, 0, 3] == pytest.approx(0.1) and poses[3, 0, 3] == pytest.approx(0.2 - bench.SPEED)  # back
    np.testing.assert_allclose(poses[0, :3, :3] @ [0, 1, 0], [1, 0, 0])   # rolling along world x


def test_the_synthesised_frames_map_onto_the_benchs_texture_in_place(tmp_path):
    """The mapper, given the bench's bands at the raster's poses, maps the texture where it lies: the bench
    measures a real map, not noise."""
    bench = load_bench_script("map_scale")
    from touchroller_perception.geometry import CameraModel
    from touchroller_perception.world_map import WorldMapConfig, WorldMapper

    camera = CameraModel()
    raster = bench.Raster(0.07)
    mapper = WorldMapper(camera, raster.poses, WorldMapConfig(latency=0.0))
    mapper.source_rows((camera.height, camera.width))
    rows, cols = mapper.band_shape
    sampler = mapper.strip.sampler
    rows_m = (np.arange(rows) - (rows - 1) / 2.0) * sampler.mm_per_px * 1e-3
    cols_m = (np.arange(cols) - sampler.centre_u) * sampler.mm_per_px_cols * 1e-3
    texture = bench._texture(size=1024)
    for t in np.arange(0, raster.duration, 1 / bench.FPS):
        stamp = int(round(t * 1e9))
        mapper.push_band(bench._band(texture, raster.poses(np.array([stamp]))[0], rows_m, cols_m), stamp)
    mapper.finalise()
    assert mapper.stats.passes == raster.passes and mapper.stats.mapped > 0.8 * mapper.stats.frames
    grey, weight = mapper.canvas.value(mapper._level)
    r, c = np.nonzero(weight > 0.5)
    x = mapper.canvas.origin[0] + (c + 0.5) * bench.RES
    y = mapper.canvas.origin[1] + (r + 0.5) * bench.RES
    truth = texture[np.mod(np.round(y / bench.RES - 0.5), 1024).astype(int),
                    np.mod(np.round(x / bench.RES - 0.5), 1024).astype(int)]
    assert np.corrcoef(grey[r, c], truth)[0, 1] > 0.9
    mapper.close()


def _case(bench, side, rss, write_s=3.0, window=2.0):
    return bench.CaseResult(side, 22, 30000, 29000, (10000, 10000), 100.0, 90.0, 300.0, rss - 10, rss, 300, 400, 900,
                            write_s * 2, write_s, 150.0, 6, 8, window * 3, window, window * 1.5, window / 2)


def test_the_goal_rows_judge_the_largest_raster_and_a_quick_run_is_not_judged():
    bench = load_bench_script("map_scale")
    from bench._common import Provenance

    stamp = Provenance("cmd", "machine", "now", "0.00 0.00 0.00")
    good = bench.MapScaleResult(stamp, False, [_case(bench, 1.0, 600.0), _case(bench, 0.5, 560.0)], 600 / 560,
                                "0.00")
    assert [met for _, _, met in bench.goals(good)] == [True, True, True, True, None]   # no update measured
    bad = dataclasses.replace(good, cases=[_case(bench, 1.0, 1500.0, write_s=12.0, window=20.0),
                                           _case(bench, 0.5, 560.0)], rss_ratio=1500 / 560)
    assert [met for _, _, met in bench.goals(bad)] == [False, False, False, False, None]
    assert all(met is None for _, _, met in bench.goals(dataclasses.replace(bad, quick=True)))
    text = bench.to_markdown(good)
    assert "| 1 m x 1 m | 22 |" in text and "1.07" in text


def _update(bench, surface, median):
    return bench.UpdateResult(surface, 1.0, 22, 0.05, 13830, 13200, 300, 200 if surface == "textured" else 0,
                              median, 3 * median, 1.5 * median, 1500, 200)


def test_the_update_goal_judges_the_slower_surface_and_says_when_it_was_not_measured():
    bench = load_bench_script("map_scale")
    from bench._common import Provenance

    stamp = Provenance("cmd", "machine", "now", "0.00 0.00 0.00")
    cases = [_case(bench, 1.0, 600.0), _case(bench, 0.5, 560.0)]
    result = bench.MapScaleResult(stamp, False, cases, 600 / 560, "0.00",
                                  updates=[_update(bench, "textured", 0.5), _update(bench, "featureless", 1.9)])
    name, figure, met = bench.goals(result)[-1]
    assert name == "map update" and met is True and figure.startswith("1.90 ms CPU median, featureless")
    slow = dataclasses.replace(result, updates=[_update(bench, "textured", 0.5), _update(bench, "featureless", 3.4)])
    assert bench.goals(slow)[-1][2] is False
    assert bench.goals(dataclasses.replace(slow, quick=True))[-1][2] is None
    # a result recorded before the update was measured: said, not judged
    assert bench.goals(dataclasses.replace(result, updates=[]))[-1][1:] == ("not measured by this run", None)
    assert "| featureless | 22 passes of 1 m at 50 mm/s | 13830 (13200) | 300 (0) | 1.90 / 5.70 / 2.85 |" \
        in bench.to_markdown(result)


def test_a_recorded_result_reads_back_with_its_update_figures(tmp_path):
    bench = load_bench_script("map_scale")
    from bench._common import Provenance, to_json

    stamp = Provenance("cmd", "machine", "now", "0.00 0.00 0.00")
    result = bench.MapScaleResult(stamp, False, [_case(bench, 1.0, 600.0)], 1.0, "0.00",
                                  updates=[_update(bench, "featureless", 0.6)])
    path = tmp_path / "map_scale.json"
    path.write_text(to_json(result))
    assert bench.load(path) == result


def test_the_update_timing_maps_a_featureless_surface_without_finding_offsets():
    """`run_update` on the featureless surface: every pressed frame mapped, registrations attempted and none
    finding an offset (nothing to match): the case it times is the one it says."""
    bench = load_bench_script("map_scale")
    update = bench.run_update("featureless", passes=2, side=0.2)
    assert update.passes == 2 and update.mapped > 0.8 * update.frames
    assert update.registrations > 0 and update.registered == 0
    assert update.cpu_ms_median > 0
