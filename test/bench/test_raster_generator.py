"""bench/raster_generator: its geometry (a planted feature lands where the truth says once the latency is
told), its truth file round trip, its bag's TF, and its independence from the simulator."""
from __future__ import annotations

import dataclasses
import re
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from bench.raster_generator import MotionConfig, RasterSpec, generate, load_truth
from bench.raster_generator.generate import raster_surface
from bench.raster_generator.motion import pass_spacing, plan
from bench.raster_generator.render import Camera, Look
from bench.raster_generator.truth import RasterTruth, write_truth
from bench.raster_score import score_map

ROOT = Path(__file__).resolve().parents[2]
LATENCY = 0.04      # s: 0.8 mm of roll at 20 mm/s


def one_pass(**changes) -> RasterSpec:
    """One 4 cm pass along base x over the grained surface, 4 grooves and pits planted inside the raster."""
    spec = RasterSpec(surface="grained", corner=(0.40, -0.032), length=0.04, width=0.064, passes=1, latency=LATENCY,
                      motion=MotionConfig(profile="ramp"), features=4, seed=3)
    return dataclasses.replace(spec, **changes)


def touchroller_map(bag: Path, out: Path, *extra: str) -> str:
    done = subprocess.run([sys.executable, "-m", "touchroller_bringup.cli", "map", str(bag), "--out", str(out),
                           *extra], capture_output=True, text=True, cwd=ROOT, check=True)
    return done.stdout


@pytest.fixture(scope="module")
def filmed(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, RasterTruth]:
    folder = tmp_path_factory.mktemp("raster")
    return folder, generate(one_pass(), folder)


def test_a_planted_feature_appears_where_the_truth_says_with_the_latency_told(filmed, tmp_path: Path) -> None:
    folder, truth = filmed
    touchroller_map(folder / "bag", tmp_path / "map.png", "--latency", str(LATENCY), "--no-register")
    score = score_map(tmp_path / "map.yaml", truth)
    assert len(score.features) == 4
    for feature in score.features:
        assert feature.peak > 0.5, feature
        assert feature.error_mm <= 0.1, feature
    assert score.worst_residual_mm <= 0.1
    assert score.coverage_percent >= 98.0
    assert score.ssim >= 0.9


def test_the_latency_is_in_the_stamps_taken_as_zero_every_feature_lies_one_roll_of_it_ahead(filmed,
                                                                                              tmp_path: Path) -> None:
    """The control of the test above: placed with latency 0, the pass (rolled along +x at 20 mm/s) lands
    20 mm/s x 40 ms = 0.8 mm further along +x, and only along x."""
    folder, truth = filmed
    touchroller_map(folder / "bag", tmp_path / "map.png", "--latency", "0", "--no-register")
    score = score_map(tmp_path / "map.yaml", truth)
    assert len(score.features) == 4
    for feature in score.features:
        assert feature.offset_mm[0] == pytest.approx(0.8, abs=0.1), feature
        assert abs(feature.offset_mm[1]) <= 0.1, feature


def test_the_bag_holds_tf_at_its_rate_the_mount_and_the_frames_stamped_late(filmed) -> None:
    from touchroller_bringup.bags import ImageRecord, read_images_and_tf

    folder, truth = filmed
    records = list(read_images_and_tf(folder / "bag"))
    images = [r for r in records if isinstance(r, ImageRecord)]
    moving = [r for r in records if not isinstance(r, ImageRecord) and not r.static]
    static = {(r.parent, r.child): r for r in records if not isinstance(r, ImageRecord) and r.static}
    assert len(images) == truth.frames
    assert set(static) == {("tool0", "touchroller_cylinder"), ("touchroller_cylinder", "touchroller_camera")}
    assert static[("tool0", "touchroller_cylinder")].translation == pytest.approx((0.0, 0.0, 0.1))
    assert {(r.parent, r.child) for r in moving} == {("base", "tool0")}
    stamps = np.array([r.stamp_ns for r in moving]) * 1e-9
    assert len(moving) / (stamps[-1] - stamps[0]) == pytest.approx(125.0, rel=0.02)
    periods = np.diff(np.sort(stamps))
    assert periods.std() > 0.05 / 125.0          # jittered, not a perfect clock
    # the flange points down; the roller's axis (tool -y under the mount's yaw) lies along base y
    quaternion = np.array(moving[0].rotation)
    assert abs(quaternion[0]) == pytest.approx(1.0, abs=1e-6)
    # every image is stamped the latency after an exposure on the 30 Hz clock (+ its jitter)
    first = (np.array([r.stamp_ns for r in images]) - truth.epoch_ns) * 1e-9 - LATENCY
    assert np.abs(np.diff(first) - 1 / 30).max() < 3e-3


