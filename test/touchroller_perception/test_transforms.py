"""Transforms and the transform buffer, checked against scipy's rotations and hand-made trees."""
from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.spatial.transform import Rotation, Slerp

from touchroller_perception.transforms import (
    ConnectivityError,
    ExtrapolationError,
    Transform,
    TransformBuffer,
    interpolate,
    quaternion_to_matrix,
    transforms_to_matrices,
)

angles = st.floats(-math.pi, math.pi, allow_nan=False)
coords = st.floats(-10.0, 10.0, allow_nan=False)
quaternions = st.tuples(*[st.floats(-1.0, 1.0, allow_nan=False)] * 4).filter(
    lambda q: np.linalg.norm(q) > 0.1)


def as_scipy(t: Transform) -> tuple[Rotation, np.ndarray]:
    return Rotation.from_quat(t.rotation), np.asarray(t.translation)


@settings(max_examples=100, deadline=None)
@given(st.tuples(coords, coords, coords), st.tuples(angles, angles, angles), st.tuples(coords, coords, coords),
       quaternions, st.tuples(coords, coords, coords))
def test_compose_inverse_and_apply_agree_with_scipy(t1, rpy, t2, q2, point):
    a = Transform.from_rpy(t1, rpy)
    b = Transform(t2, q2)
    ra, ta = as_scipy(a)
    rb, tb = as_scipy(b)
    assert np.allclose(ra.as_matrix(), Rotation.from_euler("xyz", rpy).as_matrix(), atol=1e-9)
    expected = ra.apply(rb.apply(point) + tb) + ta
    assert np.allclose((a @ b).apply(point), expected, atol=1e-9)
    assert np.allclose(a.inverse().apply(a.apply(point)), point, atol=1e-9)
    assert np.allclose(Transform.from_matrix(a.matrix()).matrix(), a.matrix(), atol=1e-9)
    # rpy() gives angles that make the same rotation (not necessarily the same numbers: wrapping)
    assert np.allclose(Transform.from_rpy(t1, a.rpy()).matrix(), a.matrix(), atol=1e-6)


@settings(max_examples=100, deadline=None)
@given(quaternions, quaternions, st.floats(0.0, 1.0))
def test_interpolation_is_scipys_slerp(q0, q1, fraction):
    a, b = Transform((0, 0, 0), q0), Transform((1, 2, 3), q1)
    expected = Slerp([0.0, 1.0], Rotation.from_quat([a.rotation, b.rotation]))([fraction])[0]
    got = interpolate(a, b, fraction)
    assert np.allclose(Rotation.from_quat(got.rotation).as_matrix(), expected.as_matrix(), atol=1e-7)
    assert np.allclose(got.translation, np.array([1, 2, 3]) * fraction)


def test_rotation_vector_is_a_ur_pose():
    pose = Transform.from_rotation_vector((0.4, 0.0, 0.2), (math.pi, 0.0, 0.0))   # flange pointing down
    assert np.allclose(pose.apply([0.0, 0.0, 0.1]), [0.4, 0.0, 0.1])


def make_tree() -> TransformBuffer:
    """base -> tool0 moving along x at 1 m/s and turning about z; tool0 -> sensor static."""
    buffer = TransformBuffer(cache_ns=None)
    for k in range(11):   # every 0.1 s for 1 s
        t_ns = k * 100_000_000
        buffer.set_transform("base", "tool0", t_ns, Transform.from_rpy((k * 0.1, 0.0, 1.0), (0.0, 0.0, 0.2 * k)))
    buffer.set_transform("tool0", "sensor", 0, Transform.from_rpy((0.0, 0.0, 0.1), (math.pi, 0.0, 0.0)),
                         static=True)
    buffer.set_transform("base", "table", 0, Transform((1.0, 0.0, 0.0)), static=True)
    return buffer


def test_lookup_interpolates_and_chains_through_the_common_parent():
    buffer = make_tree()
    t = buffer.lookup("base", "sensor", 250_000_000)
    tool = Transform.from_rpy((0.25, 0.0, 1.0), (0.0, 0.0, 0.5))   # halfway between the samples at 0.2 and 0.3 s
    sensor = tool @ Transform.from_rpy((0.0, 0.0, 0.1), (math.pi, 0.0, 0.0))
    assert np.allclose(t.matrix(), sensor.matrix(), atol=1e-12)
    # into a sibling frame: table <- base <- tool0 <- sensor
    in_table = buffer.lookup("table", "sensor", 250_000_000)
    assert np.allclose(in_table.matrix(), (Transform((1.0, 0.0, 0.0)).inverse() @ sensor).matrix(), atol=1e-12)
    # and back
    assert np.allclose(buffer.lookup("sensor", "table", 250_000_000).matrix(), in_table.inverse().matrix(),
                       atol=1e-12)


def test_lookup_many_equals_one_by_one():
    buffer = make_tree()
    stamps = np.array([0, 1, 99_999_999, 100_000_000, 512_345_678, 1_000_000_000])
    many = buffer.lookup_many("table", "sensor", stamps)
    for stamp, matrix in zip(stamps, many, strict=True):
        assert np.allclose(matrix, buffer.lookup("table", "sensor", int(stamp)).matrix(), atol=1e-12)


