"""Stitching on synthetic rolls: a texture translated by known subpixel shifts behind a static gel
background (shading, dust specks), with noise, blur, textureless stretches and frame glitches."""
from __future__ import annotations

import math
from collections import deque

import cv2
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from touchroller_perception.geometry import CameraModel
from touchroller_perception.metrics import compare_to_truth
from touchroller_perception.stitching import Stitcher, StitcherConfig, StitchStep, stitch

SHAPE = (240, 320)
BAND = (80, 160)  # image rows where the roller touches the surface
FRAME_NS = 33_333_333


def texture(rows: int, cols: int, seed: int) -> np.ndarray:
    rng = np.random.default_rng(seed)
    t = cv2.GaussianBlur(rng.normal(size=(rows, cols)).astype(np.float32), (0, 0), 1.5)
    yy, xx = np.mgrid[0:rows, 0:cols]
    t = t / t.std() + 0.5 * np.sin(xx * 0.7) * np.sin(yy * 0.55)
    return np.clip(128 + 40 * t, 0, 255).astype(np.float32)


def gel_gain(seed: int) -> np.ndarray:
    """What does not move with the surface: uneven LED shading and dark specks of dust (a gain)."""
    h, w = SHAPE
    rng = np.random.default_rng(seed)
    yy, xx = np.mgrid[0:h, 0:w]
    gain = (0.8 + 0.25 * np.cos(xx / w * 3) + 0.15 * yy / h).astype(np.float32)
    for _ in range(15):
        cv2.circle(gain, (int(rng.integers(w)), int(rng.integers(h))), int(rng.integers(1, 3)), 0.3, -1)
    return gain


def roll(shifts, *, seed=0, noise=2.0, lateral=None, flat_rows=None, blur=False):
    """Frames of a surface moving down the image by `shifts[k]` px between frame k and k+1.

    Returns (frames, true positions, truth texture, row of the truth seen at image row 0 of frame 0).
    `flat_rows` = (a, b) makes that stretch of the surface textureless: image row v of frame k shows
    texture row v - pos[k] (plus a constant), so the band [BAND] is flat while pos in [BAND[1] - b, BAND[0] - a].
    """
    h, w = SHAPE
    pos = np.concatenate([[0.0], np.cumsum(shifts)])
    span = int(np.ceil(np.abs(pos).max())) + h + 20
    tex = texture(2 * span, w + 40, seed)
    if flat_rows is not None:
        a, b = flat_rows
        tex[span + a:span + b] = 128.0
    gain = gel_gain(seed + 1)
    v = np.arange(h)
    contact = np.clip(np.minimum(v - BAND[0], BAND[1] - v) / 6.0, 0, 1)[:, None].astype(np.float32)
    rng = np.random.default_rng(seed + 2)
    frames = []
    for k, p in enumerate(pos):
        lat = 0.0 if lateral is None else float(lateral[k])
        m = np.float32([[1, 0, -20 + lat], [0, 1, p - span]])
        seen = cv2.warpAffine(tex, m, (w, h), flags=cv2.INTER_CUBIC)
        if blur and k > 0:
            n = max(1, int(round(abs(pos[k] - pos[k - 1]))))
            seen = cv2.blur(seen, (1, n))
        img = gain * (128 * (1 - contact) + seen * contact) + rng.normal(0, noise, (h, w))
        frames.append(np.clip(img, 0, 255).astype(np.uint8))
    return frames, pos, tex


def stamps(n, drop=()):
    return [k * FRAME_NS for k in range(n + len(drop)) if k not in drop]


def estimated(steps: list[StitchStep]) -> np.ndarray:
    return np.array([s.position_px for s in steps])


