"""The blended raster path (sweep profiles blend and constant): touchdown and lift-off at speed."""
from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from touchroller_driver.arm import (
    DEFAULT_MOUNT_RPY,
    DEFAULT_MOUNT_XYZ,
    DEFAULT_START_POSE,
    mount_transform,
    plan_raster,
)
from touchroller_driver.path import BlendedPath, corner_accelerations, least_blend, rounded_polyline

MOUNT = mount_transform(DEFAULT_MOUNT_XYZ, DEFAULT_MOUNT_RPY)


def _plan(profile: str, **kw):
    return plan_raster(DEFAULT_START_POSE, area=(0.42, -0.045, 0.05, 0.09), mount=MOUNT, speed=0.02, accel=0.1,
                       depth=5e-4, clearance=0.002, profile=profile, **kw)


@pytest.mark.parametrize("profile", ["blend", "constant"])
def test_a_path_profile_touches_down_and_lifts_off_at_speed(profile):
    plan = _plan(profile)
    path = plan.path
    assert path is not None and plan.profile == profile
    t = np.arange(0.0, path.duration, 1e-3)
    poses = path.poses(t)
    pressed_z = plan.segments[plan.rolls[0]].target[2]
    speed = np.hypot(*np.diff(poses[:, :2], axis=0).T) / 1e-3
    pressed = np.abs(poses[:-1, 2] - pressed_z) < 1e-5
    # along every stretch in contact the arm moves at the roll speed: no start or stop while pressed
    assert pressed.sum() > 0.5 * 0.1 / 0.02 / 1e-3
    assert speed[pressed].min() > 0.019 and speed[pressed].max() < 0.0201
    # at the first and last pressed instant of each pass it is already (still) moving
    edges = np.flatnonzero(np.diff(pressed.astype(int)))
    assert len(edges) == 4 and (speed[edges] > 0.015).all()


def test_ramp_plans_have_no_path_and_path_plans_run_each_pass_as_one_path_move():
    ramp = _plan("ramp")
    assert ramp.path is None and ramp.motion() == (ramp.segments, ramp.rolls)
    plan = _plan("blend")
    moves, rolls = plan.motion()
    assert [type(m).__name__ for m in moves] == ["Segment", "PathSegment"] * 2 and rolls == (1, 3)
    for k, index in enumerate(rolls):   # before, touchdown, lift-off, after: the ramp pass's press and roll
        np.testing.assert_allclose(moves[index].waypoints[1], plan.segments[plan.rolls[k] - 1].target)
        np.testing.assert_allclose(moves[index].waypoints[2], plan.segments[plan.rolls[k]].target)
        np.testing.assert_allclose(moves[index - 1].target, moves[index].waypoints[0])
    with pytest.raises(ValueError, match="sweep.profile"):
        _plan("zigzag")


@pytest.mark.parametrize("speed", [0.005, 0.02, 0.1])
def test_corner_accelerations_and_the_least_blend_agree_with_the_rounded_path(speed):
    points = np.array([[0, 0, 0.01, 0, 0, 0], [0.01, 0, 0, 0, 0, 0], [0.05, 0, 0, 0, 0, 0],
                       [0.05, 0.03, 0, 0, 0, 0]], float)
    r = least_blend(points, speed, 0.5)
    needed = corner_accelerations(points, speed, r)
    assert needed[[0, -1]].tolist() == [0.0, 0.0]
    if r <= 0.005:   # half the shortest leg: the radius fits
        assert needed.max() == pytest.approx(0.5, rel=1e-6)
    else:   # clamped to half a leg, the corner is too tight at this speed (an arm refuses the path)
        assert speed == 0.1 and needed.max() > 0.5
    assert np.isinf(corner_accelerations(points, speed, 0.0)[1:-1]).all()   # a sharp turn at speed
    # the rounded path's curvature (turning angle per arc length) at the sharpest corner (the right angle)
    blend = 0.004
    dense = rounded_polyline(points, blend, step=blend / 400)[:, :3]
    steps = np.diff(dense, axis=0)
    lengths = np.linalg.norm(steps, axis=1)
    heading = steps / lengths[:, None]
    w = 20
    turn = np.arccos(np.clip(np.einsum("ij,ij->i", heading[:-w], heading[w:]), -1, 1))
    arc = np.convolve(lengths, np.ones(w), "valid")[1:]
    assert (turn / arc).max() == pytest.approx(corner_accelerations(points, 1.0, blend)[2], rel=0.05)


@settings(max_examples=30, deadline=None)
@given(blend=st.floats(0.0, 0.01), jitter=st.floats(0.0, 0.05), seed=st.integers(0, 1000),
       pause=st.floats(0.0, 1.0), lead=st.floats(0.002, 0.02))
def test_property_a_path_is_continuous_ends_where_it_should_and_holds_its_speed(blend, jitter, seed, pause, lead):
    plan = _plan("blend", lead=lead, blend=blend)
    assert plan.path is not None
    path = BlendedPath(plan.path.waypoints, 0.02, 0.1, blend, jitter, seed, ((0.03, pause),))
    t = np.arange(0.0, path.duration + 1e-3, 2e-3)
    poses = path.poses(t)
    step = np.linalg.norm(np.diff(poses[:, :3], axis=0), axis=1)
    assert step.max() <= 0.02 * (1 + 4 * jitter) * 2e-3 + 1e-6   # no jump: at most the (varied) speed
    np.testing.assert_allclose(poses[0], path.waypoints[0], atol=1e-9)
    np.testing.assert_allclose(poses[-1], path.waypoints[-1], atol=1e-6)   # to within a micrometre
    assert path.duration >= path.length / (0.02 * (1 + 4 * jitter)) + pause - 1e-3


def test_planning_a_long_blended_raster_never_samples_its_whole_path():
    """The raster's whole path (what simulate_sweep films) is made on first use only: 0.9 m x 0.8 m in 1 mm
    passes would be 720 m of path sampled every 0.2 mm, for 18 h at 11 mm/s at 1 ms, gigabytes."""
    plan = plan_raster((0.0, 0.0, 0.2, 3.141592653589793, 0.0, 0.0), area=(-0.45, -0.4, 0.9, 0.8), mount=MOUNT,
                       speed=0.011, accel=0.1, depth=5e-4, clearance=0.002, usable_width=0.001, overlap=0.2,
                       profile="blend")
    assert len(plan.passes) == 1000 and "path" not in vars(plan)
    assert len(plan.motion()[0]) == 2000
    small = _plan("blend")
    assert small.path is not None and "path" in vars(small)   # made when asked for, then kept
