import math

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

from touchroller_driver.motion import TrapezoidProfile


def test_trapezoid_reaches_cruise_speed():
    prof = TrapezoidProfile(1.0, v_max=0.5, a_max=1.0)
    # ramp 0.5 s covers 0.125 m each, cruise 0.75 m at 0.5 m/s = 1.5 s
    assert prof.duration == pytest.approx(2.5)
    assert prof.velocity(1.0) == pytest.approx(0.5)
    assert prof.position(prof.duration) == pytest.approx(1.0)
    assert prof.position(0.25) == pytest.approx(0.5 * 1.0 * 0.25**2)


def test_triangular_when_too_short():
    prof = TrapezoidProfile(0.01, v_max=1.0, a_max=1.0)
    assert prof.peak_velocity == pytest.approx(0.1)
    assert prof.duration == pytest.approx(0.2)
    assert prof.velocity(0.1) == pytest.approx(0.1)


def test_negative_distance_and_clamping():
    prof = TrapezoidProfile(-0.2, v_max=0.1, a_max=0.5)
    t = np.array([-1.0, 0.0, prof.duration, prof.duration + 3])
    np.testing.assert_allclose(prof.position(t), [0.0, 0.0, -0.2, -0.2], atol=1e-12)
    assert prof.velocity(prof.duration / 2) == pytest.approx(-0.1)
    assert prof.velocity(-0.5) == 0.0


def test_zero_distance_and_bad_input():
    assert TrapezoidProfile(0.0, 1.0, 1.0).duration == 0.0
    with pytest.raises(ValueError):
        TrapezoidProfile(1.0, 0.0, 1.0)
    with pytest.raises(ValueError):
        TrapezoidProfile(math.nan, 1.0, 1.0)


@given(
    distance=st.floats(-2.0, 2.0, allow_nan=False),
    v_max=st.floats(1e-3, 3.0),
    a_max=st.floats(1e-2, 20.0),
)
def test_profile_is_consistent(distance, v_max, a_max):
    prof = TrapezoidProfile(distance, v_max, a_max)
    t = np.linspace(0.0, prof.duration, 201)
    s = prof.position(t)
    v = prof.velocity(t)
    assert np.all(np.abs(v) <= v_max * (1 + 1e-9))
    assert s[-1] == pytest.approx(distance, abs=1e-9)
    # position is monotone in the direction of travel
    assert np.all(np.diff(s) * math.copysign(1.0, distance) >= -1e-12)
    # velocity is the derivative of position (trapezoid rule integration)
    if prof.duration > 0:
        fine = np.linspace(0.0, prof.duration, 20001)
        integral = np.trapezoid(prof.velocity(fine), fine)
        assert integral == pytest.approx(distance, abs=1e-3 * abs(distance) + 1e-12)