@settings(max_examples=50, deadline=None)
@given(st.lists(quaternions, min_size=1, max_size=40), st.integers(0, 2 ** 32 - 1))
def test_matrices_in_one_product_are_quaternion_to_matrix_bit_for_bit(qs, seed):
    q = np.asarray(qs, np.float64)
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    t = np.random.default_rng(seed).normal(size=(len(q), 3))
    m = transforms_to_matrices(t, q)
    assert np.array_equal(m[:, :3, :3], quaternion_to_matrix(q))
    assert np.array_equal(m[:, :3, 3], t)
    assert np.array_equal(m[:, 3], np.tile([0.0, 0.0, 0.0, 1.0], (len(q), 1)))


def test_lookup_many_of_a_moving_edge_is_its_interpolation_bit_for_bit_and_nan_outside():
    buffer = make_tree()
    stamps = np.array([-5, 0, 1, 99_999_999, 512_345_678, 1_000_000_000, 2_000_000_000], np.int64)
    many = buffer.lookup_many("base", "tool0", stamps, missing=True)
    inside = (stamps >= 0) & (stamps <= 1_000_000_000)
    assert np.isnan(many[~inside, :3]).all() and np.isfinite(many[inside]).all()
    t, q = buffer._edges["tool0"].at(stamps[inside], "tool0")
    expected = np.tile(np.eye(4), (int(inside.sum()), 1, 1))
    expected[:, :3, :3], expected[:, :3, 3] = quaternion_to_matrix(q), t
    assert np.array_equal(many[inside], expected)


def test_no_extrapolation_and_no_unknown_frames():
    buffer = make_tree()
    with pytest.raises(ExtrapolationError, match="base -> tool0"):
        buffer.lookup("base", "sensor", 1_000_000_001)
    with pytest.raises(ExtrapolationError):
        buffer.lookup("base", "sensor", -1)
    with pytest.raises(ConnectivityError, match="camera does not exist"):
        buffer.lookup("base", "camera", 0)
    buffer.set_transform("elsewhere", "camera", 0, Transform(), static=True)
    with pytest.raises(ConnectivityError, match="not connected"):
        buffer.lookup("base", "camera", 0)
    assert not buffer.can_transform("base", "camera")
    assert buffer.can_transform("base", "sensor")
    assert buffer.latest_common_stamp("table", "sensor") == 1_000_000_000
    latest = buffer.lookup("base", "sensor").translation
    assert np.allclose(latest, buffer.lookup("base", "sensor", 10 ** 9).translation)


def test_covers_says_whether_a_lookup_finds_the_transform():
    buffer = make_tree()
    buffer.set_transform("base", "probe", 300_000_000, Transform((0.0, 1.0, 0.0)))   # a moving edge, one sample
    buffer.set_transform("elsewhere", "camera", 0, Transform(), static=True)
    stamps = [-1, 0, 1, 99_999_999, 100_000_000, 250_000_000, 299_999_999, 300_000_000, 300_000_001,
              999_999_999, 1_000_000_000, 1_000_000_001, 10 ** 18]
    pairs = [("base", "sensor"), ("table", "sensor"), ("sensor", "table"), ("tool0", "sensor"), ("base", "table"),
             ("base", "probe"), ("sensor", "probe"), ("base", "camera"), ("base", "nowhere")]
    seen = set()
    for target, source in pairs:
        for stamp in stamps:
            try:
                found = bool(np.isfinite(buffer.lookup_many(target, source, [stamp], missing=True)).all())
            except ConnectivityError:
                found = False
            assert buffer.covers(target, source, stamp) == found, (target, source, stamp)
            seen.add(found)
    assert seen == {True, False}


def test_static_edges_hold_at_any_time_and_frames_ignore_a_leading_slash():
    buffer = TransformBuffer()
    buffer.set_transform("/base", "tool0", 5, Transform((1.0, 2.0, 3.0)), static=True)
    assert buffer.lookup("base", "/tool0", 10 ** 18).translation == (1.0, 2.0, 3.0)
    assert buffer.lookup("tool0", "tool0", 0) == Transform()


def test_cache_drops_old_samples_but_keeps_what_interpolation_needs():
    buffer = TransformBuffer(cache_ns=1_000_000_000)
    for k in range(100):   # 10 s at 10 Hz
        buffer.set_transform("base", "tool0", k * 100_000_000, Transform((k * 0.1, 0.0, 0.0)))
    first, last = buffer.time_range("tool0")
    assert last == 9_900_000_000 and 8_800_000_000 <= first <= 8_900_000_000
    assert buffer.lookup("base", "tool0", 9_000_000_000).translation[0] == pytest.approx(9.0)
    with pytest.raises(ExtrapolationError):
        buffer.lookup("base", "tool0", 1_000_000_000)


def test_out_of_order_samples_are_sorted_and_a_new_parent_rewires_the_child():
    buffer = TransformBuffer()
    for k in (3, 1, 2, 0):
        buffer.set_transform("base", "tool0", k, Transform((float(k), 0.0, 0.0)))
    assert buffer.lookup("base", "tool0", 2).translation[0] == 2.0
    buffer.set_transform("world", "tool0", 0, Transform(), static=True)
    assert buffer.parent("tool0") == "world"


def test_bad_transforms_are_refused():
    with pytest.raises(ValueError, match="rotation"):
        Transform((0, 0, 0), (0, 0, 0, 0))
    with pytest.raises(ValueError, match="translation"):
        Transform((0, math.nan, 0))
    with pytest.raises(ValueError, match="own parent"):
        TransformBuffer().set_transform("a", "a", 0, Transform())