@pytest.mark.parametrize("speed", [0.4, 1.7, -2.3, 6.6])
def test_default_tracks_subpixel_speeds_in_both_directions(speed):
    frames, pos, _ = roll(np.full(60, speed))
    _, steps = stitch(frames)
    assert len(steps) == len(frames)
    assert np.max(np.abs(estimated(steps) - pos)) < 0.5
    total = steps[-1].position_px
    assert abs(total - pos[-1]) / abs(pos[-1]) < 0.01  # length error <= 1 %


def test_paper_method_rounds_slow_rolls_to_integer_shifts():
    frames, pos, _ = roll(np.full(40, 0.4))
    _, steps = stitch(frames, StitcherConfig(method="paper"))
    shifts = np.array([s.shift_px for s in steps])
    assert np.all(shifts == np.round(shifts))
    assert abs(steps[-1].position_px) < 0.5 * pos[-1]  # rounding eats most of a sub-pixel roll


def test_paper_method_finds_integer_shifts():
    frames, pos, _ = roll(np.full(20, -3.0))
    _, steps = stitch(frames, StitcherConfig(method="paper"))
    assert [s.shift_px for s in steps[1:]] == [-3.0] * 20


@settings(max_examples=8, deadline=None)
@given(speed=st.floats(0.3, 9.0), sign=st.sampled_from([-1, 1]), seed=st.integers(0, 50))
def test_default_length_error_below_one_percent(speed, sign, seed):
    frames, pos, _ = roll(np.full(max(30, math.ceil(150 / speed)), sign * speed), seed=seed, blur=True)
    _, steps = stitch(frames)
    assert abs(steps[-1].position_px - pos[-1]) <= 0.01 * abs(pos[-1]) + 0.2


def test_speed_change_dropped_and_duplicated_frames():
    shifts = np.r_[np.full(20, 1.5), np.full(20, 5.5)]
    frames, pos, _ = roll(shifts)
    # drop frame 30, duplicate frame 10 (same stamp), and keep the stamps honest
    keep = [k for k in range(len(frames)) if k != 30]
    images = [frames[k] for k in keep]
    times = [k * FRAME_NS for k in keep]
    truth = [pos[k] for k in keep]
    images.insert(11, frames[10])
    times.insert(11, 10 * FRAME_NS)
    truth.insert(11, pos[10])
    _, steps = stitch(images, stamps=times)
    assert np.max(np.abs(estimated(steps) - np.array(truth))) < 0.5
    assert abs(steps[11].shift_px) < 0.2  # the duplicate did not move
    assert not any(s.used_prior for s in steps)


def test_textureless_stretch_falls_back_on_prior_and_flags_it():
    speed = 3.0
    frames, pos, _ = roll(np.full(60, speed), flat_rows=(-40, 140), noise=1.0)
    stitcher = Stitcher()
    steps = [stitcher.push(f, k * FRAME_NS, prior_px=speed) for k, f in enumerate(frames)]
    flagged = [s for s in steps if s.used_prior]
    assert flagged, "a textureless stretch must be flagged"
    assert all(s.shift_px == pytest.approx(speed) for s in flagged)
    assert abs(steps[-1].position_px - pos[-1]) < 2.0


def test_unregistered_frames_take_the_prior_and_the_next_registered_frame_finds_the_truth():
    """A caller sure of a steady roll skips registering frames (`register=False`): they move by the prior.
    When the roll slowed meanwhile (the prior lags it: 5 px a frame while the surface moves 2.5), the next
    registered frame is still located on the image, against the keyframe, not left where the prior put it."""
    shifts = np.r_[np.full(12, 5.0), np.full(12, 2.5)]
    frames, pos, _ = roll(shifts)
    stitcher = Stitcher()
    steps = []
    for k, frame in enumerate(frames):
        register = k % 3 == 0 or k < 6
        steps.append(stitcher.push_band(stitcher.band(frame), k * FRAME_NS, prior_px=5.0, register=register))
        if not register:
            assert steps[-1].used_prior and steps[-1].shift_px == 5.0
    registered = [k for k in range(len(frames)) if k % 3 == 0 or k < 6]
    errors = np.abs(estimated(steps) - pos)[registered]
    assert errors.max() < 0.5
    assert not any(steps[k].used_prior for k in registered[1:])
    # without a prior or a recent velocity there is nothing to move an unregistered frame by: registered
    fresh = Stitcher()
    fresh.push(frames[0], 0)
    assert not fresh.push_band(fresh.band(frames[1]), FRAME_NS, register=False).used_prior


