"""The simulated clock's frame gate: how far the clock may run ahead of the frames."""
from __future__ import annotations

import pytest

from touchroller_driver.sim.clock import FrameGate

MS = 1_000_000


def test_free_until_the_camera_has_published_and_then_held_to_the_oldest_unfinished_frame():
    gate = FrameGate(lead_ns=50 * MS)
    assert gate.allows(10**12, consumer=True)              # nothing published yet: the camera needs the clock
    gate.published(1000 * MS)
    assert gate.limit_ns(consumer=True) == 1050 * MS      # the consumer has not finished it
    gate.published(1033 * MS)
    gate.published(1066 * MS)
    assert gate.limit_ns(consumer=True) == 1050 * MS      # still the oldest unfinished frame
    gate.finished(1033 * MS)                              # done with the first two
    assert gate.limit_ns(consumer=True) == 1116 * MS
    assert not gate.allows(1117 * MS, consumer=True) and gate.allows(1116 * MS, consumer=True)


def test_with_everything_finished_or_no_consumer_the_clock_may_reach_the_next_frame_and_the_lead():
    gate = FrameGate(lead_ns=10 * MS)
    for stamp in (1000, 1200, 1400):   # 5 fps: frames further apart than the lead
        gate.published(stamp * MS)
    # no consumer: the camera's next frame (newest + the interval seen) plus the lead, never a deadlock
    assert gate.limit_ns(consumer=False) == 1610 * MS
    gate.finished(1400 * MS)
    assert gate.limit_ns(consumer=True) == 1610 * MS
    gate.finished(1200 * MS)   # an older report changes nothing
    assert gate.limit_ns(consumer=True) == 1610 * MS


def test_a_frame_the_consumer_never_saw_does_not_hold_the_clock_once_a_later_one_is_finished():
    gate = FrameGate(lead_ns=0)
    for stamp in (100, 200, 300):
        gate.published(stamp)
    gate.finished(300)   # 100 and 200 were lost on the way
    assert gate.limit_ns(consumer=True) == 400


def test_events_count_and_wait_returns_on_a_report():
    import threading

    gate = FrameGate(lead_ns=0)
    threading.Timer(0.05, gate.published, args=(5,)).start()
    gate.wait(10.0)
    assert gate.events == 1
    with pytest.raises(ValueError):
        FrameGate(lead_ns=-1)
