"""The recorder's queue: bounded in bytes, never silent about what it refuses."""
from __future__ import annotations

import threading

import pytest

from touchroller_bringup.recording_queue import BoundedQueue


def test_a_message_past_the_bound_is_refused_and_counted_per_topic():
    queue = BoundedQueue(max_bytes=100)
    assert queue.put("a", 60, "/image") and queue.put("b", 40, "/image")
    assert not queue.put("c", 1, "/image") and not queue.put("d", 10, "/tf")   # full: refused, counted
    queue.put_always("control")                                                 # never refused
    stats = queue.stats()
    assert stats.queued == 3 and stats.queued_bytes == 100 and stats.peak_bytes == 100
    assert stats.overflowed == {"/image": 1, "/tf": 1} and stats.overflowed_total == 2
    assert [queue.get(0), queue.get(0), queue.get(0)] == ["a", "b", "control"]   # in order
    assert queue.stats().queued_bytes == 0 and queue.put("e", 100, "/image")     # room again


def test_one_message_larger_than_the_bound_still_goes_through_an_empty_queue():
    queue = BoundedQueue(max_bytes=10)
    assert queue.put("big", 1000, "/image")
    assert not queue.put("next", 1, "/image")
    assert queue.get(0) == "big" and queue.stats().peak_bytes == 1000


def test_get_waits_for_an_item_or_times_out_and_the_bound_can_change():
    queue = BoundedQueue(max_bytes=10)
    with pytest.raises(TimeoutError):
        queue.get(timeout=0.01)
    threading.Timer(0.02, queue.put, args=("late", 1, "/x")).start()
    assert queue.get(timeout=10.0) == "late"
    queue.max_bytes = 20
    assert queue.stats().max_bytes == 20
    with pytest.raises(ValueError):
        queue.max_bytes = 0
    with pytest.raises(ValueError):
        BoundedQueue(0)