def test_textureless_without_prior_uses_recent_velocity():
    frames, pos, _ = roll(np.full(60, 2.5), flat_rows=(-40, 140), noise=1.0)
    _, steps = stitch(frames)
    flagged = [s for s in steps if s.used_prior]
    assert flagged
    assert all(abs(s.shift_px - 2.5) < 0.3 for s in flagged)
    assert abs(steps[-1].position_px - pos[-1]) < 3.0


def test_lateral_wander_is_tracked():
    n = 80
    lateral = np.linspace(0, 6.0, n + 1)
    frames, pos, _ = roll(np.full(n, 2.5), lateral=lateral)
    _, steps = stitch(frames)
    est_lat = np.cumsum([s.lateral_px for s in steps])
    # the surface moving left by +lat in texture coordinates appears shifted right in the image
    assert abs(abs(est_lat[-1]) - 6.0) < 0.5
    assert np.max(np.abs(estimated(steps) - pos)) < 0.5


def test_map_matches_truth_and_beats_the_paper():
    frames, pos, tex = roll(np.full(80, 1.3), noise=3.0)
    results = {}
    for method in ("default", "paper"):
        stitcher = Stitcher(StitcherConfig(method=method))
        for k, f in enumerate(frames):
            stitcher.push(f, k * FRAME_NS)
        results[method] = compare_to_truth(stitcher.map_image(), tex, valid=stitcher.map_coverage())
    assert results["default"]["ssim"] > 0.8
    assert results["default"]["ssim"] > results["paper"]["ssim"] + 0.1


def test_map_grows_along_the_roll_and_keeps_width():
    frames, pos, _ = roll(np.full(30, -4.0))
    image, _ = stitch(frames, StitcherConfig(lateral=False))
    assert image.dtype == np.uint8
    assert image.shape[1] in (SHAPE[1], SHAPE[1] + 1)
    assert image.shape[0] == pytest.approx(70 + abs(pos[-1]), abs=3)


def test_camera_model_gives_metric_scale():
    cam = CameraModel(fx=250.0, fy=250.0, cx=159.5, cy=119.5, width=320, height=240)
    frames, pos, _ = roll(np.full(20, 2.0))
    stitcher = Stitcher(camera=cam)
    for k, f in enumerate(frames):
        stitcher.push(f, k * FRAME_NS)
    assert stitcher.mm_per_px == pytest.approx(50.0 / 250.0, rel=1e-3)
    native = stitcher.map_image()
    half = stitcher.map_image(mm_per_px=2 * stitcher.mm_per_px)
    assert half.shape[0] == pytest.approx(native.shape[0] / 2, abs=1)
    assert half.shape[1] == pytest.approx(native.shape[1] / 2, abs=1)
    assert stitcher.pixels_per_metre() == pytest.approx(1000.0 / stitcher.mm_per_px)


def test_metric_map_needs_a_camera():
    frames, _, _ = roll(np.full(3, 2.0))
    stitcher = Stitcher()
    stitcher.push(frames[0], 0)
    with pytest.raises(ValueError, match="camera"):
        stitcher.map_image(mm_per_px=0.1)


def test_bad_input_is_rejected_clearly():
    with pytest.raises(ValueError, match="method"):
        StitcherConfig(method="magic")
    stitcher = Stitcher()
    stitcher.push(np.zeros(SHAPE, np.uint8), 0)
    with pytest.raises(ValueError, match="size changed"):
        stitcher.push(np.zeros((100, 100), np.uint8), 1)
    with pytest.raises(ValueError, match="band_rows"):
        StitcherConfig(band_rows=4)
    with pytest.raises(ValueError, match="band_rows"):
        Stitcher(StitcherConfig(band_rows=300)).push(np.zeros(SHAPE, np.uint8), 0)