def test_the_truth_round_trips(tmp_path: Path) -> None:
    spec = dataclasses.replace(one_pass(), surface="weave", yaw_deg=35.0, passes=2, width=0.1,
                               motion=MotionConfig(profile="pauses", jitter=0.04))
    surface = raster_surface(spec)
    trajectory = plan(spec.length, pass_spacing(spec.width, spec.passes), spec.motion)
    truth = RasterTruth(spec, Camera(), Look(), surface, trajectory.passes, 123, 45)
    write_truth(tmp_path, truth)
    back = load_truth(tmp_path)
    assert back.spec == spec
    assert back.camera == truth.camera and back.look == truth.look
    assert back.passes == truth.passes
    assert (back.epoch_ns, back.frames) == (123, 45)
    assert np.array_equal(back.surface.height, surface.height)
    assert back.surface.features == surface.features
    assert (back.surface.origin, back.surface.yaw, back.surface.resolution, back.surface.weave_period) == \
        (surface.origin, surface.yaw, surface.resolution, surface.weave_period)
    np.testing.assert_array_equal(back.appearance((0.41, -0.02), (20, 30), 1e-4),
                                  truth.appearance((0.41, -0.02), (20, 30), 1e-4))
    (tmp_path / "truth.json").write_text('{"format": "something else"}')
    with pytest.raises(ValueError, match="not a touchroller-raster-truth"):
        load_truth(tmp_path)


@pytest.mark.parametrize("profile", ["ramp", "blend", "constant", "pauses"])
def test_each_profile_rolls_its_passes_as_it_says(profile: str) -> None:
    config = MotionConfig(profile=profile, jitter=0.05)
    trajectory = plan(0.06, [0.03, 0.07], config)
    assert [p.u_start for p in trajectory.passes] == [0.0, 0.06]
    dt = np.diff(trajectory.t)
    speed = np.abs(np.diff(trajectory.u)) / dt
    for p in trajectory.passes:
        pressed = (trajectory.t[1:] >= p.contact_start_s) & (trajectory.t[1:] <= p.contact_end_s)
        rolling = speed[pressed]
        if profile in ("ramp", "pauses"):
            assert rolling[:5].max() < 1e-9 and rolling[-5:].max() < 1e-9      # at rest pressed, both ends
        else:
            assert rolling[:5].min() > 0.019 and rolling[-5:].min() > 0.019    # touchdown and lift-off at speed
        if profile == "constant":
            assert rolling.max() - rolling.min() < 1e-9
        if profile == "blend":
            assert 0.004 < (rolling.max() - rolling.min()) / 0.02 < 0.025        # about 1 % either way
        if profile == "pauses":
            stopped = rolling < 1e-9
            starts_of_rest = np.flatnonzero(stopped[1:] & ~stopped[:-1])
            assert len(starts_of_rest) >= 3                                      # two pauses and the end
            cruising = rolling[rolling > 0.5 * 0.02]
            assert cruising.std() / cruising.mean() > 0.01                       # jittered


def test_it_imports_nothing_of_the_simulator(tmp_path: Path) -> None:
    sources = "\n".join(p.read_text() for p in (ROOT / "bench" / "raster_generator").glob("*.py"))
    assert not re.search(r"^\s*(from|import)\s+touchroller_driver", sources, re.MULTILINE)
    code = ("import sys, dataclasses\nfrom bench.raster_generator import RasterSpec, MotionConfig, generate\n"
            "import bench.raster_score, bench.world_map_grid\n"
            "generate(RasterSpec(corner=(0.4, -0.03), length=0.01, width=0.064, passes=1, features=0), "
            f"{str(tmp_path)!r})\n"
            "print(sorted(m for m in sys.modules if m.startswith('touchroller_driver')))\n")
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, cwd=ROOT, check=True)
    assert "touchroller_driver.sim" not in done.stdout


