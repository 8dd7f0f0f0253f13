"""The world map on simulated raster scans: placed by TF, latency found from the data, passes registered."""
from __future__ import annotations

import numpy as np
import pytest

from touchroller_perception.transforms import TransformBuffer
from touchroller_perception.world_map import WorldMapConfig, WorldMapper, buffer_lookup

sim = pytest.importorskip("touchroller_driver.sim")

from touchroller_driver.arm import (  # noqa: E402
    DEFAULT_MOUNT_RPY,
    DEFAULT_MOUNT_XYZ,
    DEFAULT_START_POSE,
    mount_transform,
    plan_raster,
    simulated_arm_origin,
)
from touchroller_driver.sim.camera import surface_frame  # noqa: E402
from touchroller_driver.sim.sweep import simulate_sweep  # noqa: E402
from touchroller_perception.metrics import ssim  # noqa: E402

MOUNT = mount_transform(DEFAULT_MOUNT_XYZ, DEFAULT_MOUNT_RPY)
AREA = (0.42, -0.045, 0.05, 0.09)   # 5 cm x 9 cm: two passes


@pytest.fixture(scope="module")
def sensor():
    return sim.SimulatedSensor(sim.load_scene("large_surface"), seed=0)


@pytest.fixture(scope="module")
def scans(sensor):
    """Frames and TF of the same raster filmed with a camera latency of 0 and 40 ms."""
    plan = plan_raster(DEFAULT_START_POSE, area=AREA, mount=MOUNT, speed=0.02, accel=0.1, depth=5e-4,
                       clearance=0.002, approach_speed=0.005)
    rest, _ = simulated_arm_origin(DEFAULT_START_POSE, 0.002)
    # start above the first pass: a short approach
    start = np.array(plan.segments[0].target)
    out = {}
    for latency in (0.0, 0.04):
        out[latency] = list(simulate_sweep(sensor, plan, start, MOUNT, latency_s=latency))
    assert len(plan.rolls) == 2
    return plan, rest, out


def run(events, sensor, **config):
    buffer = TransformBuffer(cache_ns=None)
    buffer.set_transform("tool0", "touchroller_cylinder", 0, MOUNT, static=True)
    bounds = (AREA[0] - 0.01, AREA[1] - 0.01, AREA[0] + AREA[2] + 0.01, AREA[1] + AREA[3] + 0.01)
    mapper = WorldMapper(sensor.camera, buffer_lookup(buffer, "base", "touchroller_cylinder"),
                         WorldMapConfig(bounds=bounds, **config))
    for event in events:
        if event[0] == "tf":
            buffer.set_transform("base", "tool0", event[1], event[2])
        else:
            mapper.push(event[2], event[1])
    mapper.finalise()
    return mapper


def in_place_ssim(mapper, sensor) -> float:
    """SSIM of the map against the true surface where it lies, no alignment, over the mapped rectangle."""
    grey, weight = mapper.canvas.value(mapper._level)
    _, tactile = sensor.world_truth(surface_frame(sensor.scene), mapper.canvas.origin, grey.shape,
                                    mapper.config.resolution)
    (c0, r0), (c1, r1) = (np.round(mapper.canvas.to_grid(np.array(p)) + 0.5).astype(int)
                          for p in (AREA[:2], (AREA[0] + AREA[2], AREA[1] + AREA[3])))
    a, b = grey[r0:r1, c0:c1], tactile[r0:r1, c0:c1].astype(np.float32)
    assert (weight[r0:r1, c0:c1] > 0.05).mean() > 0.98
    return ssim(*(np.clip((x - x.mean()) / x.std() * 40 + 128, 0, 255) for x in (a, b)))


@pytest.mark.slow
def test_a_two_pass_raster_maps_in_place_with_the_latency_found(scans, sensor):
    plan, _, events = scans
    mapper = run(events[0.04], sensor)
    assert mapper.stats.latency_estimated
    assert mapper.stats.latency_s == pytest.approx(0.04, abs=0.003)
    assert mapper.stats.passes == 2 and mapper.stats.mapped > 0.5 * mapper.stats.frames
    assert mapper.coverage((AREA[0], AREA[1], AREA[0] + AREA[2], AREA[1] + AREA[3])) >= 98.0
    assert in_place_ssim(mapper, sensor) >= 0.90
    # told nothing and assuming no latency (TF only), the passes land 0.8 mm off, in opposite directions
    tf_only = run(events[0.04], sensor, latency=0.0, register=False)
    assert in_place_ssim(tf_only, sensor) < in_place_ssim(mapper, sensor) - 0.1