def test_flat_frames_give_zero_confidence_not_a_wrong_number():
    stitcher = Stitcher()
    flat = np.full(SHAPE, 90, np.uint8)
    steps = [stitcher.push(flat, k * FRAME_NS) for k in range(5)]
    assert all(math.isfinite(s.shift_px) for s in steps)
    assert all(s.confidence < 0.15 for s in steps)
    assert all(s.shift_px == 0.0 for s in steps)


def test_non_finite_frames_are_rejected():
    image = np.full(SHAPE, 100.0, np.float32)
    image[5, 5] = np.nan
    with pytest.raises(ValueError, match="non-finite"):
        Stitcher().push(image, 0)


def test_finalise_divides_out_dust_and_shading_from_the_first_frame_on():
    frames, pos, tex = roll(np.full(70, 2.5), noise=1.0)
    live = Stitcher()
    offline = Stitcher(StitcherConfig(live_map=False))
    for k, f in enumerate(frames):
        live.push(f, k * FRAME_NS)
        offline.push(f, k * FRAME_NS)
    live_map = compare_to_truth(live.map_image(), tex, valid=live.map_coverage())
    offline.finalise()
    live.finalise()
    final = compare_to_truth(live.map_image(), tex, valid=live.map_coverage())
    assert np.array_equal(live.map_image(), offline.map_image())  # same result without the live layer
    assert final["ssim"] > 0.85
    assert final["ssim"] >= live_map["ssim"] - 0.01


def test_estimate_flat_field_keeps_stripes_along_the_roll_out_of_the_field():
    rng = np.random.default_rng(0)
    stripes = (10 * np.sin(np.arange(320) * 0.9)).astype(np.float32)  # constant along the roll
    gain = gel_gain(3)[80:150]
    bands = [gain * (128 + stripes + rng.normal(0, 5, (70, 320)).astype(np.float32)) for _ in range(50)]
    from touchroller_perception.stitching import estimate_flat_field

    field = estimate_flat_field(bands)
    flattened = np.mean([b / field for b in bands], axis=0)
    profile = flattened.mean(axis=0)
    assert np.corrcoef(profile, stripes)[0, 1] > 0.9  # the surface's stripes survive
    speck_rows, speck_cols = np.nonzero(gain < 0.5)
    if speck_rows.size:  # dust divides out
        assert np.std(flattened[speck_rows, speck_cols] / flattened.mean()) < 0.1


# -- standing still: lead-ins, pauses, stalls (a scan starts by approaching the surface from above) --

def lead_in(kind: str, n: int, seed: int = 0) -> list[np.ndarray]:
    """Frames before the roll: the roller lifted off (only the gel's static background) or touching the
    surface at the roll's first position without moving."""
    if kind == "touching":
        frames, _, _ = roll(np.zeros(n - 1), seed=seed)
        return frames
    h, w = SHAPE
    rng = np.random.default_rng(seed + 7)
    gain = gel_gain(seed + 1)  # the same gel as `roll`'s
    return [np.clip(gain * 128 + rng.normal(0, 2.0, (h, w)), 0, 255).astype(np.uint8) for _ in range(n)]


def stitch_live(frames, *, first_stamp=0, **kwargs):
    stitcher = Stitcher(StitcherConfig(history=None, **kwargs))
    steps = [stitcher.push(f, first_stamp + k * FRAME_NS) for k, f in enumerate(frames)]
    return stitcher, steps