def test_the_score_command_prints_the_scores_and_refuses_a_folder_without_truth(filmed, tmp_path: Path,
                                                                                  capsys) -> None:
    import json

    from bench import raster_score

    folder, _ = filmed
    touchroller_map(folder / "bag", tmp_path / "map.png", "--latency", str(LATENCY), "--no-register")
    assert raster_score.main([str(folder), str(tmp_path / "map.yaml")]) == 0
    printed = json.loads(capsys.readouterr().out)
    assert printed["coverage_percent"] >= 98.0 and len(printed["features"]) == 4
    assert raster_score.main([str(tmp_path), str(tmp_path / "map.yaml")]) == 1
    assert capsys.readouterr().err.startswith("error: ")


@settings(max_examples=25, deadline=None)
@given(profile=st.sampled_from(["ramp", "blend", "constant", "pauses"]), speed=st.floats(0.005, 0.05),
       passes=st.integers(1, 4), length=st.floats(0.01, 0.08), jitter=st.floats(0.01, 0.05),
       seed=st.integers(0, 1000))
def test_any_raster_plan_moves_continuously_and_presses_every_pass(profile: str, speed: float, passes: int,
                                                                   length: float, jitter: float, seed: int) -> None:
    config = MotionConfig(profile=profile, speed=speed, jitter=jitter, seed=seed)
    trajectory = plan(length, pass_spacing(0.064 + 0.03 * (passes - 1), passes), config)
    assert np.allclose(np.diff(trajectory.t), 1e-3)
    step = np.hypot(np.diff(trajectory.u), np.diff(trajectory.w))
    fastest = max(speed * (1 + 4 * jitter + config.variation), config.transit_speed)
    assert np.all(np.isfinite(step)) and step.max() <= fastest * 1e-3 * 1.001
    assert np.abs(np.diff(trajectory.h)).max() <= max(config.approach_speed * 1e-3, fastest * 1e-3) * 1.001
    assert len(trajectory.passes) == passes
    for k, p in enumerate(trajectory.passes):
        assert p.contact_end_s - p.contact_start_s >= 0.9 * length / (speed * (1 + 4 * jitter))
        assert (p.u_start, p.u_end) == ((0.0, length) if k % 2 == 0 else (length, 0.0))


def _fine_relief_shading(pixel_samples: int) -> np.ndarray:
    """The irradiance (summed over the colours) along the contact line of the roller pressed on a 3 um
    cosine of 0.4 mm wavelength (about 4 pixels there) running along the roller's axis, no noise nor
    flat field, high-passed."""
    from bench.raster_generator.render import BandRenderer
    from bench.raster_generator.surfaces import Surface

    resolution = 2.5e-5
    y = (np.arange(int(0.08 / resolution)) + 0.5) * resolution
    height = np.repeat((3e-6 * np.cos(2 * np.pi * y / 0.4e-3))[:, None], int(0.02 / resolution), axis=1)
    surface = Surface("grained", height.astype(np.float32), resolution, (0.49, -0.04, 0.0), 0.0, ())
    look = Look(electrons_per_level=1e9, read_noise=0.0, row_noise=0.0, specks=0, vignetting=0.0, axial_falloff=0.0,
                exposure_samples=1, pixel_samples=pixel_samples)
    renderer = BandRenderer(Camera(), surface, look, depth=5e-4, window=20)
    # the roller's axis at (0.5, 0) along base y, rolling along base x: as `frame` places it
    xy = np.stack([np.float32(0.5) + renderer.y_roll, renderer.x_axial], axis=-1)
    lit = renderer._shade(renderer.membrane(-surface.sample(xy))).sum(axis=-1)
    line = lit[lit.shape[0] // 2, 170:470].astype(np.float64)
    return line - np.convolve(line, np.ones(9) / 9, mode="same")


def test_a_pixel_shows_the_mean_shading_of_its_footprint_not_slopes_two_pixels_wide() -> None:
    """Relief a few pixels across keeps the shading contrast its pixels' footprints see (converged: 3
    shading points per pixel against 9); slopes taken between pixel centres (1 point) lose about a third
    of it at a 4-pixel wavelength."""
    reference = _fine_relief_shading(9)[10:-10]
    default = _fine_relief_shading(Look().pixel_samples)[10:-10]
    centres = _fine_relief_shading(1)[10:-10]
    assert reference.std() > 0.5                               # the cosine is seen (grey levels of contrast)
    assert default.std() / reference.std() == pytest.approx(1.0, abs=0.05)
    assert float(np.corrcoef(default, reference)[0, 1]) > 0.98
    assert centres.std() / reference.std() < 0.85