@pytest.mark.slow
def test_without_latency_the_estimate_is_zero_and_registration_changes_nothing(scans, sensor):
    _, _, events = scans
    mapper = run(events[0.0], sensor)
    assert mapper.stats.latency_s == pytest.approx(0.0, abs=0.003)
    assert all(abs(dx) < 0.3 and abs(dy) < 0.3 for dx, dy in mapper.stats.pass_corrections_px)


@pytest.mark.slow
def test_steady_rolling_is_registered_one_frame_in_three_and_maps_as_well(scans, sensor):
    """`steady_stride`: while the roll is steady most frames take the motion instead of being registered;
    the starts and stops, which the latency is found from, are still registered frame by frame."""
    _, _, events = scans
    every = run(events[0.04], sensor, steady_stride=1)
    steady = run(events[0.04], sensor)
    assert steady.config.steady_stride == 3
    assert steady.strip.prior_frames - every.strip.prior_frames > 0.3 * steady.strip.frames
    assert steady.stats.latency_s == pytest.approx(0.04, abs=0.003)
    assert steady.stats.mapped == every.stats.mapped
    assert in_place_ssim(steady, sensor) >= in_place_ssim(every, sensor) - 0.01


@pytest.mark.slow
def test_a_frame_exposed_before_tf_began_holds_no_one_back(scans, sensor):
    """The first frames were exposed before the arm's first transform: they can never be placed, and the
    frames after them are placed as their poses come (the live map grows while rolling), not at the end."""
    _, _, events = scans
    first_image = next(e[1] for e in events[0.04] if e[0] != "tf")
    late = [e for e in events[0.04] if e[0] != "tf" or e[1] >= first_image]
    buffer = TransformBuffer(cache_ns=None)
    buffer.set_transform("tool0", "touchroller_cylinder", 0, MOUNT, static=True)
    bounds = (AREA[0] - 0.01, AREA[1] - 0.01, AREA[0] + AREA[2] + 0.01, AREA[1] + AREA[3] + 0.01)
    mapper = WorldMapper(sensor.camera, buffer_lookup(buffer, "base", "touchroller_cylinder"),
                         WorldMapConfig(bounds=bounds))
    images = sum(1 for e in late if e[0] != "tf")
    pushed, mapped_halfway = 0, None
    for event in late:
        if event[0] == "tf":
            buffer.set_transform("base", "tool0", event[1], event[2])
            continue
        mapper.push(event[2], event[1])
        pushed += 1
        if pushed == images // 2:
            mapped_halfway = mapper.stats.mapped
    mapper.finalise()
    assert mapper.stats.no_pose >= 1 and mapper.stats.latency_s == pytest.approx(0.04, abs=0.003)
    assert mapped_halfway is not None and mapped_halfway > 0.25 * images
    assert in_place_ssim(mapper, sensor) >= 0.90


def test_median_and_percentile_are_numpys_to_the_bit():
    """The mapper's own median and 90th percentile (numpy's import numpy.ma, tens of milliseconds of a
    command's start-up) give numpy's numbers exactly: odd and even counts, any scale."""
    from touchroller_perception.world_map import _median, _percentile

    rng = np.random.default_rng(7)
    for n in [*range(1, 30), 600]:
        for scale in (1e-4, 1.0, 1e4):
            values = rng.normal(size=n) * scale
            assert _median(values) == float(np.median(values))
            assert _percentile(values, 90) == float(np.percentile(values, 90))


def test_config_is_checked():
    with pytest.raises(ValueError, match="resolution"):
        WorldMapConfig(resolution=0.0)
    with pytest.raises(ValueError, match="bounds"):
        WorldMapConfig(bounds=(1.0, 0.0, 0.0, 1.0))
    with pytest.raises(ValueError, match="max_pixels"):
        WorldMapConfig(bounds=(0.0, 0.0, 10.0, 10.0))
    with pytest.raises(ValueError, match="steady_stride"):
        WorldMapConfig(steady_stride=0)