@pytest.mark.parametrize("kind", ["lifted", "touching"])
def test_a_lead_in_standing_still_does_not_freeze_the_map(kind):
    frames, pos, tex = roll(np.full(70, 2.5), noise=1.0)
    plain, _ = stitch_live(frames)
    pre = lead_in(kind, 20)
    led, steps = stitch_live(pre + frames)
    rolled = steps[-1].position_px - steps[len(pre)].position_px
    assert abs(rolled - pos[-1]) <= 0.01 * pos[-1]
    assert led.map_image().shape[0] == pytest.approx(plain.map_image().shape[0], abs=2)
    for stitcher in (plain, led):
        stitcher.finalise()
    quality = {name: compare_to_truth(s.map_image(), tex, valid=s.map_coverage())["ssim"]
               for name, s in (("plain", plain), ("led", led))}
    assert quality["led"] > 0.85
    assert quality["led"] >= quality["plain"] - 0.03


def test_lead_in_frames_do_not_enter_the_map_or_the_background():
    frames, _, _ = roll(np.full(70, 2.5), noise=1.0)
    led, _ = stitch_live(lead_in("lifted", 30) + frames)
    plain, _ = stitch_live(frames)
    assert led.flat.count <= plain.flat.count
    led.finalise()
    plain.finalise()
    a, b = led.map_image(), plain.map_image()
    assert a.shape[0] == pytest.approx(b.shape[0], abs=1)
    # the first rows would be half grey (lifted-off frames averaged in) if the lead-in were splatted
    assert rows_differ(a[:40], b[:40]) < 4.0


def rows_differ(a: np.ndarray, b: np.ndarray) -> float:
    """Mean |a - b| over the columns both have, at the best of a few column offsets (the maps' left
    edges may differ by a column of lateral jitter)."""
    w = min(a.shape[1], b.shape[1]) - 4
    return min(float(np.mean(np.abs(a[:, 2 + d:2 + d + w].astype(float) - b[:, 2:2 + w]))) for d in (-2, -1, 0, 1, 2))


def test_a_map_before_the_roller_moves_shows_the_latest_frame():
    stitcher = Stitcher()
    for k, f in enumerate(lead_in("lifted", 5)):
        stitcher.push(f, k * FRAME_NS)
    frames, _, _ = roll(np.zeros(4))
    for k, f in enumerate(frames):
        stitcher.push(f, (5 + k) * FRAME_NS)
    image = stitcher.map_image()
    assert image.shape[0] == pytest.approx(70, abs=1)
    assert stitcher.map_coverage().shape == image.shape
    band = cv2.cvtColor(frames[-1], cv2.COLOR_GRAY2BGR) if frames[-1].ndim == 2 else frames[-1]
    expected = stitcher.band(band)
    assert np.corrcoef(image[5:-5].ravel(), expected[5:-5, :image.shape[1]].ravel())[0, 1] > 0.95
    stitcher.finalise()
    assert stitcher.map_image().shape == image.shape
    assert np.mean(stitcher.map_image() == 0) < 0.01


def test_a_roll_that_pauses_and_resumes():
    shifts = np.r_[np.full(30, 2.5), np.linspace(2.5, 0, 6), np.zeros(25), np.linspace(0, 2.5, 6), np.full(30, 2.5)]
    frames, pos, tex = roll(shifts, noise=1.0)
    stitcher, steps = stitch_live(frames)
    assert np.max(np.abs(estimated(steps) - pos)) < 0.5
    assert abs(steps[-1].position_px - pos[-1]) <= 0.01 * pos[-1]
    stitcher.finalise()
    assert compare_to_truth(stitcher.map_image(), tex, valid=stitcher.map_coverage())["ssim"] > 0.85


def test_a_long_gap_in_the_stream_follows_the_recent_velocity():
    """A camera stall: 40 frames missing at 2.5 px/frame is 100 px, beyond any overlap with the key."""
    frames, pos, _ = roll(np.full(120, 2.5), noise=1.0)
    keep = [k for k in range(len(frames)) if not 50 <= k < 90]
    stitcher = Stitcher(StitcherConfig(history=None))
    steps = [stitcher.push(frames[k], k * FRAME_NS) for k in keep]
    assert steps[50].used_prior  # the first frame after the gap: no overlap to register
    assert abs(steps[-1].position_px - pos[keep[-1]]) <= 0.01 * pos[keep[-1]]


