"""The simulated clock's frame gate: how far the clock may run ahead of the frames."""
from __future__ import annotations

import pytest

from touchroller_driver.sim.clock import FrameGate

MS = 1_000_000


def test_free_until_the_camera_has_published_and_then_held_to_the_oldest_unfinished_frame():
    gate = FrameGate(lead_ns=50 * MS)
    assert gate.allows(10**12, consumers=True)              # nothing published yet: the camera needs the clock
    gate.published(1000 * MS)
    assert gate.limit_ns(consumers=True) == 1050 * MS      # the consumer has not finished it
    gate.published(1033 * MS)
    gate.published(1066 * MS)
    assert gate.limit_ns(consumers=True) == 1050 * MS      # still the oldest unfinished frame
    gate.finished(1033 * MS)                              # done with the first two
    assert gate.limit_ns(consumers=True) == 1116 * MS
    assert not gate.allows(1117 * MS, consumers=True) and gate.allows(1116 * MS, consumers=True)


def test_with_everything_finished_or_no_consumer_the_clock_may_reach_the_next_frame_and_the_lead():
    gate = FrameGate(lead_ns=10 * MS)
    for stamp in (1000, 1200, 1400):   # 5 fps: frames further apart than the lead
        gate.published(stamp * MS)
    # no consumer: the camera's next frame (newest + the interval seen) plus the lead, never a deadlock
    assert gate.limit_ns(consumers=False) == 1610 * MS
    gate.finished(1400 * MS)
    assert gate.limit_ns(consumers=True) == 1610 * MS
    gate.finished(1200 * MS)   # an older report changes nothing
    assert gate.limit_ns(consumers=True) == 1610 * MS


def test_a_frame_the_consumer_never_saw_does_not_hold_the_clock_once_a_later_one_is_finished():
    gate = FrameGate(lead_ns=0)
    for stamp in (100, 200, 300):
        gate.published(stamp)
    gate.finished(300)   # 100 and 200 were lost on the way
    assert gate.limit_ns(consumers=True) == 400


def test_events_count_and_wait_returns_on_a_report():
    import threading

    gate = FrameGate(lead_ns=0)
    threading.Timer(0.05, gate.published, args=(5,)).start()
    gate.wait(10.0)
    assert gate.events == 1
    with pytest.raises(ValueError):
        FrameGate(lead_ns=-1)


def test_with_two_consumers_the_clock_waits_for_the_slower_one():
    """The perception node and a recorder: the clock holds to the oldest frame either has not finished, and
    only the consumers present count (a recorder that is gone holds nothing)."""
    gate = FrameGate(lead_ns=0)
    for stamp in (100, 200, 300, 400):
        gate.published(stamp)
    gate.finished(300, "perception")
    gate.finished(100, "recorder")
    assert gate.limit_ns(["perception", "recorder"]) == 200      # the recorder has not written 200 yet
    assert gate.limit_ns(["perception"]) == 400
    assert gate.limit_ns(["recorder"]) == 200
    gate.finished(400, "recorder")
    assert gate.limit_ns(["perception", "recorder"]) == 400      # perception's 400 now
    gate.finished(400, "perception")
    assert gate.limit_ns(["perception", "recorder"]) == 500      # both done: the next frame (+ the lead)
    assert gate.limit_ns(["recorder", "nobody yet"]) == 100      # a consumer present that finished nothing