@pytest.mark.parametrize("turn", [((0, 1), (1, 0)), ((0, -1), (1, 0)), ((0, 1), (-1, 0)), ((0, -1), (-1, 0)),
                                  ((1, 0), (0, 1)), ((-1, 0), (0, 1)), ((1, 0), (0, -1)), ((-1, 0), (0, -1))])
def test_an_axis_aligned_band_lands_where_the_bilinear_warp_puts_it(turn):
    """The fast placement (quarter turns and flips, then a 2x2 bilinear blend) against OpenCV's affine warp
    of the same band, for every orientation and a subpixel offset; OpenCV rounds positions to 1/32 px."""
    import cv2

    from touchroller_perception.world_map import _axis_aligned, _blend, _orient

    rng = np.random.default_rng(3)
    plane = cv2.GaussianBlur(rng.normal(100, 30, (30, 50)).astype(np.float32), (0, 0), 2.0)
    matrix = np.array([[turn[0][0], turn[0][1], 70.3], [turn[1][0], turn[1][1], 60.7]], np.float64)
    axes, c0, r0, kernel = _axis_aligned(matrix, plane.shape)
    patch = _blend(_orient(plane, axes), kernel)
    warped = cv2.warpAffine(plane, matrix, (200, 200), flags=cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT)
    h, w = patch.shape
    assert 0 <= c0 and 0 <= r0 and c0 + w <= 200 and r0 + h <= 200
    outside = warped.copy()
    outside[r0:r0 + h, c0:c0 + w] = 0
    assert np.abs(outside).max() == 0   # the patch holds all of the band
    assert np.abs(patch - warped[r0:r0 + h, c0:c0 + w]).max() < 0.05   # grey levels (0.02 px off: 2)
    assert _axis_aligned(matrix + np.array([[0, 1e-3, 0], [0, 0, 0]]), plane.shape) is None   # not a pure turn


@pytest.mark.slow
def test_frames_past_max_pixels_are_left_out_and_counted(scans, sensor):
    """A growing map (no bounds) that reaches max_pixels keeps what it has and counts what it leaves out,
    rather than failing (the live node then switched its map off for good)."""
    _, _, events = scans
    buffer = TransformBuffer(cache_ns=None)
    buffer.set_transform("tool0", "touchroller_cylinder", 0, MOUNT, static=True)
    mapper = WorldMapper(sensor.camera, buffer_lookup(buffer, "base", "touchroller_cylinder"),
                         WorldMapConfig(max_pixels=200_000, latency=0.0))   # the raster needs ~600 000
    for event in events[0.0]:
        if event[0] == "tf":
            buffer.set_transform("base", "tool0", event[1], event[2])
        else:
            mapper.push(event[2], event[1])
    mapper.finalise()
    assert mapper.stats.beyond_max_pixels > 0 and mapper.stats.mapped > 0
    assert mapper.canvas.shape[0] * mapper.canvas.shape[1] <= 200_000
    assert mapper.map_image().grey.size > 0


def _reordered(events, tf_lead_ns: int):
    """The same frames and transforms, each image delivered once TF reaches its stamp + `tf_lead_ns`
    (negative: before its own pose has arrived, as a live graph may deliver it)."""
    images = [e for e in events if e[0] != "tf"]
    out, waiting = [], list(images)
    for event in (e for e in events if e[0] == "tf"):
        while waiting and waiting[0][1] + tf_lead_ns < event[1]:
            out.append(waiting.pop(0))
        out.append(event)
    return out + waiting


@pytest.mark.slow
def test_the_map_does_not_depend_on_whether_a_frame_or_its_pose_arrives_first(scans, sensor):
    """Live, perception may take an image before the TF of its time (both come through one executor);
    read from a recording, the TF is usually ahead. The map must be the same either way."""
    _, _, events = scans
    ahead = run(_reordered(events[0.04], 100_000_000), sensor)      # TF 100 ms ahead of every frame
    behind = run(_reordered(events[0.04], -20_000_000), sensor)     # every frame 20 ms ahead of its pose
    assert behind.stats.mapped == ahead.stats.mapped and behind.stats.no_pose == 0
    assert behind.stats.latency_s == ahead.stats.latency_s
    np.testing.assert_array_equal(behind.map_image().grey, ahead.map_image().grey)
    assert in_place_ssim(behind, sensor) >= 0.90