def test_lifting_off_at_the_end_leaves_the_map_alone():
    frames, pos, tex = roll(np.r_[np.full(60, 2.5), np.linspace(2.5, 0, 6)], noise=1.0)
    plain, _ = stitch_live(frames)
    lifted, steps = stitch_live(frames + lead_in("lifted", 15))
    assert abs(steps[-1].position_px - pos[-1]) < 1.0
    for stitcher in (plain, lifted):
        stitcher.finalise()
    a, b = lifted.map_image(), plain.map_image()
    assert a.shape[0] == pytest.approx(b.shape[0], abs=2)
    h = min(a.shape[0], b.shape[0])
    assert rows_differ(a[h - 40:h], b[h - 40:h]) < 4.0


@pytest.mark.parametrize("depth", [-0.002, 5e-4])
def test_simulated_scan_with_a_lead_in_has_the_full_length(depth):
    """The issue's repro: 20 frames of the simulated sensor lifted off (or touching) at the start, then
    the roll; the map used to stay one band (~72 rows)."""
    from touchroller_driver.sim import SimulatedSensor, load_scene
    from touchroller_driver.sim.render import RollerState

    sensor = SimulatedSensor(load_scene("surface_mapping", **{"motion.length": 0.03, "motion.duration": 3.0}))
    frames = list(sensor.frames())
    travel = [f.truth["state"]["travel"] for f in frames]
    pre = [sensor.render(RollerState(travel=travel[0], depth=depth)) for _ in range(20)]
    true_px = (travel[-1] - travel[0]) * 1e3 / (sensor.metres_per_px_at_contact()[1] * 1e3)
    results = {}
    for name, lead in (("plain", []), ("led", pre)):
        stitcher = Stitcher(StitcherConfig(history=None), camera=sensor.camera)
        stamp0 = frames[0].stamp_ns - len(lead) * FRAME_NS
        for k, image in enumerate(lead):
            stitcher.push(image, stamp0 + k * FRAME_NS)
        start = stitcher.position_px
        for f in frames:
            stitcher.push(f.image, f.stamp_ns)
        stitcher.finalise()
        rolled = abs(stitcher.position_px - start)
        assert abs(rolled - true_px) <= 0.01 * true_px
        truth = sensor.surface_map_truth().tactile
        results[name] = compare_to_truth(stitcher.map_image(), truth, valid=stitcher.map_coverage())["ssim"]
    assert results["led"] >= results["plain"] - 0.03


@pytest.mark.parametrize("speed", [2.6, -2.6])
def test_finalise_on_a_live_stitcher_is_at_least_as_good_as_the_live_map(speed):
    """Fed frame by frame as the perception node does (lead-in, a map longer than the canvas's first
    allocation in either direction, bounded history), then finalised: nothing is lost or zeroed."""
    frames, pos, tex = roll(np.full(420, speed), noise=1.0)
    stitcher = Stitcher(StitcherConfig(history=50))
    for k, f in enumerate(lead_in("lifted", 10) + frames):
        stitcher.push(f, k * FRAME_NS)
    live, covered = stitcher.map_image(), stitcher.map_coverage()
    assert live.shape[0] > 1100
    stitcher.finalise()
    final = stitcher.map_image()
    assert final.shape == live.shape
    assert np.array_equal(stitcher.map_coverage(), covered)
    assert np.mean(final[covered] == 0) < 1e-3
    scores = [compare_to_truth(image, tex, valid=covered)["ssim"] for image in (live, final)]
    assert scores[1] >= scores[0] - 0.005
    assert scores[1] > 0.85


def history_size(stitcher: Stitcher) -> int:
    """Entries the stitcher keeps besides the map itself: per-frame records, the placement histogram
    and any other list or deque attribute."""
    size = sum(len(v) for v in vars(stitcher).values() if isinstance(v, (list, deque)))
    canvas = stitcher._canvas
    return size + sum(shares.size for shares in canvas.placed.values()) + canvas.weight.size


def test_live_history_is_bounded():
    frames, _, _ = roll(np.full(40, 2.5), noise=1.0)
    still = frames[-1]
    bounded, unbounded = Stitcher(StitcherConfig(history=25)), Stitcher(StitcherConfig(history=None))
    sizes = {}
    for k in range(400):  # a short roll, then standing still: the map stops growing, so must the rest
        image = frames[k] if k < len(frames) else still
        for stitcher in (bounded, unbounded):
            stitcher.push(image, k * FRAME_NS)
        if k in (100, 399):
            sizes[k] = (history_size(bounded), history_size(unbounded))
    assert sizes[399][0] == sizes[100][0]
    assert sizes[399][1] > sizes[100][1]  # offline: every frame kept
    assert len(bounded.steps) == len(bounded.stamps) == len(bounded.shifts) == 25
    assert bounded.frames == len(unbounded.steps) == 400
    assert list(bounded.steps) == unbounded.steps[-25:]
    assert bounded.position_px == unbounded.steps[-1].position_px
    assert Stitcher().history is not None  # what the perception node constructs is bounded
    with pytest.raises(ValueError, match="history"):
        StitcherConfig(history=0)


def canvas_cells(stitcher: Stitcher) -> int:
    """Values the stitcher's map holds: the layers, the row weights and the placement histogram."""
    canvas = stitcher._canvas
    return (sum(layer.size for layer in canvas.layers) + canvas.weight.size
            + sum(shares.size for shares in canvas.placed.values()))


def test_a_live_map_is_a_rolling_window_of_max_rows():
    """Frames for ever (a camera left running with no sweep to start a new map) must not grow the map
    without end: past `max_rows` the rows farthest from the newest band go, and are counted."""
    frames, _, _ = roll(np.full(300, 6.0), noise=1.0, lateral=np.linspace(0.0, 12.0, 301))
    max_rows = 8 * StitcherConfig().band_rows
    bounded = Stitcher(StitcherConfig(max_rows=max_rows))
    unbounded = Stitcher(StitcherConfig(max_rows=None))
    cells = []
    for k, image in enumerate(frames):
        for stitcher in (bounded, unbounded):
            stitcher.push(image, k * FRAME_NS)
        if k % 50 == 49:
            cells.append(canvas_cells(bounded))
    full, window = unbounded.map_image(), bounded.map_image()
    assert full.shape[0] > 3 * max_rows   # the roll is far longer than the window
    assert 0 < window.shape[0] <= max_rows
    assert max(cells[1:]) <= 2 * max_rows * (SHAPE[1] + 64) * 3
    assert cells[-1] <= cells[2]   # the memory stopped growing with the frames
    assert bounded.dropped_rows >= full.shape[0] - max_rows
    assert unbounded.dropped_rows == 0
    # The surface moves down the image, so the newest rows are at the top of the map: the window is
    # the unbounded map's first rows (the columns may differ: the window's bands span wider than all).
    rows = window.shape[0] - 2 * StitcherConfig().band_rows   # away from the cut
    offset = bounded._canvas.col_lo - unbounded._canvas.col_lo
    width = min(window.shape[1], full.shape[1])
    a = window[:rows, max(-offset, 0):][:, :width - abs(offset)]
    b = full[:rows, max(offset, 0):][:, :width - abs(offset)]
    assert a.shape == b.shape and a.size > 0
    assert np.abs(a.astype(int) - b.astype(int)).max() <= 1
    assert Stitcher().config.max_rows is not None   # what the perception node constructs is bounded
    with pytest.raises(ValueError, match="max_rows"):
        StitcherConfig(max_rows=100)
